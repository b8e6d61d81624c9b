"""The suite's own rules (tests/conftest.py), run on small suites made here.

A skip outside the real-data set turns a green run red and names the test; a test marked
``real_data`` is skipped, naming the frames, when they are absent, and that alone passes.
"""

from __future__ import annotations

from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent

INI = """
[pytest]
addopts = -p no:cacheprovider -p no:dash --strict-markers
markers =
    real_data(*frames): reads the external mOSD frames
"""


def _suite(pytester: pytest.Pytester, body: str) -> None:
    pytester.makeconftest((HERE / "conftest.py").read_text())
    pytester.makeini(INI)
    pytester.syspathinsert(HERE)  # tests/real_data.py
    pytester.makepyfile(test_it=body)


def test_a_plain_skip_fails_the_run_and_is_named(pytester: pytest.Pytester) -> None:
    _suite(pytester, """
        import pytest

        def test_fine():
            pass

        def test_hidden():
            pytest.skip("boxloc.simulate moved")
    """)
    r = pytester.runpytest()
    r.assert_outcomes(passed=1, skipped=1)
    assert r.ret == pytest.ExitCode.TESTS_FAILED
    r.stdout.fnmatch_lines(
        ["*SKIPPED (not allowed) test_it.py::test_hidden: boxloc.simulate moved*"])


def test_a_module_that_skips_itself_fails_the_run(pytester: pytest.Pytester) -> None:
    _suite(pytester, """
        import pytest

        helpers = pytest.importorskip("no_such_helper_module")

        def test_never_collected():
            pass
    """)
    r = pytester.runpytest()
    assert r.ret == pytest.ExitCode.TESTS_FAILED
    r.stdout.fnmatch_lines(["*SKIPPED (not allowed) test_it.py:*no_such_helper_module*"])


def test_real_data_skips_name_the_frames_and_pass(pytester: pytest.Pytester) -> None:
    _suite(pytester, """
        import pytest

        @pytest.mark.real_data("no-such-frame.pcd", ".")
        def test_absent_frame():
            raise AssertionError("must not run without its frame")

        @pytest.mark.real_data
        def test_skips_itself():
            pytest.skip("the data said so")

        @pytest.mark.xfail(strict=True, reason="a known limitation")
        def test_known():
            assert False
    """)
    r = pytester.runpytest("-rs")
    r.assert_outcomes(skipped=2, xfailed=1)
    assert r.ret == pytest.ExitCode.OK
    r.stdout.fnmatch_lines(["*real data absent: no-such-frame.pcd*not found in *mosd*"])
    r.stdout.no_fnmatch_line("*not allowed*")


def test_the_rule_holds_across_xdist_workers(pytester: pytest.Pytester) -> None:
    _suite(pytester, """
        import pytest

        @pytest.mark.parametrize("k", range(4))
        def test_many(k):
            if k == 3:
                pytest.skip("only on a worker")

        @pytest.mark.real_data("no-such-frame.pcd")
        def test_absent_frame():
            pass
    """)
    r = pytester.runpytest_subprocess("-n", "2")
    assert r.ret == pytest.ExitCode.TESTS_FAILED
    r.stdout.fnmatch_lines(["*SKIPPED (not allowed) test_it.py::test_many?3?: only on a worker*"])
    r.stdout.no_fnmatch_line("*not allowed*test_absent_frame*")


def _real_data_tests() -> tuple[set[str], set[str]]:
    """(tests marked real_data, tests whose body names MOSD) in this folder."""
    import ast

    marked, reading = set(), set()
    for f in sorted(HERE.glob("test_*.py")):
        for node in ast.walk(ast.parse(f.read_text())):
            if not (isinstance(node, ast.FunctionDef) and node.name.startswith("test_")):
                continue
            name = f"{f.name}::{node.name}"
            if any("real_data" in ast.unparse(d) for d in node.decorator_list):
                marked.add(name)
            if any(isinstance(n, ast.Name) and n.id == "MOSD" for n in ast.walk(node)):
                reading.add(name)
    return marked, reading


def test_the_real_data_set_is_exactly_the_tests_that_read_it() -> None:
    # a test reading the frames without the marker would fail where they are absent; one
    # marked without reading them could skip for no reason
    marked, reading = _real_data_tests()
    assert reading, "no test reads the mOSD frames any more: update tests/real_data.py"
    assert marked == reading, {"unmarked": sorted(reading - marked),
                               "marked without reading": sorted(marked - reading)}
