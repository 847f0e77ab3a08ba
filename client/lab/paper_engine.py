"""Many runs of the protocol at once: the papers' DPSO and the particle filters, vectorised.

The papers' protocol replays a query round from every test image as a start image (Sec. 6):
hundreds of runs of hundreds of frames per case. Stepping one estimator object per run costs
about 0.4-1 ms per frame in Python overhead. Here R runs advance together, every array carries
a leading run axis, and one frame of all runs is a few NumPy calls.

The arithmetic is that of ``service/estimators/paper_dpso.py`` (``DPSO``, journal Sec. 5,
``variant="paper"``) and ``service/estimators/particle_filter.py`` (PF-g, PF-l, Sec. 7.2), line
by line, and the random numbers
are drawn in the same order and shapes with a run axis in front: with one run and the same
seed the trajectories are the service's, bit for bit (tests/test_paper.py checks that).
With many runs, the runs share one generator (statistically the same, not the same numbers).

Nearest map images come from a raster of candidate images (the k nearest to each cell's
centre) refined by exact distances; cells where the candidates cannot be proven to contain the
nearest image (far from the route) fall back to the map's k-d tree. The result is exact.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.api.params import DPSOParams, PFParams
from service.estimators.registry import params_for

Arr = np.ndarray
GatherFn = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (q (R,), ids (R, N)) -> m (R, N)


class NearestGrid:
    """Exact nearest map image for many points: raster candidates + k-d tree fallback."""

    def __init__(self, positions: np.ndarray, cell_m: float = 0.3, margin_m: float = 12.0,
                 k: int = 10) -> None:
        from scipy.spatial import cKDTree

        self.pos = np.asarray(positions, float)
        self.tree = cKDTree(self.pos)
        self.cell = cell_m
        self.lo = self.pos.min(axis=0) - margin_m
        shape = np.ceil((self.pos.max(axis=0) + margin_m - self.lo) / cell_m).astype(int) + 1
        self.shape = (int(shape[0]), int(shape[1]))
        gx, gy = np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij")
        centres = self.lo + (np.stack([gx, gy], -1).reshape(-1, 2) + 0.5) * cell_m
        k = min(k, len(self.pos))
        dist, idx = self.tree.query(centres, k=k)
        dist, idx = dist.reshape(len(centres), k), idx.reshape(len(centres), k)
        # a point p of the cell is within h = half diagonal of the centre c; its nearest image
        # is within d1(c) + h of p, so within d1(c) + 2h of c: among the k candidates when the
        # k-th candidate is farther than that (or there are no more images)
        safe = (dist[:, -1] > dist[:, 0] + 2 * math.sqrt(2) * cell_m / 2) \
            | (k == len(self.pos))
        self.candidates = idx.astype(np.int16 if len(self.pos) < 2**15 else np.int32)  # compact
        self.safe = safe

    def __call__(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ids, distances) of the nearest map image for points of any shape (..., 2)."""
        shp = pts.shape[:-1]
        p = np.ascontiguousarray(pts.reshape(-1, 2), np.float64)
        ids = np.empty(len(p), np.int64)
        dist = np.empty(len(p))
        ok = np.empty(len(p), np.bool_)
        _kernel("nearest")(p, self.lo, self.cell, self.shape[0], self.shape[1], self.candidates,
                        self.safe, self.pos, ids, dist, ok)
        if not ok.all():
            bad = ~ok
            dist[bad], ids[bad] = self.tree.query(p[bad])
        return ids.reshape(shp), dist.reshape(shp)


def _nearest_kernel(p: Arr, lo: Arr, cell: float, nx: int, ny: int, cand: Arr, safe: Arr,
                    pos: Arr, ids: Arr, dist: Arr, ok: Arr) -> None:
    k = cand.shape[1]
    for i in range(p.shape[0]):
        cx = int(np.floor((p[i, 0] - lo[0]) / cell))
        cy = int(np.floor((p[i, 1] - lo[1]) / cell))
        if cx < 0 or cy < 0 or cx >= nx or cy >= ny:
            ok[i] = False
            continue
        c = cx * ny + cy
        ok[i] = safe[c]
        best = np.inf
        bj = 0
        for j in range(k):
            idx = cand[c, j]
            dx = pos[idx, 0] - p[i, 0]
            dy = pos[idx, 1] - p[i, 1]
            d2 = dx * dx + dy * dy
            if d2 < best:
                best = d2
                bj = idx
        ids[i] = bj
        dist[i] = np.sqrt(best)


def _distinct_kernel(ids: Arr, n_images: int, out: Arr) -> None:
    stamp = np.full(n_images, -1, np.int64)
    for r in range(ids.shape[0]):
        c = 0
        for j in range(ids.shape[1]):
            i = ids[r, j]
            if stamp[i] != r:
                stamp[i] = r
                c += 1
        out[r] = c


def _pf_linear_kernel(x: Arr, v: Arr, c: Arr, s: Arr, scale: Arr, dt: float) -> None:
    """Eqs. 7-8 in place, the operations of ``ParticleFilter._predict`` in the same order."""
    for r in range(x.shape[0]):
        for i in range(x.shape[1]):
            vx = v[r, i, 0]
            vy = v[r, i, 1]
            nvx = scale[r, i] * (c[r, i] * vx - s[r, i] * vy)
            nvy = scale[r, i] * (s[r, i] * vx + c[r, i] * vy)
            v[r, i, 0] = nvx
            v[r, i, 1] = nvy
            x[r, i, 0] = x[r, i, 0] + nvx * dt
            x[r, i, 1] = x[r, i, 1] + nvy * dt


def _pf_update_kernel(f: Arr, total: Arr, x: Arr, v: Arr, u0: Arr, est: Arr, spread: Arr,
                      x_new: Arr, v_new: Arr) -> None:
    """Weights, weighted-mean estimate, spread and low-variance resampling of every run
    (``ParticleFilter._step``; the cumulative sum and the search are those of NumPy)."""
    n = x.shape[1]
    w = np.empty(n)
    cum = np.empty(n)
    for r in range(x.shape[0]):
        tot = total[r]
        for i in range(n):
            w[i] = f[r, i] / tot if tot > 0 else 1.0 / n
        ex = 0.0
        ey = 0.0
        mx = 0.0
        my = 0.0
        for i in range(n):
            ex += w[i] * x[r, i, 0]
            ey += w[i] * x[r, i, 1]
            mx += x[r, i, 0]
            my += x[r, i, 1]
        est[r, 0] = ex
        est[r, 1] = ey
        mx /= n
        my /= n
        sp = 0.0
        for i in range(n):
            dx = x[r, i, 0] - mx
            dy = x[r, i, 1] - my
            sp += np.sqrt(dx * dx + dy * dy)
        spread[r] = sp / n
        acc = 0.0
        for i in range(n):
            acc += w[i]
            cum[i] = acc
        cum[n - 1] = 1.0
        j = 0
        for k in range(n):
            u = u0[r] + k / n
            while j < n - 1 and cum[j] < u:  # searchsorted(cum, u, side="left")
                j += 1
            x_new[r, k, 0] = x[r, j, 0]
            x_new[r, k, 1] = x[r, j, 1]
            v_new[r, k, 0] = v[r, j, 0]
            v_new[r, k, 1] = v[r, j, 1]


def _dpso_move_kernel(x: Arr, v: Arr, p_n: Arr, r0: Arr, r2: Arr, z: Arr, k: Arr, v0: Arr,
                      phi2: Arr, high: Arr, delta: Arr, lower: Arr, upper: Arr, omega: float,
                      phi0: float, high_factor: float, x_out: Arr, v_out: Arr) -> None:
    """``DPSO._move`` of every run, the operations of ``BatchDPSO.move`` in the same order
    (the random numbers drawn before, by NumPy)."""
    nv = np.empty(2)
    for r in range(x.shape[0]):
        for i in range(x.shape[1]):
            for d in range(2):
                a = omega * v[r, i, d]
                b = phi0 * r0[r, i, d] * delta[d] * v0[r]
                c = phi2[r] * r2[r, i, d] * (p_n[r, d] - x[r, i, d])
                nv[d] = a + b + c
            q0 = nv[0] / delta[0]
            q1 = nv[1] / delta[1]
            norm = np.sqrt(q0 * q0 + q1 * q1)
            limit = v0[r] * (high_factor if high[i] else 1.0)
            fac = min(1.0, limit / max(norm, 1e-12))
            for d in range(2):
                vd = nv[d] * fac
                xd = x[r, i, d] + vd
                if i < k[r]:
                    xd = p_n[r, d] + delta[d] * z[r, i, d]
                    vd = 0.0
                if xd < lower[d]:
                    xd = 2 * lower[d] - xd
                    vd = -vd
                elif xd > upper[d]:
                    xd = 2 * upper[d] - xd
                    vd = -vd
                x_out[r, i, d] = min(max(xd, lower[d]), upper[d])
                v_out[r, i, d] = vd


_SOURCES: dict[str, Callable[..., None]] = {
    "nearest": _nearest_kernel, "distinct": _distinct_kernel, "pf_linear": _pf_linear_kernel,
    "pf_update": _pf_update_kernel, "dpso_move": _dpso_move_kernel}
_COMPILED: dict[str, Callable[..., None]] = {}


def _kernel(name: str) -> Callable[..., None]:
    """A numba kernel of this module (compiled on first use, cached on disk)."""
    if name not in _COMPILED:
        from service.vision.matcher import _jit

        _COMPILED[name] = _jit(_SOURCES[name])
    return _COMPILED[name]


@dataclass
class BatchResult:
    """R runs of T frames."""

    estimator: str
    frames: np.ndarray  # (R, T) query image per iteration
    est_xy: np.ndarray  # (R, T, 2)
    true_xy: np.ndarray  # (R, T, 2)
    comparisons: np.ndarray  # (R, T) distinct map images compared per frame
    spread_m: np.ndarray  # (R, T) mean distance of particles to their centre

    @property
    def errors(self) -> np.ndarray:
        return np.linalg.norm(self.est_xy - self.true_xy, axis=-1)


def distinct_per_row(ids: np.ndarray, n_images: int) -> np.ndarray:
    """Number of distinct values in each row of an (R, N) id array."""
    out = np.empty(ids.shape[0], np.int64)
    _kernel("distinct")(np.ascontiguousarray(ids), n_images, out)
    return out


class _Common:
    """Status counters of ``Estimator.update_status`` and the EMA of ``frame_dt`` /
    ``track_motion`` for R runs."""

    def __init__(self, positions: np.ndarray, p: Any, r: int) -> None:
        self.pos = np.asarray(positions, float)
        self.p = p
        self.r = r
        self.bad = np.zeros(r, np.int64)
        self.good = np.zeros(r, np.int64)
        self.converged = np.zeros(r, bool)
        self.point_prev: np.ndarray | None = None
        self.ema_step: np.ndarray | None = None  # (R, 2) metres per frame
        self.last_t: float | None = None

    def frame_dt(self, t: float) -> float:
        dt = self.p.default_dt_s
        if self.last_t is not None and t > self.last_t:
            dt = t - self.last_t
        self.last_t = t
        return dt

    def track_motion(self, point: np.ndarray) -> None:
        if self.point_prev is not None:
            d = point - self.point_prev
            a = self.p.ema_alpha
            self.ema_step = d.copy() if self.ema_step is None else \
                (1 - a) * self.ema_step + a * d
        self.point_prev = np.array(point, float)

    def update_status(self, best_m: np.ndarray) -> np.ndarray:
        """Lost flag per run (the papers' absolute trigger)."""
        p = self.p
        low = best_m < p.lost_threshold
        self.bad = np.where(low, self.bad + 1, 0)
        self.good = np.where(low, 0, self.good + 1)
        self.converged |= self.good >= p.converge_frames
        return self.bad >= p.lost_frames

    def sample_map_positions(self, rng: np.random.Generator, n: int) -> np.ndarray:
        ids = rng.integers(0, len(self.pos), (self.r, n))
        return self.pos[ids] + rng.normal(0, self.p.init_spread_m, (self.r, n, 2))


class BatchDPSO(_Common):
    """``service.estimators.paper_dpso.DPSO`` (the journal's DPSO) for R runs at once."""

    def __init__(self, positions: np.ndarray, p: DPSOParams, r: int,
                 rng: np.random.Generator) -> None:
        super().__init__(positions, p, r)
        self.rng = rng
        pos = self.pos
        self.delta = np.maximum(pos.max(axis=0) - pos.min(axis=0), p.min_axis_range_m)
        self.lower = pos.min(axis=0) - 0.1 * self.delta
        self.upper = pos.max(axis=0) + 0.1 * self.delta
        n = p.n_particles
        self.high_energy = np.arange(n) >= n - round(p.high_energy_ratio * n)
        # _initialize
        self.x = self.sample_map_positions(rng, n)
        ang = rng.uniform(0, 2 * math.pi, (r, n))
        mag = rng.uniform(0, 1, (r, n)) * p.v0
        self.v = np.stack([np.cos(ang), np.sin(ang)], -1) * mag[..., None] * self.delta
        self.v0 = np.full(r, p.v0)
        self.q_r = np.full(r, p.quantum_ratio)
        self.phi2 = np.full(r, p.phi2)
        self.recovering = np.zeros(r, bool)
        self.v0_before = np.full(r, p.v0)

    def step(self, fitness: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], t: float
             ) -> tuple[np.ndarray, np.ndarray]:
        """One frame of every run: (estimate (R, 2), spread (R,))."""
        self.frame_dt(t)
        f, m = fitness(self.x)
        best = np.argmax(f, axis=1)
        rr = np.arange(self.r)
        p_n = self.x[rr, best].copy()
        best_m = m.max(axis=1)
        centre = self.x.mean(axis=1)
        spread = np.linalg.norm(self.x - centre[:, None], axis=-1).mean(axis=1)
        total = f.sum(axis=1)
        wc = np.einsum("rn,rnk->rk", f, self.x) / np.where(total > 0, total, 1.0)[:, None]
        self.track_motion(np.where((total > 0)[:, None], wc, centre))
        lost = self.update_status(best_m)
        self.recovery_phase(lost)
        self.move(p_n)
        return p_n, spread

    def recovery_phase(self, lost: np.ndarray) -> None:
        p = self.p
        start = lost & ~self.recovering
        end = ~start & self.recovering & (self.good >= p.recovered_frames)
        self.v0_before = np.where(start, self.v0, self.v0_before)
        self.recovering = (self.recovering | start) & ~end
        self.v0 = np.where(end, self.v0_before, self.v0)
        self.q_r = np.where(end, p.quantum_ratio, self.q_r)
        self.phi2 = np.where(end, p.phi2, self.phi2)
        rec = self.recovering
        a = p.recovery_step
        self.v0 = np.where(rec, np.minimum(self.v0 * (1 + a), p.v0_max), self.v0)
        self.q_r = np.where(rec, np.minimum(self.q_r * (1 + a), p.quantum_ratio_max), self.q_r)
        self.phi2 = np.where(rec, np.maximum(self.phi2 * (1 - a), p.phi2_min), self.phi2)
        if self.ema_step is not None:  # _adapt_v0 of the runs not recovering
            v_sw = np.linalg.norm(self.ema_step / self.delta, axis=1)
            ratio = v_sw / self.v0
            v0 = np.where(ratio < p.adapt_low, self.v0 * (1 - p.adapt_step),
                          np.where(ratio > p.adapt_high, self.v0 * (1 + p.adapt_step), self.v0))
            self.v0 = np.where(rec, self.v0, np.clip(v0, p.v0_min, p.v0_max))

    def move(self, p_n: np.ndarray) -> None:
        p, rng, n, r = self.p, self.rng, self.p.n_particles, self.r
        r0 = rng.uniform(-1.0, 1.0, (r, n, 2))
        r2 = rng.uniform(0.0, 1.0, (r, n, 2))
        k = np.minimum(np.round(self.q_r * n).astype(np.int64), n - int(self.high_energy.sum()))
        kmax = int(k.max())
        z = rng.normal(0.0, p.quantum_sigma, (r, kmax, 2)) if kmax else np.zeros((r, 1, 2))
        x, v = np.empty_like(self.x), np.empty_like(self.v)
        _kernel("dpso_move")(self.x, self.v, np.ascontiguousarray(p_n), r0, r2, z, k, self.v0,
                             self.phi2, self.high_energy, self.delta, self.lower, self.upper,
                             float(p.omega), float(p.phi0), float(p.high_energy_factor), x, v)
        self.x, self.v = x, v


class BatchPF(_Common):
    """``service.estimators.particle_filter.ParticleFilter`` (PF-g, PF-l) for R runs at once."""

    def __init__(self, positions: np.ndarray, p: PFParams, r: int, rng: np.random.Generator,
                 motion: str) -> None:
        super().__init__(positions, p, r)
        self.rng = rng
        self.motion = motion
        n = p.n_particles
        self.x = self.sample_map_positions(rng, n)
        ang = rng.uniform(0, 2 * math.pi, (r, n))
        self.v = p.v_init_mps * np.stack([np.cos(ang), np.sin(ang)], -1)
        self.first = True

    def predict(self, dt: float) -> None:
        p, rng, n, r = self.p, self.rng, self.p.n_particles, self.r
        if self.motion == "gauss":
            self.x = self.x + rng.normal(0.0, p.sigma_gauss_m, (r, n, 2))
            return
        rot = rng.normal(0.0, math.radians(p.sigma_rot_deg), (r, n))  # Eq. 7
        scale = np.exp(rng.normal(0.0, p.sigma_acc, (r, n)))
        _kernel("pf_linear")(self.x, self.v, np.cos(rot), np.sin(rot), scale, dt)  # Eq. 8

    def step(self, fitness: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], t: float
             ) -> tuple[np.ndarray, np.ndarray]:
        dt = self.frame_dt(t)
        if self.first:
            self.first = False
        else:
            self.predict(dt)
        f, m = fitness(self.x)
        n = self.p.n_particles
        total = f.sum(axis=1)
        u = self.rng.uniform(0.0, 1.0 / n, self.r)
        est = np.empty((self.r, 2))
        spread = np.empty(self.r)
        x_new, v_new = np.empty_like(self.x), np.empty_like(self.v)
        _kernel("pf_update")(np.ascontiguousarray(f), total, self.x, self.v, u, est, spread,
                             x_new, v_new)
        self.track_motion(est)
        self.update_status(m.max(axis=1))
        self.x, self.v = x_new, v_new
        return est, spread


def run_batch(positions: np.ndarray, gather: GatherFn, frames: np.ndarray, truth: np.ndarray,
              estimator: str, params: dict[str, Any] | None, rng: np.random.Generator,
              dt: float = 1.0, penalty_sigma_m: float | None = None,
              nearest: NearestGrid | None = None) -> BatchResult:
    """Replay R runs (``frames`` (R, T) query image indices) of one estimator at once.

    ``gather(q, ids)`` returns the similarities m(query q_r, map image ids[r, j]).
    """
    p = params_for(estimator, params)
    nearest = nearest or NearestGrid(positions)
    r, t_len = frames.shape
    n_img = len(positions)
    est: BatchDPSO | BatchPF
    if estimator == "dpso":
        assert isinstance(p, DPSOParams)
        if p.variant != "paper":
            raise ValueError("the batched DPSO is the papers' variant; run the product's "
                             "multi-swarm DPSO per run")
        est = BatchDPSO(positions, p, r, rng)
    else:
        assert isinstance(p, PFParams)
        est = BatchPF(positions, p, r, rng, "gauss" if estimator == "pf-g" else "linear")
    inv = 1.0 / (2.0 * (penalty_sigma_m or p.penalty_sigma_m) ** 2)
    out_xy = np.empty((r, t_len, 2))
    comps = np.empty((r, t_len), np.int64)
    spread = np.empty((r, t_len))
    for it in range(t_len):
        q = frames[:, it]

        def fitness(x: np.ndarray, q: np.ndarray = q, it: int = it
                    ) -> tuple[np.ndarray, np.ndarray]:
            ids, dist = nearest(x)
            m = gather(q, ids)
            comps[:, it] = distinct_per_row(ids, n_img)
            return m * np.exp(-(dist**2) * inv), m

        out_xy[:, it], spread[:, it] = est.step(fitness, it * dt)
    return BatchResult(estimator, frames, out_xy, truth[frames], comps, spread)
