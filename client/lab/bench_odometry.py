"""``swarmloc bench odometry``: DPSO with and without the rounds' wheel odometry (issue 33).

For each rendered world (a dataset with a map round, a query round and their
``odometry.csv``): the protocol of docs/research/lighting.md (evenly spaced starts, errors
after a warm-up) with and without odometry, the kidnap runs with odometry, and the heading
error of located frames against the world's exact heading. Prints numbers; asserts nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:  # the CLI's start-up imports none of the benchmark's modules
    import numpy as np


@dataclass
class WorldResult:
    name: str
    error_plain: float  # mean error without odometry, m
    error_odom: float  # with odometry, m
    same_light_odom: float | None  # the same-light round with odometry, m (where given)
    same_light_plain: float | None
    kidnap_frames: list[int | None]  # frames to recover per kidnap run, with odometry
    heading_err_deg: np.ndarray  # |heading error| of located frames with odometry, degrees
    heading_sources: dict[str, int]
    # |heading error| of the tracked frames with odometry by heading_source, degrees
    heading_err_by_source: dict[str, np.ndarray]


def true_poses(dataset: Path, round_name: str, n: int) -> np.ndarray | None:
    """The exact pose (x, y, heading, pitch; m and rad) of each image of a rendered round,
    from the world's seed and the round's index in ``dataset.json``; None for a dataset the
    world did not render."""
    import json

    import numpy as np

    meta_path = dataset / "dataset.json"
    if not meta_path.is_file():
        return None
    meta = json.loads(meta_path.read_text())
    gen, rounds = meta.get("generator"), meta.get("rounds", {})
    if not gen or round_name not in rounds:
        return None
    from client.lab.world import World

    world = World(int(gen["seed"]), float(gen["length_m"]), float(gen["spacing_m"]))
    poses, _, _ = world.round_trajectory(int(rounds[round_name]["index"]), n)
    return np.asarray(poses, float)


def _mean_error(runs: list, warmup: int) -> float:
    import numpy as np

    return float(np.mean([r.errors[warmup:].mean() for r in runs]))


def bench_world(dataset: Path, map_round: str, query: str, same: str | None, method: str,
                starts: int, warmup: int, length: int | None, seed: int,
                features: str = "clahe-rootsift") -> WorldResult:
    import numpy as np

    from client.dataset import read_round
    from client.lab.experiment_cli import _starts, cached_table, map_for, save_table
    from client.lab.experiments import run
    from client.lab.methods import METHODS
    from client.runs import frames_to_recover

    mth = METHODS[method]
    m = map_for(dataset, map_round, mth.papers_map, features)

    tables: dict[str, tuple] = {}  # round -> (round, its similarity table), extracted once

    def runs(rnd_name: str, odometry: bool, kidnap: bool = False) -> list:
        if rnd_name not in tables:
            rnd = read_round(dataset / rnd_name)
            tables[rnd_name] = (rnd, cached_table(dataset, m, rnd))
        rnd, table = tables[rnd_name]
        out = [run(m, table, rnd, mth.estimator, mth.params, seed=seed + k, start=s,
                   kidnap=kidnap, length=length, odometry=odometry)
               for k, s in enumerate(_starts(len(rnd), starts))]
        save_table(table)
        return out

    plain, odom = runs(query, False), runs(query, True)
    same_odom = same_plain = None
    if same:
        same_plain = _mean_error(runs(same, False), warmup)
        same_odom = _mean_error(runs(same, True), warmup)
    kid = [frames_to_recover(r) for r in runs(query, True, kidnap=True)]
    poses = true_poses(dataset, query, len(tables[query][0]))
    truth = None if poses is None else poses[:, 2]  # the exact headings
    errs: list[float] = []
    by_source: dict[str, list[float]] = {}
    for r in odom:
        if truth is None or r.located is None:
            break
        h = np.asarray(r.heading)[warmup:]
        tracked = np.array(r.status[warmup:]) == "tracking"
        d = np.degrees(np.abs(np.angle(np.exp(1j * (h - truth[r.frames[warmup:]])))))
        errs.extend(d[r.located[warmup:] & tracked].tolist())
        for src, e in zip(np.asarray(r.heading_sources[warmup:])[tracked], d[tracked],
                          strict=True):
            by_source.setdefault(str(src), []).append(float(e))
    sources: dict[str, int] = {}
    for r in odom:
        for src in r.heading_sources or []:
            sources[src] = sources.get(src, 0) + 1
    return WorldResult(dataset.name, _mean_error(plain, warmup), _mean_error(odom, warmup),
                       same_odom, same_plain, kid, np.asarray(errs), sources,
                       {k: np.asarray(v) for k, v in by_source.items()})


def report(results: list[WorldResult]) -> None:
    import math

    import numpy as np

    typer.echo(f"{'world':8s} {'no odom (m)':>11s} {'odom (m)':>9s} {'ratio':>6s} "
               f"{'same-light odom':>15s} {'cross/same':>10s} {'kidnap back':>11s} "
               f"{'median':>6s} {'heading med (deg)':>17s} {'located':>7s}  sources")
    ratios, kid_all, head_all = [], [], []
    by_source: dict[str, list[float]] = {}
    for w in results:
        ratio = w.error_odom / w.error_plain
        ratios.append(ratio)
        done = [f for f in w.kidnap_frames if f is not None]
        kid_all.extend(w.kidnap_frames)
        head_all.extend(w.heading_err_deg.tolist())
        for src, e in w.heading_err_by_source.items():
            by_source.setdefault(src, []).extend(e.tolist())
        cross = (f"{w.error_odom / w.same_light_odom:10.2f}" if w.same_light_odom
                 else f"{'–':>10s}")
        same = f"{w.same_light_odom:15.2f}" if w.same_light_odom else f"{'–':>15s}"
        med = f"{np.median(done):6.1f}" if done else f"{'–':>6s}"
        hmed = (f"{np.median(w.heading_err_deg):17.2f}" if len(w.heading_err_deg)
                else f"{'–':>17s}")
        typer.echo(f"{w.name:8s} {w.error_plain:11.2f} {w.error_odom:9.2f} {ratio:6.2f} "
                   f"{same} {cross} {len(done):>5d}/{len(w.kidnap_frames):<5d} {med} "
                   f"{hmed} {len(w.heading_err_deg):7d}  {w.heading_sources}")
        if w.heading_err_by_source:
            typer.echo(f"{'':8s} heading error of tracked frames by source: "
                       + _by_source(w.heading_err_by_source))
        if w.same_light_plain:
            typer.echo(f"{'':8s} same light without odometry {w.same_light_plain:.2f} m: "
                       f"cross/same {w.error_plain / w.same_light_plain:.2f}")
    done = [f for f in kid_all if f is not None]
    typer.echo(f"mean error ratio (odometry / none) over worlds: {np.mean(ratios):.3f} "
               f"(per world {', '.join(f'{r:.2f}' for r in ratios)}); summed errors "
               f"{sum(w.error_odom for w in results) / sum(w.error_plain for w in results):.3f}")
    typer.echo(f"kidnap with odometry: {len(done)}/{len(kid_all)} back, median "
               f"{np.median(done) if done else math.nan:.1f} frames, max "
               f"{max(done) if done else math.nan}")
    if head_all:
        h = np.asarray(head_all)
        typer.echo(f"heading error of located frames: median {np.median(h):.2f} deg, "
                   f"p90 {np.percentile(h, 90):.2f} deg over {len(h)} frames")
    if by_source:
        typer.echo("heading error of tracked frames by source: "
                   + _by_source({k: np.asarray(v) for k, v in by_source.items()}))


def _by_source(errs: dict[str, np.ndarray]) -> str:
    """'source: median / p90 deg (frames)' for each heading source."""
    import numpy as np

    return ", ".join(f"{k} {np.median(v):.2f} / {np.percentile(v, 90):.2f} deg ({len(v)})"
                     for k, v in sorted(errs.items()) if len(v))


def register(bench_app: typer.Typer) -> None:
    """``bench odometry`` on the CLI's bench group."""

    @bench_app.command("odometry")
    def odometry_cmd(
        datasets: Annotated[list[Path], typer.Argument(help="rendered worlds (swarmloc world "
                                                            "render; rounds with "
                                                            "odometry.csv)")],
        map_round: Annotated[str, typer.Option("--map", help="round used as the map")]
        = "sunny1",
        query: Annotated[str, typer.Option(help="round replayed with and without "
                                                "odometry")] = "cloudy1",
        same_light: Annotated[str, typer.Option(help="same-light round for the "
                                                     "cross/same ratio, where the world "
                                                     "has it ('' for none)")] = "sunny2",
        method: Annotated[str, typer.Option(help="a method of swarmloc experiment")]
        = "DPSO-80",
        starts: Annotated[int, typer.Option(help="runs from evenly spaced starts")] = 6,
        warmup: Annotated[int, typer.Option(help="frames not scored")] = 20,
        frames: Annotated[int, typer.Option(help="frames per run (0: the whole round)")] = 0,
        seed: int = 0,
        features: Annotated[str, typer.Option(help="the map's feature type: clahe-rootsift, "
                                                   "xfeat or clahe-rootsift+xfeat (both, as "
                                                   "swarmloc map build makes by default)")]
        = "clahe-rootsift",
    ) -> None:
        """Mean error with the rounds' odometry against without, the cross/same-light ratio,
        kidnap recovery with odometry, and the heading error of located frames."""
        from client.lab.experiment_cli import check_feature_type

        check_feature_type(features)
        results = []
        for d in datasets:
            same = same_light if same_light and (d / same_light).is_dir() else None
            results.append(bench_world(d, map_round, query, same, method, starts, warmup,
                                       frames or None, seed, features))
            typer.echo(f"{d.name}: done", err=True)
        report(results)
