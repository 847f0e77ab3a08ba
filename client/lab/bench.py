"""Benchmarks that print numbers (never asserted in tests)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from client.lab.stats import median_ms, percentile
from client.lab.world import Pose, World
from client.transports import Client
from service.maps.route_map import prune
from service.vision.features import BatchMatch, extract, match_batch, similarity_bfmatcher


@dataclass
class SimilarityBench:
    extract_ms: float
    batched_ms_per_comparison: float
    bfmatcher_ms_per_comparison: float
    speedup: float
    k: int
    frame_features: float
    map_features: float
    counts_equal: bool


def bench_similarity(seed: int = 0, k: int = 20, repeats: int = 7) -> SimilarityBench:
    """SIFT extraction per 320x240 frame; batched m(A, B) vs BFMatcher on the same descriptors.

    Frames come from a rendered round; the K map-side sets are pruned like a real map.
    """
    world = World(seed)
    poses, t, _ = world.round_trajectory(0)
    frames = [world.render(Pose(*poses[i]), "sunny", t=float(t[i]), noise_seed=i)
              for i in range(0, 2 * (k + 2), 2)]
    extract_ms = float(np.median([median_ms(partial(extract, f), 1) for f in frames]))
    feats = [extract(f) for f in frames]
    pruned, _ = prune(feats)
    query = extract(world.render(Pose(*poses[1]), "cloudy", t=float(t[1]), noise_seed=99))
    sets = [p.descriptors for p in pruned[:k]]
    a = query.descriptors
    batched = median_ms(lambda: match_batch(a, sets), repeats) / k
    bf = median_ms(lambda: [similarity_bfmatcher(a, b) for b in sets], max(3, repeats // 2)) / k
    counts = match_batch(a, sets).counts.tolist()
    ref = [similarity_bfmatcher(a, b)[0] for b in sets]
    return SimilarityBench(extract_ms, batched, bf, bf / batched, k, float(len(a)),
                           float(np.mean([len(s) for s in sets])), counts == ref)


@dataclass
class LatencyBench:
    transport: str
    frames: int
    p50_ms: float
    p99_ms: float
    mean_ms: float


def bench_latency(maps_dir: str, round_dir: str, frames: int = 200, seed: int = 0
                  ) -> list[LatencyBench]:
    """Per-frame latency as a robot sees it, 320x240 PNG frames, against a real server
    (uvicorn + Zenoh bridge on loopback) and in process (no transport) for reference."""
    from client.dataset import read_round
    from client.transports import HttpClient, LocalClient, ZenohClient
    from service.engine.localization_service import LocalizationService
    from service.server import free_port, running_server
    from service.settings import Settings

    rnd = read_round(round_dir)
    data = [rnd.image_path(i % len(rnd)).read_bytes() for i in range(frames)]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(maps_dir=Path(maps_dir), host="127.0.0.1", port=free_port(),
                        zenoh_listen=[endpoint], zenoh_multicast_scouting=False,
                        session_store="memory")  # as the in-process client's
    with running_server(LocalizationService(settings)) as url:
        clients: dict[str, Client] = {
                   "in-process": LocalClient(maps_dir), "http": HttpClient(url),
                   "zenoh": ZenohClient([endpoint], mode="peer")}
        try:
            return [_time_frames(name, c, data, seed) for name, c in clients.items()]
        finally:
            for c in clients.values():
                c.close()


def _time_frames(name: str, client: Client, data: list[bytes], seed: int) -> LatencyBench:
    client.create_session("bench", None, "dpso", None, seed)
    times = []
    for k, frame in enumerate(data):
        t0 = time.perf_counter()
        client.localize("bench", frame, t=float(k))
        times.append(1e3 * (time.perf_counter() - t0))
    client.delete_session("bench")
    warm = np.array(times[10:])  # the first frames pay for global convergence
    return LatencyBench(name, len(warm), percentile(warm, 50),
                        percentile(warm, 99), float(warm.mean()))


@dataclass
class Ros2Bench:
    jpeg_bytes: int
    compressed_in_ms: float  # CDR CompressedImage -> validated bytes
    image_in_ms: float  # CDR mono8 Image -> grayscale pixels
    bgr_in_ms: float  # CDR bgr8 Image -> grayscale pixels
    pose_out_ms: float  # Estimate -> CDR PoseWithCovarianceStamped
    status_out_ms: float  # Estimate -> CDR DiagnosticStatus
    extract_ms: float  # SIFT on the same frame, for scale


def bench_ros2(seed: int = 0, repeats: int = 200) -> Ros2Bench:
    """What the ROS 2 layer adds per frame: CDR decoding of a 320x240 frame (rosbags) and
    encoding of the answer, beside the frame's SIFT extraction."""
    import cv2

    from service.api.models import Estimate
    from service.zenoh.ros2 import COMPRESSED_IMAGE, IMAGE, Codec, Stamp

    codec = Codec()
    t = codec.types
    world = World(seed)
    poses, times, _ = world.round_trajectory(0)
    img = world.render(Pose(*poses[5]), "sunny", t=float(times[5]), noise_seed=5)
    jpeg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].ravel()
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="camera")
    comp = codec.serialize(t[COMPRESSED_IMAGE](header=header, format="jpeg", data=jpeg),
                           COMPRESSED_IMAGE)
    h, w = img.shape

    def raw(enc: str, pixels: np.ndarray) -> bytes:
        return codec.serialize(t[IMAGE](header=header, height=h, width=w, encoding=enc,
                                        is_bigendian=0, step=pixels.size // h,
                                        data=pixels.ravel()), IMAGE)

    mono, bgr = raw("mono8", img), raw("bgr8", np.dstack([img, img, img]))
    big = 1 << 30
    est = Estimate(seq=1, stamp=1.0, frame_id="map", estimator="dpso", x=1.0, y=2.0,
                   heading=0.5, speed=1.0, status="tracking", lost=False, score=0.2,
                   comparisons=20, covariance=[[1.0, 0.0], [0.0, 1.0]],
                   pose_covariance=[0.0] * 36, accuracy_m=1.5, nearest_image=0,
                   nearest_image_name="00000.png", spread_m=1.0)
    body = est.model_dump(mode="json")
    return Ros2Bench(
        len(jpeg),
        median_ms(lambda: codec.frame(comp, COMPRESSED_IMAGE, big, big), repeats),
        median_ms(lambda: codec.frame(mono, IMAGE, big, big), repeats),
        median_ms(lambda: codec.frame(bgr, IMAGE, big, big), repeats),
        median_ms(lambda: codec.pose(est, Stamp(1, 0), "map", 0.3), repeats),
        median_ms(lambda: codec.status("robot1", body), repeats),
        median_ms(lambda: extract(img), 15))
# ---- event stream -----------------------------------------------------------------------
@dataclass
class EventsBench:
    condition: str
    frames: int
    frame_ms_p50: float  # process_frame (decode, SIFT, estimator, publish), median
    hook_us_p50: float  # particles_due + publish alone, median
    hook_us_mean: float  # the same, mean (includes the rate-limited particle snapshots)
    messages: int  # event messages the viewer received
    bytes_per_estimate: float


class _SseViewer:
    """A viewer on GET /events in a thread: reads and counts what arrives."""

    def __init__(self, url: str, params: dict) -> None:
        import threading

        self.messages = 0
        self.estimate_bytes = 0
        self.estimates = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(url, params), daemon=True)
        self._thread.start()

    def _run(self, url: str, params: dict) -> None:
        import json

        import httpx

        with httpx.stream("GET", f"{url}/events", params=params, timeout=60) as resp:
            for line in resp.iter_lines():
                if self._stop.is_set():
                    return
                if line.startswith("data:"):
                    for m in json.loads(line[5:])["m"]:
                        self.messages += 1
                        if m["k"] == "e":
                            self.estimates += 1
                            self.estimate_bytes += len(json.dumps(m, separators=(",", ":")))

    def close(self) -> None:
        self._stop.set()


def bench_events(maps_dir: str, round_dir: str, frames: int = 150, block: int = 25,
                 hook_calls: int = 400, seed: int = 0) -> list[EventsBench]:
    """Cost of the event stream per frame: no viewer, one viewer, one viewer with particles.

    Frames go through ``LocalizationService.process_frame`` (the code both transports call,
    with the stream's hook in it) of a real server whose /events is read by a real HTTP
    client in a thread. Conditions alternate in blocks of ``block`` frames so drift hits
    all of them alike. The hook alone (``particles_due`` + ``publish``) is timed apart,
    ``hook_calls`` times per condition, one call per millisecond.
    """
    from client.dataset import read_round
    from service.api.models import SessionConfig
    from service.engine.localization_service import LocalizationService
    from service.server import free_port, running_server
    from service.settings import Settings

    rnd = read_round(round_dir)
    data = [rnd.image_path(i % len(rnd)).read_bytes() for i in range(frames)]
    settings = Settings(maps_dir=Path(maps_dir), host="127.0.0.1", port=free_port(),
                        zenoh_enabled=False, session_store="memory")
    service = LocalizationService(settings)
    hub = service.events
    conditions = {"no viewer": None, "one viewer": {},
                  "one viewer + particles": {"particles": "bench"}}
    frame_ms: dict[str, list[float]] = {c: [] for c in conditions}
    hook_us: dict[str, list[float]] = {c: [] for c in conditions}
    received = dict.fromkeys(conditions, 0)
    est_bytes = dict.fromkeys(conditions, 0.0)
    with running_server(service, zenoh=False) as url:
        service.put_session("bench", SessionConfig(estimator="dpso", seed=seed))
        session = service.session("bench")
        k = 0

        def frame() -> float:
            nonlocal k
            t0 = time.perf_counter()
            service.process_frame("bench", data[k % frames], t=float(k), session=session)
            k += 1
            return 1e3 * (time.perf_counter() - t0)

        def hook() -> float:
            last = session.localizer.last
            assert last is not None  # the warm-up frames made estimates
            est = last.model_copy(update={"robot_id": "bench"})
            t0 = time.perf_counter()
            with session.lock:
                xy = hub.particles_due("bench", session.localizer)
            hub.publish(est, 0.02, xy)
            return 1e6 * (time.perf_counter() - t0)

        frame()
        rounds = max(1, frames // (block * len(conditions)))
        for _ in range(rounds):
            for name, params in conditions.items():
                viewer = _SseViewer(url, params) if params is not None else None
                if viewer is not None:
                    _wait(lambda: hub.subscribers == 1)
                for _ in range(block):
                    frame_ms[name].append(frame())
                    time.sleep(0.01)  # the event loop writes to the viewer meanwhile
                for _ in range(hook_calls // rounds):
                    hook_us[name].append(hook())
                    time.sleep(0.001)
                if viewer is not None:
                    time.sleep(0.2)
                    viewer.close()
                    received[name] += viewer.messages
                    if viewer.estimates:
                        est_bytes[name] = viewer.estimate_bytes / viewer.estimates
                    frame()  # the stream ends at its next message; the viewer sees it closed
                    _wait(lambda: hub.subscribers == 0)
    return [EventsBench(c, len(frame_ms[c]), float(np.median(frame_ms[c])),
                        float(np.median(hook_us[c])), float(np.mean(hook_us[c])),
                        received[c], est_bytes[c]) for c in conditions]


def _wait(cond: Callable[[], bool], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise RuntimeError("the event stream did not connect or close in time")
        time.sleep(0.01)


def bench_build_latency(maps_dir: str, round_dir: str, frames: int = 150, fps: float = 5.0,
                        seed: int = 0, duty: float = 0.5
                        ) -> tuple[list[LatencyBench], float, str]:
    """Frame latency of one robot streaming over HTTP at ``fps``: with no build, then while
    the service builds a map from ``round_dir``, then with no build again (real server; the
    maps are copied to a temporary folder). Returns the three latencies, the build's duration
    (s) and its final state."""
    import shutil
    import tempfile
    from pathlib import Path

    from client.dataset import read_round
    from client.map_remote import zip_round
    from client.transports import HttpClient
    from service.engine.localization_service import LocalizationService
    from service.server import free_port, running_server
    from service.settings import Settings

    rnd = read_round(round_dir)
    data = [rnd.image_path(i).read_bytes() for i in range(len(rnd))]
    period = 1.0 / fps if fps > 0 else 0.0
    with tempfile.TemporaryDirectory() as tmp:
        maps = Path(tmp) / "maps"
        maps.mkdir()
        for f in Path(maps_dir).glob("*.swmap"):
            shutil.copy(f, maps / f.name)
        archive = zip_round(round_dir, Path(tmp) / "round.zip")
        settings = Settings(maps_dir=maps, host="127.0.0.1", port=free_port(),
                            zenoh_enabled=False, build_duty=duty, session_store="memory")
        with running_server(LocalizationService(settings), zenoh=False) as url:
            client = HttpClient(url)
            try:
                client.create_session("bench", None, "dpso", None, seed)
                k = 0

                def frame() -> float:
                    nonlocal k
                    t0 = time.perf_counter()
                    client.localize("bench", data[k % len(data)], t=float(k))
                    k += 1
                    took = time.perf_counter() - t0
                    time.sleep(max(0.0, period - took))
                    return 1e3 * took

                idle = [frame() for _ in range(frames)][10:]  # after global convergence
                job = client.build_map_remote("bench-build", archive)
                busy, polled = [], time.monotonic()
                while job.state in ("queued", "running"):
                    busy.append(frame())
                    if time.monotonic() - polled > 1.0:
                        job, polled = client.job(job.id), time.monotonic()
                job = client.job(job.id)
                build_s = (job.finished or 0.0) - (job.started or 0.0)
                after = [frame() for _ in range(frames - 10)]  # brackets drifting load
            finally:
                client.close()
    return ([_stats("no build", idle), _stats("during build", busy),
             _stats("no build, after", after)], build_s, job.state)


def _stats(name: str, times: list[float]) -> LatencyBench:
    a = np.array(times)
    return LatencyBench(name, len(a), percentile(a, 50), percentile(a, 99),
                        float(a.mean()))


# ---- matcher: exact uint8 similarity vs the float path ---------------------------------------
@dataclass
class MatcherBench:
    source: str
    queries: int
    k: int
    frame_features: float
    map_features: float
    float_ms: float  # match_batch on float32 unit vectors, 1 BLAS thread (per comparison)
    float_default_blas_ms: float  # the same with the process's default BLAS threads
    fast_ms: float  # match_batch_u8, default backend (NumKong), prepared sets
    fast_blas_ms: float  # match_batch_u8, float32 BLAS GEMM backend, 1 BLAS thread
    float_2threads_ms: float  # two threads at once (throughput per comparison)
    fast_2threads_ms: float
    counts_identical: bool  # fast paths == exact reference, on every comparison
    float_counts_identical: bool  # float path == exact reference
    comparisons: int

    @property
    def speedup(self) -> float:
        return self.float_ms / self.fast_ms


def _rendered_matcher_sets(seed: int, k: int, places: int) -> tuple[list, list]:
    """Cloudy query frames (round 1) and, per query, K sunny map frames (round 0): the ten
    nearest frames around the place (as a swarm compares) and the rest from other places."""

    world = World(seed)
    poses0, t0, _ = world.round_trajectory(0)
    poses1, t1, _ = world.round_trajectory(1)
    n = min(len(poses0), len(poses1))
    centres = [int(n * (p + 0.5) / places) for p in range(places)]
    near = k // 2
    cache: dict[int, np.ndarray] = {}

    def map_frame(i: int) -> np.ndarray:
        i %= n
        if i not in cache:
            cache[i] = _codes(world.render(Pose(*poses0[i]), "sunny", t=float(t0[i]),
                                                noise_seed=i))
        return cache[i]

    queries, sets = [], []
    for c in centres:
        queries.append(_codes(world.render(Pose(*poses1[c]), "cloudy", t=float(t1[c]),
                                                noise_seed=10_000 + c)))
        idx = [c + 2 * (j - near // 2) for j in range(near)]
        far = [o for o in centres if o != c]
        idx += [far[j % len(far)] + 4 * (j // len(far)) for j in range(k - near)]
        sets.append([map_frame(i) for i in idx])
    return queries, sets


def _codes(image: np.ndarray) -> np.ndarray:
    """The map's default descriptor codes (CLAHE + RootSIFT, uint8) of a frame."""
    from service.vision.features import extract

    return extract(image).codes


def _photo_matcher_sets(photos: str, k: int, places: int) -> tuple[list, list]:
    """Query photos spread over the sequence; per query, its K/2 nearest photos by index and
    K/2 others spread over the sequence."""
    from pathlib import Path

    import cv2


    paths = sorted(p for p in Path(photos).iterdir()
                   if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if len(paths) < k + 1:
        raise ValueError(f"{photos}: need at least {k + 1} images, found {len(paths)}")
    feats = [_codes(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)) for p in paths]
    n = len(feats)
    queries, sets = [], []
    for p in range(places):
        c = int(n * (p + 0.5) / places)
        order = sorted((i for i in range(n) if i != c), key=lambda i: abs(i - c))
        idx = order[: k // 2]
        rest = [i for i in range(n) if i != c and i not in idx]
        idx += [rest[int(j * len(rest) / (k - k // 2))] for j in range(k - k // 2)]
        queries.append(feats[c])
        sets.append([feats[i] for i in idx])
    return queries, sets


def _per_comparison_ms(fn: Callable[[int], object], queries: int, k: int, repeats: int,
                       cpu: bool = True) -> float:
    """Median over queries of the median time of one query against its K sets, per set:
    CPU time of the thread (single-threaded work) or wall time."""
    return percentile([median_ms(partial(fn, q), repeats, cpu) for q in range(queries)], 50) / k


def _two_threads_ms(fn: Callable[[int], object], queries: int, k: int, repeats: int) -> float:
    """Two threads run the same workload at once (as two robots would): wall time per
    comparison, so a value equal to the one-thread figure means no parallel speed-up."""
    from concurrent.futures import ThreadPoolExecutor

    def work() -> None:
        for _ in range(repeats):
            for q in range(queries):
                fn(q)

    with ThreadPoolExecutor(2) as pool:
        t0 = time.perf_counter()
        for f in [pool.submit(work), pool.submit(work)]:
            f.result()
        wall = time.perf_counter() - t0
    return 1e3 * wall / (2 * repeats * queries * k)


def bench_matcher(photos: str | None = None, seed: int = 0, k: int = 20, places: int = 3,
                  repeats: int = 5) -> MatcherBench:
    """Exact uint8 matcher (NumKong GEMM + numba top-2) against the float ``match_batch`` on
    the same descriptors (quantised CLAHE + RootSIFT; the float path gets them normalised)."""
    from threadpoolctl import threadpool_limits

    from service.vision.features import unit_descriptors
    from service.vision.matcher import match_batch_u8, match_batch_u8_reference, prepare, warm_up

    if photos:
        queries, sets = _photo_matcher_sets(photos, k, places)
        source = f"photos {photos}"
    else:
        queries, sets = _rendered_matcher_sets(seed, k, places)
        source = f"rendered world seed {seed} (sunny map, cloudy queries)"
    warm_up()  # numba compiles (or loads its cache) here, outside every timed section
    fq = [unit_descriptors(a) for a in queries]
    fsets = [[unit_descriptors(b) for b in s] for s in sets]
    prepared = [[prepare(b) for b in s] for s in sets]
    prepared_blas = [[prepare(b, "blas") for b in s] for s in sets]

    def float_path(q: int) -> BatchMatch:
        return match_batch(fq[q], fsets[q])

    def fast(q: int) -> BatchMatch:
        return match_batch_u8(queries[q], prepared[q])

    def fast_blas(q: int) -> BatchMatch:
        return match_batch_u8(queries[q], prepared_blas[q], backend="blas")

    nq = len(queries)
    identical, float_identical = True, True
    for q in range(nq):
        ref = match_batch_u8_reference(queries[q], sets[q]).counts
        identical &= bool(np.array_equal(fast(q).counts, ref))
        identical &= bool(np.array_equal(fast_blas(q).counts, ref))
        float_identical &= bool(np.array_equal(float_path(q).counts, ref))
    float_default = _per_comparison_ms(float_path, nq, k, repeats, cpu=False)
    with threadpool_limits(1, "blas"):
        float_ms = _per_comparison_ms(float_path, nq, k, repeats)
        fast_ms = _per_comparison_ms(fast, nq, k, repeats)
        fast_blas_ms = _per_comparison_ms(fast_blas, nq, k, repeats)
        float2 = _two_threads_ms(float_path, nq, k, repeats)
        fast2 = _two_threads_ms(fast, nq, k, repeats)
    return MatcherBench(
        source, nq, k, float(np.mean([len(a) for a in queries])),
        float(np.mean([len(b) for s in sets for b in s])), float_ms, float_default, fast_ms,
        fast_blas_ms, float2, fast2, identical, float_identical, nq * k)


# ---- feature types: SIFT, CLAHE + RootSIFT (uint8), ORB (AKAZE where OpenCV has it) -----
@dataclass
class FeatureTypeBench:
    name: str
    features: float  # per frame (mean)
    extract_ms: float  # per 320x240 frame (median)
    match_ms: float  # per comparison (median over queries of one frame vs the whole map)
    cross_light_top1: float  # cloudy frames whose most similar map image lies within 5 m
    same_light_top1: float  # sunny frames of another round, the same
    map_images: int
    queries: int


def _binary_similarity(a: np.ndarray, b: np.ndarray, ratio: float = 0.8) -> float:
    """The symmetric ratio test on Hamming distances (binary descriptors have no angle):
    reciprocal nearest neighbours with d1 < ratio * d2 both ways, over min(|A|, |B|)."""
    import cv2

    if len(a) < 2 or len(b) < 2:
        return 0.0
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)

    def one_way(q: np.ndarray, t: np.ndarray) -> dict[int, int]:
        return {m1.queryIdx: m1.trainIdx for m1, m2 in bf.knnMatch(q, t, k=2)
                if m1.distance < ratio * m2.distance}

    ab, ba = one_way(a, b), one_way(b, a)
    return sum(1 for i, j in ab.items() if ba.get(j) == i) / min(len(a), len(b))


def _feature_types() -> dict[str, tuple[Callable, Callable]]:
    """name -> (extract(image) -> descriptors, similarities(query, map sets) -> scores)."""
    import cv2

    from service.vision.features import SiftParams, extract, to_working_size
    from service.vision.matcher import match_batch_u8, prepare

    def clahe(image: np.ndarray) -> np.ndarray:
        gray = to_working_size(image, SiftParams())
        return cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(gray)

    def binary(detector: Callable[[], Any]) -> Callable[[np.ndarray], np.ndarray]:
        def run(image: np.ndarray) -> np.ndarray:
            _, d = detector().detectAndCompute(clahe(image), None)
            return d if d is not None else np.zeros((0, 32), np.uint8)
        return run

    def binary_scores(q: np.ndarray, sets: list) -> np.ndarray:
        return np.array([_binary_similarity(q, b) for b in sets])

    types = {
        "SIFT (float32, all)": (
            lambda im: extract(im, SiftParams.papers()).descriptors,
            lambda q, sets: match_batch(q, sets).scores),
        "CLAHE + RootSIFT (uint8)": (
            _codes, lambda q, sets: match_batch_u8(q, sets).scores),
        "CLAHE + ORB (1500)": (binary(lambda: cv2.ORB_create(nfeatures=1500)), binary_scores),
    }
    if hasattr(cv2, "AKAZE_create"):  # OpenCV 5 moved AKAZE out of the main modules
        types["CLAHE + AKAZE"] = (binary(cv2.AKAZE_create), binary_scores)
    types["_prepare"] = (prepare, lambda q, sets: None)  # type: ignore[assignment,return-value]
    return types


def bench_features(seed: int = 0, length_m: float = 120.0, map_step: int = 3,
                   queries: int = 10, repeats: int = 3) -> list[FeatureTypeBench]:
    """Extraction time, matching time and place recognition (top-1 within 5 m) per feature
    type, on a sunny map against cloudy (cross-light) and sunny (same-light) frames."""
    from threadpoolctl import threadpool_limits

    from service.vision.matcher import warm_up

    world = World(seed, length_m=length_m)
    p0, t0, _ = world.round_trajectory(0)
    map_idx = list(range(0, len(p0), map_step))
    map_imgs = [world.render(Pose(*p0[i]), "sunny", t=float(t0[i]), noise_seed=i) for i in map_idx]
    map_xy = p0[map_idx, :2]
    q_sets = {}
    for label, rnd, cond in (("cross", 1, "cloudy"), ("same", 2, "sunny")):
        p, t, _ = world.round_trajectory(rnd)
        idx = [int(len(p) * (j + 0.5) / queries) for j in range(queries)]
        q_sets[label] = ([world.render(Pose(*p[i]), cond, t=float(t[i]), noise_seed=50_000 + i)
                          for i in idx], p[idx, :2])
    warm_up()
    types = _feature_types()
    prepare = types.pop("_prepare")[0]
    with threadpool_limits(1, "blas"):  # CPU time of this thread is then all the work
        return [_bench_feature_type(name, extract_fn, scores_fn, prepare, map_imgs, map_xy,
                                    q_sets, queries, repeats)
                for name, (extract_fn, scores_fn) in types.items()]


def _bench_feature_type(name: str, extract_fn: Callable, scores_fn: Callable,
                        prepare: Callable, map_imgs: list, map_xy: np.ndarray, q_sets: dict,
                        queries: int, repeats: int) -> FeatureTypeBench:
    extract_fn(map_imgs[0])  # first-call set-up outside the timing
    map_desc = [extract_fn(im) for im in map_imgs]
    if "uint8" in name:
        map_desc = [prepare(d) for d in map_desc]
    top1, match_ms, ext_ms, n_feat = {}, [], [], []
    for label, (imgs, xy) in q_sets.items():
        hits = 0
        for img, truth in zip(imgs, xy, strict=True):
            times = []
            for _ in range(repeats):
                t = time.thread_time()
                q = extract_fn(img)
                times.append(time.thread_time() - t)
            ext_ms.append(1e3 * float(np.median(times)))
            n_feat.append(len(q))
            t = time.thread_time()
            scores = scores_fn(q, map_desc)
            match_ms.append(1e3 * (time.thread_time() - t) / len(map_desc))
            best = int(np.argmax(scores))
            hits += bool(np.linalg.norm(map_xy[best] - truth) <= 5.0)
        top1[label] = hits / len(imgs)
    return FeatureTypeBench(name, float(np.mean(n_feat)), float(np.median(ext_ms)),
                            float(np.median(match_ms)), top1["cross"], top1["same"],
                            len(map_imgs), queries)
