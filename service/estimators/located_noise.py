"""How sharply the geometry locates the camera in this session, from the located positions.

A located position (service/vision/metric_pose.py) is the map image's recorded position plus the
camera's offset from it. Two errors add up in it:

- the recorded position's, which no frame can see (a map's positions come from GPS or
  odometry; ``map_sigma_m`` says how far off they are);
- the offset's, which changes from frame to frame and grows where the light differs from
  the map's (fewer, poorer matches).

The second shows in the located positions themselves: over three consecutive frames the
robot moves nearly uniformly, so the second difference ``x[t+1] - 2 x[t] + x[t-1]`` is the
offsets' noise alone, with a per-axis std of sqrt(6) times theirs. Its median length over
the last ``window`` triples (robust to a wrong image now and then) gives that std. The
radius reported for a located frame is then sqrt(map_sigma_m^2 + (gain * jitter)^2) per
axis: the same light gets a tighter one than another light, measured rather than assumed.

With wheel odometry the reported position filters the located ones (the odometry predicts, a
located frame corrects a share of the difference), so only a share of the jitter is left in
it (``share``, the session's ``odom_jitter_share``): calibrated, because the located
positions' errors are correlated from frame to frame and an alpha filter's white-noise share,
sqrt(alpha / (2 - alpha)), left too narrow a radius (docs/research/lighting.md).
"""

from __future__ import annotations

import math

import numpy as np

# median length of a 2-D vector with independent N(0, s^2) axes is s * sqrt(2 ln 2); the
# second difference of iid positions has s = sqrt(6) * (their std)
_MEDIAN_PER_STD = math.sqrt(6.0) * math.sqrt(2.0 * math.log(2.0))


class LocatedNoise:
    """The located positions' frame-to-frame noise, over the last ``window`` triples."""

    def __init__(self, window: int = 64) -> None:
        self.window = window
        self.reset()

    def reset(self) -> None:
        self.recent: list[tuple[int, np.ndarray]] = []  # (frame, position), last two
        self.diffs: list[float] = []  # lengths of the second differences, newest last

    def add(self, frame: int, xy: np.ndarray) -> None:
        """The position located at frame number ``frame`` (frames counted by the caller)."""
        xy = np.asarray(xy, np.float64)
        if len(self.recent) == 2 and self.recent[0][0] == frame - 2 \
                and self.recent[1][0] == frame - 1:
            d = xy - 2.0 * self.recent[1][1] + self.recent[0][1]
            self.diffs = [*self.diffs, float(np.hypot(d[0], d[1]))][-self.window:]
        self.recent = [*self.recent, (frame, xy)][-2:]

    def jitter(self, prior: float, min_samples: int = 8) -> float:
        """Std (m) of a located position's frame-to-frame noise in each axis; ``prior``
        until ``min_samples`` triples were seen."""
        if len(self.diffs) < min_samples:
            return prior
        return float(np.median(self.diffs)) / _MEDIAN_PER_STD

    def sigma(self, map_sigma_m: float, gain: float, prior: float, share: float = 1.0
              ) -> float:
        """Std (m) of a located position in each axis; ``share``: of the jitter, what is left
        in the reported position (1: all)."""
        return math.hypot(map_sigma_m, gain * share * self.jitter(prior))
