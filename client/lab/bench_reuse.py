"""``swarmloc bench reuse``: the two-view geometry on the matches the similarity kept, against
matching the frame again, side by side on the same map, frames and seed.

Per query round, three localizers (DPSO, the service's defaults, one seed; each on its own
copy of the map, so that each computes its own structures) step through the same extracted
frames, in alternating order:

- ``again``: the similarity keeps nothing, so the geometry matches the frame with the image
  it locates it at a second time (the service before this change, less its extra float GEMM);
- ``kept``: the service's path (the similarity's pass keeps the geometry's matches);
- ``kept+structures``: the same, every map image's structure computed beforehand
  (``MapGeometry.warm``), as a map in use for a while has them.

Printed: the median ``Localizer.step`` after the warm-up, step / extraction, the mean error
after the warm-up, and whether every estimate equals ``again``'s (bit for bit).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np

from client.dataset import Round
from client.lab.bench_extract import extract_timed
from service.engine.localizer import Localizer
from service.maps.route_map import RouteMap, build_map_from_rounds, load_map, save_map
from service.vision.features import Features, named_params
from service.vision.map_geometry import FramePairs

VARIANTS = ("again", "kept", "kept+structures")


class _MatchAgain:
    """The map, its similarity keeping no matches (everything else delegated)."""

    def __init__(self, route_map: RouteMap) -> None:
        self._map = route_map

    def similarity(self, frame: Features | np.ndarray, image_ids: Any,
                   keep: FramePairs | None = None,
                   keep_second: FramePairs | None = None, first: Any = None) -> np.ndarray:
        return self._map.similarity(frame, image_ids, first=first)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._map, name)


@dataclass(frozen=True)
class ReuseRow:
    query: str
    features: float  # median per frame
    extract_ms: float
    warm_s: float  # computing every structure beforehand
    step_ms: dict[str, float]
    error_m: dict[str, float]
    identical: dict[str, bool]  # every estimate equal to "again"'s


def compare(map_path: Path, query: Round, name: str, size: tuple[int, int], frames: int,
            warmup: int, seed: int) -> ReuseRow:
    params = named_params("clahe-rootsift", *size)
    maps = {k: load_map(map_path) for k in VARIANTS}
    geometry = maps["kept+structures"].geometry
    if geometry is None:
        raise ValueError("the map has no camera: nothing is located (dataset.json 'camera')")
    t0 = time.perf_counter()
    geometry.warm()
    warm_s = time.perf_counter() - t0
    n = min(len(query), frames + warmup)
    feats, ext_ms = extract_timed(query, n, params)
    truth = query.reference_xy[:n]
    locs = {k: Localizer(cast(RouteMap, _MatchAgain(maps[k])) if k == "again" else maps[k],
                         "dpso", {}, seed) for k in VARIANTS}
    ms: dict[str, list[float]] = {k: [] for k in VARIANTS}
    xy: dict[str, list[tuple[float, float]]] = {k: [] for k in VARIANTS}
    for i, f in enumerate(feats):
        for k in VARIANTS if i % 2 == 0 else VARIANTS[::-1]:
            t0 = time.perf_counter()
            est = locs[k].step(f, float(i))
            ms[k].append(1e3 * (time.perf_counter() - t0))
            xy[k].append((est.x, est.y))
    err = {k: float(np.mean(np.hypot(*(np.array(xy[k][warmup:]) - truth[warmup:]).T)))
           for k in VARIANTS}
    return ReuseRow(name, float(np.median([len(f) for f in feats])), float(np.median(ext_ms)),
                    warm_s, {k: float(np.median(ms[k][warmup:])) for k in VARIANTS}, err,
                    {k: xy[k] == xy["again"] for k in VARIANTS})


def bench_reuse(map_round: Round, queries: Sequence[tuple[str, Round]], size: tuple[int, int],
                frames: int = 60, warmup: int = 20, seed: int = 0) -> list[ReuseRow]:
    """One row per query round; OpenCV and BLAS on one thread (as ``swarmloc serve``)."""
    from threadpoolctl import threadpool_limits

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(1, "blas"), tempfile.TemporaryDirectory() as tmp:
            path = save_map(build_map_from_rounds([map_round],
                                                  params=named_params("clahe-rootsift", *size)),
                            Path(tmp) / "map")
            return [compare(path, q, name, size, frames, warmup, seed) for name, q in queries]
    finally:
        cv2.setNumThreads(threads)


def report(rows: Sequence[ReuseRow], say: Callable[[str], object] = print) -> None:
    say("| query | features/frame | extract ms | step ms " + " / ".join(VARIANTS)
        + " | step / extract | error m | identical estimates | structures beforehand s |")
    say("|---|---|---|---|---|---|---|---|")
    for r in rows:
        steps = " / ".join(f"{r.step_ms[k]:.1f}" for k in VARIANTS)
        ratios = " / ".join(f"{r.step_ms[k] / r.extract_ms:.2f}" for k in VARIANTS)
        errs = " / ".join(f"{r.error_m[k]:.3f}" for k in VARIANTS)
        same = "yes" if all(r.identical.values()) else \
            ", ".join(k for k, v in r.identical.items() if not v) + " differ"
        say(f"| {r.query} | {r.features:.0f} | {r.extract_ms:.1f} | {steps} | {ratios} | "
            f"{errs} | {same} | {r.warm_s:.1f} |")
