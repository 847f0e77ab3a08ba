"""Wheel odometry as evidence of motion: the step between two frames and the map's heading.

The robot sends its pose in its own odometry frame (nav2's ``odom->base_link``); the engine
turns two consecutive poses into ``OdomStep``, the motion in the robot's body frame at the
previous frame (forward, left, turn), which no choice of odometry origin changes.

To move particles in the map by that step, the estimator needs the robot's heading in the
map. ``OdomHeading`` keeps the odometry integrated from the session's first step (its own
dead-reckoned frame) and fits the rotation between that frame and the map from the places
the images located the robot at: the rotation that best maps the dead-reckoned positions
onto the image estimates (a weighted 2-D Procrustes fit with scale, Umeyama 1991; recent
travel weighted more, so the odometry's heading drift is followed; the scale corrects the
odometry's scale error). The map heading is then the dead-reckoned yaw plus
that rotation. Until the fit has seen ``min_span_m`` of travel, the heading is the direction
of motion the estimator tracks, with a wide uncertainty.

Odometry never says where the robot is: it moves hypotheses, it never makes one. A place
the images keep contradicting is still left (the estimators' scouts and lost detection see
to that), and the fit forgets the old place's positions within a few ``tau_m``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from service.api.geo import wrap_angle
from service.estimators.odom_drift import DriftRate

# the direction of motion as a heading: its std (rad) when no odometry fit is there yet
MOTION_HEADING_SIGMA = math.radians(20.0)


@dataclass(frozen=True)
class OdomStep:
    """The robot's motion since the previous frame, in its body frame at that frame."""

    forward: float  # m
    left: float  # m
    turn: float  # rad, counter-clockwise
    var_xy: float  # position variance per metre travelled, m^2/m
    var_yaw: float  # heading variance per metre travelled, rad^2/m

    @property
    def distance(self) -> float:
        return math.hypot(self.forward, self.left)

    @property
    def sigma_xy(self) -> float:
        """Std (m) of this step's position in each axis."""
        return math.sqrt(self.var_xy * self.distance)


def body_step(prev: tuple[float, float, float], cur: tuple[float, float, float],
              var_xy: float, var_yaw: float) -> OdomStep:
    """The step from odometry pose ``prev`` (x, y, yaw) to ``cur``, in ``prev``'s body
    frame (odom->base_link at the previous frame inverted, composed with the current)."""
    dx, dy = cur[0] - prev[0], cur[1] - prev[1]
    c, s = math.cos(prev[2]), math.sin(prev[2])
    return OdomStep(c * dx + s * dy, -s * dx + c * dy, wrap_angle(cur[2] - prev[2]),
                    var_xy, var_yaw)


class OdomHeading:
    """The robot's heading in the map from odometry and the image estimates."""

    tau_m = 12.0  # travel over which a pair's weight falls by e
    min_span_m = 3.0  # rms spread of the dead-reckoned points a fit needs
    keep = 200  # pairs kept at most
    # class-level starts too: a session state stored before the camera's yaw was fused
    # (service/engine/state_codec.py) restores without them
    seen: float | None = None
    seen_var = 0.0
    # the odometry's heading drift from the located yaws (service/estimators/odom_drift.py;
    # None until the first, or with odom_drift off) and the raw dead-reckoned yaw it is
    # measured against (rad); class-level for a state stored before them
    drift: DriftRate | None = None
    raw_yaw = 0.0

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.pose = np.zeros(3)  # dead-reckoned (x, y, yaw) in the session's odometry frame
        self.travelled = 0.0  # m of odometry since the first step
        self.pairs = np.zeros((0, 5))  # (travelled, odom x, odom y, map x, map y)
        self.offset: float | None = None  # map yaw - dead-reckoned yaw, rad
        self.offset_sigma = math.pi  # its std, rad
        self.scale = 1.0  # map metres per odometry metre, from the same fit
        # the offset seen by the located camera's yaw (a Kalman filter over located frames;
        # its variance grows with the odometry's drift between them); None: none seen
        self.seen: float | None = None
        self.seen_var = 0.0
        self.drift = None
        self.raw_yaw = 0.0

    def advance(self, step: OdomStep) -> None:
        """Integrate one step into the dead-reckoned pose, its turn corrected by the
        estimated drift where there is one."""
        x, y, yaw = self.pose
        c, s = math.cos(yaw), math.sin(yaw)
        turn = step.turn
        if self.drift is not None:
            turn -= self.drift.drift * step.distance
            self.drift.advance(step.distance)
        self.raw_yaw = wrap_angle(self.raw_yaw + step.turn)
        self.pose = np.array([x + c * step.forward - s * step.left,
                              y + s * step.forward + c * step.left,
                              wrap_angle(yaw + turn)])
        self.travelled += step.distance
        if self.seen is not None:
            self.seen_var += step.var_yaw * step.distance
        if self.offset is not None:  # the odometry's heading drifts while no fit corrects it
            self.offset_sigma = math.hypot(self.offset_sigma,
                                           math.sqrt(step.var_yaw * step.distance))

    def heading(self, motion_heading: float | None) -> tuple[float | None, float]:
        """(map heading of the robot now, its std): from the fit and the camera's yaw where
        there are (weighted by their variances), else the tracked direction of motion (None
        where there is none either)."""
        offset, sigma = self.offset, self.offset_sigma
        if self.seen is not None:
            if offset is None:
                offset, sigma = self.seen, math.sqrt(self.seen_var)
            else:
                v_fit = sigma * sigma
                w = v_fit / (v_fit + self.seen_var)
                offset = offset + w * wrap_angle(self.seen - offset)
                sigma = math.sqrt(v_fit * self.seen_var / (v_fit + self.seen_var))
        if offset is not None:
            return wrap_angle(float(self.pose[2]) + offset), sigma
        return motion_heading, MOTION_HEADING_SIGMA

    def look(self, heading: float, sigma: float, drift: bool = False) -> None:
        """The located camera's yaw ``heading`` (std ``sigma``) at the current pose: a direct
        measurement of the offset between the dead-reckoned yaw and the map's; with
        ``drift``, also of the odometry's heading drift (``DriftRate``)."""
        if drift:
            if self.drift is None:
                self.drift = DriftRate()
            self.drift.look(wrap_angle(heading - self.raw_yaw), sigma)
        z = wrap_angle(heading - float(self.pose[2]))
        if self.seen is None:
            self.seen, self.seen_var = z, sigma * sigma
            return
        gain = self.seen_var / (self.seen_var + sigma * sigma)
        self.seen = wrap_angle(self.seen + gain * wrap_angle(z - self.seen))
        self.seen_var = (1.0 - gain) * self.seen_var

    def displacement(self, step: OdomStep, motion_heading: float | None
                     ) -> tuple[np.ndarray, float]:
        """The step in the map frame (m) and the std (m, per axis) of where it ends: the
        odometry's own noise and the heading's uncertainty over the step's length. Call
        before ``advance`` (the step starts at the previous pose's heading)."""
        heading, sigma = self.heading(motion_heading)
        if heading is None:  # no direction known: the step only spreads the particles
            return np.zeros(2), step.distance + step.sigma_xy
        c, s = math.cos(heading), math.sin(heading)
        d = self.scale * np.array([c * step.forward - s * step.left,
                                   s * step.forward + c * step.left])
        return d, math.hypot(step.sigma_xy, step.distance * min(sigma, 1.0))

    def observe(self, xy: np.ndarray) -> None:
        """The images located the robot at ``xy`` (map frame) at the current pose: refit."""
        row = np.array([[self.travelled, self.pose[0], self.pose[1], float(xy[0]),
                         float(xy[1])]])
        pairs = np.concatenate([self.pairs, row])[-self.keep:]
        self.pairs = pairs[self.travelled - pairs[:, 0] <= 4.0 * self.tau_m]
        self._fit()

    def forget(self) -> None:
        """The place was lost: the pairs may belong to a wrong place; the drift since the
        last fit is kept as the heading's uncertainty."""
        self.pairs = np.zeros((0, 5))
        self.seen = None

    def restart(self) -> None:
        """The estimate jumped far from where the odometry carried it (a kidnap): the map
        heading fitted at the old place says nothing of the new one, so the direction of
        motion stands in until a new fit."""
        self.forget()
        self.offset, self.offset_sigma = None, math.pi
        if self.drift is not None:  # the wheels did not see the jump: their drift holds
            self.drift.restart()

    def _fit(self) -> None:
        p = self.pairs
        if len(p) < 3:
            return
        w = np.exp(-(self.travelled - p[:, 0]) / self.tau_m)
        w = w / w.sum()
        a, b = p[:, 1:3], p[:, 3:5]
        a = a - w @ a
        b = b - w @ b
        span = math.sqrt(float(w @ np.einsum("ij,ij->i", a, a)))
        if span < self.min_span_m:
            return
        dot = float(w @ np.einsum("ij,ij->i", a, b))
        cross = float(w @ (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
        theta = math.atan2(cross, dot)
        # the odometry's scale error (wheel circumference): the similarity transform's scale
        self.scale = float(np.clip(math.hypot(dot, cross) / (span * span), 0.8, 1.25))
        # residual scatter of the fit across the dead-reckoned spread gives its std
        c, s = math.cos(theta), math.sin(theta)
        rot = self.scale * (a @ np.array([[c, s], [-s, c]]))
        resid = math.sqrt(float(w @ np.einsum("ij,ij->i", b - rot, b - rot)))
        n_eff = 1.0 / float(w @ w)
        self.offset = theta
        self.offset_sigma = max(resid / (span * math.sqrt(n_eff)), math.radians(0.5))


class LocatedGate:
    """Whether a frame the geometry located is taken while the odometry carries the
    estimate: a located position farther than ``gate_m`` from where the odometry predicts the
    robot is held back, unless the previous one held back (at most ``keep_frames`` frames
    old) lies within the odometry's distance travelled since plus half the gate (distance
    only: after a kidnap the odometry's map heading is wrong). One wrong match (an
    unmatchable stretch's look-alike image) then moves nothing; images that keep saying
    another place (the odometry's drift, a kidnap) are taken at the second frame, and then
    in full (``moved``: the reported position restarts there, the heading fit forgets).

    A move can be wrong: two frames in a row located at the same look-alike agree with each
    other. For ``keep_frames`` frames after a move, the track the odometry carried before it
    is kept (as its offset from the new track: the same odometry steps move both); a
    located frame that contradicts the new track but lies within ``gate_m`` of the old one
    undoes the move (one located frame and the odometry's track against the two frames
    that made it)."""

    keep_frames = 5
    # class defaults: a gate stored by a version without the undo (a durable session from
    # before it) reads these until its first move
    undo: np.ndarray | None = None  # the track before the last move, from the prediction (m)
    undo_age = 0  # frames since the move

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._clear_pending()
        self.undo = None
        self.undo_age = 0

    def _clear_pending(self) -> None:
        self.pending: np.ndarray | None = None  # the last located position held back, m
        self.pending_age = 0  # frames since
        self.pending_travel = 0.0  # odometry distance travelled since, m
        self.moved = False  # this frame's located position was taken as a move

    def admit(self, located: np.ndarray | None, predicted: np.ndarray | None,
              travel: float, gate_m: float) -> bool:
        """Whether ``located`` (None: the frame was not located) is taken, given the
        odometry's prediction ``predicted`` (None: none) and this frame's odometry distance
        ``travel`` (m); call once per frame with odometry."""
        self.moved = False
        if self.pending is not None:
            self.pending_age += 1
            self.pending_travel += travel
            if self.pending_age > self.keep_frames:
                self._clear_pending()
        if self.undo is not None:
            self.undo_age += 1
            if self.undo_age > self.keep_frames:
                self.undo = None
        if located is None or predicted is None or gate_m <= 0:
            return True
        if float(np.linalg.norm(located - predicted)) <= gate_m:
            return True
        if self.undo is not None and \
                float(np.linalg.norm(located - (predicted + self.undo))) <= gate_m:
            self._clear_pending()  # back on the track the odometry carried before the move
            self.undo, self.moved = None, True
            return True
        if self.pending is not None and float(np.linalg.norm(located - self.pending)) \
                <= self.pending_travel + 0.5 * gate_m:
            self._clear_pending()
            self.undo, self.undo_age = predicted - located, 0
            self.moved = True
            return True
        self.pending, self.pending_age, self.pending_travel = np.array(located, float), 0, 0.0
        return False
