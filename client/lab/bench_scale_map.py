"""``swarmloc bench scale-map``: what a map's size costs, from 400 to 40,000 images.

For each map of a long route (client/lab/world/long_route.py): the file size, the time to open
it (memory-mapped, lazily verified, as the service does), the start-up time and resident
memory of a real service process (``python -m service``) before and after tracking a robot
over HTTP, and the per-frame localizer time and comparisons while tracking the same leg
(in process, features extracted beforehand, one BLAS thread as in the service). Then, on the
largest map, global relocalisation: fresh starts and kidnaps onto random legs of the route,
frames until the estimate is back within 5 m, comparisons and the place-index query time,
against the cost of comparing the frame with every map image. Numbers are printed, never
asserted.
"""

from __future__ import annotations

import contextlib
import functools
import json
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

RECOVER_RADIUS_M = 5.0
STAY_FRAMES = 5  # back = within the radius for this many frames in a row (or to the leg's end)


@dataclass(frozen=True)
class SizeResult:
    n_images: int
    file_mb: float
    open_ms: float  # load_map(verify="lazy"), median of 3
    startup_s: float  # service process: start until /readyz answers
    rss_start_mib: float
    rss_after_mib: float  # after tracking the leg over HTTP
    step_p50_ms: float  # localizer step while tracking (no extraction), CPU time
    step_mean_ms: float  # CPU time
    wall_p50_ms: float  # the same steps' wall time (noisy on a shared machine)
    comparisons: float  # mean distinct map images compared per tracked frame
    tracked: int  # frames counted (status tracking)
    error_median_m: float


@dataclass(frozen=True)
class RelocalRun:
    kind: str  # "fresh" or "kidnap"
    leg: str
    frames_to_recover: int | None  # None: not back within the leg
    comparisons: int  # map-image comparisons until back (or over the leg)
    index_ms: float  # place-index query time until back (or over the leg)
    step_ms: float  # localizer time until back (index queries included)


def frames_to_recover(err: np.ndarray, radius: float = RECOVER_RADIUS_M,
                      stay: int = STAY_FRAMES) -> int | None:
    """Frames (1-based) until the error is within ``radius`` and stays there ``stay`` frames
    (or to the end); None when that never happens."""
    ok = err <= radius
    for k in range(len(ok)):
        if ok[k: k + stay].all():
            return k + 1
    return None


@functools.lru_cache(maxsize=64)  # the same legs for every map size: extract them once
def _features(round_dir: Path, params: object) -> tuple[list, np.ndarray]:
    from client.dataset import read_round
    from service.vision.features import SiftParams, extract

    assert isinstance(params, SiftParams)
    rnd = read_round(round_dir)
    assert rnd.truth_xy is not None
    return [extract(rnd.load_image(i), params) for i in range(len(rnd))], rnd.truth_xy


@contextlib.contextmanager
def _service(maps_dir: Path) -> Iterator[tuple[str, int, float]]:
    """``swarmloc serve`` (HTTP only) on loopback: (url, pid, start-up seconds)."""
    from client.lab.processes import ServiceProcess
    from service.engine.sqlite_store import sqlite_url

    with tempfile.TemporaryDirectory() as logs:
        t0 = time.perf_counter()
        svc = ServiceProcess("scale-map", {
            "SWARMLOC_MAPS_DIR": str(maps_dir), "SWARMLOC_ZENOH_ENABLED": "false",
            "SWARMLOC_SESSION_STORE": sqlite_url(Path(logs) / "sessions.sqlite")}, Path(logs))
        try:
            svc.start().wait_ready(180.0)
            startup = time.perf_counter() - t0
            assert svc.proc is not None
            yield svc.url, svc.proc.pid, startup
        finally:
            svc.stop()


def _server(path: Path, track_dir: Path, frames: int) -> tuple[float, float, float]:
    """(start-up s, RSS at ready MiB, RSS after ``frames`` frames over HTTP MiB)."""
    from client.lab.bench_load import rss_mib
    from client.transports import HttpClient

    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / path.name).symlink_to(path.resolve())
        with _service(Path(tmp)) as (url, pid, startup):
            rss0 = rss_mib(pid)
            from client.dataset import read_round

            rnd = read_round(track_dir)
            with contextlib.closing(HttpClient(url, timeout=300)) as client:
                client.create_session("scale", path.stem, "dpso", None, 0)
                for k in range(min(frames, len(rnd))):
                    client.localize("scale", rnd.image_path(k).read_bytes(), t=float(k))
            return startup, rss0, rss_mib(pid)


def bench_size(path: Path, track_dir: Path, server_frames: int = 100,
               seed: int = 0) -> SizeResult:
    from service.engine.localizer import Localizer
    from service.maps.route_map import load_map

    opens = []
    for _ in range(3):
        t0 = time.perf_counter()
        m = load_map(path, verify="lazy")
        opens.append(time.perf_counter() - t0)
    feats, truth = _features(track_dir, m.feature_params)
    loc = Localizer(m, "dpso", None, seed)
    steps, walls, comps, errs = [], [], [], []
    for k, f in enumerate(feats):
        t0, c0 = time.perf_counter(), time.process_time()
        e = loc.step(f, float(k))
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        if e.status == "tracking":
            steps.append(dc)
            walls.append(dt)
            comps.append(e.comparisons)
            errs.append(float(np.hypot(e.x - truth[k, 0], e.y - truth[k, 1])))
    startup, rss0, rss1 = (_server(path, track_dir, server_frames) if server_frames
                           else (float("nan"),) * 3)
    st = np.asarray(steps or [np.nan]) * 1e3
    return SizeResult(m.n_images, path.stat().st_size / 1e6, float(np.median(opens)) * 1e3,
                      startup, rss0, rss1, float(np.median(st)), float(st.mean()),
                      float(np.median(walls)) * 1e3 if walls else float("nan"),
                      float(np.mean(comps)) if comps else float("nan"), len(steps),
                      float(np.median(errs)) if errs else float("nan"))


def bench_relocal(path: Path, route_dir: Path, kidnap_after: int = 40, seed: int = 0,
                  params: dict | None = None, legs: int | None = None) -> list[RelocalRun]:
    """Fresh starts on every leg, and kidnaps from the tracking leg onto every leg."""
    from client.lab.world.long_route import read_legs
    from service.engine.localizer import Localizer
    from service.maps.route_map import load_map

    m = load_map(path, verify="lazy")
    per_loop = int(json.loads((route_dir / "route.json").read_text())["per_loop"])
    plan = [leg for leg in read_legs(route_dir) if leg.name != "track"
            and (leg.loop + 1) * per_loop <= m.n_images][: legs]
    track, _ = _features(route_dir / "queries" / "track", m.feature_params)
    out = []
    for j, leg in enumerate(plan):
        feats, truth = _features(route_dir / "queries" / leg.name, m.feature_params)
        for kind in ("fresh", "kidnap"):
            loc = Localizer(m, "dpso", params, seed + j)
            k0 = 0
            if kind == "kidnap":
                for k in range(kidnap_after):
                    loc.step(track[k], float(k))
                k0 = kidnap_after
            errs, comps, idx_s, step_s = [], [], [], []
            for k, f in enumerate(feats):
                t0 = time.perf_counter()
                e = loc.step(f, float(k0 + k))
                step_s.append(time.perf_counter() - t0)
                idx_s.append(loc.seeder.last_query_s if loc.seeder is not None else 0.0)
                comps.append(e.comparisons)
                errs.append(float(np.hypot(e.x - truth[k, 0], e.y - truth[k, 1])))
            n = frames_to_recover(np.asarray(errs))
            upto = n if n is not None else len(errs)
            out.append(RelocalRun(kind, leg.name, n, int(sum(comps[:upto])),
                                  1e3 * float(sum(idx_s[:upto])),
                                  1e3 * float(sum(step_s[:upto]))))
    return out


def brute_force_ms(path: Path, route_dir: Path, sample: int = 400) -> tuple[float, int]:
    """(ms to compare one frame with every map image, images), from ``sample`` images timed
    and scaled to the map (the cost a global search without an index pays per frame)."""
    from service.maps.route_map import load_map

    m = load_map(path, verify="lazy")
    feats, _ = _features(route_dir / "queries" / "track", m.feature_params)
    ids = np.linspace(0, m.n_images - 1, sample).astype(int)
    m.similarity(feats[0].codes, ids)  # prepare the sampled images once (cached)
    t0 = time.perf_counter()
    m.similarity(feats[1].codes, ids)
    per = (time.perf_counter() - t0) / sample
    return per * m.n_images * 1e3, m.n_images


def run_bench(route_dir: Path, sizes: list[int], server_frames: int, relocal: bool,
              baseline: bool, emit: Callable[[str], None] = print) -> None:
    from threadpoolctl import threadpool_limits

    route_dir = Path(route_dir)
    maps = {n: route_dir / "maps" / f"route-{n}.swmap" for n in sizes}
    missing = [str(p) for p in maps.values() if not p.is_file()]
    if missing:
        raise FileNotFoundError(f"no such map(s) {missing}: run 'swarmloc world long-route "
                                f"{route_dir} --maps {','.join(map(str, sizes))}' first")
    track = route_dir / "queries" / "track"
    with threadpool_limits(1, "blas"):
        res = []
        emit(f"{'images':>7} {'file MB':>9} {'open ms':>8} {'start s':>8} {'RSS MiB':>8} "
             f"{'RSS+trk':>8} {'cpu p50':>8} {'mean':>6} {'wall p50':>8} {'comps':>6} "
             f"{'frames':>6} {'err m':>6}")
        for p in maps.values():
            r = bench_size(p, track, server_frames)
            res.append(r)
            emit(f"{r.n_images:7d} {r.file_mb:9.1f} {r.open_ms:8.1f} {r.startup_s:8.2f} "
                 f"{r.rss_start_mib:8.1f} {r.rss_after_mib:8.1f} {r.step_p50_ms:8.2f} "
                 f"{r.step_mean_ms:6.2f} {r.wall_p50_ms:8.2f} {r.comparisons:6.1f} "
                 f"{r.tracked:6d} "
                 f"{r.error_median_m:6.2f}")
        if len(res) > 1:
            a, b = res[0], res[-1]
            emit(f"ratio {b.n_images}/{a.n_images}: step CPU p50 "
                 f"x{b.step_p50_ms / a.step_p50_ms:.2f}, mean "
                 f"x{b.step_mean_ms / a.step_mean_ms:.2f}, wall p50 "
                 f"x{b.wall_p50_ms / a.wall_p50_ms:.2f} (target <= 1.5); comparisons "
                 f"x{b.comparisons / a.comparisons:.2f}; RSS at start "
                 f"x{b.rss_start_mib / a.rss_start_mib:.2f}; file x{b.file_mb / a.file_mb:.0f}")
        if not relocal:
            return
        big = maps[max(maps)]
        variants: list[tuple[str, dict | None]] = [("place index", None)]
        if baseline:
            variants.append(("random images (place_candidates=0)", {"place_candidates": 0}))
        for label, params in variants:
            runs = bench_relocal(big, route_dir, params=params)
            emit(f"relocalisation on {max(maps)} images, {label}:")
            for kind in ("fresh", "kidnap"):
                for line in summarise([r for r in runs if r.kind == kind], kind):
                    emit(line)
        full_ms, n = brute_force_ms(big, route_dir)
        emit(f"comparing one frame with every image of the {n}-image map: {n} comparisons, "
             f"~{full_ms:.0f} ms per frame (timed on 400 images, scaled)")


def summarise(rr: list[RelocalRun], kind: str) -> list[str]:
    """Lines for one kind of relocalisation run: how many were back in <= 30 frames,
    frames (median, max), comparisons and the index's share of the time until back."""
    back = [r for r in rr if r.frames_to_recover is not None]
    frames = [r.frames_to_recover for r in back if r.frames_to_recover is not None]
    within = sum(1 for f in frames if f <= 30)

    def med(x: Sequence[float]) -> float:
        return float(np.median(x)) if x else float("nan")

    lines = [
        f"  {kind:6s}: {len(rr)} runs, back within {RECOVER_RADIUS_M:.0f} m in <= 30 frames: "
        f"{within}/{len(rr)}; frames to recover median {med(frames):.0f}, max "
        f"{max(frames) if frames else float('nan')}",
        f"          until back (medians): {med([r.comparisons for r in back]):.0f} comparisons"
        f" ({med([r.comparisons / max(r.frames_to_recover or 1, 1) for r in back]):.1f} per"
        f" frame), place-index queries {med([r.index_ms for r in back]):.1f} ms of "
        f"{med([r.step_ms for r in back]):.1f} ms localizer time"]
    lines += [f"    {r.leg}: {r.frames_to_recover or 'not back'} frames" for r in rr
              if r.frames_to_recover is None or r.frames_to_recover > 30]
    return lines
