"""``swarmloc bench extract``: what each feature type costs per frame, on one CPU thread.

For each feature type (CLAHE + RootSIFT, XFeat) and working size, two numbers measured in one
run, with OpenCV on one thread (``cv2.setNumThreads(1)``), ONNX Runtime on one thread (the
service's default session) and BLAS on one thread (as ``swarmloc serve`` runs it):

- ``extract``: the median ms of ``service.vision.features.extract`` on a frame already at the
  working size (one image, resized to each size: a real photo such as a KITTI frame, or a
  frame of the query round);
- ``step``: the median ms of ``Localizer.step`` on a map of that feature type at that size,
  over the query frames the localizer reports ``tracking`` after a warm-up (DPSO, the
  service's defaults, the two-view geometry where the dataset has the camera), with the map's
  geometry structures built first, as the service's background warmer builds them after a
  map is loaded (``SWARMLOC_WARM_GEOMETRY``, default on). The map is the ``map`` round;
  when the query round is the map round, the map takes its even frames and the query its
  odd frames (KITTI's protocol).

The ratio step / extraction of each row (issue 29's target: at most 0.5) and the ratio
XFeat / RootSIFT of each are printed beside them.

The sweep (``caps``; ``--sweep 500,1000,2000,4000``): the same step on maps and frames capped at N
features per frame (SIFT's ``n_features`` with a low contrast threshold, XFeat's ``top_k``
with a low detection threshold, so that the cap, not the detector, sets the count; on
maps of both types XFeat keeps at most its own cap of 1,024, as the product's frames do), at
one size; the step's growth from the first count on is printed beside the growth of the count
(linear: equal; the target is at most linear from 1,000 to 4,000).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from itertools import pairwise
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from client.dataset import Round, read_round
from service.engine.geometry_warmer import GeometryWarmer
from service.engine.localizer import Localizer
from service.maps.route_map import build_map_from_rounds
from service.vision.features import DualParams, Features, SiftParams, extract, named_params

if TYPE_CHECKING:
    from service.vision.features import FeatureParams

SIZES = ((320, 240), (640, 480), (1226, 370))
KINDS = ("clahe-rootsift", "xfeat", "clahe-rootsift+xfeat")


@dataclass(frozen=True)
class ExtractRow:
    kind: str
    size: tuple[int, int]
    features: float  # median features per frame
    extract_ms: float  # median
    step_ms: float | None  # median of the tracked frames; None: not measured
    tracked: int  # frames whose step was timed

    @property
    def step_ratio(self) -> float | None:
        """step / extraction (medians)."""
        return None if self.step_ms is None else self.step_ms / self.extract_ms


def time_extract(image: np.ndarray, params: FeatureParams, repeats: int) -> tuple[float, int]:
    """(median ms, features) of extracting ``image`` at ``params``' size (one warm-up)."""
    frame = cv2.resize(image, (params.width, params.height), interpolation=cv2.INTER_AREA)
    n = len(extract(frame, params))  # warm-up (the ONNX session is made on first use)
    ms = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        extract(frame, params)
        ms.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(ms)), n


def split_rounds(dataset: Path, map_round: str, query_round: str) -> tuple[Round, Round]:
    """The map's round and the query round (even / odd frames of one round when equal)."""
    m = read_round(dataset / map_round)
    if query_round == map_round:
        return m.subset(list(range(0, len(m), 2))), m.subset(list(range(1, len(m), 2)))
    return m, read_round(dataset / query_round)


def extract_timed(query: Round, n: int, params: FeatureParams
                  ) -> tuple[list[Features], list[float]]:
    """The first ``n`` frames' features and each extraction's ms (image loading not timed)."""
    feats: list[Features] = []
    ms: list[float] = []
    for i in range(n):
        img = query.load_image(i)
        t0 = time.perf_counter()
        feats.append(extract(img, params))
        ms.append(1e3 * (time.perf_counter() - t0))
    return feats, ms


def time_steps(map_rnd: Round, query: Round, params: FeatureParams, frames: int, warmup: int,
               seed: int) -> list[float]:
    """ms of ``Localizer.step`` for the frames after ``warmup`` that the localizer reports
    tracking (at most ``frames`` of them)."""
    m = build_map_from_rounds([map_rnd], params=params)
    warmer = GeometryWarmer(duty=1.0)  # the service's, at a whole core
    warmer.submit(m)
    warmer.wait(3600)
    loc = Localizer(m, "dpso", {}, seed)
    n = min(len(query), frames + warmup)
    feats = [extract(query.load_image(i), params) for i in range(n)]
    dt = 1.0
    ms: list[float] = []
    for i, f in enumerate(feats):
        t0 = time.perf_counter()
        est = loc.step(f, i * dt)
        took = 1e3 * (time.perf_counter() - t0)
        if i >= warmup and est.status == "tracking":
            ms.append(took)
    return ms


def bench_extract(image: np.ndarray, sizes: Sequence[tuple[int, int]] = SIZES,
                  kinds: Sequence[str] = KINDS, repeats: int = 15,
                  rounds: tuple[Round, Round] | None = None, frames: int = 60,
                  warmup: int = 20, seed: int = 0, caps: Sequence[int] = ()
                  ) -> list[ExtractRow]:
    """Extraction (and, given the map and query ``rounds``, the localizer step) per feature
    type and size, or per cap of features per frame (``caps``, the module docstring); OpenCV, ONNX
    Runtime and BLAS on one thread."""
    from threadpoolctl import threadpool_limits

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    rows = []
    try:
        with threadpool_limits(1, "blas"):
            for size in sizes:
                for kind in kinds:
                    for cap in caps or (0,):
                        params = capped_params(kind, size, cap) if cap else \
                            named_params(kind, *size)
                        rows.append(_row(image, params, kind, size, repeats, rounds, frames,
                                         warmup, seed))
    finally:
        cv2.setNumThreads(threads)
    return rows


def _row(image: np.ndarray, params: FeatureParams, kind: str, size: tuple[int, int],
         repeats: int, rounds: tuple[Round, Round] | None, frames: int, warmup: int,
         seed: int) -> ExtractRow:
    ms, n = time_extract(image, params, repeats)
    steps = time_steps(*rounds, params, frames, warmup, seed) if rounds else []
    return ExtractRow(kind, size, n, ms, float(np.median(steps)) if steps else None, len(steps))


def capped_params(kind: str, size: tuple[int, int], n: int) -> FeatureParams:
    """Feature parameters of ``kind`` at ``size`` keeping the ``n`` strongest features, with
    a detector threshold low enough that most frames have that many. Both types (the default
    map): RootSIFT's ``n``, XFeat's at most its own cap (``top_k``, 1,024), as a richer frame
    gives them; the ``xfeat`` rows sweep XFeat's cap itself."""
    params = named_params(kind, *size)
    if isinstance(params, DualParams):
        return DualParams(replace(params.sift, n_features=n, contrast_threshold=0.005),
                          replace(params.xfeat, top_k=min(n, params.xfeat.top_k),
                                  detection_threshold=0.005))
    if isinstance(params, SiftParams):
        return replace(params, n_features=n, contrast_threshold=0.005)
    return replace(params, top_k=n, detection_threshold=0.005)


def report(rows: Sequence[ExtractRow], say: Callable[[str], object] = print) -> None:
    """One line per feature type and size, then the ratio XFeat / RootSIFT per size."""
    say("| features | size | features/frame | extract ms (median) | step ms (median, "
        "tracking) | tracked frames | step / extract |")
    say("|---|---|---|---|---|---|---|")
    for r in rows:
        step = "n/a" if r.step_ms is None else f"{r.step_ms:.1f}"
        ratio = "n/a" if r.step_ratio is None else f"{r.step_ratio:.2f}"
        say(f"| {r.kind} | {r.size[0]}x{r.size[1]} | {r.features:.0f} | {r.extract_ms:.1f} | "
            f"{step} | {r.tracked} | {ratio} |")
    by = {(r.kind, r.size): r for r in rows}
    for size in dict.fromkeys(r.size for r in rows):
        a = by.get(("clahe-rootsift", size))
        for kind in KINDS[1:]:
            b = by.get((kind, size))
            if a is None or b is None:
                continue
            step = "n/a" if a.step_ms is None or b.step_ms is None else \
                f"x{b.step_ms / a.step_ms:.2f}"
            say(f"ratio {kind} / clahe-rootsift at {size[0]}x{size[1]}: extract "
                f"x{b.extract_ms / a.extract_ms:.2f}, step {step}")


def report_sweep(rows: Sequence[ExtractRow], counts: Sequence[int],
                 say: Callable[[str], object] = print) -> None:
    """The sweep: per feature type, the step's growth against the features' growth."""
    say("| features | cap | features/frame | extract ms | step ms | step / extract | "
        "step growth / feature growth (from the first cap) |")
    say("|---|---|---|---|---|---|---|")
    for kind in dict.fromkeys(r.kind for r in rows):
        mine = [r for r in rows if r.kind == kind]
        first = mine[0]
        for cap, r in zip(counts, mine, strict=True):
            step = "n/a" if r.step_ms is None else f"{r.step_ms:.1f}"
            ratio = "n/a" if r.step_ratio is None else f"{r.step_ratio:.2f}"
            growth = "n/a" if r.step_ms is None or first.step_ms is None else \
                f"{(r.step_ms / first.step_ms) / (r.features / first.features):.2f}"
            say(f"| {kind} | {cap} | {r.features:.0f} | {r.extract_ms:.1f} | {step} | "
                f"{ratio} | {growth} |")
    say("(growth 1.00: the step grows as the features do, linearly; above 1: faster)")
    for line in step_growth_lines(rows, counts):
        say(line)


def step_growth_lines(rows: Sequence[ExtractRow], counts: Sequence[int]) -> list[str]:
    """Per feature type, the step's growth from each cap to the next beside the features'
    (a step that grows faster than the features between two caps shows there, even where the
    growth from the first cap does not)."""
    out = []
    for kind in dict.fromkeys(r.kind for r in rows):
        mine = [(c, r) for c, r in zip(counts, [r for r in rows if r.kind == kind],
                                      strict=True) if r.step_ms is not None]
        parts = [f"{a} → {b}: step x{rb.step_ms / ra.step_ms:.2f} for features "
                 f"x{rb.features / ra.features:.2f}"
                 for (a, ra), (b, rb) in pairwise(mine)
                 if ra.step_ms and rb.step_ms is not None]
        if parts:
            out.append(f"{kind}: " + "; ".join(parts))
    return out
