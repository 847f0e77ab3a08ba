"""Along-track smoothing of the reported position (an alpha-beta filter along the map's path).

The image estimate of one frame scatters along the route: neighbouring map images look alike
in the direction of travel, while across it the scene shifts and the images tell the place
sharply. A particle filter averages that scatter through its motion model; the swarm's
estimate is one frame's. This filter predicts the position with its own velocity and takes
the measurement's correction in full across the path but only ``alpha`` of it along the path
(the map's direction at the measurement, from the nearest image and its neighbours), so it
lags less at a turn than a two-dimensional smoother does. The velocity takes
beta = alpha^2 / (2 - alpha) of the correction (the Benedict-Bordner pairing of an alpha-beta
tracker), so a robot that speeds up is followed within a few frames. A correction longer
than ``gate_m`` restarts it at the measurement: a jump the swarm makes is reported at once.

It smooths the reported position only; the swarm and its tracked velocity see the raw
estimate.
"""

from __future__ import annotations

import numpy as np


def path_tangent(positions: np.ndarray, nearest: int, spacing: float) -> np.ndarray | None:
    """Unit direction of the map's path at image ``nearest``: towards its successor from its
    predecessor, where they lie within four spacings (a neighbour in the id order farther
    away belongs to another traversal or a gap); None where neither does."""
    here = positions[nearest]

    def neighbour(j: int) -> np.ndarray:
        near = 0 <= j < len(positions) and \
            float(np.linalg.norm(positions[j] - here)) <= 4.0 * spacing
        return positions[j] if near else here

    a, b = neighbour(nearest - 1), neighbour(nearest + 1)
    d = b - a
    norm = float(np.linalg.norm(d))
    return d / norm if norm > 0 else None


def along_path(at: np.ndarray, tangent: np.ndarray, right_m: float, ahead_m: float
               ) -> np.ndarray:
    """The point ``right_m`` right of ``at`` and ``ahead_m`` ahead of it along the unit
    direction ``tangent`` (the map's path there)."""
    right = np.array([tangent[1], -tangent[0]])
    return np.asarray(at + right_m * right + ahead_m * tangent, float)


def located_position(positions: np.ndarray, image: int, right_m: float, ahead_m: float,
                     spacing: float) -> np.ndarray | None:
    """A camera ``right_m`` right of map image ``image`` and ``ahead_m`` ahead of it along the
    map's path there (``path_tangent``): its position in the map; None where the path has no
    direction there."""
    tangent = path_tangent(positions, image, spacing)
    return None if tangent is None else along_path(positions[image], tangent, right_m, ahead_m)


def path_tangents(positions: np.ndarray, ids: np.ndarray, spacing: float) -> np.ndarray:
    """``path_tangent`` at each image ``ids`` (n, 2): a zero row where it has none."""
    out = np.zeros((len(ids), 2))
    for k, i in enumerate(np.asarray(ids, np.int64)):
        d = path_tangent(positions, int(i), spacing)
        if d is not None:
            out[k] = d
    return out


class AlongTrackSmoother:
    """State of the filter: the smoothed position and its velocity (m per frame)."""

    # frames carried by odometry alone since the last update (``carry``); a class default
    # too, so a smoother stored before it existed (a durable session) restores with none
    carried = 0

    def __init__(self) -> None:
        self.position: np.ndarray | None = None
        self.velocity = np.zeros(2)
        self.carried = 0

    def reset(self) -> None:
        self.position = None
        self.velocity = np.zeros(2)
        self.carried = 0

    def carry(self, motion: np.ndarray) -> np.ndarray:
        """The position moved by ``motion`` (m, an odometry step) with no measurement; call
        only where there is a position (``predicted`` is not None)."""
        assert self.position is not None
        self.position = self.position + motion
        self.carried += 1
        return self.position.copy()

    def update(self, z: np.ndarray, tangent: np.ndarray | None, alpha: float, gate_m: float,
               velocity: np.ndarray | None = None, motion: np.ndarray | None = None,
               across: float = 1.0, hold: bool = False) -> np.ndarray:
        """The smoothed position for measurement ``z`` (m); ``tangent``: the path's unit
        direction there (None: no path, the measurement is taken in full); ``velocity``:
        the tracked velocity (m per frame) a restart starts from (None: standing).
        ``motion``: the step measured by odometry (m), which predicts instead of the
        filter's own velocity; ``across``: the share of the correction across the path
        taken; ``hold``: a correction beyond the gate is not taken (the prediction stands)
        instead of restarting at the measurement."""
        z = np.asarray(z, float)
        self.carried = 0
        if self.position is None or tangent is None:
            return self._restart(z, velocity)
        predicted = self.position + (self.velocity if motion is None else motion)
        r = z - predicted
        if float(np.linalg.norm(r)) > gate_m:
            if hold:
                self.position = predicted
                return predicted.copy()
            return self._restart(z, velocity)
        along = float(r @ tangent) * tangent
        self.position = predicted + alpha * along + across * (r - along)
        self.velocity = self.velocity + alpha * alpha / (2.0 - alpha) * r
        return self.position.copy()

    def predicted(self, motion: np.ndarray) -> np.ndarray | None:
        """Where the filter's position moves by ``motion`` (m); None before it has one."""
        return None if self.position is None else self.position + motion

    def _restart(self, z: np.ndarray, velocity: np.ndarray | None) -> np.ndarray:
        self.position = z.copy()
        self.velocity = np.zeros(2) if velocity is None else np.array(velocity, float)
        return z.copy()
