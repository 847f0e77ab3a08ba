"""The fleet viewer driven by headless Chromium: the screenshot (docs/reference/viewer.md)
and a load benchmark.

Both use Debian's ``chromium`` through Playwright (``pip install -e ".[dev]"``; no browser
download) against a real server on loopback.
"""

from __future__ import annotations

import math
import shutil
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.api.models import Estimate

STATUSES = ("initializing", "tracking", "recovering", "lost")


def chromium_executable() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        raise RuntimeError("chromium is not installed: run 'sh tests/install-system-deps.sh'")
    return exe


@contextmanager
def chromium_page(width: int, height: int) -> Iterator:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium_executable(), headless=True,
                                     args=["--no-sandbox", "--disable-gpu"])
        try:
            yield browser.new_page(viewport={"width": width, "height": height})
        finally:
            browser.close()


def _noise_png(seed: int) -> bytes:
    import cv2

    img = np.random.default_rng(seed).integers(0, 256, (240, 320), dtype=np.uint8)
    return cv2.imencode(".png", cv2.GaussianBlur(img, (0, 0), 3))[1].tobytes()


def screenshot(maps_dir: Path, round_dir: Path, out: Path, map_name: str | None = None,
               robots: int = 6, frames: int = 24, width: int = 1280, height: int = 760) -> Path:
    """A fleet on a real server, seen by the viewer: tracking robots, one recovering (its
    particles shown), one lost (PF-l), all fed real frames of ``round_dir`` over HTTP."""
    from client.dataset import read_round
    from client.transports import HttpClient
    from service.engine.localization_service import LocalizationService
    from service.server import free_port, running_server
    from service.settings import Settings

    rnd = read_round(round_dir)
    settings = Settings(maps_dir=maps_dir, host="127.0.0.1", port=free_port(),
                        zenoh_enabled=False, workers=2, session_store="memory")
    service = LocalizationService(settings)
    name = map_name or service.default_map
    ids = [f"robot-{i + 1}" for i in range(robots)]
    lost, recovering = ids[-1], ids[-2]
    n = len(rnd)
    with running_server(service, zenoh=False) as url:
        api = HttpClient(url)
        try:
            for i, rid in enumerate(ids):
                api.create_session(rid, name, "pf-l" if rid == lost else "dpso", seed=i)
            with chromium_page(width, height) as page:
                page.goto(f"{url}/viewer?map={name}")
                page.wait_for_selector('#conn[data-state="live"]')
                for k in range(frames):  # every robot one frame at a time: they move together
                    for i, rid in enumerate(ids):
                        img = rnd.image_path((i * n // robots + k) % n).read_bytes()
                        api.localize(rid, img, t=0.6 * k)
                    time.sleep(0.05)
                for k in range(4):  # frames that match nothing
                    t = 0.6 * (frames + k)
                    api.localize(recovering, _noise_png(k), t=t)
                    api.localize(lost, _noise_png(10 + k), t=t)
                page.locator(f'li.robot[data-robot="{recovering}"] input').check()
                page.wait_for_selector('#conn[data-state="live"]')
                time.sleep(0.6)  # past the particle interval
                api.localize(recovering, _noise_png(99), t=0.6 * (frames + 5))
                page.wait_for_function(f"() => window.swarmloc.fleet.robots.get('{recovering}')"
                                       "?.particles?.length > 0")
                page.locator(f'li.robot[data-robot="{ids[0]}"]').click()
                page.wait_for_selector(f'li.robot[data-robot="{lost}"][data-status="lost"]')
                time.sleep(0.5)
                out.parent.mkdir(parents=True, exist_ok=True)
                page.screenshot(path=str(out))
        finally:
            api.close()
    return out


# ---- load ---------------------------------------------------------------------------------
@dataclass
class ViewerBench:
    robots: int
    fps: float
    seconds: float
    particles: bool
    published: int
    received: int
    dropped: int
    raf_ms_p50: float
    raf_ms_p95: float
    raf_ms_max: float
    draw_ms_p50: float
    draw_ms_p95: float
    long_tasks: int


_RECORDER = """() => {
  window.__bench = { raf: [], longTasks: 0, draws0: window.swarmloc.stats.drawTimes.length,
                     messages0: window.swarmloc.fleet.messages };
  new PerformanceObserver((l) => { window.__bench.longTasks += l.getEntries().length; })
    .observe({ entryTypes: ["longtask"] });
  let last = performance.now();
  const f = (t) => { window.__bench.raf.push(t - last); last = t; requestAnimationFrame(f); };
  requestAnimationFrame(f);
}"""

_RESULT = """() => ({ raf: window.__bench.raf.slice(1), longTasks: window.__bench.longTasks,
  draws: window.swarmloc.stats.drawTimes.slice(window.__bench.draws0),
  messages: window.swarmloc.fleet.messages - window.__bench.messages0 })"""


def _synthetic_fleet(route: np.ndarray, robots: int, fps: float, seconds: float,
                     particles: bool,
                     publish: Callable[[Estimate, float, np.ndarray | None], None],
                     seed: int = 0) -> int:
    """Estimates of ``robots`` robots driving along the route at ``fps``; returns the count.

    The service cannot localize 64 x 5 real frames per second on a small machine, so the
    load on the stream and the page is made here: what the hub publishes is what a real
    fleet would send.
    """
    rng = np.random.default_rng(seed)
    seg = np.linalg.norm(np.diff(route, axis=0), axis=1)
    s_of = np.concatenate([[0.0], np.cumsum(seg)])
    length = float(s_of[-1])
    start = rng.uniform(0, length, robots)
    speed = rng.uniform(0.5, 1.5, robots)
    period = 1.0 / fps
    count, t0 = 0, time.perf_counter()
    k = 0
    while True:
        now = time.perf_counter() - t0
        if now > seconds:
            return count
        s = (start + speed * k * period) % length
        x = np.interp(s, s_of, route[:, 0])
        y = np.interp(s, s_of, route[:, 1])
        for i in range(robots):
            status = STATUSES[1] if i % 16 else STATUSES[2 + (i // 16) % 2]
            est = Estimate(seq=k + 1, stamp=k * period, frame_id="m", estimator="dpso",
                           x=float(x[i]), y=float(y[i]), heading=float(rng.uniform(-math.pi,
                                                                                  math.pi)),
                           speed=float(speed[i]), status=status,  # type: ignore[arg-type]
                           lost=status == "lost",
                           score=0.2, comparisons=20, covariance=[[1, 0], [0, 1]],
                           pose_covariance=[0.0] * 36, accuracy_m=1.5, nearest_image=0,
                           nearest_image_name="0", spread_m=1.0, robot_id=f"robot-{i:02d}")
            xy = None
            if particles and (k + i) % max(1, round(fps / 2)) == 0:  # 2 snapshots/s
                xy = np.column_stack([x[i], y[i]]) + rng.normal(0, 2.0, (80, 2))
            publish(est, 0.025, xy)
            count += 1
        k += 1
        time.sleep(max(0.0, (k * period) - (time.perf_counter() - t0)))


def bench_viewer(maps_dir: Path, map_name: str | None = None, robots: int = 64,
                 fps: float = 5.0, seconds: float = 10.0, particles: bool = False
                 ) -> ViewerBench:
    """The viewer in headless Chromium with ``robots`` robots at ``fps`` estimates per
    second: animation-frame intervals, canvas draw time, long tasks, messages delivered."""
    from service.engine.localization_service import LocalizationService
    from service.server import free_port, running_server
    from service.settings import Settings

    settings = Settings(maps_dir=maps_dir, host="127.0.0.1", port=free_port(),
                        zenoh_enabled=False, session_store="memory")
    service = LocalizationService(settings)
    name = map_name or service.default_map
    route = service.get_map(name).positions
    hub = service.events

    def publish(est: Estimate, latency: float, xy: np.ndarray | None) -> None:
        hub.publish(est.model_copy(update={"frame_id": name}), latency, xy)

    with running_server(service, zenoh=False) as url, chromium_page(1280, 800) as page:
        page.goto(f"{url}/viewer?map={name}")
        page.wait_for_selector('#conn[data-state="live"]')
        if particles:
            page.locator("#all-particles").check()
            time.sleep(0.5)
            page.wait_for_selector('#conn[data-state="live"]')
        dropped0 = service.metrics.events_dropped._value.get()
        page.evaluate(_RECORDER)
        box: dict = {}
        th = threading.Thread(target=lambda: box.setdefault(
            "n", _synthetic_fleet(route, robots, fps, seconds, particles, publish)))
        th.start()
        th.join()
        time.sleep(0.3)
        res = page.evaluate(_RESULT)
        dropped = int(service.metrics.events_dropped._value.get() - dropped0)
    raf = np.array(res["raf"] or [0.0])
    draws = np.array(res["draws"] or [0.0])
    return ViewerBench(robots, fps, seconds, particles, box["n"], int(res["messages"]), dropped,
                       float(np.median(raf)), float(np.percentile(raf, 95)), float(raf.max()),
                       float(np.median(draws)), float(np.percentile(draws, 95)),
                       int(res["longTasks"]))
