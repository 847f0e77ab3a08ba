"""A robot following a learning one: what it gains when its session moves onto the new
experiences live.

Robot ``teacher`` replays round 1 of a light with ``learn`` (and the round's odometry) on the
world's sunny map; two followers replay round 2 ``--lag`` frames behind it, one frame each
per teacher frame once they start, their sessions created before the teacher's first frame and
never reset:

- *live* on the sunny map itself, which the teacher's collections extend every
  ``SWARMLOC_LEARN_COMMIT_IMAGES`` images (the session moves onto each new version);
- *frozen* on a copy of the sunny map under another name that nobody teaches (what the same
  session got before sessions moved live: the version it was created on).

Everything goes through ``LocalizationService.process_frame`` in this process (the real
frame path, a maps directory in a temporary folder), once the service has built both maps'
two-view structures (a service that has run a while). Printed per follower: the mean and median
error from frame ``--warmup`` of its round, the share of its frames matched with a learned
layer and its frame time (``process_frame``, median and mean, the mean against the frozen
follower's in the same run); then the map's versions and the moves. Nothing is asserted.

    PYTHONPATH=. python scripts/experience_follow.py /work/expd/w23 cloudy --lag 100
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from client.dataset import read_round
from client.lab.experiment_cli import map_for
from client.runs import odometry_poses
from service.api.models import Estimate, SessionConfig
from service.engine.localization_service import LocalizationService
from service.maps.route_map import save_map
from service.settings import Settings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("world", type=Path)
    ap.add_argument("light", help="the rounds LIGHT1 (taught) and LIGHT2 (followed)")
    ap.add_argument("--lag", type=int, default=100, help="frames the followers start later")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--features", default="clahe-rootsift+xfeat")
    a = ap.parse_args()
    taught, followed = read_round(a.world / f"{a.light}1"), read_round(a.world / f"{a.light}2")
    n = min(a.frames, len(taught), len(followed))
    base = map_for(a.world, "sunny1", papers=False, features=a.features)
    maps = Path(tempfile.mkdtemp()) / "maps"
    maps.mkdir()
    save_map(dataclasses.replace(base, name="live"), maps / "live")
    save_map(dataclasses.replace(base, name="frozen"), maps / "frozen")
    service = LocalizationService(Settings(maps_dir=maps, session_store="memory",
                                           zenoh_enabled=False))
    service.warmer.wait(900)  # a service that has run a while: its maps' structures built
    service.put_session("teacher", SessionConfig(map="live", learn=True, condition=a.light))
    for name in ("live", "frozen"):
        service.put_session(name, SessionConfig(map=name))
    teach_odom = odometry_poses(taught.odometry, np.arange(n))
    follow_odom = odometry_poses(followed.odometry, np.arange(n))
    out: dict[str, list[Estimate]] = {"live": [], "frozen": []}
    took: dict[str, list[float]] = {"live": [], "frozen": []}
    for k in range(n + a.lag):
        if k < n:
            service.process_frame("teacher", taught.image_path(k).read_bytes(), t=float(k),
                                  odom=teach_odom[k])
        elif k == n:
            service.delete_session("teacher")  # what it collected since the last write
        j = k - a.lag
        if 0 <= j < n:
            for name, ests in out.items():
                data = followed.image_path(j).read_bytes()
                t0 = time.perf_counter()
                ests.append(service.process_frame(name, data, t=float(j), odom=follow_odom[j]))
                took[name].append(time.perf_counter() - t0)
    service.writer.wait(120)
    truth = followed.reference_xy[:n]
    print(f"{a.world.name} {a.light}: teacher on {a.light}1, followers on {a.light}2 "
          f"{a.lag} frames behind, {n} frames each")
    frozen_ms = 1e3 * float(np.mean(took["frozen"]))
    for name, ests in out.items():
        err = np.linalg.norm(np.array([[e.x, e.y] for e in ests]) - truth, axis=1)[a.warmup:]
        learned = np.mean([e.experience is not None for e in ests])
        ms = 1e3 * np.array(took[name])
        print(f"  {name}: {err.mean():.2f} m (median {np.median(err):.2f}), "
              f"{learned:.0%} of frames on a learned layer; frame time median "
              f"{np.median(ms):.1f} ms, mean {ms.mean():.1f} ms (x{ms.mean() / frozen_ms:.2f} of "
              "frozen)")
    m = service.get_map("live")
    print(f"  map: {len(m.positions) - len(base.positions)} images learned, "
          f"{len(m.meta.get('compatible_versions') or [])} earlier versions; sessions moved "
          f"{service.metrics.sessions_moved._value.get():.0f} times")
    service.close()


if __name__ == "__main__":
    main()
