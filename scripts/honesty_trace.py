"""Honesty of DPSO on a map, per run: frames more than 10 m off that are reported ``tracking``.

Replays the first N frames of a rendered world's second round of a light (``WORLD/COND2``,
with its odometry, as ``swarmloc replay`` sends it) on MAP, once per DPSO seed, and prints
per run the mean error after 20 frames and the frames more than 10 m from the truth that
were reported ``tracking`` (issue 34's honesty check of a learned map). With ``-v`` every
frame is printed too: error, status, the reported heading and its source, the direction the
robot really drove, and the odometry's map-heading offsets (the fit's and the located
camera yaws', in degrees; ``None``: none).

    PYTHONPATH=. python scripts/honesty_trace.py MAP WORLD COND N SEEDS [-v]
    PYTHONPATH=. python scripts/honesty_trace.py \
        out/exp/w23-dusk-clahe-rootsift+xfeat/sunny1.swmap data/w23 dusk 200 0,1,2

The learned map is the one ``swarmloc bench experiences ... --work DIR`` leaves in ``DIR``.
Run from another checkout (``cd CHECKOUT && python /path/to/honesty_trace.py ...`` with that
checkout on ``PYTHONPATH``) to compare two versions of the estimator on the same map.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from client.dataset import read_round
from client.lab.bench_experience import WARMUP
from client.runs import odometry_poses
from service.engine.localizer import Localizer
from service.maps.route_map import load_map
from service.vision.features import extract

OFF_M = 10.0  # a frame this far off must not be reported tracking


def _deg(v: float | None) -> str:
    return "None" if v is None else f"{math.degrees(v):.1f}"


def main(argv: list[str]) -> None:
    verbose = "-v" in argv
    args = [a for a in argv if a != "-v"]
    if len(args) != 5:
        raise SystemExit(__doc__)
    m = load_map(Path(args[0]))
    rnd = read_round(Path(args[1]) / f"{args[2]}2")
    if rnd.odometry is None:
        raise SystemExit(f"{rnd.name} has no odometry.csv: render the world again")
    feats = [extract(rnd.load_image(i), m.feature_params)
             for i in range(min(int(args[3]), len(rnd)))]
    truth = rnd.reference_xy[: len(feats)]
    drive = np.degrees(np.arctan2(*np.diff(truth, axis=0).T[::-1]))
    dt = float(np.median(np.diff(rnd.t))) if rnd.t is not None and len(rnd) > 1 else 1.0
    poses = odometry_poses(rnd.odometry, np.arange(len(feats)))
    for seed in (int(s) for s in args[4].split(",")):
        loc = Localizer(m, seed=seed)
        errors, dishonest = [], []
        for i, f in enumerate(feats):
            e = loc.step(f, t=i * dt, odom=poses[i])
            err = float(np.hypot(e.x - truth[i, 0], e.y - truth[i, 1]))
            errors.append(err)
            if err > OFF_M and e.status == "tracking":
                dishonest.append(i)
            if verbose:
                od = loc.estimator.odometry
                print(f"{i:4d} err {err:7.2f} m {e.status:12s} heading "
                      f"{math.degrees(e.heading):7.1f} {e.heading_source:9s} drove "
                      f"{drive[min(i, len(drive) - 1)]:7.1f} fit "
                      f"{_deg(None if od is None else od.offset)} yaws "
                      f"{_deg(None if od is None else od.seen)}")
        print(f"DPSO seed {seed}: mean {np.mean(errors[WARMUP:]):.2f} m, frames > {OFF_M:g} m "
              f"off reported tracking: {len(dishonest)} {dishonest}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
