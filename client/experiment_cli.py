"""``swarmloc experiment`` / ``sweep``: DPSO (product and papers' variant) against the filters.

Each estimator runs from evenly spaced start images of a query round against a map round and
is scored after a warm-up of global convergence (``run_metrics``): error, share within 5 m,
comparisons per frame, share of frames in recovery, accuracy-radius calibration, honesty (how
many badly wrong frames admit it) and, with ``--kidnap``, the frames to recover from a
kidnapping. The product's DPSO and the filters use the map's default features (CLAHE +
RootSIFT, unpruned); the papers' DPSO runs on a map built as in the papers (SIFT, pruned).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from client.dataset import read_round
from client.experiments import RunResult, SimilarityTable, frames_to_recover, run
from service.features import SiftParams
from service.route_map import RouteMap, build_map, load_map, save_map


@dataclass(frozen=True)
class Config:
    estimator: str
    params: dict[str, Any]
    papers_map: bool = False  # SIFT + pruning as in the papers, else the service's features


CONFIGS = {
    "DPSO-80": Config("dpso", {}),
    "DPSO-80-paper": Config("dpso", {"variant": "paper"}, papers_map=True),
    "PF-l-100": Config("pf-l", {"n_particles": 100}),
    "PF-l-300": Config("pf-l", {"n_particles": 300}),
    "PF-g-300": Config("pf-g", {"n_particles": 300}),
}


def map_for(dataset: Path, rounds: str, papers: bool) -> RouteMap:
    """The map of one round (or rounds joined by '+'), built once and kept in DATASET/.maps."""
    names = [r for r in rounds.split("+") if r]
    path = dataset / ".maps" / f"{'+'.join(names)}{'-papers' if papers else ''}.swmap"
    if path.is_file():
        return load_map(path)
    rnds = [read_round(dataset / r) for r in names]
    params = SiftParams.papers() if papers else SiftParams()
    m = build_map("+".join(names), [r.load_image(i) for r in rnds for i in range(len(r))],
                  np.concatenate([r.xy for r in rnds]),
                  [f"{r.name}/{n}" for r in rnds for n in r.images], params,
                  origin=rnds[0].origin, prune_features=papers,
                  layers=np.concatenate([np.full(len(r), k) for k, r in enumerate(rnds)]))
    return load_map(save_map(m, path))  # loaded: with its checksum, memory-mapped


def cached_table(dataset: Path, m: RouteMap, rnd: Any) -> SimilarityTable:
    """The similarity table of a map and a query round, kept in DATASET/.maps between runs
    (keyed by the map's checksum: a rebuilt map starts a new table)."""
    table = SimilarityTable.from_round(m, rnd)
    path = dataset / ".maps" / f"{m.meta['checksum'][:16]}-{rnd.name}.table.npy"
    if path.is_file():
        saved = np.load(path)
        if saved.shape == table.table.shape:
            table.table = saved
    table.cache_path = path
    return table


def save_table(table: SimilarityTable) -> None:
    path = table.cache_path
    if path is not None:
        tmp = path.with_suffix(".tmp.npy")
        np.save(tmp, table.table)
        tmp.replace(path)


def run_metrics(runs: list[RunResult], warmup: int) -> dict[str, float]:
    """Named metrics over runs (means of per-run values), frames after ``warmup`` only."""
    per: dict[str, list[float]] = {k: [] for k in (
        "mean_error_m", "median_error_m", "within_5m", "comparisons", "recovering",
        "calibration", "honesty", "speed_error")}
    for res in runs:
        e = res.errors[warmup:]
        status = np.array(res.status[warmup:])
        per["mean_error_m"].append(float(e.mean()))
        per["median_error_m"].append(float(np.median(e)))
        per["within_5m"].append(float(np.mean(e <= 5)))
        per["comparisons"].append(float(res.comparisons[warmup:].mean()))
        admits = np.isin(status, ["recovering", "lost"])
        per["recovering"].append(float(np.mean(admits)))
        tracking = status == "tracking"
        if tracking.any() and len(res.accuracy_m):
            per["calibration"].append(float(np.mean(e[tracking]
                                                    <= res.accuracy_m[warmup:][tracking])))
        if (e > 10).any():
            per["honesty"].append(float(np.mean(admits[e > 10])))
        if tracking.any():
            per["speed_error"].append(float(abs(np.median(res.speed[warmup:][tracking])
                                                / np.median(res.true_speed) - 1)))
    out = {k: float(np.mean(v)) if v else float("nan") for k, v in per.items()}
    out["mean_error_std_m"] = float(np.std(per["mean_error_m"]))
    return out


def _starts(n: int, count: int) -> list[int]:
    return [k * n // count for k in range(count)]


def _kidnap(m: RouteMap, table: SimilarityTable, rnd: Any, cfg: Config, starts: list[int],
            seed: int) -> list[int | None]:
    return [frames_to_recover(run(m, table, rnd, cfg.estimator, cfg.params, seed=seed + k,
                                  start=s, kidnap=True)) for k, s in enumerate(starts)]


def _fmt(x: float, pct: bool = False) -> str:
    if not np.isfinite(x):
        return "–"
    return f"{100 * x:.1f}%" if pct else f"{x:.2f}"


def experiment(
    dataset: Annotated[Path, typer.Argument(help="dataset with the rounds")],
    map_round: Annotated[str, typer.Option(
        "--map", help="round used as the map; rounds joined by '+' make a multi-condition map")]
    = "sunny1",
    query: Annotated[str, typer.Option(help="comma-separated rounds replayed against it")]
    = "sunny2,cloudy1",
    methods: Annotated[str, typer.Option(help=f"comma-separated, of {list(CONFIGS)}")]
    = ",".join(CONFIGS),
    starts: Annotated[int, typer.Option(help="runs from evenly spaced start images")] = 8,
    warmup: Annotated[int, typer.Option(help="frames of global convergence not scored")] = 20,
    kidnap: Annotated[bool, typer.Option(help="also run the kidnapping experiment")] = True,
    seed: int = 0,
) -> None:
    """Every estimator's error (mean, median, within 5 m), comparisons, share of frames in
    recovery, accuracy_m calibration (tracked frames within it), honesty (frames with error
    > 10 m reported lost or recovering), speed error and kidnap recovery (back within 5 m
    for 5 frames)."""
    chosen = [x for x in methods.split(",") if x]
    unknown = [x for x in chosen if x not in CONFIGS]
    if unknown:
        raise typer.BadParameter(f"unknown method(s) {unknown}; choose from {list(CONFIGS)}")
    maps = {papers: map_for(dataset, map_round, papers)
            for papers in {CONFIGS[c].papers_map for c in chosen}}
    for q in [x for x in query.split(",") if x]:
        rnd = read_round(dataset / q)
        tables = {papers: cached_table(dataset, m, rnd) for papers, m in maps.items()}
        start_list = _starts(len(rnd), starts)
        typer.echo(f"\n{map_round} (map) vs {q}: {starts} runs x {len(rnd)} frames, errors "
                   f"after {warmup} frames")
        typer.echo(f"{'method':14s} {'mean err (m)':>13s} {'median':>7s} {'<=5 m':>7s} "
                   f"{'comp/frame':>10s} {'recov':>6s} {'calib':>6s} {'honest':>7s} "
                   f"{'speed':>6s} {'kidnap: back/runs, median':>26s}")
        rows = {}
        for name in chosen:
            cfg = CONFIGS[name]
            m, table = maps[cfg.papers_map], tables[cfg.papers_map]
            runs = [run(m, table, rnd, cfg.estimator, cfg.params, seed=seed + k, start=s)
                    for k, s in enumerate(start_list)]
            r = run_metrics(runs, warmup)
            rows[name] = r
            kid = ""
            if kidnap:
                rec = _kidnap(m, table, rnd, cfg, start_list, seed)
                done = [f for f in rec if f is not None]
                kid = (f"{len(done)}/{len(rec)}, "
                       f"{_fmt(float(np.median(done))) if done else '–'} {rec}")
            typer.echo(f"{name:14s} {r['mean_error_m']:6.2f} ± {r['mean_error_std_m']:4.2f} "
                       f"{r['median_error_m']:7.2f} {_fmt(r['within_5m'], True):>7s} "
                       f"{r['comparisons']:10.1f} {_fmt(r['recovering'], True):>6s} "
                       f"{_fmt(r['calibration'], True):>6s} {_fmt(r['honesty'], True):>7s} "
                       f"{_fmt(r['speed_error'], True):>6s} {kid}")
        for table in tables.values():
            save_table(table)
        if "DPSO-80" in rows and "PF-l-300" in rows:
            d, pf = rows["DPSO-80"], rows["PF-l-300"]
            typer.echo(f"DPSO-80 / PF-l-300: error x{d['mean_error_m'] / pf['mean_error_m']:.2f}"
                       f", comparisons x{d['comparisons'] / pf['comparisons']:.2f}")


def sweep(
    dataset: Annotated[Path, typer.Argument(help="dataset with the rounds")],
    param: Annotated[str, typer.Option(help="DPSO parameter to vary, e.g. distinct_ratio")],
    values: Annotated[str, typer.Option(help="comma-separated values, e.g. 2,3,4")],
    map_round: Annotated[str, typer.Option("--map", help="round used as the map")] = "sunny1",
    query: Annotated[str, typer.Option(help="comma-separated query rounds")] = "sunny2,cloudy1",
    variant: Annotated[str, typer.Option(help="DPSO variant: swarmloc or paper")] = "swarmloc",
    starts: int = 9,
    warmup: int = 20,
) -> None:
    """DPSO mean error, comparisons, share of frames in recovery and kidnap recovery for each
    value of one parameter (how the choices in the README were made)."""
    papers = variant == "paper"
    m = map_for(dataset, map_round, papers)
    tables = {}
    for q in [x for x in query.split(",") if x]:
        rnd = read_round(dataset / q)
        tables[q] = (rnd, cached_table(dataset, m, rnd))
    for raw in values.split(","):
        value: Any = float(raw) if "." in raw or "e" in raw else int(raw)
        cfg = Config("dpso", {"variant": variant, param: value}, papers)
        for q, (rnd, table) in tables.items():
            start_list = _starts(len(rnd), starts)
            runs = [run(m, table, rnd, "dpso", cfg.params, seed=k, start=s)
                    for k, s in enumerate(start_list)]
            r = run_metrics(runs, warmup)
            kid = _kidnap(m, table, rnd, cfg, start_list, 0)
            done = [f for f in kid if f is not None]
            typer.echo(f"{param}={value} {map_round} vs {q}: mean error {r['mean_error_m']:.2f} m"
                       f", {r['comparisons']:.1f} comparisons, recovering "
                       f"{100 * r['recovering']:.1f} % of frames, kidnap recovery median "
                       f"{np.median(done) if done else float('nan'):.0f} frames, never "
                       f"recovered {len(kid) - len(done)}/{len(kid)}")
