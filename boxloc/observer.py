"""The observer protocol: how stages hand their products to whoever listens (the recorder).

``boxloc`` defines the protocol and calls it; it never imports an implementation.
Observers must not mutate products (they are immutable anyway) and their failures are
their own: the pipeline does not catch them, so a recorder that cannot write stops the run
instead of silently losing data.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

if TYPE_CHECKING:
    from boxloc.config import Config
    from boxloc.products import (
        EdgeMap,
        HypothesisSet,
        LineSet,
        NoiseEstimate,
        Result,
        Selection,
        SurfaceSet,
        Verification,
        VertexSet,
    )
    from boxloc.scan import Scan


@runtime_checkable
class Observer(Protocol):
    """Receives each product of :func:`boxloc.pipeline.find_graspable_surfaces` in order.

    The order for one scan is: ``on_scan``, ``on_noise``, ``on_edges``, ``on_lines``,
    ``on_vertices``, ``on_hypotheses``, ``on_verification``, ``on_selection``, ``on_surfaces``,
    ``on_result`` (which carries the wall-clock timing).
    """

    def on_scan(self, scan: Scan, config: Config) -> None: ...
    def on_noise(self, scan: Scan, noise: NoiseEstimate) -> None: ...
    def on_edges(self, scan: Scan, edges: EdgeMap) -> None: ...
    def on_lines(self, scan: Scan, lines: LineSet) -> None: ...
    def on_vertices(self, scan: Scan, vertices: VertexSet) -> None: ...
    def on_hypotheses(self, scan: Scan, hypotheses: HypothesisSet) -> None: ...
    def on_verification(self, scan: Scan, verification: Verification) -> None: ...
    def on_selection(self, scan: Scan, selection: Selection) -> None: ...
    def on_surfaces(self, scan: Scan, surfaces: SurfaceSet) -> None: ...
    def on_result(self, scan: Scan, result: Result) -> None: ...


class NullObserver:
    """Does nothing; the default."""

    def on_scan(self, scan: Scan, config: Config) -> None:
        pass

    def on_noise(self, scan: Scan, noise: NoiseEstimate) -> None:
        pass

    def on_edges(self, scan: Scan, edges: EdgeMap) -> None:
        pass

    def on_lines(self, scan: Scan, lines: LineSet) -> None:
        pass

    def on_vertices(self, scan: Scan, vertices: VertexSet) -> None:
        pass

    def on_hypotheses(self, scan: Scan, hypotheses: HypothesisSet) -> None:
        pass

    def on_verification(self, scan: Scan, verification: Verification) -> None:
        pass

    def on_selection(self, scan: Scan, selection: Selection) -> None:
        pass

    def on_surfaces(self, scan: Scan, surfaces: SurfaceSet) -> None:
        pass

    def on_result(self, scan: Scan, result: Result) -> None:
        pass


class FanOut(NullObserver):
    """Forwards every call to several observers, in order."""

    def __init__(self, *observers: Observer) -> None:
        self.observers = [o for o in observers if o is not None]

    def __getattribute__(self, name: str) -> Any:
        if name.startswith("on_"):
            obs = object.__getattribute__(self, "observers")

            def call(*args: Any, **kwargs: Any) -> None:
                for o in obs:
                    getattr(o, name)(*args, **kwargs)

            return call
        return object.__getattribute__(self, name)
