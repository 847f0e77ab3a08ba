"""``swarmloc bench geometry``: what locating frames between map images costs per frame.

Two DPSO localizers with one seed on one map (built with the camera) take the same frames,
interleaved: one with ``metric_pose`` (the default), one without. Printed: the step's p50 and
p99 of each and their ratio, the time inside the geometry (the frame's matches and PnP, and
the structure of map images seen for the first time, kept per map afterwards), the share of
tracked frames located (within DPSO's reach), and each localizer's mean error against the
round's truth.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from client.lab.stats import percentile


@dataclass(frozen=True)
class GeometryBench:
    frames: int
    step_ms: dict[str, tuple[float, float]]  # "with" / "without": (p50, p99)
    locate_ms: tuple[float, float]  # p50, p99 of one locate call (frame matches + PnP)
    structure_ms: tuple[float, float]  # p50, p99 of a map image's structure, first use
    located: float  # share of tracked frames whose position was located
    error_m: dict[str, float]


def report(b: GeometryBench) -> None:
    import typer

    w, wo = b.step_ms["with"], b.step_ms["without"]
    typer.echo(f"{b.frames} frames; localizer step p50 / p99: with geometry {w[0]:.2f} / "
               f"{w[1]:.2f} ms, without {wo[0]:.2f} / {wo[1]:.2f} ms; ratio p50 "
               f"x{w[0] / wo[0]:.2f}, p99 x{w[1] / wo[1]:.2f}")
    typer.echo(f"inside it: locate (frame matches + PnP) p50 {b.locate_ms[0]:.2f} ms, p99 "
               f"{b.locate_ms[1]:.2f} ms; a map image's structure on first use p50 "
               f"{b.structure_ms[0]:.2f} ms, p99 {b.structure_ms[1]:.2f} ms (kept per map)")
    typer.echo(f"tracked frames located: {100 * b.located:.1f} %; mean error with "
               f"{b.error_m['with']:.2f} m, without {b.error_m['without']:.2f} m")


def bench_geometry(dataset: Path, map_round: str, query_round: str, frames: int = 200,
                   warmup: int = 20, seed: int = 0) -> GeometryBench:
    from client.dataset import read_round
    from client.lab.experiment_cli import map_for
    from service.api.params import DPSOParams
    from service.engine.localizer import Localizer
    from service.vision.features import Features, extract
    from service.vision.map_geometry import FramePairs, GeometryParams, MapGeometry
    from service.vision.metric_pose import Offset, Structure

    m = map_for(dataset, map_round, papers=False)
    if m.geometry is None:
        raise ValueError(f"{dataset}/{map_round}: no camera (dataset.json 'camera' or "
                         "calib.txt), nothing to locate with")
    rnd = read_round(dataset / query_round)
    n = min(len(rnd), frames + warmup)
    feats = [extract(rnd.load_image(i), m.feature_params) for i in range(n)]
    truth = rnd.reference_xy
    locs = {"with": Localizer(m, "dpso", {}, seed),
            "without": Localizer(m, "dpso", {"metric_pose": False}, seed)}
    steps: dict[str, list[float]] = {k: [] for k in locs}
    errors: dict[str, list[float]] = {k: [] for k in locs}
    locate_ms: list[float] = []
    located: list[bool] = []
    structure_ms: list[float] = []
    timed_structure = MapGeometry.structure
    timed_locate = MapGeometry.locate

    def structure(self: MapGeometry, image_id: int, p: GeometryParams) -> Structure | None:
        cold = (int(image_id), p) not in self._cache
        t0 = time.perf_counter()
        out = timed_structure(self, image_id, p)
        if cold:
            structure_ms.append(1e3 * (time.perf_counter() - t0))
        return out

    def locate(self: MapGeometry, frame: Features, image_id: int, p: GeometryParams,
               kept: FramePairs | None = None) -> Offset | None:
        self.structure(image_id, p)  # its first use is timed apart
        t0 = time.perf_counter()
        out = timed_locate(self, frame, image_id, p, kept)
        locate_ms.append(1e3 * (time.perf_counter() - t0))
        reach = DPSOParams().metric_reach_m  # what DPSO takes (the default sessions here)
        located.append(out is not None and math.hypot(out.right_m, out.ahead_m) <= reach)
        return out

    tracked = hits = 0
    MapGeometry.structure = structure  # type: ignore[method-assign]
    MapGeometry.locate = locate  # type: ignore[method-assign]
    try:
        for i in range(n):
            order = ("with", "without") if i % 2 == 0 else ("without", "with")
            for k in order:
                calls = len(locate_ms)
                t0 = time.perf_counter()
                est = locs[k].step(feats[i], float(i))
                dt = 1e3 * (time.perf_counter() - t0)
                if i >= warmup:
                    steps[k].append(dt)
                    errors[k].append(float(np.hypot(est.x - truth[i][0], est.y - truth[i][1])))
                    if k == "with" and est.status == "tracking":
                        tracked += 1
                        hits += len(located) > calls and located[-1]
                if k == "without" or i < warmup:
                    del locate_ms[calls:], located[calls:]
    finally:
        MapGeometry.structure = timed_structure  # type: ignore[method-assign]
        MapGeometry.locate = timed_locate  # type: ignore[method-assign]

    def pct(x: list[float]) -> tuple[float, float]:
        return percentile(x, 50), percentile(x, 99)

    return GeometryBench(
        frames=n - warmup, step_ms={k: pct(v) for k, v in steps.items()},
        locate_ms=pct(locate_ms), structure_ms=pct(structure_ms),
        located=hits / max(tracked, 1),
        error_m={k: float(np.mean(v)) for k, v in errors.items()})
