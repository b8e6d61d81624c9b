"""Default layouts of the Rerun viewer for boxloc recordings.

:func:`default_blueprint`: the range image with the edges (and the found surfaces and lines
projected into it); a 3D view of the points, edges, lines, vertices, hypotheses coloured by
verdict and the labelled surfaces; plots of each scan's test statistics, counts and stage
timings. :func:`side_by_side_blueprint`: the same for two runs (``baseline``, ``candidate``)
in one recording, next to each other.

The entity paths are those of :mod:`recorder.rerun.sink`.
"""

from __future__ import annotations

import rerun.blueprint as rrb

from recorder.rerun.sink import (
    AMBIGUOUS,
    EDGE_IMAGE,
    LINES,
    RANGE,
    SCAN,
    STATS_COUNTS,
    STATS_SELECTION,
    STATS_TESTS,
    STATS_TIMING,
    SURFACES,
    TIMELINE_SCAN,
    WORLD,
    entity,
)


def _root(prefix: str) -> str:
    p = prefix.strip("/")
    return f"/{p}" if p else "/"


def image_view(prefix: str = "", name: str = "range + edges") -> rrb.Spatial2DView:
    """The range image with the edge map over it, and the surfaces and lines projected."""
    return rrb.Spatial2DView(
        origin=entity(prefix, SCAN),
        contents=[
            f"+ {entity(prefix, RANGE)}",
            f"+ {entity(prefix, EDGE_IMAGE)}",
            # 3D entities seen through the scan's pinhole: drawn over the image
            f"+ {entity(prefix, SURFACES)}",
            f"+ {entity(prefix, AMBIGUOUS)}",
            f"+ {entity(prefix, LINES)}",
        ],
        name=name,
    )


def world_view(prefix: str = "", name: str = "3D") -> rrb.Spatial3DView:
    """Points, edges, lines, vertices, hypotheses, surfaces and ambiguous regions, and the
    camera frustum."""
    return rrb.Spatial3DView(
        origin=_root(prefix),
        contents=[
            f"+ {entity(prefix, WORLD)}/**",
            # the camera (its frustum), not its images: the cloud is world/points
            f"+ {entity(prefix, SCAN)}",
        ],
        name=name,
    )


def tests_view(prefix: str = "", measure: str = "median_ratio",
               name: str | None = None) -> rrb.TimeSeriesView:
    """One series per test kind of one measure (see ``TEST_MEASURES``)."""
    titles = {
        "median_ratio": "tests: median statistic / critical",
        "max_ratio": "tests: max statistic / critical",
        "accepted_fraction": "tests: fraction accepted",
        "n_tested": "tests: number tested",
        "n_accepted": "tests: number accepted",
    }
    fraction = measure == "accepted_fraction"
    return rrb.TimeSeriesView(
        origin=entity(prefix, f"{STATS_TESTS}/{measure}"),
        name=name or titles.get(measure, f"tests: {measure}"),
        axis_y=rrb.ScalarAxis(range=(0.0, 1.05)) if fraction else None,
        plot_legend=rrb.PlotLegend(rrb.Corner2D.LeftBottom if fraction else rrb.Corner2D.LeftTop),
    )


def timing_view(prefix: str = "", name: str = "stage timing [ms]") -> rrb.TimeSeriesView:
    return rrb.TimeSeriesView(origin=entity(prefix, STATS_TIMING), name=name,
                              plot_legend=rrb.PlotLegend(rrb.Corner2D.LeftTop))


def counts_view(prefix: str = "", name: str = "counts") -> rrb.TimeSeriesView:
    return rrb.TimeSeriesView(origin=entity(prefix, STATS_COUNTS), name=name)


def _plots(prefix: str) -> rrb.Tabs:
    return rrb.Tabs(
        tests_view(prefix, "accepted_fraction"),
        tests_view(prefix, "median_ratio"),
        tests_view(prefix, "max_ratio"),
        tests_view(prefix, "n_tested"),
        counts_view(prefix),
        rrb.TimeSeriesView(origin=entity(prefix, STATS_SELECTION), name="MDL objective"),
        active_tab=0,
    )


def _panels() -> list[rrb.BlueprintPart]:
    return [
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=TIMELINE_SCAN),
    ]


def default_blueprint(prefix: str = "") -> rrb.Blueprint:
    """The default layout: image and plots on the left, the 3D view on the right."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                image_view(prefix),
                rrb.Horizontal(_plots(prefix), timing_view(prefix)),
                row_shares=[3, 2],
            ),
            world_view(prefix),
            column_shares=[2, 3],
        ),
        *_panels(),
    )


def side_by_side_blueprint(
    baseline: str = "baseline", candidate: str = "candidate"
) -> rrb.Blueprint:
    """Two runs logged under two prefixes, side by side: image, 3D view and plots of each."""

    def column(prefix: str) -> rrb.Vertical:
        return rrb.Vertical(
            image_view(prefix, name=f"{prefix}: range + edges"),
            world_view(prefix, name=f"{prefix}: 3D"),
            rrb.Tabs(
                counts_view(prefix, name=f"{prefix}: counts"),
                tests_view(prefix, "median_ratio",
                           name=f"{prefix}: median statistic / critical"),
                timing_view(prefix, name=f"{prefix}: timing [ms]"),
            ),
            row_shares=[2, 3, 2],
        )

    return rrb.Blueprint(rrb.Horizontal(column(baseline), column(candidate)), *_panels())
