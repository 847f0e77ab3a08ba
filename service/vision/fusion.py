"""Two feature types' similarities fused into one (maps of type ``clahe-rootsift+xfeat``).

m(A, B) of CLAHE + RootSIFT and of XFeat live on different scales: on the rendered worlds two
unrelated images share about 0.15 % of their RootSIFT features and 2.4 % of their XFeat ones,
two neighbouring map images about 30 % and 50 %. So each map measures, when it is built and
without labels, two levels per type: *chance* c (the mean m of map images more than
``CHANCE_M`` apart) and *typical* t (the median m of consecutive images of a traversal, a
right place in the map's own light). XFeat's m is scaled onto RootSIFT's scale (zero to zero,
typical to typical) and the fused m is the mean of the two (rule ``mean-scaled``):

    m = (m_1 + m_2 t_1 / t_2) / 2

Zero stays zero: the fused m of two unrelated images is the mean of both types' chance
levels, XFeat's ~0.014 on RootSIFT's scale included. The estimators judge a place by how many
times the far images' m it is (``distinct_ratio``, service/estimators/lost_detection.py) and
that ratio means "times chance" only where the scale's zero means "nothing shared". The
first rule, ``mean-affine`` (maps built before it, kept bit for bit), mapped XFeat's chance
level onto RootSIFT's (~0.001):

    m = max(0, (m_1 + c_1 + (m_2 - c_2) (t_1 - c_1) / (t_2 - c_2)) / 2)

which ranks images the same way (the two differ by a constant and a slope within 5 %) but
moves the far images' m to ~0: a wrong place that XFeat matched at twice its chance level
stood out 30x from them, and DPSO reported `tracking` on most dusk frames more than 10 m off
(docs/research/lighting.md, "Both feature types").

On RootSIFT's scale the estimators' absolute floors (``distinct_floor_m``) keep their
meaning. The mean was chosen against the larger normalised score, sums and products with
other normalisers, on the cloudy and dusk rounds of rendered worlds against a sunny map
(client/lab/fusion_study.py): it keeps a right place in front where either type alone loses
it, and a frame where one type finds nothing (a dark frame without RootSIFT features) still
ranks by the other.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

LEVEL_PAIRS = 40  # images whose pairs measure the levels: their next image, ...
FAR_PAIRS = 4  # ... and this many images more than CHANCE_M away
CHANCE_M = 20.0  # beyond a place's neighbours, which look like it (metres)
_MIN_SPAN = 1e-3  # a typical level less than this above chance is taken as this above it
RULES = ("mean-scaled", "mean-affine")  # the first is what new maps get


@dataclass(frozen=True)
class Fusion:
    """Each type's chance and typical levels on one map (and the rule's name)."""

    first_chance: float  # RootSIFT
    first_typical: float
    second_chance: float  # XFeat
    second_typical: float
    rule: str = RULES[0]

    def __post_init__(self) -> None:
        if self.rule not in RULES:
            raise ValueError(f"unknown fusion rule {self.rule!r} (this swarmloc knows "
                             f"{', '.join(RULES)})")
        levels = (self.first_chance, self.first_typical, self.second_chance,
                  self.second_typical)
        if not all(isinstance(v, float) and 0.0 <= v <= 1.0 for v in levels):
            raise ValueError(f"levels must be similarities in [0, 1], got {levels}")

    @property
    def slope(self) -> float:
        """RootSIFT units per XFeat unit (``mean-scaled``: typical over typical;
        ``mean-affine``: the span from chance to typical over the other's)."""
        if self.rule == "mean-scaled":
            return max(self.first_typical, _MIN_SPAN) / max(self.second_typical, _MIN_SPAN)
        return (max(self.first_typical - self.first_chance, _MIN_SPAN)
                / max(self.second_typical - self.second_chance, _MIN_SPAN))

    def fuse(self, first: np.ndarray, second: np.ndarray) -> np.ndarray:
        """The fused similarity of each pair, on the first type's scale."""
        if self.rule == "mean-scaled":
            return (first + second * self.slope) / 2.0
        mapped = self.first_chance + (second - self.second_chance) * self.slope
        return np.maximum((first + mapped) / 2.0, 0.0)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Fusion:
        return cls(float(d["first_chance"]), float(d["first_typical"]),
                   float(d["second_chance"]), float(d["second_typical"]), str(d["rule"]))


def level_pairs(positions: np.ndarray, layers: np.ndarray
                ) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """(consecutive, far) image pairs that measure the levels: up to ``LEVEL_PAIRS`` images
    spread evenly over the map with their next image of the same traversal, and each with
    up to ``FAR_PAIRS`` images more than ``CHANCE_M`` away, spread evenly over those."""
    pos = np.asarray(positions, float)
    n = len(pos)
    picks = np.unique(np.linspace(0, n - 1, min(LEVEL_PAIRS, n)).round().astype(np.int64))
    same = np.asarray(layers[:-1]) == np.asarray(layers[1:])
    consecutive = [(int(i), int(i) + 1) for i in picks if i < n - 1 and same[i]]
    far = []
    for i in picks:
        cand = np.flatnonzero(np.linalg.norm(pos - pos[i], axis=1) > CHANCE_M)
        if len(cand):
            take = cand[np.linspace(0, len(cand) - 1, min(FAR_PAIRS, len(cand)))
                        .round().astype(np.int64)]
            far += [(int(i), int(j)) for j in np.unique(take)]
    return consecutive, far


def fusion_levels(positions: np.ndarray, layers: np.ndarray,
                  scores: Callable[[int, list[int]], tuple[np.ndarray, np.ndarray]]) -> Fusion:
    """The map's fusion (``scores(i, ids)``: both types' m of map image i against images
    ``ids``). Without consecutive pairs a type's typical level is 1, without far pairs its
    chance level 0."""
    consecutive, far = level_pairs(positions, layers)

    def measure(pairs: list[tuple[int, int]]) -> np.ndarray:
        out = []
        for i in dict.fromkeys(a for a, _ in pairs):
            ids = [b for a, b in pairs if a == i]
            first, second = scores(i, ids)
            out += list(zip(first, second, strict=True))
        return np.array(out, float).reshape(-1, 2)

    typical = np.median(measure(consecutive), axis=0) if consecutive else np.ones(2)
    chance = np.mean(measure(far), axis=0) if far else np.zeros(2)
    return Fusion(float(chance[0]), float(typical[0]), float(chance[1]), float(typical[1]))
