"""``swarmloc experiment``: the papers' comparison of DPSO with the particle filters."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from client.dataset import read_round
from client.experiments import SimilarityTable, frames_to_recover, run
from service.route_map import RouteMap, build_map, load_map, save_map

CONFIGS = {
    "DPSO-80": ("dpso", {}),
    "PF-l-100": ("pf-l", {"n_particles": 100}),
    "PF-l-300": ("pf-l", {"n_particles": 300}),
    "PF-g-300": ("pf-g", {"n_particles": 300}),
}


def _map_for(round_dir: Path, cache_dir: Path) -> RouteMap:
    path = cache_dir / f"{round_dir.name}.swmap"
    if path.is_file():
        return load_map(path)
    rnd = read_round(round_dir)
    m = build_map(round_dir.name, [rnd.load_image(i) for i in range(len(rnd))], rnd.xy,
                  list(rnd.images), origin=rnd.origin)
    save_map(m, path)
    return m


def _score(m: RouteMap, table: SimilarityTable, rnd, est: str, params: dict, starts: list[int],
           seed: int, warmup: int) -> dict[str, list]:
    """Per-run mean/median error, share within 5 m, comparisons, speed error, share of frames
    recovering or lost, and frames to recover from a kidnapping (when asked)."""
    out: dict[str, list] = {k: [] for k in ("err", "med", "w5", "comps", "speed", "bad")}
    for k, s in enumerate(starts):
        res = run(m, table, rnd, est, params, seed=seed + k, start=s)
        e = res.errors[warmup:]
        out["err"].append(e.mean())
        out["med"].append(np.median(e))
        out["w5"].append(np.mean(e <= 5))
        out["comps"].append(res.comparisons[warmup:].mean())
        tracking = np.array(res.status) == "tracking"
        tracking[: 2 * warmup] = False
        if tracking.any():
            out["speed"].append(abs(np.median(res.speed[tracking]) / np.median(res.true_speed)
                                    - 1))
        out["bad"].append(np.mean(np.isin(res.status, ["recovering", "lost"])))
    return out


def _kidnap(m: RouteMap, table: SimilarityTable, rnd, params: dict, starts: list[int],
            seed: int) -> list[int | None]:
    return [frames_to_recover(run(m, table, rnd, "dpso", params, seed=seed + k, start=s,
                                  kidnap=True)) for k, s in enumerate(starts)]


def experiment(
    dataset: Annotated[Path, typer.Argument(help="dataset with the rounds")],
    map_round: Annotated[str, typer.Option("--map", help="round used as the map")] = "sunny1",
    query: Annotated[str, typer.Option(help="comma-separated rounds replayed against it")]
    = "sunny2,cloudy1",
    starts: Annotated[int, typer.Option(help="runs from evenly spaced start images")] = 8,
    warmup: Annotated[int, typer.Option(help="frames of global convergence not scored")] = 20,
    kidnap: Annotated[bool, typer.Option(help="also run the kidnapping experiment")] = True,
    seed: int = 0,
) -> None:
    """Mean error and comparisons per frame of DPSO-80, PF-l-100/300, PF-g-300 (Tab. 4),
    DPSO kidnap recovery (Sec. 7.1), speed-estimate error and estimator time per frame
    ('step ms': median of one run on an empty similarity cache, so it includes the
    comparisons; feature extraction of the frame excluded)."""
    m = _map_for(dataset / map_round, dataset / ".maps")
    for q in [x for x in query.split(",") if x]:
        rnd = read_round(dataset / q)
        table = SimilarityTable.from_round(m, rnd)
        n = len(rnd)
        start_list = [k * n // starts for k in range(starts)]
        typer.echo(f"\n{map_round} (map) vs {q}: {starts} runs x {n} frames, errors after "
                   f"{warmup} frames")
        typer.echo(f"{'method':10s} {'mean err (m)':>14s} {'median':>7s} {'<=5 m':>7s} "
                   f"{'comp/frame':>10s} {'speed err':>9s} {'recov %':>7s} {'step ms':>8s}")
        rows = {}
        for name, (est, params) in CONFIGS.items():
            sc = _score(m, table, rnd, est, params, start_list, seed, warmup)
            # estimator time per frame with real comparisons: a fresh table, nothing cached
            timed = run(m, SimilarityTable(m, table.queries), rnd, est, params, seed=seed,
                        start=start_list[0])
            step_ms = float(np.median(timed.step_ms[warmup:]))
            rows[name] = (np.mean(sc["err"]), np.mean(sc["comps"]))
            spd = sc["speed"]
            typer.echo(f"{name:10s} {np.mean(sc['err']):7.2f} ± {np.std(sc['err']):4.2f} "
                       f"{np.mean(sc['med']):7.2f} {100 * np.mean(sc['w5']):6.1f}% "
                       f"{np.mean(sc['comps']):10.1f} "
                       f"{100 * np.mean(spd) if spd else float('nan'):8.1f}% "
                       f"{100 * np.mean(sc['bad']):6.1f}% {step_ms:8.2f}")
        d_err, d_cmp = rows["DPSO-80"]
        typer.echo(f"DPSO-80 / PF-l-300: error x{d_err / rows['PF-l-300'][0]:.2f}, "
                   f"comparisons x{d_cmp / rows['PF-l-300'][1]:.2f}; DPSO-80 / PF-g-300: "
                   f"comparisons x{d_cmp / rows['PF-g-300'][1]:.2f}")
        if kidnap:
            rec_frames = _kidnap(m, table, rnd, {}, start_list, seed)
            done = [f for f in rec_frames if f is not None]
            typer.echo(f"kidnapped DPSO-80: back within 5 m (5 frames in a row) in "
                       f"{len(done)}/{len(rec_frames)} runs, median "
                       f"{np.median(done) if done else float('nan'):.0f} frames "
                       f"(each: {rec_frames})")


def sweep(
    dataset: Annotated[Path, typer.Argument(help="dataset with the rounds")],
    param: Annotated[str, typer.Option(help="DPSO parameter to vary, e.g. lost_threshold")],
    values: Annotated[str, typer.Option(help="comma-separated values, e.g. 0.05,0.035")],
    map_round: Annotated[str, typer.Option("--map", help="round used as the map")] = "sunny1",
    query: Annotated[str, typer.Option(help="comma-separated query rounds")] = "sunny2,cloudy1",
    starts: int = 9,
    warmup: int = 20,
) -> None:
    """DPSO mean error, share of frames in recovery and kidnap recovery for each value of one
    parameter (how the choices in README 'Choices measured' were made)."""
    m = _map_for(dataset / map_round, dataset / ".maps")
    tables = {}
    for q in [x for x in query.split(",") if x]:
        rnd = read_round(dataset / q)
        tables[q] = (rnd, SimilarityTable.from_round(m, rnd))
    for raw in values.split(","):
        value = float(raw) if "." in raw or "e" in raw else int(raw)
        for q, (rnd, table) in tables.items():
            n = len(rnd)
            start_list = [k * n // starts for k in range(starts)]
            sc = _score(m, table, rnd, "dpso", {param: value}, start_list, 0, warmup)
            kid = _kidnap(m, table, rnd, {param: value}, start_list, 0)
            done = [f for f in kid if f is not None]
            typer.echo(f"{param}={value} {map_round} vs {q}: mean error {np.mean(sc['err']):.2f} "
                       f"m, recovering {100 * np.mean(sc['bad']):.1f} % of frames, kidnap recovery "
                       f"median {np.median(done) if done else float('nan'):.0f} frames, "
                       f"never recovered {len(kid) - len(done)}/{len(kid)}")
