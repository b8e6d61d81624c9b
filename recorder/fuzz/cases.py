"""What a fuzz case is: its category, its seed, the steps it generates; the plan of a run.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: The case categories, and the order in which cases cycle through them (weights: how
#: often each appears in 20 consecutive cases).
CATEGORIES: tuple[str, ...] = ("log-bytes", "log-records", "npz", "image", "cloud", "scan",
                               "pipeline", "bag")
_CYCLE: tuple[str, ...] = (
    "log-bytes", "log-records", "npz", "image", "cloud", "scan", "pipeline",
    "log-bytes", "log-records", "npz", "log-bytes", "log-records", "npz", "image",
    "cloud", "scan", "pipeline", "log-bytes", "log-records", "log-bytes", "bag",
)

#: Default per-case wall-time limit, seconds (the worker is killed past it).
DEFAULT_TIMEOUT_S = 30.0
#: Default bound on a case's peak resident-memory growth, MB.
DEFAULT_MEM_BOUND_MB = 512
#: A worker is restarted when its resident memory has grown this much since warm-up, MB.
_RESTART_GROWTH_MB = 1024
#: Failures listed in full in the report (all are saved to disk).
_MAX_LISTED = 50

Step = tuple[str, Callable[[], Any]]


@dataclass(frozen=True)
class Case:
    """One fuzz case: its number, category and the run's seed (the case's generator is
    ``np.random.default_rng([seed, index])``)."""

    index: int
    category: str
    seed: int

    def rng(self) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.index])


@dataclass
class Job:
    """A generated case: what it is (``kind``) and the calls to make (``steps``)."""

    kind: str
    steps: list[Step] = field(default_factory=list)
    #: the reader's keyword arguments, for a file case (saved with a failure)
    read_kw: dict[str, Any] = field(default_factory=dict)


def _pick(rng: np.random.Generator, seq: Sequence[Any]) -> Any:
    """One element of ``seq`` as it is (``rng.choice`` would make big ints floats)."""
    return seq[int(rng.integers(0, len(seq)))]


def plan(n: int, seed: int) -> list[Case]:
    """The ``n`` cases of a run (categories cycle through :data:`_CYCLE`)."""
    return [Case(i, _CYCLE[i % len(_CYCLE)], int(seed)) for i in range(int(n))]
