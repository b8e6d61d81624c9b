#!/usr/bin/env bash
# Set up, then run the linter, the type checker and the test suite.
#
# In CI (CI=true, as .ci/run is run) every test runs, the slow ones included (-m "").
# Elsewhere pyproject.toml's addopts deselect the tests marked slow, for a quicker loop;
# `bash scripts/test.sh -m ""` runs them all locally too (a later -m replaces an earlier one).
# Any skip outside the real-data set fails the run (tests/conftest.py).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup.sh"
VENV="${BOXLOC_VENV:-$ROOT/.venv}"
cd "$ROOT"
"$VENV/bin/ruff" check boxloc recorder replay tests
"$VENV/bin/mypy"  # mypy.ini: boxloc, recorder, replay
ALL=()
case "${CI:-}" in
  ""|false|0) ;;
  *) ALL=(-m "") ;;
esac
"$VENV/bin/python" -m pytest -q -n 2 --timeout=300 "${ALL[@]}" "$@" || exit $?
