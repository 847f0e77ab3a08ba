"""A far jump of the reported place is not ``tracking`` until the new place is confirmed.

While DPSO tracks, the reported position moves with the robot. When it lands farther than
``jump_hold_m`` from where the previous frame predicted it (the previous reported position
plus the tracked step per frame, or the odometry's step), the estimate has switched to
another sub-swarm's place. A kidnapped robot found again does that, and so does a swarm that
follows a look-alike place that matched a little better for a frame or two (at dusk such a
place holds for several frames while its matches still count as good). Both look the same
from one frame, so the new place has to earn ``tracking`` the way a start does: the status
says ``recovering`` until ``confirm_frames`` good frames in a row, or one good frame that the
two-view geometry located, have been seen since the jump (DPSO judges jumps from its first
convergence on: the global search before it has no place to leave). This is a report only:
the swarm, the reported position and the lost detection are untouched. Meanwhile
``accuracy_m`` is at least the jump's length, since the robot may be at either place.
"""

from __future__ import annotations

import numpy as np


def off_prediction(last: np.ndarray, now: np.ndarray, step: np.ndarray | None) -> float:
    """How far ``now`` lies from where ``last`` moved by the predicted ``step`` (None: no
    step known) puts it (m): a jump's length."""
    return float(np.linalg.norm(now - (last + (step if step is not None else 0.0))))


class JumpHold:
    """The jump being held (its length, 0 when none) and the good frames seen since."""

    def __init__(self) -> None:
        self.last: np.ndarray | None = None  # the previous frame's reported position
        self.distance = 0.0  # length of the jump being held (m); 0: none held
        self.good = 0  # good frames in a row since the jump

    def reset(self) -> None:
        self.last, self.distance, self.good = None, 0.0, 0

    def judge(self, reported: np.ndarray, step: np.ndarray | None, limit_m: float, good: bool,
              located: bool, confirm_frames: int) -> float:
        """The length of the jump held at this frame (m), 0.0 when none: ``reported`` is this
        frame's reported position, ``step`` the motion predicted since the previous one (None:
        none known), ``good`` whether the frame's evidence counts as good, ``located``
        whether the two-view geometry located it. ``limit_m`` 0 turns the hold off."""
        last, self.last = self.last, np.array(reported, float)
        if limit_m <= 0:
            self.distance, self.good = 0.0, 0
            return 0.0
        if last is not None:
            jump = off_prediction(last, reported, step)
            if jump > limit_m:
                self.distance, self.good = jump, 0
        self.good = self.good + 1 if good else 0
        if self.distance and (self.good >= confirm_frames or (good and located)):
            self.distance, self.good = 0.0, 0
        return self.distance
