"""``swarmloc bench first-frame``: the first frame after a fresh install and start, beside a
later one.

A fresh install is simulated by a copy of the ``service`` and ``client`` packages in a
temporary directory (no numba cache beside the source, none in the cache directory, which is
new and empty, or cannot be created with ``unwritable``). ``swarmloc serve`` runs from that
copy on the demo map (service/demo); the time from the process start to GET /readyz
answering 200 is the start-up, then one robot sends the demo round's frames over HTTP.
Printed: the start-up, the first frame's round trip, the median of the later ones and their
ratio (the issue's target: at most 2), and a second robot's first frame afterwards (what a new
session's first frame costs in a warm process: its global search).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from client.lab.stats import percentile

ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class FirstFrame:
    startup_s: float  # process start to ready
    first_ms: float  # the first frame's round trip
    later_ms: float  # the median round trip of the later frames
    second_robot_first_ms: float  # a second robot's first frame, after them (warm process)
    frames: int
    banner_kernels: str  # the banner's "kernels" line

    @property
    def ratio(self) -> float:
        return self.first_ms / self.later_ms


def copy_packages(dest: Path) -> Path:
    """``service`` and ``client`` copied to ``dest`` without caches: a fresh install."""
    for name in ("service", "client"):
        shutil.copytree(ROOT / name, dest / name,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc"))
    return dest


def bench_first_frame(frames: int = 20, unwritable: bool = False) -> FirstFrame:
    from client.dataset import read_round
    from client.lab.processes import ServiceProcess
    from client.transports import HttpClient
    from service.demo import DEMO_ROUND_DIR, ensure_demo_map

    with tempfile.TemporaryDirectory(prefix="swarmloc-first-frame-") as tmp:
        root = Path(tmp)
        pkg = copy_packages(root / "pkg")
        ensure_demo_map(root / "maps")
        cache = root / "numba-cache"
        if unwritable:
            cache.write_text("a file: the cache directory cannot be made below it")
            cache = cache / "numba"
        rnd = read_round(DEMO_ROUND_DIR)
        data = [rnd.image_path(i % len(rnd)).read_bytes() for i in range(frames)]
        proc = ServiceProcess("first-frame", {
            "PYTHONPATH": str(pkg), "SWARMLOC_MAPS_DIR": str(root / "maps"),
            "SWARMLOC_NUMBA_CACHE_DIR": str(cache), "SWARMLOC_ZENOH_ENABLED": "false",
            "SWARMLOC_SESSION_STORE": "memory"}, root)
        t0 = time.perf_counter()
        try:
            proc.start().wait_ready(timeout_s=600)
            startup = time.perf_counter() - t0
            kernels = next((line.strip() for line in proc.log_tail(20_000).splitlines()
                            if line.strip().startswith("kernels")), "kernels: (no line)")
            client = HttpClient(proc.url, timeout=120)
            try:
                client.create_session("bench", "demo")
                ms = []
                for k, frame in enumerate(data):
                    t1 = time.perf_counter()
                    client.localize("bench", frame, t=float(k))
                    ms.append(1e3 * (time.perf_counter() - t1))
                client.create_session("bench-2", "demo")
                t1 = time.perf_counter()
                client.localize("bench-2", data[0], t=0.0)
                second = 1e3 * (time.perf_counter() - t1)
            finally:
                client.close()
        finally:
            proc.stop()
    return FirstFrame(startup, ms[0], percentile(ms[1:], 50), second, frames, kernels)


def report(b: FirstFrame, say: Callable[[str], object] = print) -> None:
    say(f"start-up to ready: {b.startup_s:.1f} s ({b.banner_kernels})")
    say(f"first frame {b.first_ms:.1f} ms; later frames (median of {b.frames - 1}) "
        f"{b.later_ms:.1f} ms; first / later = {b.ratio:.2f} (target <= 2)")
    say(f"a second robot's first frame (the process warm, its session new): "
        f"{b.second_robot_first_ms:.1f} ms")
