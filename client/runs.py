"""One run of the papers' protocol (journal Sec. 6-7) and its metrics, for replays and the lab.

A round is replayed against a map from a chosen start image (wrapping around the loop), at a
simulated speed (every k-th image, or each image repeated), optionally kidnapped at the
middle of the run (image index + n/2). ``Run`` is the one record of such a run, whether its
frames went through a transport (``client.replay``) or straight into an estimator in process
(``client.lab.experiments``); ``run_metrics`` is the one place its numbers are computed.
Light: NumPy only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from service.api.models import Estimate, Odometry

#: statuses in which an estimator admits it does not know where it is
BAD_STATUS = ("recovering", "lost")
#: an error above this is "badly wrong" (honesty: such frames should be reported as bad), m
WRONG_M = 10.0


def frame_sequence(n: int, start: int = 0, speed: float = 1.0, kidnap: bool = False,
                   length: int | None = None) -> np.ndarray:
    """Query image indices of one run (Sec. 6-7.1).

    ``speed`` k > 1 uses every k-th image; 1/r repeats each image r times. ``kidnap`` adds
    n/2 to the image index from the middle of the run on.
    """
    length = length or n
    if speed >= 1:
        seq = start + np.arange(length) * round(speed)
    else:
        seq = start + np.arange(length) // round(1 / speed)
    seq = seq % n
    if kidnap:
        seq[length // 2 :] = (seq[length // 2 :] + n // 2) % n
    return seq


def odometry_along(odom: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """The odometry poses (x, y, yaw) a robot sends along a run's ``frames``, from a round's
    odometry poses ``odom`` (N, 3): each frame's step is the round's step into its image from
    the previous frame's; where the run jumps (the kidnap, the loop's wrap) the wheels saw
    only the round's ordinary step into the new image (from the image one stride before it;
    at the loop's start, the last step of the round), never the jump."""
    n = len(odom)
    frames = np.asarray(frames)
    out = np.zeros((len(frames), 3))
    diffs = np.diff(frames)
    forward = diffs[(diffs > 0) & (diffs < n // 4)]
    stride = int(np.median(forward)) if len(forward) else 1
    for k in range(1, len(frames)):
        q, a = int(frames[k]), int(frames[k - 1])
        if q == a:  # the same image again: standing
            out[k] = out[k - 1]
            continue
        if not 0 < q - a < n // 4:  # a jump: the wheels saw an ordinary step
            a = q - stride
            if a < 0:
                a, q = n - 1 - stride, n - 1
        out[k] = _compose(out[k - 1], _relative(odom[a], odom[q]))
    return out


def odometry_poses(odom: np.ndarray | None, frames: np.ndarray) -> list[Odometry | None]:
    """The odometry pose a robot sends with each of a run's ``frames`` (``odometry_along``
    of a round's odometry poses ``odom``), or None for each where the round has none."""
    from service.api.models import Odometry

    if odom is None:
        return [None] * len(frames)
    along = odometry_along(odom, frames)
    return [Odometry(x=float(x), y=float(y), yaw=float(a)) for x, y, a in along]


def _relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose ``b`` in the body frame of pose ``a`` (x, y, yaw)."""
    c, s = np.cos(a[2]), np.sin(a[2])
    d = b[:2] - a[:2]
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], b[2] - a[2]])


def _compose(a: np.ndarray, step: np.ndarray) -> np.ndarray:
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([a[0] + c * step[0] - s * step[1], a[1] + s * step[0] + c * step[1],
                     a[2] + step[2]])


def true_speed(xy: np.ndarray, dt: float) -> np.ndarray:
    """Speed (m/s) between consecutive iterations; the first repeats the second."""
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    return np.concatenate([step[:1] if len(step) else [0.0], step]) / dt


def frames_until_within(err: np.ndarray, since: int, within_m: float = 5.0, hold: int = 5
                        ) -> int | None:
    """Iterations from ``since`` until the error stays within ``within_m`` for ``hold``
    frames in a row; None if it never does."""
    ok = err[since:] <= within_m
    for i in range(len(ok) - hold + 1):
        if ok[i : i + hold].all():
            return i
    return None


@dataclass
class Run:
    """What the estimator answered for every frame of one run, beside the truth."""

    estimator: str
    start: int  # first image
    seed: int
    frames: np.ndarray  # (N,) image index per iteration
    true_xy: np.ndarray  # (N, 2) m
    dt: float  # s between frames
    kidnap: bool
    est_xy: np.ndarray  # (N, 2) m
    status: list[str]
    comparisons: np.ndarray  # (N,) map images compared
    speed: np.ndarray  # (N,) estimated m/s
    heading: np.ndarray  # (N,) rad
    scores: np.ndarray  # (N,) best similarity m
    accuracy_m: np.ndarray  # (N,) 68 % radius
    lost: np.ndarray  # (N,) bool
    # per frame, ms: the round trip the client saw (replay), or the estimator's step with
    # feature extraction excluded (in process)
    latency_ms: np.ndarray
    estimates: list[Estimate] = field(default_factory=list)  # as received (replay only)
    located: np.ndarray | None = None  # (N,) bool: located by two-view geometry (in process)
    heading_sources: list[str] | None = None  # (N,) what each heading is (in process)

    @classmethod
    def from_estimates(cls, estimates: Sequence[Estimate], *, estimator: str, start: int,
                       seed: int, frames: np.ndarray, true_xy: np.ndarray, dt: float,
                       kidnap: bool, latency_ms: np.ndarray) -> Run:
        e = list(estimates)
        return cls(
            estimator=estimator, start=start, seed=seed, frames=np.asarray(frames),
            true_xy=np.asarray(true_xy, float), dt=dt, kidnap=kidnap,
            est_xy=np.array([[v.x, v.y] for v in e], float).reshape(-1, 2),
            status=[v.status for v in e],
            comparisons=np.array([v.comparisons for v in e], np.int64),
            speed=np.array([v.speed for v in e], float),
            heading=np.array([v.heading for v in e], float),
            scores=np.array([v.score for v in e], float),
            accuracy_m=np.array([v.accuracy_m for v in e], float),
            lost=np.array([v.lost for v in e], bool),
            latency_ms=np.asarray(latency_ms, float), estimates=e)

    @property
    def errors(self) -> np.ndarray:
        return np.linalg.norm(self.est_xy - self.true_xy, axis=1)

    @property
    def true_speed(self) -> np.ndarray:
        return true_speed(self.true_xy, self.dt)


def episodes(flags: np.ndarray) -> list[tuple[int, int]]:
    """(start, length) of runs of True."""
    out, start = [], None
    for i, f in enumerate(flags):
        if f and start is None:
            start = i
        elif not f and start is not None:
            out.append((start, i - start))
            start = None
    if start is not None:
        out.append((start, len(flags) - start))
    return out


def frames_to_recover(run: Run, within_m: float = 5.0, hold: int = 5) -> int | None:
    """Iterations after the kidnapping (middle of the run) until back within ``within_m``."""
    return frames_until_within(run.errors, len(run.errors) // 2, within_m, hold)


def run_metrics(run: Run, warmup: int = 0) -> dict[str, Any]:
    """The metrics of one run. Error, share, comparison, latency, status and speed figures
    use the frames after ``warmup``; convergence and kidnap recovery the whole run. A value
    that is undefined for the run (e.g. calibration without a tracked frame) is None."""
    err_all = run.errors
    err = err_all[warmup:]
    status = np.array(run.status[warmup:])
    comps = run.comparisons[warmup:].astype(float)
    speed = run.speed[warmup:]
    latency = run.latency_ms[warmup:]
    tracking = status == "tracking"
    speed_true = run.true_speed
    speed_true_w = speed_true[warmup:]
    admits = np.isin(status, BAD_STATUS)
    eps = episodes(admits)
    wrong = err > WRONG_M
    m: dict[str, Any] = {
        "frames": len(err),
        "error_mean_m": float(err.mean()),
        "error_std_m": float(err.std()),
        "error_median_m": float(np.median(err)),
        "error_p95_m": float(np.percentile(err, 95)),
        "within_2m": float(np.mean(err <= 2.0)),
        "within_5m": float(np.mean(err <= 5.0)),
        "comparisons_per_frame": float(comps.mean()),
        "latency_p50_ms": float(np.percentile(latency, 50)),
        "latency_p95_ms": float(np.percentile(latency, 95)),
        "latency_p99_ms": float(np.percentile(latency, 99)),
        "speed_true_mps": float(np.median(speed_true)),
        "speed_error_mps": float(np.mean(np.abs(speed[tracking] - speed_true_w[tracking])))
        if tracking.any() else None,
        "speed_error_rel": float(abs(np.median(speed[tracking]) / np.median(speed_true) - 1))
        if tracking.any() and np.median(speed_true) > 0 else None,
        "status_frames": {s: int(np.sum(status == s)) for s in sorted(set(status.tolist()))},
        "bad_status_share": float(np.mean(admits)),
        "calibration": float(np.mean(err[tracking] <= run.accuracy_m[warmup:][tracking]))
        if tracking.any() and len(run.accuracy_m) else None,
        "honesty": float(np.mean(admits[wrong])) if wrong.any() else None,
        "recoveries": len(eps),
        "recovery_frames_median": float(np.median([n for _, n in eps])) if eps else 0.0,
        "converged_after_frames": frames_until_within(err_all, 0),
    }
    if run.kidnap:
        m["kidnap_recover_frames"] = frames_until_within(err_all, len(err_all) // 2)
    return m


#: metrics averaged over runs by ``summarize``
AGG_KEYS = ("error_mean_m", "error_std_m", "error_median_m", "error_p95_m", "within_2m",
            "within_5m", "comparisons_per_frame", "latency_p50_ms", "latency_p95_ms",
            "latency_p99_ms", "speed_error_mps", "speed_error_rel", "bad_status_share",
            "calibration", "honesty", "recoveries")


def summarize(per_run: list[dict[str, Any]]) -> dict[str, Any]:
    """Means over runs of the per-run metrics (None where no run defines one); the spread of
    the per-run mean errors; kidnap recovery counted over runs."""
    out: dict[str, Any] = {"runs": len(per_run)}
    for k in AGG_KEYS:
        vals = [r[k] for r in per_run if r.get(k) is not None]
        out[k] = float(np.mean(vals)) if vals else None
    out["error_mean_std_m"] = float(np.std([r["error_mean_m"] for r in per_run])) \
        if per_run else None
    if per_run and "kidnap_recover_frames" in per_run[0]:
        rec = [r["kidnap_recover_frames"] for r in per_run]
        out["kidnap_recovered"] = sum(r is not None for r in rec)
        done = [r for r in rec if r is not None]
        out["kidnap_recover_frames_median"] = float(np.median(done)) if done else None
    return out
