"""Where the camera stands relative to a map image, in metres: two-view geometry.

Image retrieval places the robot *at* a map image; it cannot tell how far the robot is beside
or ahead of it (two traversals of a street differ by a lane position, neighbouring images look
alike). The features matched with a map image can. The map image ``i`` and neighbours ``j``
of the same traversal, known distances apart, give the 3-D points of ``i``'s features (each
pair's essential matrix, its translation scaled to the distance between their recorded
positions, then triangulation: from one neighbour, ``triangulate``, or from several at once,
``triangulate_views``); the frame's features matched with ``i``'s give the frame's
camera pose against those points (PnP with RANSAC). The result is the camera centre in the
frame of ``i``'s camera: metres to the right and ahead, and the camera's yaw relative to
``i``'s (its turn about the vertical axis, counter-clockwise seen from above, as the map's
headings).

Everything here is pure computation on arrays (OpenCV's RANSAC draws from its own fixed-seed
generator, so one input always gives one result).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from service.vision.matcher import PreparedSet, match_batch_u8_pairs


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics as fractions of the image's width (fx, cx) and height (fy, cy), so
    that one camera serves any working size of the same aspect."""

    fx: float
    fy: float
    cx: float = 0.5
    cy: float = 0.5

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        cam = cls(float(d["fx"]), float(d["fy"]), float(d.get("cx", 0.5)),
                  float(d.get("cy", 0.5)))
        if not all(math.isfinite(v) and v > 0 for v in (cam.fx, cam.fy, cam.cx, cam.cy)):
            raise ValueError(f"camera intrinsics must be finite and positive, got {d}")
        return cam

    def as_dict(self) -> dict[str, float]:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy}

    def matrix(self, width: int, height: int) -> np.ndarray:
        return np.array([[self.fx * width, 0.0, self.cx * width],
                         [0.0, self.fy * height, self.cy * height],
                         [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Structure:
    """3-D points (n, 3) of some of a map image's features, in that image's camera frame
    (x right, y down, z ahead; metres), and the features' indices in the image."""

    feature_ids: np.ndarray
    points: np.ndarray

    def rows(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For the image's features ``ids``: their rows in ``points`` and which of them have
        a point (rows of those without one are meaningless)."""
        pos = np.searchsorted(self.feature_ids, ids)
        pos = np.minimum(pos, len(self.feature_ids) - 1)
        return pos, self.feature_ids[pos] == ids


@dataclass(frozen=True)
class Offset:
    """A frame's camera centre in a map image's camera frame: metres right and ahead; its
    yaw relative to the map image's camera; and, where the map knows that camera's heading
    (service/vision/map_geometry.py), the frame camera's heading in the map and its std."""

    right_m: float
    ahead_m: float
    yaw: float = 0.0  # rad, counter-clockwise seen from above (turned left: positive)
    inliers: int = 0  # PnP RANSAC inliers
    heading: float | None = None  # rad counter-clockwise from east: the map's heading + yaw
    heading_sigma: float | None = None  # its std, rad


def relative_yaw(rot: np.ndarray) -> float:
    """Yaw (rad, counter-clockwise seen from above) of a camera whose rotation from a
    reference camera's frame (x right, y down, z ahead) is ``rot`` (x_cam = rot x_ref + t):
    the angle of its optical axis, ``rot``'s third row in the reference frame, left of the
    reference's axis."""
    return -math.atan2(float(rot[2, 0]), float(rot[2, 2]))


def match_pairs(a: np.ndarray, b: np.ndarray | PreparedSet, delta: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of the symmetric ratio-test matches between uint8 descriptor codes
    ``a`` and ``b`` (the similarity's own matches, service/vision/matcher.py)."""
    return match_batch_u8_pairs(a, [b], delta, delta)[1][0]


@dataclass(frozen=True)
class PairPose:
    """Where a neighbour ``j`` of map image ``i`` stands: ``x_j = rot @ x_i + t`` in camera
    frames (x right, y down, z ahead), ``t`` in metres (the essential matrix's translation
    scaled to the distance between their recorded positions), and the matches that are
    inliers of it (feature ids in ``i`` and in ``j``)."""

    rot: np.ndarray
    t: np.ndarray
    ids_i: np.ndarray
    ids_j: np.ndarray

    def inverse(self) -> PairPose:
        """The same pair seen from ``j``."""
        back = self.rot.T
        return PairPose(back, -back @ self.t, self.ids_j, self.ids_i)


def relative_pose(kp_i: np.ndarray, kp_j: np.ndarray, pairs: tuple[np.ndarray, np.ndarray],
                  baseline_m: float, k: np.ndarray, min_points: int) -> PairPose | None:
    """The pose of image ``j`` taken ``baseline_m`` from image ``i``, from their matches
    ``pairs``; None when they give no reliable geometry (too few matches or inliers)."""
    ia, ib = pairs
    if len(ia) < max(min_points, 8) or baseline_m <= 0:
        return None
    p1 = np.ascontiguousarray(kp_i[ia], np.float64)
    p2 = np.ascontiguousarray(kp_j[ib], np.float64)
    e, mask = cv2.findEssentialMat(p1, p2, k, cv2.RANSAC, 0.999, 1.0)
    if e is None or e.shape != (3, 3) or mask is None:
        return None
    _, r, t, mask = cv2.recoverPose(e, p1, p2, k, mask=mask.copy())
    ok = mask.ravel() > 0
    if ok.sum() < min_points:
        return None
    return PairPose(r, t.ravel() * baseline_m, ia[ok], ib[ok])


def triangulate(kp_i: np.ndarray, kp_j: np.ndarray, pairs: tuple[np.ndarray, np.ndarray],
                baseline_m: float, k: np.ndarray, min_points: int,
                max_depth_m: float = 100.0) -> Structure | None:
    """Structure of image ``i`` from its matches with image ``j`` taken ``baseline_m`` away:
    None when the pair gives no reliable geometry (too few matches or inliers)."""
    pose = relative_pose(kp_i, kp_j, pairs, baseline_m, k, min_points)
    if pose is None:
        return None
    p1 = np.ascontiguousarray(kp_i[pose.ids_i], np.float64)
    p2 = np.ascontiguousarray(kp_j[pose.ids_j], np.float64)
    proj_i = k @ np.hstack([np.eye(3), np.zeros((3, 1))])
    proj_j = k @ np.hstack([pose.rot, pose.t[:, None]])
    xh = cv2.triangulatePoints(proj_i, proj_j, p1.T, p2.T)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (xh[:3] / xh[3]).T
    good = np.isfinite(x).all(axis=1) & (x[:, 2] > 0.5) & (x[:, 2] < max_depth_m)
    if good.sum() < min_points:
        return None
    return Structure(pose.ids_i[good].astype(np.int64), x[good])


def triangulate_views(kp_i: np.ndarray, views: list[tuple[PairPose, np.ndarray]],
                      k: np.ndarray, min_views: int, min_points: int,
                      max_depth_m: float = 100.0) -> Structure | None:
    """Structure of image ``i`` from several neighbours at once: ``views`` holds each
    neighbour's pose and keypoints. A feature of ``i`` that the poses of at least
    ``min_views`` neighbours hold as an inlier is triangulated from all the images that see
    it (the linear least-squares point of their rays, in normalised image coordinates); the
    others are left out, as a match that only one pair explains is more often wrong. The
    depth noise of two views (a neighbour straight ahead sees little parallax) averages over
    the views: docs/research/lighting.md has the fixes it gives. None with fewer than
    ``min_points`` points."""
    if not views:
        return None
    kinv = np.linalg.inv(k)

    def normalised(kp: np.ndarray) -> np.ndarray:
        return np.asarray(kp, np.float64) @ kinv[:2, :2].T + kinv[:2, 2]

    ids = np.unique(np.concatenate([pose.ids_i for pose, _ in views]))
    rows = np.zeros((len(ids), 2 * (len(views) + 1), 4))
    xi = normalised(kp_i[ids])
    rows[:, 0, 0], rows[:, 0, 2] = -1.0, xi[:, 0]  # image i: P = [I | 0]
    rows[:, 1, 1], rows[:, 1, 2] = -1.0, xi[:, 1]
    seen = np.zeros(len(ids), np.int64)
    for v, (pose, kp_j) in enumerate(views):
        at = np.searchsorted(ids, pose.ids_i)
        proj = np.hstack([pose.rot, pose.t[:, None]])
        xj = normalised(kp_j[pose.ids_j])
        rows[at, 2 + 2 * v] = xj[:, :1] * proj[2] - proj[0]
        rows[at, 3 + 2 * v] = xj[:, 1:] * proj[2] - proj[1]
        seen[at] += 1
    keep = seen >= min_views
    if keep.sum() < min_points:
        return None
    xh = np.linalg.svd(rows[keep])[2][:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = xh[:, :3] / xh[:, 3:]
    good = np.isfinite(x).all(axis=1) & (x[:, 2] > 0.5) & (x[:, 2] < max_depth_m)
    if good.sum() < min_points:
        return None
    return Structure(ids[keep][good].astype(np.int64), x[good])


def locate(kp_q: np.ndarray, pairs: tuple[np.ndarray, np.ndarray], structure: Structure,
           k: np.ndarray, min_inliers: int, reprojection_px: float = 2.0,
           max_offset_m: float = 50.0) -> Offset | None:
    """The frame's camera centre in the structure's camera frame from the frame's matches
    ``pairs`` (frame feature, map image feature) by PnP with RANSAC; None with fewer than
    ``min_inliers`` inliers, or a centre farther than ``max_offset_m`` (a degenerate
    configuration: image points that do not span the view). The offset's yaw is the frame
    camera's relative to the structure's."""
    iq, ii = pairs
    pos, hit = structure.rows(ii)
    if hit.sum() < max(min_inliers, 6):
        return None
    obj = np.ascontiguousarray(structure.points[pos[hit]], np.float64)
    img = np.ascontiguousarray(kp_q[iq[hit]], np.float64)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, k, None,
                                             reprojectionError=reprojection_px,
                                             iterationsCount=200, confidence=0.999)
    if not ok or inl is None or len(inl) < min_inliers:
        return None
    rot, _ = cv2.Rodrigues(rvec)
    centre = (-rot.T @ tvec).ravel()
    if not np.isfinite(centre).all() or float(np.linalg.norm(centre)) > max_offset_m:
        return None
    return Offset(float(centre[0]), float(centre[2]), relative_yaw(rot), len(inl))
