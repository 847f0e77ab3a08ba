"""What a map image's structure costs to build: two views against several neighbours.

For the images of a map in order (as a robot or the geometry warmer meets them), each image's
structure is built on a fresh geometry, once with the partner alone (``min_views`` 0) and once
with the neighbours (the default), alternating per image so that both see the same machine
load. Printed per feature type: the median and p90 of one structure's build (ms, the pairs'
poses it finds computed by an earlier image included, as on a route) and the ratio of the
medians, and the points per structure. Nothing is asserted.

    PYTHONPATH=. python scripts/structure_cost.py /work/expd/w23 --images 120
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from client.lab.experiment_cli import map_for
from service.maps.route_map import load_map
from service.vision.map_geometry import GeometryParams


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("world", type=Path)
    ap.add_argument("--map", default="sunny1")
    ap.add_argument("--images", type=int, default=120)
    ap.add_argument("--start", type=int, default=20)
    ap.add_argument("--features", default="clahe-rootsift+xfeat")
    ap.add_argument("--views-m", default=",".join(f"{d:g}" for d in GeometryParams().views_m),
                    help="the neighbours' distances ahead and behind (m, comma-separated)")
    a = ap.parse_args()
    built = map_for(a.world, a.map, papers=False, features=a.features)
    assert built.path is not None
    views = GeometryParams(views_m=tuple(float(d) for d in a.views_m.split(",")))
    two = replace(views, min_views=0)
    m = load_map(built.path)
    for name, geo in (("rootsift", m.geometry), ("xfeat", m.second_geometry)):
        if geo is None:
            continue
        ms: dict[str, list[float]] = {"two views": [], "neighbours": []}
        pts: dict[str, list[int]] = {"two views": [], "neighbours": []}
        for i in range(a.start, min(a.start + a.images, m.n_images)):
            for label, p in (("two views", two), ("neighbours", views)):
                t0 = time.perf_counter()
                st = geo.structure(i, p)
                ms[label].append((time.perf_counter() - t0) * 1000)
                if st is not None:
                    pts[label].append(len(st.feature_ids))
        (t2, tn) = (np.median(ms["two views"]), np.median(ms["neighbours"]))
        print(f"{a.world.name} {name}: structure p50 / p90: two views {t2:.1f} / "
              f"{np.percentile(ms['two views'], 90):.1f} ms, neighbours {tn:.1f} / "
              f"{np.percentile(ms['neighbours'], 90):.1f} ms, ratio p50 x{tn / t2:.2f}; points "
              f"{np.median(pts['two views']):.0f} / {np.median(pts['neighbours']):.0f}")


if __name__ == "__main__":
    main()
