"""Where round 2's frames are located at a learned image, at the map's own image of the place,
and at both (service/engine/both_layers.py), against their true places.

Every ``--step``-th frame of round 2 of a light is located, with the localizer's own geometry
(RootSIFT's, else XFeat's: ``Localizer.locator``), at the learned image nearest its true place
(within ``GAP_SPACINGS`` map spacings) and at the map's own image nearest that learned image;
printed: how many frames each locates, the fixes' median and mean distance from the truth,
the RANSAC inliers, and the two layers' mean where both locate the frame within ``AGREE_M``
of each other. The frames are taken at their true places, not where a replay's swarm holds
them, so the figures do not depend on the code's estimates. Nothing is asserted.

    PYTHONPATH=. python scripts/layer_fixes.py /work/expd/w7 dusk \
        WORK/w7-dusk-clahe-rootsift+xfeat/sunny1.swmap
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from client.dataset import read_round
from service.engine.both_layers import AGREE_M
from service.engine.localizer import Localizer
from service.estimators.along_track import located_position
from service.maps.experiences import (
    GAP_SPACINGS,
    base_layers,
    base_spacing,
    experience_layers,
    nearest_base,
)
from service.maps.route_map import load_map
from service.vision.features import extract
from service.vision.map_geometry import FramePairs, GeometryParams


def _line(name: str, err: list[float], inliers: list[int] | None = None) -> str:
    e = np.asarray(err, float)
    if not len(e):
        return f"  {name}: none located"
    s = f"  {name}: {len(e)} located, from the truth median {np.median(e):.2f} m, mean " \
        f"{e.mean():.2f} m, more than 1 m {100 * np.mean(e > 1):.0f} %"
    return s if inliers is None else s + f", inliers median {np.median(inliers):.0f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("world", type=Path)
    ap.add_argument("light")
    ap.add_argument("map", type=Path, help="a learned map (.swmap)")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--step", type=int, default=2)
    a = ap.parse_args()
    m = load_map(a.map)
    rnd = read_round(a.world / f"{a.light}2")
    loc = Localizer(m)
    spacing = loc.estimator.spacing
    gap = GAP_SPACINGS * base_spacing(m)
    layers = list(experience_layers(m).values())
    base = base_layers(m)
    learned_e, own_e, both_e, both_only_e = [], [], [], []
    learned_n, own_n = [], []
    frames = range(20, min(a.frames, len(rnd)), a.step)
    for i in frames:
        truth = rnd.reference_xy[i]
        near = [m.nearest_in_layer(truth[None, :], k) for k in layers]
        k = int(np.argmin([d[0] for _, d in near]))
        if float(near[k][1][0]) > gap:
            continue  # a gap of the experiences
        image = int(near[k][0][0])
        ids, dist = nearest_base(m, m.positions[image][None, :], base)
        own = int(ids[0, int(np.argmin(dist[0]))])
        locate = loc.locator(extract(rnd.load_image(i), m.feature_params),
                             FramePairs(GeometryParams().delta))
        assert locate is not None, "the map has no camera"
        fixes = []
        for img, errs, ns in ((image, learned_e, learned_n), (own, own_e, own_n)):
            off = locate(img)
            at = None if off is None else \
                located_position(m.positions, img, off.right_m, off.ahead_m, spacing)
            fixes.append(at)
            if at is not None and off is not None:
                errs.append(float(np.linalg.norm(at - truth)))
                ns.append(off.inliers)
        here, there = fixes
        if here is not None:
            agree = there is not None and float(np.linalg.norm(there - here)) <= AGREE_M
            mean = (here + there) / 2 if agree and there is not None else here
            both_e.append(float(np.linalg.norm(mean - truth)))
            if agree:
                both_only_e.append(both_e[-1])
    print(f"{a.world.name} {a.light}2 at {a.map} ({len(frames)} frames, one in {a.step} "
          f"from the 21st)")
    print(_line("the learned image", learned_e, learned_n))
    print(_line("the map's own image", own_e, own_n))
    print(_line("both (the product's fix at a learned image)", both_e))
    print(_line("both, where both locate it", both_only_e))


if __name__ == "__main__":
    main()
