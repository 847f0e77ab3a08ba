"""``swarmloc bench approx``: the service's ``words`` matcher (the inverted file,
service/vision/vocabulary.py; ``SWARMLOC_MATCHER=words``) against the exact one, side by
side, on the same map, frames and seed.

Per query round, two localizers with one map, one estimator (DPSO, the service's defaults)
and one seed step in turn through the same extracted frames: one on the map with the exact
matcher, one on the same map with the ``words`` matcher (``RouteMap.with_words``: the
similarity and the two-view geometry's kept pairs and structures through the inverted file;
``--exact-geometry``: the geometry on the exact matcher's pairs, the similarity keeping
none). Printed per round:

- ``k``, ``train ms``: the map's vocabulary and its training (what loading the map with the
  ``words`` matcher adds);
- ``step ms``: the median ``Localizer.step`` over the frames after the warm-up (one thread,
  as ``swarmloc serve`` runs), and step / extraction;
- ``error m``: the mean distance of the estimate to the frame's recorded position after the
  warm-up (the lab's error), and its change;
- ``counts``: over the map images nearest each frame's position (``images`` of them), the
  inverted file's match counts over the exact ones, and how often both pick the same best
  image.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np

from client.dataset import Round
from client.lab.bench_extract import capped_params, extract_timed
from service.engine.localizer import Localizer
from service.maps.route_map import RouteMap, build_map_from_rounds
from service.vision.features import Features, named_params
from service.vision.vocabulary import DEFAULT_PROBES


class _ExactGeometry:
    """The words map, its two-view geometry on the exact matcher's pairs (the similarity
    keeps no matches; everything else delegated): the ``--exact-geometry`` variant."""

    def __init__(self, words_map: RouteMap, exact_map: RouteMap) -> None:
        self._map = words_map
        self.geometry = exact_map.geometry

    def similarity(self, frame: Features | np.ndarray, image_ids: Any, keep: Any = None,
                   keep_second: Any = None, first: Any = None) -> np.ndarray:
        return self._map.similarity(frame, image_ids, first=first)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._map, name)


@dataclass(frozen=True)
class ApproxRow:
    query: str
    features: float  # median per frame
    extract_ms: float
    step_ms: tuple[float, float]  # exact, inverted file
    error_m: tuple[float, float]
    count_ratio: float  # inverted file's counts / exact counts
    best_same: float  # share of frames whose best image is the same
    words: int  # k of the map's vocabulary
    train_ms: float  # its training (what a load with the words matcher adds)


def _run(locs: Sequence[Localizer], feats: Sequence[Any], truth: np.ndarray, warmup: int
         ) -> list[tuple[list[float], list[float]]]:
    """Each localizer's step times (ms) and errors (m) after the warm-up, the localizers
    stepping in turn on each frame (a change of the machine's load hits both alike)."""
    out: list[tuple[list[float], list[float]]] = [([], []) for _ in locs]
    for i, f in enumerate(feats):
        for loc, (ms, err) in zip(locs, out, strict=True):
            t0 = time.perf_counter()
            est = loc.step(f, float(i))
            took = 1e3 * (time.perf_counter() - t0)
            if i >= warmup:
                ms.append(took)
                err.append(float(np.hypot(est.x - truth[i, 0], est.y - truth[i, 1])))
    return out


def compare(map_rnd: Round, query: Round, name: str, size: tuple[int, int], frames: int,
            warmup: int, seed: int, k: int, probes: int, cap: int = 0,
            exact_geometry: bool = False, images: int = 18, exact_top: int = 0) -> ApproxRow:
    params = capped_params("clahe-rootsift", size, cap) if cap else \
        named_params("clahe-rootsift", *size)
    m = build_map_from_rounds([map_rnd], params=params).with_matcher("exact")
    t0 = time.perf_counter()
    wm = m.with_words(k or None, probes, exact_top)
    train_ms = 1e3 * (time.perf_counter() - t0)
    ivf = wm.inverted_file
    n = min(len(query), frames + warmup)
    feats, ext_ms = extract_timed(query, n, params)
    truth = query.reference_xy[:n]
    exact = Localizer(m, "dpso", {}, seed)
    approx = Localizer(cast(RouteMap, _ExactGeometry(wm, m)) if exact_geometry else wm, "dpso",
                       {}, seed)
    (ms_e, err_e), (ms_a, err_a) = _run([exact, approx], feats, truth, warmup)
    got, want, same = 0, 0, 0
    for i, f in enumerate(feats):
        ids = np.argsort(np.linalg.norm(m.positions - truth[i], axis=1))[:images]
        ce = m.similarity(f.codes, ids)
        ca = wm.similarity(f.codes, ids)
        got += int(np.round(ca * np.minimum(len(f), [len(m.codes_of(int(j))) for j in ids]))
                   .sum())
        want += int(np.round(ce * np.minimum(len(f), [len(m.codes_of(int(j))) for j in ids]))
                    .sum())
        same += int(np.argmax(ce) == np.argmax(ca))
    return ApproxRow(name, float(np.median([len(f) for f in feats])), float(np.median(ext_ms)),
                     (float(np.median(ms_e)), float(np.median(ms_a))),
                     (float(np.mean(err_e)), float(np.mean(err_a))),
                     got / max(want, 1), same / n, ivf.vocabulary.k, train_ms)


def bench_approx(pairs: Sequence[tuple[str, Round, Round]], size: tuple[int, int],
                 frames: int = 60, warmup: int = 20, seed: int = 0, k: int = 0,
                 probes: int = DEFAULT_PROBES, cap: int = 0, exact_geometry: bool = False,
                 exact_top: int = 0) -> list[ApproxRow]:
    """One row per (name, map round, query round), OpenCV and BLAS on one thread; ``k`` 0:
    the map's own (``words_for`` its features per image); ``cap``:
    at most that many features per frame, with a low detector threshold (``bench extract``'s
    sweep), 0: the default features; ``exact_geometry``: the two-view geometry keeps the exact
    matcher's pairs (only the similarity goes through the inverted file); ``exact_top``: the
    best N images of each comparison matched again exactly (``RouteMap.with_words``)."""
    from threadpoolctl import threadpool_limits

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(1, "blas"):
            return [compare(mr, q, name, size, frames, warmup, seed, k, probes, cap,
                            exact_geometry, exact_top=exact_top) for name, mr, q in pairs]
    finally:
        cv2.setNumThreads(threads)


def report(rows: Sequence[ApproxRow], say: Callable[[str], object] = print) -> None:
    say("| query | features/frame | k | train ms | extract ms | step ms exact / ivf | "
        "step / extract exact / ivf | error m exact / ivf (change) | counts ivf / exact | "
        "same best image |")
    say("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        (se, sa), (ee, ea) = r.step_ms, r.error_m
        change = 100 * (ea - ee) / ee if ee > 0 else float("nan")
        say(f"| {r.query} | {r.features:.0f} | {r.words} | {r.train_ms:.0f} | "
            f"{r.extract_ms:.1f} | {se:.1f} / {sa:.1f} | "
            f"{se / r.extract_ms:.2f} / {sa / r.extract_ms:.2f} | {ee:.2f} / {ea:.2f} "
            f"({change:+.1f} %) | {r.count_ratio:.3f} | {100 * r.best_same:.0f} % |")


def report_growth(rows: Sequence[ApproxRow], queries: int = 1,
                  say: Callable[[str], object] = print) -> None:
    """A sweep's growth (rows: ``queries`` per cap, caps in turn): each step's median over
    the first cap's of the same query, beside the features'."""
    for i, r in enumerate(rows[queries:], queries):
        first = rows[i % queries]
        f = r.features / first.features
        say(f"{r.query}: features x{f:.2f}, step exact x{r.step_ms[0] / first.step_ms[0]:.2f}"
            f", ivf x{r.step_ms[1] / first.step_ms[1]:.2f} (linear: x{f:.2f})")
