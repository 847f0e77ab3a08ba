"""The journal's evaluation (Sec. 6-7) in full protocol: Fig. 4, Tab. 1-4 and their figures.

Every case replays a query round against a map round from many start images and scores each
run's mean error after a warm-up (``warmup`` frames of global convergence) and its comparisons
per image. The papers' DPSO (``variant="paper"``) and the particle filters run on the papers'
features (plain SIFT, map pruned as in Sec. 6) and are vectorised over runs
(client/paper_engine.py): every test image is a start image, as in the papers. The product's
multi-swarm DPSO runs on the product's features (CLAHE + RootSIFT, unpruned), one run at a
time (its speciation does not vectorise), from ``product_starts`` evenly spaced start images.
Cases run in ``workers`` processes (client/lab/paper_pool.py); a case that recurs in several
tables is run once.

Similarities m(frame, map image) are computed on first use and kept per map checksum in
DATASET/.maps (shared with ``swarmloc experiment``), so a rerun costs estimator time only.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from itertools import permutations, product
from pathlib import Path
from typing import Any

import numpy as np

# ---- the one place that imports the lab modules (client/lab/ after the move) ------------------
from client.dataset import Round, read_round
from client.lab.experiment_cli import map_for, stored_table
from client.lab.experiments import SimilarityTable, run
from client.lab.paper_engine import BatchResult, NearestGrid, run_batch
from client.runs import frame_sequence
from service.maps.route_map import RouteMap
from service.vision.features import Features, SiftParams, extract

# -------------------------------------------------------------------------------------------

ADAPTIVE: dict[str, Any] = {}
NON_ADAPTIVE: dict[str, Any] = {"adapt_step": 0.0, "recovery_step": 0.0}  # v0 fixed at 0.015
VARIANTS = ("paper", "product")  # the faithful journal DPSO and the service's default


@dataclass(frozen=True)
class Method:
    """An estimator with its parameters and the features it runs on."""

    label: str
    estimator: str
    params: tuple[tuple[str, Any], ...] = ()
    papers_features: bool = True

    @property
    def batched(self) -> bool:
        return self.papers_features  # the papers' DPSO and the filters

    def with_params(self, label: str, **kw: Any) -> Method:
        return Method(label, self.estimator, tuple({**dict(self.params), **kw}.items()),
                      self.papers_features)


def dpso(n: int, variant: str, **kw: Any) -> Method:
    """DPSO-n of one variant: the papers' on the papers' features, the product's on its own."""
    if variant == "paper":
        return Method(f"DPSO-{n} (paper)", "dpso",
                      tuple({"variant": "paper", "n_particles": n, **kw}.items()), True)
    return Method(f"DPSO-{n} (product)", "dpso", tuple({"n_particles": n, **kw}.items()), False)


def pf(kind: str, n: int, **kw: Any) -> Method:
    return Method(f"PF-{kind}-{n}", f"pf-{kind}", tuple({"n_particles": n, **kw}.items()), True)


@dataclass(frozen=True)
class Case:
    """One method on one (map, query) round pair at one speed, optionally kidnapped."""

    method: Method
    map_round: str
    query: str
    speed: float = 1.0
    kidnap: bool = False


@dataclass
class CaseResult:
    case: Case
    run_error: np.ndarray  # (R,) mean error per run after the warm-up (m)
    run_comparisons: np.ndarray  # (R,) mean comparisons per image per run
    error_curve: np.ndarray  # (T,) mean error over runs per iteration (m)
    spread_curve: np.ndarray  # (T,) mean particle spread per iteration (m); nan if unknown
    recovered: np.ndarray = field(default_factory=lambda: np.zeros(0))  # kidnap: frames or nan
    seconds: float = 0.0


@dataclass(frozen=True)
class Settings:
    starts: int = 0  # start images per case for the vectorised methods; 0 = every test image
    product_starts: int = 24  # start images per case for the product's DPSO (one run each:
    # every test image would cost ~2 h of CPU; docs/research/papers.md, "What the full
    # protocol costs")
    warmup: int = 20
    seed: int = 0
    speeds: tuple[float, ...] = (0.25, 0.5, 1.0, 2.0, 4.0)
    sizes: tuple[int, ...] = (40, 60, 80, 100, 120)
    grid_rot: tuple[int, ...] = (20, 30, 40, 50, 60)
    grid_acc: tuple[float, ...] = (1e-2, 1e-3, 1e-4, 1e-5)
    grid_v: tuple[int, ...] = (1, 2, 3)
    pair_limit: int = 0  # Tab. 4 cases per scenario; 0 = every ordered pair
    threads: int = 2  # similarity computations in parallel (numba releases the GIL)
    workers: int = 2  # cases in parallel processes (1: in this process)
    product_chunk: int = 8  # product runs per task of a worker (the runs are independent)

    @classmethod
    def quick(cls) -> Settings:
        return cls(starts=4, product_starts=2, warmup=5, speeds=(0.5, 1.0, 2.0),
                   sizes=(40, 80), grid_rot=(20, 60), grid_acc=(1e-3,), grid_v=(1, 3),
                   pair_limit=1)


def starts_of(n: int, count: int) -> list[int]:
    """``count`` evenly spaced start images; every image when count is 0 or >= n."""
    if count <= 0 or count >= n:
        return list(range(n))
    return [k * n // count for k in range(count)]


class _LazyFeatures(Sequence[Features]):
    """Query features of a round, extracted on first use (only rows a table misses)."""

    def __init__(self, load: Callable[[int], Features], n: int) -> None:
        self._load = load
        self._items: list[Features | None] = [None] * n

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i: Any) -> Any:
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        f = self._items[i]
        if f is None:
            f = self._items[i] = self._load(i)
        return f


def _codes_of(m: RouteMap) -> Callable[[int], Features]:
    def load(i: int) -> Features:
        codes = np.asarray(m.codes[m.offsets[i]: m.offsets[i + 1]])
        return Features(np.zeros((len(codes), 2), np.float32), codes)
    return load


def _extractor(rnd: Round, params: SiftParams) -> Callable[[int], Features]:
    def load(i: int) -> Features:
        return extract(rnd.load_image(i), params)
    return load


class Lab:
    """A dataset's maps, query features, similarity tables and nearest-image rasters."""

    def __init__(self, dataset: Path, threads: int = 2) -> None:
        self.dataset = dataset
        self.threads = threads
        self._rounds: dict[str, Round] = {}
        self._maps: dict[tuple[str, bool], RouteMap] = {}
        self._queries: dict[tuple[str, bool], _LazyFeatures] = {}
        self._tables: dict[tuple[str, str, bool], SimilarityTable] = {}
        self._grids: dict[str, NearestGrid] = {}
        self._pool = ThreadPoolExecutor(threads) if threads > 1 else None

    def round(self, name: str) -> Round:
        if name not in self._rounds:
            self._rounds[name] = read_round(self.dataset / name)
        return self._rounds[name]

    def map(self, name: str, papers: bool) -> RouteMap:
        key = (name, papers)
        if key not in self._maps:
            # the papers' comparison: every method's map on the recorded positions
            self._maps[key] = map_for(self.dataset, name, papers, positions="recorded")
        return self._maps[key]

    def queries(self, name: str, papers: bool) -> _LazyFeatures:
        """Unpruned query features; the product's are the codes of the round's own map when
        it has one (same extraction, no pruning)."""
        key = (name, papers)
        if key not in self._queries:
            rnd = self.round(name)
            params = SiftParams.papers() if papers else SiftParams()
            load: Callable[[int], Features]
            if not papers:  # the round's own map (built once, also used as a map)
                load = _codes_of(self.map(name, False))
            else:
                load = _extractor(rnd, params)
            self._queries[key] = _LazyFeatures(load, len(rnd))
        return self._queries[key]

    def table(self, map_round: str, query: str, papers: bool) -> SimilarityTable:
        key = (map_round, query, papers)
        if key not in self._tables:
            m = self.map(map_round, papers)
            self._tables[key] = stored_table(self.dataset, m, query,
                                             self.queries(query, papers))
        return self._tables[key]

    def grid(self, map_round: str) -> NearestGrid:
        if map_round not in self._grids:
            self._grids[map_round] = NearestGrid(self.map(map_round, True).positions)
        return self._grids[map_round]

    def save(self) -> None:
        """Write the tables, merged with what is on disk (another run may have added to it)."""
        for t in self._tables.values():
            path = t.cache_path
            if path is None:
                continue
            if path.is_file():
                try:
                    disk = np.load(path)
                except (OSError, ValueError):  # a torn or foreign file: ours replaces it
                    disk = None
                if disk is not None and disk.shape == t.table.shape:
                    fill_missing(t.table, disk)
            tmp = path.with_suffix(f".{os.getpid()}.tmp.npy")
            with open(tmp, "wb") as fh:
                np.save(fh, t.table)
                fh.flush()
                os.fsync(fh.fileno())
            tmp.replace(path)

    def gather(self, table: SimilarityTable) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        """m(q_r, ids[r, j]) for all runs at once; missing entries computed per query row,
        rows in parallel threads."""
        pool = self._pool

        def fill(qv: int, need: np.ndarray) -> None:
            table.scores(qv, need)

        def gather(q: np.ndarray, ids: np.ndarray) -> np.ndarray:
            vals = table.table[q[:, None], ids]
            miss = np.isnan(vals)
            if miss.any():
                rows, cols = np.nonzero(miss)
                key = np.unique(q[rows].astype(np.int64) * table.table.shape[1] + ids[rows, cols])
                qs, cs = np.divmod(key, table.table.shape[1])
                cut = np.flatnonzero(np.diff(qs)) + 1
                jobs = [(int(a[0]), b) for a, b in zip(np.split(qs, cut), np.split(cs, cut),
                                                        strict=True)]
                if pool is not None and len(jobs) > 1:
                    list(pool.map(lambda j: fill(*j), jobs))
                else:
                    for j in jobs:
                        fill(*j)
                vals = table.table[q[:, None], ids]
            return vals

        return gather


def fill_missing(table: np.ndarray, known: np.ndarray) -> None:
    """Fill the NaN entries of ``table`` from ``known`` (same shape), in place."""
    miss = np.isnan(table)
    table[miss] = known[miss]


def run_case(lab: Lab, case: Case, s: Settings, seed: int,
             runs: tuple[int, int] | None = None) -> CaseResult:
    """All runs of one case (or, for the product's DPSO, the runs ``runs[0]:runs[1]``; the
    k-th run has seed ``seed + k`` wherever it runs); scored after the warm-up."""
    t0 = time.perf_counter()
    m = case.method
    rnd = lab.round(case.query)
    n = len(rnd)
    table = lab.table(case.map_round, case.query, m.papers_features)
    route_map = lab.map(case.map_round, m.papers_features)
    dt = float(np.median(np.diff(rnd.t))) if rnd.t is not None and n > 1 else 1.0
    params = dict(m.params)
    w = s.warmup
    if m.batched:
        starts = starts_of(n, s.starts)
        frames = np.stack([frame_sequence(n, st, case.speed, case.kidnap) for st in starts])
        res: BatchResult = run_batch(route_map.positions, lab.gather(table), frames,
                                     rnd.reference_xy, m.estimator, params,
                                     np.random.default_rng(seed), dt,
                                     nearest=lab.grid(case.map_round))
        err, comps, spread = res.errors, res.comparisons.astype(float), res.spread_m
    else:
        starts = starts_of(n, s.product_starts)
        lo, hi = runs if runs is not None else (0, len(starts))
        one = [run(route_map, table, rnd, m.estimator, params, seed=seed + k, start=starts[k],
                   speed=case.speed, kidnap=case.kidnap) for k in range(lo, hi)]
        err = np.stack([r.errors for r in one])
        comps = np.stack([r.comparisons for r in one]).astype(float)
        spread = np.full(err.shape, np.nan)
    recovered = np.zeros(0)
    if case.kidnap:
        recovered = np.array([_frames_until_back(e, len(e) // 2) for e in err])
    return CaseResult(case, err[:, w:].mean(axis=1), comps[:, w:].mean(axis=1),
                      err.mean(axis=0), spread.mean(axis=0), recovered,
                      time.perf_counter() - t0)


def merge_results(parts: Sequence[CaseResult]) -> CaseResult:
    """One case's result from the results of its run slices, in run order."""
    if len(parts) == 1:
        return parts[0]
    runs = np.array([len(p.run_error) for p in parts], float)
    w = runs / runs.sum()
    return CaseResult(parts[0].case, np.concatenate([p.run_error for p in parts]),
                      np.concatenate([p.run_comparisons for p in parts]),
                      sum(wi * p.error_curve for wi, p in zip(w, parts, strict=True)),
                      sum(wi * p.spread_curve for wi, p in zip(w, parts, strict=True)),
                      np.concatenate([p.recovered for p in parts]),
                      sum(p.seconds for p in parts))


def _frames_until_back(err: np.ndarray, since: int, within_m: float = 5.0, hold: int = 5
                       ) -> float:
    ok = err[since:] <= within_m
    run_ok = np.convolve(ok.astype(int), np.ones(hold, int), "valid") == hold
    hit = np.flatnonzero(run_ok)
    return float(hit[0]) if len(hit) else float("nan")


# ---- the protocol ------------------------------------------------------------------------------
SC_MAP, SC_QUERY = "sunny1", "cloudy1"  # the "difficult case" of Sec. 7.1 and Tab. 1-3


def tab4_pairs(rounds: Sequence[str], limit: int = 0) -> dict[str, list[tuple[str, str]]]:
    """Ordered (map, query) pairs of distinct rounds per scenario: sunny vs sunny (6),
    cloudy vs cloudy (6), sunny (map) vs cloudy (query, 9)."""
    sunny = [r for r in rounds if r.startswith("sunny")]
    cloudy = [r for r in rounds if r.startswith("cloudy")]
    out = {
        "sunny vs sunny": list(permutations(sunny, 2)),
        "cloudy vs cloudy": list(permutations(cloudy, 2)),
        "sunny vs cloudy": list(product(sunny, cloudy)),
    }
    return {k: v[:limit] if limit else v for k, v in out.items()}


def protocol(rounds: Sequence[str], s: Settings) -> dict[str, list[Case]]:
    """Every case of every section, in the order they run."""
    sc: dict[str, Any] = {"map_round": SC_MAP, "query": SC_QUERY}
    tab1 = [Case(dpso(n, v), **sc) for v in VARIANTS for n in s.sizes]
    tab1 += [Case(pf(k, n), **sc) for k in ("g", "l") for n in (100, 300)]
    tab2 = [Case(dpso(80, v, **mode).with_params(f"DPSO-80 ({v}, {name})", **mode), **sc,
                 kidnap=kid)
            for v in VARIANTS for name, mode in (("adaptive", ADAPTIVE),
                                                 ("non-adaptive", NON_ADAPTIVE))
            for kid in (False, True)]
    fig4 = [Case(dpso(80, v, **mode).with_params(f"DPSO-80 ({v}, {name})", **mode), **sc,
                 speed=sp)
            for v in VARIANTS for name, mode in (("adaptive", ADAPTIVE),
                                                 ("non-adaptive", NON_ADAPTIVE))
            for sp in s.speeds]
    v_r = 0.6  # replaced by the round's driven speed in ``grid_cases``
    tab3 = [Case(pf("l", 300, sigma_rot_deg=float(r), sigma_acc=a, v_init_mps=v * v_r)
                 .with_params(f"PF-l-300 rot={r} acc={a:g} v={v}vR"), **sc)
            for a in s.grid_acc for r in s.grid_rot for v in s.grid_v]
    # pairs interleaved over the scenarios, so that a partial run covers all three
    scen = list(tab4_pairs(rounds, s.pair_limit).values())
    order = [p[i] for i in range(max(map(len, scen), default=0)) for p in scen if i < len(p)]
    tab4 = [Case(meth, mp, q) for mp, q in order
            for meth in (pf("g", 300), pf("l", 100), pf("l", 300), dpso(80, "paper"),
                         dpso(80, "product"))]
    # Tab. 4 (the headline) before the long Tab. 3 grid: a cut-short run still has it
    return {"tab1": tab1, "tab2": tab2, "fig4": fig4, "tab4": tab4, "tab3": tab3}


def driven_speed(rnd: Round) -> float:
    """v_R: the query round's median speed between consecutive images (m/s)."""
    xy = rnd.reference_xy
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    dt = np.diff(rnd.t) if rnd.t is not None else np.ones(len(step))
    return float(np.median(step / np.where(dt > 0, dt, 1.0)))


def with_driven_speed(cases: list[Case], v_r: float) -> list[Case]:
    """Tab. 3's v_init in multiples of the query round's driven speed v_R."""
    out = []
    for c in cases:
        p = dict(c.method.params)
        if "v_init_mps" in p:
            p["v_init_mps"] = round(p["v_init_mps"] / 0.6, 6) * v_r
        out.append(Case(Method(c.method.label, c.method.estimator, tuple(p.items()),
                               c.method.papers_features), c.map_round, c.query, c.speed,
                        c.kidnap))
    return out


def same_cases(sections: dict[str, list[Case]]) -> dict[tuple[str, int], list[tuple[str, int]]]:
    """Cases that repeat an earlier one (same estimator, parameters, features, rounds, speed
    and kidnapping; e.g. DPSO-80 on sunny1/cloudy1 in Tab. 1, Tab. 2, Fig. 4 and Tab. 4),
    by the first occurrence: they are run once and reported in each place."""
    first: dict[tuple[Any, ...], tuple[str, int]] = {}
    copies: dict[tuple[str, int], list[tuple[str, int]]] = {}
    for name, cases in sections.items():
        for i, c in enumerate(cases):
            m = c.method
            key = (m.estimator, tuple(sorted(m.params)), m.papers_features, c.map_round,
                   c.query, c.speed, c.kidnap)
            if key in first:
                copies.setdefault(first[key], []).append((name, i))
            else:
                first[key] = (name, i)
    return copies


def iter_rounds(dataset: Path) -> Iterator[str]:
    """Round directories of a dataset (those with poses.csv), sorted."""
    for p in sorted(dataset.iterdir()):
        if p.is_dir() and (p / "poses.csv").is_file():
            yield p.name
