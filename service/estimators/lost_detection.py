"""Lost detection that tells "the light changed" from "I am elsewhere" (beyond the papers).

The papers declare a robot lost when the best match of a frame is below an absolute 5 % of its
features. A change of light halves the matches at the true place as well, so that trigger fires
where the robot is. Here a frame's best match is judged against evidence of the same frame:

    distinctiveness = m_best / background

where ``m_best`` is the best similarity of the images compared near the reported position and
``background`` the median similarity of the images compared in this frame that lie farther
than ``far_m`` from it (the swarm's scouts and quantum particles always sample some). At the
true place the best image stands out from the rest even when all matches are weak; a swarm at
a wrong place sees nothing that stands out there. A frame is *good* when its
best match stands out by ``min_ratio`` and is above a small absolute floor (a frame without
any structure, e.g. at night, is never good). The background is smoothed over frames (EMA),
so a frame that compared no far image still has one.

On a map of two feature types the similarity is their fused m (service/vision/fusion.py). Where
one type sees nothing, at dusk or on a map of long shadows, its chance level in the fused m
can hide a place the other type shows clearly. So the first type (CLAHE + RootSIFT) may
*vouch* for a frame the fused m leaves in doubt (``vouch``): its own m, judged against its own
background by a second monitor, is good, and the fused m stands out at least
``vouch_distinct`` times. A vouched frame holds tracking but never restores it
(``MultiSwarmDPSO``): at the true place it keeps a weak stretch from being declared lost, and
a swarm already in doubt still needs the fused m's own evidence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Evidence:
    """What one frame says about the place: best similarity and how much it stands out."""

    best_m: float
    background: float
    distinct: float
    good: bool
    vouched: bool = False  # good only because the first feature type vouched (``vouch``)


def vouch(fused: Evidence, own: Evidence, min_distinct: float) -> Evidence:
    """The fused m's evidence ``fused``, made good where it is not and the first type's own
    evidence ``own`` is, provided the fused m stands out at least ``min_distinct`` times
    (0: never); its distinctiveness is then the larger of the two."""
    if fused.good or not own.good or min_distinct <= 0 or fused.distinct < min_distinct:
        return fused
    return Evidence(fused.best_m, fused.background, max(fused.distinct, own.distinct), True,
                    vouched=True)


class DistinctnessMonitor:
    """Per-frame distinctiveness of the best match, with a smoothed background level."""

    def __init__(self, min_ratio: float, floor_m: float, far_m: float, alpha: float) -> None:
        self.min_ratio = min_ratio
        self.floor_m = floor_m
        self.far_m = far_m
        self.alpha = alpha
        self.background: float | None = None

    def reset(self) -> None:
        self.background = None

    def judge(self, positions: np.ndarray, scores: np.ndarray, estimate: np.ndarray,
              near_m: float) -> Evidence:
        """``positions`` (k, 2) and similarities (k,) of the images compared in this frame;
        the best match is taken within ``near_m`` of the ``estimate``: what counts is whether
        the place the service reports stands out, not whether any scout found something."""
        d = np.linalg.norm(positions - np.asarray(estimate, float), axis=1)
        near = d <= near_m
        if not near.any():
            return Evidence(0.0, self.background or 0.0, 0.0, False)
        best = float(scores[near].max())
        far = d > self.far_m
        if far.sum() >= 2:
            level = float(np.median(scores[far]))
            self.background = level if self.background is None else \
                (1 - self.alpha) * self.background + self.alpha * level
        bg = self.background if self.background is not None else 0.0
        # the background of weak frames is itself near zero: floor it at a fraction of the
        # absolute floor so that a ratio of two tiny numbers never counts as distinct
        distinct = best / max(bg, 0.25 * self.floor_m)
        good = best >= self.floor_m and distinct >= self.min_ratio
        return Evidence(best, bg, distinct, good)
