"""Map image positions from GPS-like poses and wheel odometry.

A round's ``poses.csv`` positions come from GPS or something like it: right on average, but
off by a few decimetres that drift slowly (the rendered worlds: 0.3 m, correlated over about
ten images). Wheel odometry (``odometry.csv``) has the opposite errors: its shape over a few
metres is almost exact, but its scale and heading drift without bound. A map built from the
recorded poses carries their error into every estimate made against it (the error floor of
a perfect localizer is the map's own).

Each image's *fused* position is its odometry position mapped into the poses' frame by the
least-squares similarity (rotation, translation, scale: Umeyama's closed form) that aligns
the odometry of the images within ``window_m`` of travel on either side to their recorded
positions. The window averages out the poses' noise while the odometry's drift over it stays
small. On the rendered worlds (7 seeds x 5 rounds, mean distance from the truth) the
recorded positions are 0.37 m off, the fused ones 0.23 m with a 15 or 20 m window, 0.25 m
with 10 or 25 m and 0.43 m with 40 m (docs/research/lighting.md, "Map positions").

Where the odometry does not move over a window (a robot standing still), the image takes the
mean recorded position of that window. Odometry that disagrees with the poses (another
trajectory, a unit error) is not used: ``fuse_with_odometry`` reports how far the fit moved
the positions (at most ``MAX_MOVED_M``) and its scale (within ``SCALE_RANGE``). The check
is coarse: the alignment is local, so odometry of a similar shape fits.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal, Protocol, get_args

import numpy as np

_log = logging.getLogger(__name__)


WINDOW_M = 15.0  # metres of travel on either side of an image that its alignment uses
MAX_MOVED_M = 2.0  # a median move above this: the odometry does not fit the poses
SCALE_RANGE = (0.8, 1.25)  # recorded metres per odometry metre (median over the windows)
# per-axis error of fused positions: their mean distance from the truth on the rendered
# worlds' 35 rounds, 0.23 m, as a 2-D Gaussian's sigma (mean = 1.25 sigma); the recorded
# ones' 0.37 m gives the 0.28 m the estimators assume by default (metric_map_sigma_m)
FUSED_SIGMA_M = 0.18
_MIN_SPREAD_M = 0.5  # odometry spread (rms) below which a window counts as standing still
PositionsRule = Literal["fused", "recorded"]
POSITIONS_RULES: tuple[str, ...] = get_args(PositionsRule)


class PlacedRound(Protocol):
    """What the positions of a round's images come from (``route_map.RoundLike``; its
    ``odometry``, (N, 3) x, y, yaw, is optional and read with ``getattr``)."""

    @property
    def name(self) -> str: ...
    @property
    def xy(self) -> np.ndarray: ...


@dataclass(frozen=True)
class FusedPositions:
    """The fused positions (N, 2), how far they lie from the recorded ones (median m) and
    the recorded metres per odometry metre (median over the windows; 1: both in metres)."""

    xy: np.ndarray
    moved_m: float
    scale: float = 1.0

    @property
    def fits(self) -> bool:
        """Whether the odometry agreed with the poses well enough to use the fused positions:
        in metres, and no farther from them than GPS-like noise."""
        lo, hi = SCALE_RANGE
        return bool(self.moved_m <= MAX_MOVED_M and lo <= self.scale <= hi)


def _window_sums(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Sums of ``values`` (N, ...) over the rows lo[k]:hi[k] for each k."""
    c = np.concatenate([np.zeros((1, *values.shape[1:])), np.cumsum(values, axis=0)])
    return c[hi] - c[lo]


def fuse_with_odometry(recorded_xy: np.ndarray, odometry_xy: np.ndarray,
                       window_m: float = WINDOW_M, known: np.ndarray | None = None
                       ) -> FusedPositions:
    """Each image's odometry position aligned to the recorded positions of the images within
    ``window_m`` of travel (see the module's docstring). Both arrays are (N, 2) in the same
    image order; the odometry in any frame of its own. ``known`` (N, bool): only these images
    have a recorded position (the others' rows are ignored, and they are placed by their
    odometry alone); an image whose window holds no known one, or known ones that do not
    spread (nothing to align its odometry with), gets NaN."""
    g = np.asarray(recorded_xy, np.float64)
    o = np.asarray(odometry_xy, np.float64)
    if g.shape != o.shape or g.ndim != 2 or g.shape[1] != 2:
        raise ValueError(f"positions {g.shape} and odometry {o.shape} must both be (N, 2)")
    if not window_m > 0:
        raise ValueError(f"the window must be positive, got {window_m}")
    w = np.ones(len(g)) if known is None else np.asarray(known, bool).astype(np.float64)
    if w.shape != (len(g),):
        raise ValueError(f"known {w.shape} must be ({len(g)},)")
    if w.sum() < 3:
        return FusedPositions(g.copy(), 0.0)
    g = np.where(w[:, None] > 0, g, 0.0)
    g0 = (g * w[:, None]).sum(axis=0) / w.sum()  # centred: the window sums stay well conditioned
    o0 = o.mean(axis=0)
    g, o = g - g0, o - o0
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(o, axis=0), axis=1))])
    lo = np.searchsorted(arc, arc - window_m, "left")
    hi = np.searchsorted(arc, arc + window_m, "right")
    counts = _window_sums(w, lo, hi)
    n = np.maximum(counts, 1.0)[:, None]
    wo, wg = o * w[:, None], g * w[:, None]
    mo = _window_sums(wo, lo, hi) / n
    mg = _window_sums(wg, lo, hi) / n
    # cross-covariance of the window, recorded x odometry: (N, 2, 2)
    cov = (_window_sums(wg[:, :, None] * o[:, None, :], lo, hi) / n[:, :, None]
           - mg[:, :, None] * mo[:, None, :])
    var_o = _window_sums((wo * o).sum(axis=1), lo, hi) / n[:, 0] - (mo * mo).sum(axis=1)
    u, s, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt))
    d[d == 0] = 1.0
    s[:, 1] *= d
    u[:, :, 1] *= d[:, None]  # U diag(1, d) Vt: a rotation, never a reflection
    rot = u @ vt
    moving = var_o > _MIN_SPREAD_M ** 2
    scale = np.where(moving, s.sum(axis=1) / np.where(moving, var_o, 1.0), 0.0)
    fused = mg + scale[:, None] * np.einsum("kij,kj->ki", rot, o - mo)
    fused += g0
    have = w > 0
    fused[(counts == 0) | (~have & ~moving)] = np.nan  # nothing known to align it with
    moved = float(np.median(np.linalg.norm(fused[have] - (g[have] + g0), axis=1)))
    return FusedPositions(fused, moved,
                          float(np.median(scale[moving])) if moving.any() else 1.0)


def round_positions(rnd: PlacedRound, rule: PositionsRule = "fused") -> tuple[np.ndarray, str]:
    """A round's image positions for a map, and how they were made: its recorded ones, or
    (rule ``fused``, a round with wheel odometry that fits them) its odometry aligned to
    them."""
    if rule not in POSITIONS_RULES:
        raise ValueError(f"unknown positions rule {rule!r}; choose one of {list(POSITIONS_RULES)}")
    xy = np.asarray(rnd.xy, float)
    odometry = getattr(rnd, "odometry", None)
    if rule == "recorded" or odometry is None:
        return xy, "recorded"
    if len(odometry) != len(xy):  # a round cut without its odometry: nothing to align
        return xy, "recorded (the odometry lists other images)"
    if len(xy) < 3:
        return xy, "recorded (too few images to align the odometry)"
    fused = fuse_with_odometry(xy, np.asarray(odometry, float)[:, :2])
    if not fused.fits:
        _log.warning("round %s: its odometry does not fit its poses (aligning it moves them "
                     "%.1f m, median, at %.2f recorded m per odometry m): the map keeps the "
                     "recorded positions", rnd.name, fused.moved_m, fused.scale)
        return xy, (f"recorded (the odometry did not fit: {fused.moved_m:.1f} m, scale "
                    f"{fused.scale:.2f})")
    return fused.xy, f"fused with odometry ({WINDOW_M:g} m window)"
