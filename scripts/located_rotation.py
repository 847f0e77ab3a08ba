"""Whether knowing the frame's rotation relative to the map image takes the pull out of a
located fix across light.

Every ``--step``-th frame of a rendered round is located at the sunny image nearest its true
place twice, on the same matches and the same structure (``MapGeometry.structure``):
- by the product's PnP (``MapGeometry.locate``: rotation and translation together, RootSIFT's
  geometry, else XFeat's);
- by the translation alone, with the rotation between the two cameras taken from the world's
  exact poses (yaw and, unless ``--no-pitch``, pitch; ``--yaw-noise-deg``: a Gaussian error
  added to that yaw; ``--map-heading estimated``: the map image's heading in it is the
  service's estimate instead), by linear least squares inside a two-point RANSAC (2 px).

Printed for the frames both locate: the placed error from the truth (the map image's own
position error included), the *pull* (the error across the path towards the sunny lane) and
the slope of the located offset beside the map image against the true one (1: nothing pulls).
A lab check of the cause of the pull (docs/research/lighting.md); nothing is asserted.

    PYTHONPATH=. python scripts/located_rotation.py /work/expd/w23 cloudy1
    PYTHONPATH=. python scripts/located_rotation.py /work/expd/w23 cloudy1 --yaw-noise-deg 1
"""

from __future__ import annotations

import cv2
import numpy as np

from client.dataset import read_round
from client.lab.bench_odometry import true_poses
from client.lab.experiment_cli import map_for
from client.lab.located_fix import located_fix_parser
from service.estimators.along_track import path_tangent
from service.maps.experiences import base_spacing
from service.vision.features import Features, extract
from service.vision.map_geometry import GeometryParams, MapGeometry
from service.vision.metric_pose import Structure, relative_yaw

RANSAC_PX = 2.0
MIN_INLIERS = 8


def rotation(yaw: float, pitch: float) -> np.ndarray:
    """The rotation x_frame = R x_map of a camera turned by ``yaw`` (``relative_yaw``'s sign)
    and pitched by ``pitch`` about its x axis."""
    r, _ = cv2.Rodrigues(np.array([0.0, yaw, 0.0]))
    assert abs(relative_yaw(r) - yaw) < 1e-9
    rp, _ = cv2.Rodrigues(np.array([pitch, 0.0, 0.0]))
    return np.asarray(rp @ r, float)


def skew(v: np.ndarray) -> np.ndarray:
    """(n, 3, 3) cross-product matrices of the rows of ``v``."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1),
                     np.stack([v[:, 2], z, -v[:, 0]], 1),
                     np.stack([-v[:, 1], v[:, 0], z], 1)], 1)


def translation_only(points: np.ndarray, pixels: np.ndarray, rot: np.ndarray, k: np.ndarray,
                     rng: np.random.Generator) -> np.ndarray | None:
    """The frame camera's centre in the map camera's frame from 3-D points and their pixels
    in the frame, its rotation ``rot`` known: rays x ~ R X + t, so [x]_x t = -[x]_x R X."""
    rays = np.column_stack([pixels, np.ones(len(pixels))]) @ np.linalg.inv(k).T
    rx = points @ rot.T
    a = skew(rays)
    b = -np.einsum("nij,nj->ni", a, rx)

    def solve(idx: np.ndarray) -> np.ndarray:
        t, *_ = np.linalg.lstsq(a[idx].reshape(-1, 3), b[idx].ravel(), rcond=None)
        return np.asarray(t, float)

    def inliers(t: np.ndarray) -> np.ndarray:
        cam = rx + t
        front = cam[:, 2] > 1e-6
        pix = cam[:, :2] / np.where(front, cam[:, 2], 1.0)[:, None] @ k[:2, :2].T + k[:2, 2]
        return np.asarray(front & (np.linalg.norm(pix - pixels, axis=1) < RANSAC_PX))

    if len(points) < MIN_INLIERS:
        return None
    best = np.zeros(len(points), bool)
    for _ in range(200):
        inl = inliers(solve(rng.choice(len(points), 2, replace=False)))
        if inl.sum() > best.sum():
            best = inl
    for _ in range(3):
        if best.sum() < MIN_INLIERS:
            return None
        best = inliers(solve(np.flatnonzero(best)))
    return None if best.sum() < MIN_INLIERS else -rot.T @ solve(np.flatnonzero(best))


def matched(geo: MapGeometry, frame: Features, image_id: int, st: Structure,
            p: GeometryParams) -> tuple[np.ndarray, np.ndarray]:
    """The structure's points the frame matches, and the frame's pixels of them."""
    iq, ii = geo.images.pairs(frame.codes, image_id, p.delta)
    pos, hit = st.rows(ii)
    return st.points[pos[hit]].astype(float), frame.keypoints[iq[hit]].astype(float)


def main() -> None:
    ap = located_fix_parser(__doc__ or "")
    ap.add_argument("--yaw-noise-deg", type=float, default=0.0)
    ap.add_argument("--no-pitch", action="store_true", help="the relative pitch taken as 0")
    ap.add_argument("--map-heading", choices=("exact", "estimated"), default="exact",
                    help="the map image's heading in that yaw: the world's, or the service's "
                         "camera heading (MapGeometry.camera_heading)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    rnd, sun = read_round(a.world / a.round), read_round(a.world / a.map)
    pq, ps = true_poses(a.world, a.round, len(rnd)), true_poses(a.world, a.map, len(sun))
    if pq is None or ps is None:
        raise SystemExit(f"{a.world}: not a rendered world (no dataset.json generator)")
    m = map_for(a.world, a.map, papers=False, features=a.features)
    spacing, p = base_spacing(m), GeometryParams()
    rng = np.random.default_rng(a.seed)
    rows: dict[str, list[tuple[float, float, float, float]]] = {"pnp": [], "rotation known": []}
    for q in range(0, min(a.frames, len(rnd)), a.step):
        frame, truth = extract(rnd.load_image(q), m.feature_params), pq[q, :2]
        s = int(np.argmin(np.linalg.norm(ps[:, :2] - truth, axis=1)))
        tangent = path_tangent(m.positions, s, spacing)
        if tangent is None:
            continue
        right = np.array([tangent[1], -tangent[0]])
        true_right = float((truth - m.positions[s]) @ right)
        heading = float(ps[s, 2]) if a.map_heading == "exact" else \
            m.geometry.camera_heading(s, p) if m.geometry is not None else None
        if heading is None:
            continue
        yaw = float((pq[q, 2] - heading + np.pi) % (2 * np.pi) - np.pi) \
            + np.radians(rng.normal(0.0, a.yaw_noise_deg))
        rot = rotation(yaw, 0.0 if a.no_pitch else float(pq[q, 3] - ps[s, 3]))
        for geo, feats in ((m.geometry, frame), (m.second_geometry, frame.second)):
            st = None if geo is None or feats is None else geo.structure(s, p)
            off = None if st is None or geo is None or feats is None else geo.locate(feats, s, p)
            if off is None or st is None or geo is None or feats is None:
                continue
            centre = translation_only(*matched(geo, feats, s, st, p), rot, geo.k, rng)
            if centre is None:
                break
            for name, r, ah in (("pnp", off.right_m, off.ahead_m),
                                ("rotation known", centre[0], centre[2])):
                at = m.positions[s] + r * right + ah * tangent
                rows[name].append((float(np.linalg.norm(at - truth)),
                                   -float(np.sign(true_right) * ((at - truth) @ right)),
                                   float(r), true_right))
            break
    print(f"{a.world.name} {a.round} at the {a.map} map: yaw noise {a.yaw_noise_deg:g} deg, "
          f"pitch {'0' if a.no_pitch else 'exact'}, map heading {a.map_heading}")
    for name, r in rows.items():
        x = np.array(r, float).reshape(-1, 4)
        if len(x) < 3:
            print(f"  {name}: {len(x)} frames")
            continue
        slope = float(np.polyfit(x[:, 3], x[:, 2], 1)[0])
        print(f"  {name}: {len(x)} frames, placed {x[:, 0].mean():.2f} m (median "
              f"{np.median(x[:, 0]):.2f}), pull {x[:, 1].mean():+.2f} m, slope {slope:.2f}")


if __name__ == "__main__":
    main()
