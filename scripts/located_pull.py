"""How well each feature type's two-view geometry locates a frame beside the map's lane.

Every ``--step``-th frame of a round (``ROUND``: a round directory's name, ``cloudy1``; a
light alone means its round 1) is located, by RootSIFT's and by XFeat's geometry separately
(``MapGeometry.locate``, the product's PnP), at the map image nearest its true place. Printed
per type: frames located, median RANSAC inliers, the offset's error in the map camera's frame
(right and ahead, with the slope of the located right offset against the true one: 1 where
nothing pulls it), the *pull* (the error across the path towards the map's lane, positive
when the frame is placed nearer the map's lane than it was), and the distance of the placed
frame from the truth (the map image's own position error included). Also per type: the median
Sampson distance of the map's image pairs' essential-matrix inliers (3 px RANSAC), the
precision of its keypoints. Nothing is asserted.

    PYTHONPATH=. python scripts/located_pull.py /work/expd/w23 cloudy --step 4
    PYTHONPATH=. python scripts/located_pull.py /work/expd/w23 cloudy2 --map cloudy1
    PYTHONPATH=. python scripts/located_pull.py /work/expd/w23 cloudy --min-views 0

``--min-views 0``: each map image's structure from its partner alone (two views), as before
the structure was triangulated from several neighbours.
"""

from __future__ import annotations

import cv2
import numpy as np

from client.dataset import read_round
from client.lab.experiment_cli import map_for
from client.lab.located_fix import located_fix_parser
from service.estimators.along_track import path_tangent
from service.maps.experiences import base_spacing
from service.vision.features import Features, extract
from service.vision.map_geometry import GeometryParams, MapGeometry


def sampson_px(geo: MapGeometry, ids: range, p: GeometryParams) -> float:
    """Median Sampson distance (px) of the essential-matrix inliers of each image and its
    structure partner."""
    out = []
    for i in ids:
        j = geo.partner(i, p.baseline_m)
        if j is None:
            continue
        ia, ib = geo.images.image_pairs(i, j, p.delta)
        if len(ia) < 8:
            continue
        p1 = geo.images.keypoints_of(i)[ia].astype(np.float64)
        p2 = geo.images.keypoints_of(j)[ib].astype(np.float64)
        e, mask = cv2.findEssentialMat(p1, p2, geo.k, cv2.RANSAC, 0.999, 3.0)
        if e is None or e.shape != (3, 3) or mask is None:
            continue
        kinv = np.linalg.inv(geo.k)
        f = kinv.T @ e @ kinv
        x1 = np.column_stack([p1, np.ones(len(p1))])
        x2 = np.column_stack([p2, np.ones(len(p2))])
        fx1, ftx2 = x1 @ f.T, x2 @ f
        d = np.abs(np.sum(x2 * fx1, 1)) / np.sqrt(
            fx1[:, 0] ** 2 + fx1[:, 1] ** 2 + ftx2[:, 0] ** 2 + ftx2[:, 1] ** 2)
        out.append(float(np.median(d[mask.ravel() > 0])))
    return float(np.median(out)) if out else float("nan")


def main() -> None:
    ap = located_fix_parser(__doc__ or "")
    ap.add_argument("--min-views", type=int, default=GeometryParams().min_views,
                    help="neighbours that must see a structure point (0: the partner alone)")
    ap.add_argument("--views-m", default=",".join(f"{d:g}" for d in GeometryParams().views_m),
                    help="the neighbours' distances ahead and behind (m, comma-separated)")
    a = ap.parse_args()
    name = a.round if a.round[-1].isdigit() else f"{a.round}1"
    rnd = read_round(a.world / name)
    m = map_for(a.world, a.map, papers=False, features=a.features)
    map_ref = read_round(a.world / a.map).reference_xy
    spacing = base_spacing(m)
    p = GeometryParams(min_views=a.min_views,
                       views_m=tuple(float(d) for d in a.views_m.split(",")))
    types = [(t, g) for t, g in (("rootsift", m.geometry), ("xfeat", m.second_geometry))
             if g is not None]
    rows: dict[str, list[tuple[float, ...]]] = {t: [] for t, _ in types}
    for q in range(0, min(a.frames, len(rnd)), a.step):
        f = extract(rnd.load_image(q), m.feature_params)
        truth = rnd.reference_xy[q]
        i = int(np.argmin(np.linalg.norm(map_ref - truth, axis=1)))
        ahead_axis = map_ref[min(i + 1, len(map_ref) - 1)] - map_ref[max(i - 1, 0)]
        ahead_axis /= np.linalg.norm(ahead_axis)
        right_axis = np.array([ahead_axis[1], -ahead_axis[0]])
        true_right, true_ahead = float((truth - map_ref[i]) @ right_axis), \
            float((truth - map_ref[i]) @ ahead_axis)
        tangent = path_tangent(m.positions, i, spacing)
        if tangent is None:
            continue
        right = np.array([tangent[1], -tangent[0]])
        for t, geo in types:
            feats: Features | None = f if t == "rootsift" else f.second
            off = None if feats is None else geo.locate(feats, i, p)
            if off is None:
                continue
            at = m.positions[i] + off.right_m * right + off.ahead_m * tangent
            rows[t].append((true_right, true_ahead, off.right_m, off.ahead_m, off.inliers,
                            float((at - truth) @ right_axis), float(np.linalg.norm(at - truth))))
    n = len(range(0, min(a.frames, len(rnd)), a.step))
    print(f"{a.world.name} {name} on the {a.map} map ({n} frames)")
    for t, geo in types:
        r = np.array(rows[t], float).reshape(-1, 7)
        if not len(r):
            print(f"  {t}: nothing located")
            continue
        tr, ta, lr, la = r[:, 0], r[:, 1], r[:, 2], r[:, 3]
        side = np.sign(tr)
        slope = float(np.polyfit(tr, lr, 1)[0]) if len(r) > 2 else float("nan")
        print(f"  {t}: {len(r)} located, inliers {np.median(r[:, 4]):.0f}; error right "
              f"{np.abs(lr - tr).mean():.2f} m (slope {slope:.2f}), ahead "
              f"{np.abs(la - ta).mean():.2f} m; pull {np.mean(-side * r[:, 5]):+.2f} m; "
              f"placed {r[:, 6].mean():.2f} m from the truth; the frames "
              f"{np.abs(tr).mean():.2f} m beside the map's lane; keypoints' Sampson "
              f"{sampson_px(geo, range(20, len(m.positions) - 20, 10), p):.2f} px")


if __name__ == "__main__":
    main()
