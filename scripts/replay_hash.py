"""Hash of a fixed replay without odometry: the bit-identity check of issue 33.

Every estimator kind over a rendered cloudy round (seed 3, 90 m), and with a second
dataset (a rendered world with sunny1 and cloudy1) DPSO and PF-l on a map with the camera
(located frames). Each Estimate is hashed but for ``heading_source`` and ``experience``,
which did not exist before odometry and experience maps. Run it on two checkouts and
compare the lines:

    PYTHONPATH=. python scripts/replay_hash.py /tmp/rh [/tmp/w23]

With ``HEADING=0`` in the environment the heading and its variance (pose_covariance's yaw
entry) are left out too: the check that the camera's yaw (a located frame's heading) moved
no position, status or comparison.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

from client.dataset import read_round
from client.lab.world import World
from service.engine.localizer import Localizer
from service.maps.route_map import build_map, build_map_from_rounds


def _hash(loc: Localizer, rnd, frames: range) -> str:
    h = hashlib.sha256()
    for i in frames:
        d = loc.step(loc.extract(rnd.load_image(i)), t=float(i)).model_dump(mode="json")
        d.pop("heading_source", None)
        d.pop("experience", None)
        if os.environ.get("HEADING") == "0":
            d.pop("heading", None)
            d["pose_covariance"] = d["pose_covariance"][:35]
        h.update(repr(sorted(d.items())).encode())
    return h.hexdigest()[:16]


def main(root: Path, camera_world: Path | None) -> None:
    if not (root / "cloudy1").exists():
        w = World(seed=3, length_m=90.0)
        w.render_round(root / "sunny1", 0, "sunny")
        w.render_round(root / "cloudy1", 3, "cloudy")
    s1, c1 = read_round(root / "sunny1"), read_round(root / "cloudy1")
    m = build_map("small", [s1.load_image(i) for i in range(len(s1))], s1.xy, list(s1.images))
    for est, params in [("dpso", {}), ("dpso", {"variant": "paper"}), ("pf-g", {}),
                        ("pf-l", {})]:
        print(est, params, _hash(Localizer(m, est, params, seed=4), c1, range(len(c1))))
    if camera_world is not None:
        s1, c1 = read_round(camera_world / "sunny1"), read_round(camera_world / "cloudy1")
        m = build_map_from_rounds([s1.subset(range(0, 160))])
        for est in ("dpso", "pf-l"):
            print("camera", est, {}, _hash(Localizer(m, est, {}, seed=5), c1, range(120)))


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]) if len(sys.argv) > 2 else None)
