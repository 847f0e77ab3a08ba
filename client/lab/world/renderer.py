"""The renderer: one ray per image column against every wall segment (nearest hits kept,
painted far to near with mip-mapped look-ups), the ground plane and the sky panorama."""

from __future__ import annotations

import math
from collections.abc import Iterable

import cv2
import numpy as np

from client.lab.world.geometry import (
    GROUND_PPM,
    LAYERS,
    MAX_RANGE_M,
    MIP_LEVELS,
    PPM,
    Camera,
    Condition,
    Pose,
    Route,
)
from client.lab.world.scene import Mover, Scene, mover_segments


class Renderer:
    """Renders frames of scenes of one route through one camera."""

    def __init__(self, camera: Camera, route: Route) -> None:
        self.camera = camera
        self.route = route

    def render(self, scene: Scene, pose: Pose, t: float = 0.0, movers: Iterable[Mover] = (),
               noise_seed: int | None = None, exposure: float = 1.0) -> np.ndarray:
        """Render one grayscale frame (uint8, camera.height x camera.width)."""
        cam, cond = self.camera, scene.condition
        W, H, f, hc = cam.width, cam.height, cam.focal_px, cam.height_m
        cx, cy = W / 2, H / 2 - f * math.tan(pose.pitch)
        xc = (np.arange(W) + 0.5 - cx) / f
        fwd = np.array([math.cos(pose.heading), math.sin(pose.heading)])
        right = np.array([math.sin(pose.heading), -math.cos(pose.heading)])
        D = fwd[None, :] + xc[:, None] * right[None, :]  # (W, 2); ray parameter = depth
        C = np.array([pose.x, pose.y])
        slope = (cy - (np.arange(H) + 0.5)) / f  # (H,) tan of elevation per row (over depth)

        out = self._sky(scene, pose, xc, slope)
        g_val, g_mask = self._ground(scene, C, D, slope)
        out[g_mask] = g_val[g_mask]

        segs = scene.walls
        moving = mover_segments(self.route, scene, movers, t)
        if moving is not None:
            segs = segs.concat(moving)
        mid = 0.5 * (segs.p0 + segs.p1) - C
        near = np.einsum("ij,ij->i", mid, mid) < (MAX_RANGE_M + 0.5 * segs.length) ** 2
        idx_s = np.flatnonzero(near)
        p0, p1 = segs.p0[idx_s], segs.p1[idx_s]
        E = p1 - p0
        rel = p0 - C
        denom = D[:, 0:1] * E[None, :, 1] - D[:, 1:2] * E[None, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            th = (rel[None, :, 0] * E[None, :, 1] - rel[None, :, 1] * E[None, :, 0]) / denom
            sh = (rel[None, :, 0] * D[:, 1:2] - rel[None, :, 1] * D[:, 0:1]) / denom
        ok = (np.abs(denom) > 1e-12) & (th > 0.3) & (sh >= 0) & (sh <= 1)
        th = np.where(ok, th, np.inf)
        nl = min(LAYERS, th.shape[1])
        if nl == 0:
            return self._finish(out, cond, pose, noise_seed, exposure)
        part = np.argpartition(th, nl - 1, axis=1)[:, :nl] if th.shape[1] > nl else \
            np.tile(np.arange(nl), (W, 1))
        tl = np.take_along_axis(th, part, axis=1)
        order = np.argsort(-tl, axis=1)  # far to near
        part = np.take_along_axis(part, order, axis=1)
        tl = np.take_along_axis(tl, order, axis=1)
        sl = np.take_along_axis(sh, part, axis=1)

        # per-segment shading: orientation to the sun, seen from the camera's side
        n = np.column_stack([-E[:, 1], E[:, 0]]) / np.maximum(
            np.linalg.norm(E, axis=1, keepdims=True), 1e-9)
        facing = np.sign(np.einsum("ij,ij->i", n, -rel))
        n = n * facing[:, None]
        if cond.sunny:
            az, el = math.radians(cond.sun_azimuth_deg), math.radians(cond.sun_elevation_deg)
            sun = np.array([math.cos(az), math.sin(az)]) * math.cos(el)
            shade = cond.ambient + cond.diffuse * np.clip(n @ sun, 0, None)
        else:
            shade = np.full(len(idx_s), cond.ambient)
        shade = shade * (1 + cond.white_balance * segs.tint[idx_s])

        for k in range(nl):
            depth = tl[:, k]
            valid_col = np.isfinite(depth)
            if not valid_col.any():
                continue
            local = part[:, k]
            gid = idx_s[local]
            depth_f = np.where(valid_col, depth, 1.0)
            z = hc + slope[:, None] * depth_f[None, :]  # (H, W) height on the wall
            hgt = segs.height[gid]
            au = segs.u0[gid] + sl[:, k] * segs.length[gid] * PPM
            av = segs.v_top[gid][None, :] + (hgt[None, :] - z) * PPM
            vis = valid_col[None, :] & (z >= 0) & (z <= hgt[None, :])
            lvl = np.clip(np.round(np.log2(np.maximum(depth_f * PPM / f, 1.0))), 0,
                          MIP_LEVELS - 1).astype(int)
            val = np.zeros((H, W), np.float32)
            alp = np.zeros((H, W), np.float32)
            for lv in np.unique(lvl[valid_col]):
                colm = (lvl == lv) & valid_col
                sc = 1.0 / (1 << lv)
                mx = np.broadcast_to(au[colm][None, :] * sc - 0.5, (H, int(colm.sum())))
                my = av[:, colm] * sc - 0.5
                mx, my = np.ascontiguousarray(mx, np.float32), np.ascontiguousarray(my, np.float32)
                val[:, colm] = cv2.remap(scene.atlas.levels[lv], mx, my, cv2.INTER_LINEAR,
                                         borderMode=cv2.BORDER_CONSTANT)
                alp[:, colm] = cv2.remap(scene.atlas.alpha[lv], mx, my, cv2.INTER_LINEAR,
                                         borderMode=cv2.BORDER_CONSTANT)
            vis &= alp > 127
            lit = val / 255.0 * shade[local][None, :]
            if cond.sunny:  # soft diagonal shadow bands (trees, poles, roofs across the street)
                ph = segs.phase[gid][None, :]
                band = np.sin(au[None, :] / PPM * 0.6 + av / PPM * 0.45 + ph)
                lit = lit * np.where((band > 0.8) & (np.sin(3 * ph) > 0.3), 0.6, 1.0)
                # shadow of the buildings across the street: a sloped line on the facade
                z_sh = hgt * (0.45 + 0.35 * np.sin(au / PPM * 0.08 + 2 * ph[0]))
                lit = lit * np.where((z < z_sh[None, :]) & (np.cos(5 * ph) > -0.2), 0.5, 1.0)
            haze = np.exp(-depth_f / 400.0)[None, :]
            lit = lit * haze + 0.8 * (1 - haze)
            out[vis] = lit[vis]
        return self._finish(out, cond, pose, noise_seed, exposure)

    def _sky(self, scene: Scene, pose: Pose, xc: np.ndarray, slope: np.ndarray) -> np.ndarray:
        sky = scene.sky
        ppd = sky.shape[1] / 360.0
        az = (math.degrees(pose.heading) - np.degrees(np.arctan(xc))) % 360.0
        el = np.degrees(np.arctan(slope[:, None] / np.sqrt(1 + xc[None, :] ** 2)))
        mx = np.broadcast_to(az[None, :] * ppd, el.shape).astype(np.float32)
        my = ((60.0 - np.clip(el, 0, 60)) * ppd).astype(np.float32)
        return cv2.remap(sky, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

    def _ground(self, scene: Scene, C: np.ndarray, D: np.ndarray, slope: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        H, W = len(slope), len(D)
        hc, f = self.camera.height_m, self.camera.focal_px
        rows = slope < -1e-6
        depth = np.where(rows, hc / np.where(rows, -slope, 1.0), np.inf)
        val = np.zeros((H, W), np.float32)
        mask = np.zeros((H, W), bool)
        ox, oy = scene.ground_origin
        footprint = depth / f * np.sqrt(np.maximum(depth / hc, 1.0)) * GROUND_PPM
        lvl = np.clip(np.round(np.log2(np.maximum(footprint, 1.0))), 0, MIP_LEVELS - 1)
        for lv in np.unique(lvl[rows]):
            r = rows & (lvl == lv)
            dep = depth[r][:, None]
            px = C[0] + dep * D[None, :, 0]
            py = C[1] + dep * D[None, :, 1]
            sc = 1.0 / (1 << int(lv))
            mx = ((px - ox) * GROUND_PPM * sc - 0.5).astype(np.float32)
            my = ((oy - py) * GROUND_PPM * sc - 0.5).astype(np.float32)
            g = cv2.remap(scene.ground[int(lv)], mx, my, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REFLECT)
            haze = np.exp(-dep / 400.0)
            val[r] = g * haze + 0.8 * (1 - haze)
            mask[r] = True
        return val, mask

    def _finish(self, img: np.ndarray, cond: Condition, pose: Pose, noise_seed: int | None,
                exposure: float) -> np.ndarray:
        img = np.clip(img * exposure, 0, 1)
        mean = float(img.mean())
        img = np.clip(0.5 + (img - mean) * cond.contrast + 0.5 * (0.48 - mean), 0, 1) ** cond.gamma
        img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.55) * cond.gain
        if noise_seed is not None:
            rng = np.random.default_rng(noise_seed)
            img = img + rng.normal(0, cond.noise / 255, img.shape)
        return np.clip(np.round(img * 255), 0, 255).astype(np.uint8)

