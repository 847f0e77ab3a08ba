"""A learning robot's frame latency with the gates on the learner's threads (now) against the
gates on the frame path (before), in one run.

The service runs in process (``LocalizationService.process_frame``, decode, extraction,
localizer step and learning) on the world's sunny map of both feature types
(``swarmloc bench experiences`` builds it: DATA/wSEED/.maps), a learning session sent the
first FRAMES frames of round LIGHT1 with the round's odometry; the two ways alternate, twice
each, and the script prints p50 / p90 / p99 / max per run, the frames taught and bridged
(the same both ways), and the ratios over both runs of each way. "Before" calls
``Learner.observe`` where the service calls ``Learner.submit`` (lab only).

    PYTHONPATH=. python scripts/learning_latency.py /work/expd 0 dusk 150
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from client.dataset import read_round
from client.lab.experiment_cli import map_for
from client.runs import odometry_poses
from service.api.models import SessionConfig
from service.engine.localization_service import LocalizationService
from service.settings import Settings


def run(sunny: Path, frames: list[bytes], poses: list, light: str, on_path: bool
        ) -> tuple[np.ndarray, dict[str, int]]:
    d = Path(tempfile.mkdtemp())
    try:
        shutil.copy(sunny, d / "sunny1.swmap")
        svc = LocalizationService(Settings(maps_dir=d, session_store="memory"))
        if on_path:
            svc.learner.submit = svc.learner.observe  # type: ignore[method-assign]
        svc.put_session("r", SessionConfig(map="sunny1", learn=True, condition=light))
        lat = []
        for i, frame in enumerate(frames):
            t0 = time.perf_counter()
            svc.process_frame("r", frame, t=float(i), odom=poses[i])
            lat.append((time.perf_counter() - t0) * 1e3)
        stats = svc.learner.stats("r")
        svc.close()
    finally:
        shutil.rmtree(d, ignore_errors=True)
    return np.array(lat), stats


def main(data: Path, seed: int, light: str, n: int) -> None:
    world = data / f"w{seed}"
    sunny = map_for(world, "sunny1", papers=False, features="clahe-rootsift+xfeat").path
    assert sunny is not None
    rnd = read_round(world / f"{light}1")
    poses = odometry_poses(rnd.odometry, np.arange(n))
    frames = [rnd.image_path(i).read_bytes() for i in range(n)]
    runs: dict[bool, list[np.ndarray]] = {True: [], False: []}
    for on_path in (True, False, True, False):
        lat, st = run(sunny, frames, poses, light, on_path)
        runs[on_path].append(lat)
        way = "gates on the frame path" if on_path else "gates on the learner's threads"
        print(f"{way}: p50 {np.median(lat):.1f} p90 {np.percentile(lat, 90):.1f} "
              f"p99 {np.percentile(lat, 99):.1f} max {lat.max():.1f} ms; taught "
              f"{st.get('taught')} bridged {st.get('bridged')}", flush=True)
    a, b = np.concatenate(runs[True]), np.concatenate(runs[False])
    for name, q in (("p50", 50.0), ("p99", 99.0), ("max", 100.0)):
        x, y = np.percentile(a, q), np.percentile(b, q)
        print(f"{name}: {x:.1f} -> {y:.1f} ms (x{y / x:.2f})")


if __name__ == "__main__":
    main(Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3], int(sys.argv[4]))
