"""Two feature types' similarities fused into one (maps of type ``clahe-rootsift+xfeat``).

m(A, B) of CLAHE + RootSIFT and of XFeat live on different scales: on the rendered worlds two
neighbouring map images share about a tenth of their RootSIFT features and a third of their
XFeat ones. Each type's m is therefore divided by its *level* on the map, measured when the
map is built, without labels: the median m between consecutive images of a traversal (the
score of a right place in the map's own light). The larger of the two normalised scores
wins, and the result is put back on the first type's (RootSIFT's) scale, so the estimators'
absolute floors (``distinct_floor_m``) keep their meaning:

    m = L_1 * max(m_1 / L_1, m_2 / L_2)

Rule and levels were chosen on the rendered worlds, cloudy and dusk rounds against a sunny
map (client/lab/fusion_study.py; docs/research/lighting.md, "Both feature types").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

LEVEL_PAIRS = 40  # consecutive image pairs whose median similarity is a type's level
_MIN_LEVEL = 1e-3  # a level below this (a map of featureless images) is taken as this


@dataclass(frozen=True)
class Fusion:
    """The rule and each type's level on one map."""

    first: float  # the first type's (RootSIFT's) level
    second: float  # the second type's (XFeat's) level
    rule: str = "max"

    def __post_init__(self) -> None:
        if self.rule != "max":
            raise ValueError(f"unknown fusion rule {self.rule!r} (this swarmloc knows max)")
        if not (np.isfinite(self.first) and np.isfinite(self.second)
                and self.first >= _MIN_LEVEL and self.second >= _MIN_LEVEL):
            raise ValueError(f"levels must be finite numbers >= {_MIN_LEVEL:g}, got "
                             f"{self.first!r}, {self.second!r}")

    def fuse(self, first: np.ndarray, second: np.ndarray) -> np.ndarray:
        """The fused similarity of each pair, on the first type's scale."""
        return np.maximum(first, second * (self.first / self.second))

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Fusion:
        return cls(float(d["first"]), float(d["second"]), str(d["rule"]))


def consecutive_pairs(layers: np.ndarray, n_pairs: int = LEVEL_PAIRS) -> np.ndarray:
    """Up to ``n_pairs`` ids i, spread evenly over the map, whose next image i + 1 is of the
    same traversal."""
    ok = np.flatnonzero(layers[:-1] == layers[1:])
    if len(ok) <= n_pairs:
        return ok
    return ok[np.linspace(0, len(ok) - 1, n_pairs).round().astype(np.int64)]


def fusion_levels(layers: np.ndarray,
                  scores: Callable[[int, int], tuple[float, float]]) -> Fusion:
    """The map's fusion: each type's median m over consecutive image pairs (``scores(i, j)``:
    both types' m of map image i against image j)."""
    ids = consecutive_pairs(np.asarray(layers))
    if len(ids) == 0:
        return Fusion(1.0, 1.0)  # one image per traversal: no level to measure, equal weight
    pairs = np.array([scores(int(i), int(i) + 1) for i in ids], float)
    first, second = np.maximum(np.median(pairs, axis=0), _MIN_LEVEL)
    return Fusion(float(first), float(second))
