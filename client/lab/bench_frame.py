"""``swarmloc bench frame``: where the time of one frame goes, in process and through each
transport (HTTP to a real uvicorn server, Zenoh through real sessions on loopback).

The stages are timed by wrapping, in this process only and for the length of the benchmark,
the functions ``LocalizationService.process_frame`` calls (``decode_frame``,
``Localizer.extract``, ``Localizer.step`` and the matcher's ``prepare`` of a map image not
yet cached); the service's own code is unchanged and pays nothing when no benchmark runs.

Per frame and path:

- ``decode``: PNG/JPEG to grayscale pixels (``service.vision.imaging.decode_frame``);
- ``extract``: CLAHE + RootSIFT (the map's feature type);
- ``step``: the localizer step, the estimator with its comparisons and the ``Estimate``;
  ``prepare`` (inside ``step``): map images prepared for the matcher on first use;
- ``glue``: the rest of ``process_frame`` (session lookup and lock, checks, metrics, the
  event stream's hook, the answer's copy);
- ``serialise``: the ``Estimate`` to JSON as the transport's server side encodes it and
  back as its client decodes it (the same calls, timed on the frame's estimate);
- ``transport``: what remains of the robot's round trip (HTTP parsing, thread hand-offs,
  loopback, the client library); split in ``request`` (from the client's call to the start
  of ``process_frame``) and ``response`` (from its end to the client holding the
  ``Estimate``; includes the serialisation). In process, ``transport`` is the call of
  ``LocalClient`` around ``process_frame`` (microseconds).

In process, a frame is ``process_frame`` on the encoded bytes (what ``LocalClient`` does).
The three robots (in process, HTTP, Zenoh) have sessions with the same seed and get the same
frames, one after another, in a rotating order (so none always pays the map-image cache
misses for the others): their estimates must be identical, which the result reports.
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from client.lab.stats import percentile
from service.api.models import Matcher
from service.vision.matcher import fastest_gemm

STAGES = ("decode", "extract", "step", "prepare", "glue", "serialise", "transport", "request",
          "response")


@dataclass
class PathTimes:
    """Per-frame stage times (ms) of one path (``in-process``, ``http``, ``zenoh``)."""

    name: str
    stages: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in STAGES})
    total: list[float] = field(default_factory=list)  # the robot's round trip (ms)
    server: list[float] = field(default_factory=list)  # process_frame alone (ms)

    def p(self, stage: str, q: float) -> float:
        values = self.total if stage == "total" else self.stages[stage]
        return percentile(values, q)


@dataclass
class FrameBench:
    map_name: str
    map_images: int
    frames: int  # frames measured per path (after the warm-up)
    features: float  # mean features per frame
    comparisons: float  # mean comparisons per frame
    paths: dict[str, PathTimes]
    identical: bool  # the three robots got identical estimates for every frame
    matcher: str = "auto"  # the service's SWARMLOC_MATCHER (auto: and what it chose)

    @property
    def step_ratio(self) -> float:
        """In process: p50 of the localizer step / p50 of the extraction."""
        p = self.paths["in-process"]
        return p.p("step", 50) / p.p("extract", 50)

    @property
    def beyond_extraction(self) -> float:
        """In process: (p50 of everything beyond extraction) / (p50 of extraction)."""
        p = self.paths["in-process"]
        beyond = np.array(p.total) - np.array(p.stages["extract"])
        return float(np.median(beyond)) / p.p("extract", 50)

    def ratio(self, transport: str) -> float:
        """p50 of the robot's round trip over ``transport`` / p50 in process."""
        return self.paths[transport].p("total", 50) / self.paths["in-process"].p("total", 50)


class _Probe:
    """Stage timers around the functions process_frame calls (this process only)."""

    def __init__(self) -> None:
        self._local = threading.local()

    def record(self) -> dict[str, float] | None:
        return getattr(self._local, "rec", None)

    def begin(self) -> dict[str, float]:
        rec = {"decode": 0.0, "extract": 0.0, "step": 0.0, "prepare": 0.0}
        self._local.rec = rec
        return rec

    def end(self) -> None:
        self._local.rec = None

    def timed(self, stage: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                rec = self.record()
                if rec is not None:
                    rec[stage] += 1e3 * (time.perf_counter() - t0)
        return wrapper

    @contextlib.contextmanager
    def installed(self, service: Any, server_ms: dict[tuple[str, int], dict[str, float]]
                  ) -> Iterator[None]:
        """Wrap the stage functions and ``service.process_frame``; restore them on exit."""
        import service.engine.localization_service as sessions_mod
        import service.maps.route_map as route_map_mod
        from service.engine.localizer import Localizer

        saved: tuple[Callable[..., Any], ...] = (
            sessions_mod.decode_frame, route_map_mod.prepare, Localizer.extract, Localizer.step)
        original = service.process_frame

        def process_frame(robot_id: str, data: Any, **kw: Any) -> Any:
            rec = self.begin()
            t0 = time.perf_counter()
            rec["start"] = t0
            try:
                return original(robot_id, data, **kw)
            finally:
                rec["end"] = time.perf_counter()
                rec["total"] = 1e3 * (rec["end"] - t0)
                self.end()
                server_ms[(robot_id, int(kw.get("input_seq") or 0))] = rec

        patches = ((sessions_mod, "decode_frame", "decode"), (route_map_mod, "prepare", "prepare"),
                   (Localizer, "extract", "extract"), (Localizer, "step", "step"))
        for (owner, attr, stage), fn in zip(patches, saved, strict=True):
            setattr(owner, attr, self.timed(stage, fn))
        service.process_frame = process_frame
        try:
            yield
        finally:
            for (owner, attr, _), fn in zip(patches, saved, strict=True):
                setattr(owner, attr, fn)
            del service.process_frame  # the class's method again


def _serialise_ms(transport: str, est: Any, repeats: int = 3) -> float:
    """The answer's encoding on the server and decoding on the client, as each transport
    does them (HTTP: the route's JSON body and httpx's ``json()`` + ``Estimate(**...)``;
    Zenoh: ``json.dumps(model_dump(mode="json"))`` and ``json.loads`` + ``Estimate(**...)``;
    in process: the answer's ``model_copy``, already in ``glue``, so 0)."""
    from service.api.models import Estimate
    from service.http.app import estimate_json

    if transport == "in-process":
        return 0.0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        if transport == "http":
            raw = estimate_json(est)
        else:
            raw = json.dumps(est.model_dump(mode="json")).encode()
        Estimate(**json.loads(raw))
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def bench_frame(maps_dir: Path, round_dir: Path, frames: int = 100, warmup: int = 10,
                seed: int = 0, transports: tuple[str, ...] = ("http", "zenoh"),
                workers: int = 0, matcher: Matcher = "auto",
                warm_geometry: bool = True) -> FrameBench:
    """Per-frame stage times in process and over each transport, in one run (see the module
    docstring). ``maps_dir`` must hold one map (or a map named ``demo``); ``matcher``: the
    service's ``SWARMLOC_MATCHER``; ``warm_geometry``: its ``SWARMLOC_WARM_GEOMETRY``, the
    frames sent once the structures are built."""
    import cv2

    from client.dataset import read_round
    from client.transports import Client, HttpClient, LocalClient, ZenohClient
    from service.engine.localization_service import LocalizationService
    from service.server import free_port, limit_native_threads, running_server
    from service.settings import Settings
    from service.vision.features import extract
    from service.vision.matcher import warm_up

    rnd = read_round(round_dir)
    data = [rnd.image_path(i % len(rnd)).read_bytes() for i in range(frames + warmup)]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(maps_dir=Path(maps_dir), host="127.0.0.1", port=free_port(),
                        zenoh_enabled="zenoh" in transports, zenoh_listen=[endpoint],
                        zenoh_multicast_scouting=False, workers=workers,
                        session_store="memory",  # the transports' cost, not the store's
                        matcher=matcher, warm_geometry=warm_geometry)
    limit_native_threads(settings)  # as ``swarmloc serve`` does
    warm_up()
    service = LocalizationService(settings)
    service.warmer.wait(3600)  # a service some seconds after its start
    route_map = service.maps[service.default_map]
    names = ("in-process", *transports)
    paths = {n: PathTimes(n) for n in names}
    server_ms: dict[tuple[str, int], dict[str, float]] = {}
    probe = _Probe()
    identical = True
    features: list[int] = []
    comparisons: list[int] = []
    with running_server(service, zenoh="zenoh" in transports) as url, \
            probe.installed(service, server_ms):
        clients: dict[str, Client] = {"in-process": LocalClient(service=service)}
        if "http" in transports:
            clients["http"] = HttpClient(url, timeout=300)
        if "zenoh" in transports:
            clients["zenoh"] = ZenohClient([endpoint], mode="peer", timeout=300)
        try:
            for name, c in clients.items():
                c.create_session(f"bench-{name}", route_map.name, "dpso", None, seed)
            for k, frame in enumerate(data):
                order = names[k % len(names):] + names[: k % len(names)]
                answers: dict[str, str] = {}
                for name in order:
                    robot = f"bench-{name}"
                    t0 = time.perf_counter()
                    est = clients[name].localize(robot, frame, t=float(k), seq=k + 1)
                    t1 = time.perf_counter()
                    rtt = 1e3 * (t1 - t0)
                    answers[name] = est.model_dump_json(exclude={"robot_id"})
                    if k < warmup:
                        continue
                    rec = server_ms.pop((robot, k + 1))
                    p = paths[name]
                    ser = _serialise_ms(name, est)
                    inner = rec["decode"] + rec["extract"] + rec["step"]
                    for stage in ("decode", "extract", "step", "prepare"):
                        p.stages[stage].append(rec[stage])
                    p.stages["glue"].append(rec["total"] - inner)
                    p.stages["serialise"].append(ser)
                    p.stages["transport"].append(rtt - rec["total"] - ser)
                    p.stages["request"].append(1e3 * (rec["start"] - t0))
                    p.stages["response"].append(1e3 * (t1 - rec["end"]))
                    p.server.append(rec["total"])
                    p.total.append(rtt)
                    if name == "in-process":
                        comparisons.append(est.comparisons)
                identical &= len(set(answers.values())) == 1
                server_ms.clear()
            for name, c in clients.items():
                c.delete_session(f"bench-{name}")
        finally:
            for c in clients.values():
                c.close()
    params = route_map.feature_params
    for frame in data[warmup: warmup + 20]:
        img = cv2.imdecode(np.frombuffer(frame, np.uint8), cv2.IMREAD_GRAYSCALE)
        features.append(len(extract(img, params)))
    return FrameBench(route_map.name, route_map.n_images, frames, float(np.mean(features)),
                      float(np.mean(comparisons)), paths, identical,
                      f"{matcher} ({'words' if route_map.uses_words else 'exact'} on this map)"
                      if matcher == "auto" else matcher)


def report(b: FrameBench, emit: Callable[[str], None] = print) -> None:
    """The breakdown table and the issue's ratios."""
    emit(f"map '{b.map_name}' ({b.map_images} images), matcher {b.matcher}; {b.frames} frames "
         f"per path after the warm-up; {b.features:.0f} features and {b.comparisons:.1f} "
         "comparisons per frame")
    emit(f"exact GEMM: {fastest_gemm().describe()}; XFeat's: {fastest_gemm('int8').describe()}")
    head = f"{'stage (ms)':<12}" + "".join(f"{n + ' p50':>14}{'p90':>8}" for n in b.paths)
    emit(head)
    for stage in (*STAGES, "total"):
        row = f"{stage:<12}"
        for p in b.paths.values():
            row += f"{p.p(stage, 50):14.3f}{p.p(stage, 90):8.3f}"
        emit(row)
    emit("(prepare is part of step; total = decode + extract + step + glue + serialise + "
         "transport per frame; transport + serialise = request + response; medians do not "
         "add up exactly)")
    ip = b.paths["in-process"]
    beyond = float(np.median(np.array(ip.total) - np.array(ip.stages["extract"])))
    emit(f"in process: beyond extraction p50 {beyond:.2f} ms / extraction p50 "
         f"{ip.p('extract', 50):.2f} ms = {100 * b.beyond_extraction:.0f} % (target <= 50 %)")
    emit(f"in process, matcher {b.matcher}: step p50 {ip.p('step', 50):.2f} ms / extraction "
         f"p50 {ip.p('extract', 50):.2f} ms = {b.step_ratio:.2f} (target <= 0.5)")
    for name in b.paths:
        if name != "in-process":
            emit(f"{name} p50 {b.paths[name].p('total', 50):.2f} ms / in-process p50 "
                 f"{ip.p('total', 50):.2f} ms = {b.ratio(name):.3f} (target <= 1.2)")
    emit(f"estimates identical on every path: {'yes' if b.identical else 'NO'}")
