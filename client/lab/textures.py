"""Procedural textures for the synthetic route world (no files, nothing downloaded).

Every generator takes a ``numpy.random.Generator`` and a size in metres and returns a float32
luminance image in [0, 1] plus an alpha mask (uint8 0/255), at ``ppm`` texels per metre.
Textures carry structure at several scales (plaster noise, bricks, windows, floors, signs) so
that SIFT finds repeatable, distinctive features, as on real street facades.
"""

from __future__ import annotations

import cv2
import numpy as np

Texture = tuple[np.ndarray, np.ndarray]  # (luminance float32 HxW in [0,1], alpha uint8 HxW)


def value_noise(
    rng: np.random.Generator, shape: tuple[int, int], cell_px: float, octaves: int = 4
) -> np.ndarray:
    """Multi-octave value noise in roughly [-1, 1]; ``cell_px`` is the coarsest feature size."""
    h, w = shape
    out = np.zeros((h, w), np.float32)
    amp, total = 1.0, 0.0
    cell = max(cell_px, 1.0)
    for _ in range(octaves):
        gh, gw = max(2, int(h / cell) + 2), max(2, int(w / cell) + 2)
        grid = rng.uniform(-1, 1, (gh, gw)).astype(np.float32)
        up = cv2.resize(grid, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
        out += amp * up[:h, :w]
        total += amp
        amp *= 0.55
        cell = max(cell / 2.0, 1.0)
    return out / total


def _full(h: int, w: int) -> np.ndarray:
    return np.full((h, w), 255, np.uint8)


def _px(m: float, ppm: float) -> int:
    return round(m * ppm)


def _glyphs(rng: np.random.Generator, img: np.ndarray, x0: int, y0: int, w: int, h: int) -> None:
    """A sign: a plate with a border and random block 'lettering'."""
    plate = rng.uniform(0.15, 0.95)
    ink = 1.0 - plate if abs(plate - 0.5) > 0.2 else (0.05 if plate > 0.5 else 0.95)
    img[y0 : y0 + h, x0 : x0 + w] = plate
    b = max(1, h // 10)
    img[y0 : y0 + b, x0 : x0 + w] = ink
    img[y0 + h - b : y0 + h, x0 : x0 + w] = ink
    gh = max(2, int(h * rng.uniform(0.35, 0.55)))
    gy = y0 + (h - gh) // 2
    x = x0 + 2 * b
    while x < x0 + w - 2 * b:
        gw = max(2, int(gh * rng.uniform(0.3, 0.8)))
        if x + gw >= x0 + w - 2 * b:
            break
        kind = rng.integers(4)
        if kind == 0:
            img[gy : gy + gh, x : x + gw] = ink
        elif kind == 1:
            img[gy : gy + gh, x : x + max(1, gw // 3)] = ink
            img[gy : gy + max(1, gh // 4), x : x + gw] = ink
        elif kind == 2:
            cv2.circle(img, (x + gw // 2, gy + gh // 2), max(1, gw // 2), float(ink),
                       max(1, gw // 5))
        else:
            img[gy + gh // 2 - max(1, gh // 8) : gy + gh // 2 + max(1, gh // 8), x : x + gw] = ink
            img[gy : gy + gh, x + gw - max(1, gw // 3) : x + gw] = ink
        x += gw + max(1, gw // 3) + (gw if rng.random() < 0.15 else 0)


def facade(rng: np.random.Generator, width_m: float, height_m: float, ppm: float) -> Texture:
    """Building facade: plaster or bricks, floors with window grids, doors, signs, pipes."""
    h, w = _px(height_m, ppm), _px(width_m, ppm)
    base = rng.uniform(0.35, 0.85)
    img = base + 0.06 * value_noise(rng, (h, w), ppm * 2.0) + 0.03 * value_noise(rng, (h, w), 6)
    if rng.random() < 0.35:  # bricks
        bh, bw = max(2, _px(0.075, ppm)), max(4, _px(0.25, ppm))
        rows = np.arange(h) // bh
        offs = (rows % 2) * (bw // 2)
        cols = (np.arange(w)[None, :] + offs[:, None]) // bw
        brick_id = rows[:, None] * 10007 + cols
        jitter = rng.uniform(-0.08, 0.08, 50021)[brick_id % 50021]
        shifted = np.arange(w)[None, :] + offs[:, None]
        mortar = (np.arange(h) % bh == 0)[:, None] | (shifted % bw == 0)
        img = img + jitter
        img[mortar] = img[mortar] * 0.7 + 0.25
    floor_h = rng.uniform(2.9, 3.6)
    win_w, win_h = rng.uniform(0.8, 1.6), rng.uniform(1.1, 1.8)
    spacing = win_w + rng.uniform(0.7, 1.8)
    glass = rng.uniform(0.05, 0.3)
    frame = np.clip(base + rng.choice([-0.35, 0.3]), 0.02, 0.98)
    mullion = rng.random() < 0.6
    blinds_p = rng.uniform(0.0, 0.4)
    cornice = rng.random() < 0.7
    n_floors = int(height_m // floor_h)
    x_start = rng.uniform(0.3, spacing)
    for f in range(n_floors):
        y_bottom = height_m - f * floor_h  # metres from the texture top, row grows downward
        if cornice and f > 0:
            cy = _px(y_bottom, ppm)
            img[max(0, cy - _px(0.18, ppm)) : cy, :] = np.clip(base * rng.uniform(0.6, 1.3), 0, 1)
        xs = np.arange(x_start, width_m - win_w, spacing)
        for x in xs:
            if f == 0 and rng.random() < 0.25:  # a door on the ground floor
                dx0, dx1 = _px(x, ppm), _px(x + min(win_w, 1.2), ppm)
                dy0, dy1 = _px(height_m - 2.2, ppm), h
                img[dy0:dy1, dx0:dx1] = rng.uniform(0.05, 0.5)
                img[dy0:dy1, dx0 : dx0 + 2] = frame
                img[dy0 : dy0 + 2, dx0:dx1] = frame
                continue
            if rng.random() < 0.08:  # a missing window breaks the regularity
                continue
            wy1 = _px(y_bottom - 0.9, ppm)
            wy0 = _px(y_bottom - 0.9 - win_h, ppm)
            wx0, wx1 = _px(x, ppm), _px(x + win_w, ppm)
            if wy0 < 0:
                continue
            fr = max(1, _px(0.07, ppm))
            img[wy0 - fr : wy1 + fr, wx0 - fr : wx1 + fr] = frame
            pane = glass + rng.uniform(-0.04, 0.04) + np.linspace(0.15, -0.05, wy1 - wy0)[:, None]
            img[wy0:wy1, wx0:wx1] = pane
            if rng.random() < blinds_p:
                n = rng.integers(wy0, wy1)
                img[wy0:n, wx0:wx1] = rng.uniform(0.6, 0.9)
                img[wy0:n:3, wx0:wx1] -= 0.15
            if mullion:
                mx, my = (wx0 + wx1) // 2, (wy0 + wy1) // 2 - _px(0.2, ppm)
                img[wy0:wy1, mx - fr // 2 : mx + fr // 2 + 1] = frame
                img[my - fr // 2 : my + fr // 2 + 1, wx0:wx1] = frame
            sill = max(1, _px(0.06, ppm))
            ledge = np.clip(frame + 0.1, 0, 1)
            img[wy1 + fr : wy1 + fr + sill, wx0 - 2 * fr : wx1 + 2 * fr] = ledge
    for _ in range(rng.poisson(max(0.5, width_m / 12))):  # shop signs and posters
        sw, sh = rng.uniform(0.8, 3.5), rng.uniform(0.35, 0.9)
        sx = rng.uniform(0, max(0.1, width_m - sw))
        sy = rng.uniform(max(0.0, height_m - 3.4), max(0.1, height_m - 2.3 - sh))
        _glyphs(rng, img, _px(sx, ppm), _px(sy, ppm), _px(sw, ppm), _px(sh, ppm))
    if rng.random() < 0.5:  # drainpipe
        px = rng.integers(0, max(1, w - 4))
        img[:, px : px + max(2, _px(0.08, ppm))] = rng.uniform(0.2, 0.7)
    stains = value_noise(rng, (h, w), ppm * 1.5, octaves=3)
    img = img * (1.0 - 0.12 * np.clip(stains, 0, 1) * np.linspace(0, 1, h)[:, None])
    return np.clip(img, 0, 1).astype(np.float32), _full(h, w)


def hedge(rng: np.random.Generator, width_m: float, height_m: float, ppm: float) -> Texture:
    """Dense foliage: blobs at two scales over dark noise, with a ragged top edge."""
    h, w = _px(height_m, ppm), _px(width_m, ppm)
    img = (0.22 + 0.08 * value_noise(rng, (h, w), ppm)).astype(np.float32)
    for scale, count in ((0.18, 2.2), (0.07, 9.0)):
        n = int(count * width_m * height_m / scale)
        xs, ys = rng.integers(0, w, n), rng.integers(0, h, n)
        rs = rng.integers(max(1, _px(scale * 0.5, ppm)), max(2, _px(scale, ppm)) + 1, n)
        vs = rng.uniform(0.08, 0.55, n)
        for x, y, r, v in zip(xs, ys, rs, vs, strict=True):
            cv2.circle(img, (int(x), int(y)), int(r), float(v), -1)
    alpha = _full(h, w)
    top = (0.12 * ppm * (1 + value_noise(rng, (1, w), ppm * 0.4)[0])).astype(int)
    rows = np.arange(h)[:, None]
    alpha[rows < top[None, :]] = 0
    return np.clip(img, 0, 1), alpha


def fence(rng: np.random.Generator, width_m: float, height_m: float, ppm: float) -> Texture:
    """Metal bar fence or wooden boards; gaps are transparent."""
    h, w = _px(height_m, ppm), _px(width_m, ppm)
    tone = rng.uniform(0.1, 0.8)
    img = np.full((h, w), tone, np.float32) + 0.05 * value_noise(rng, (h, w), 8)
    alpha = np.zeros((h, w), np.uint8)
    if rng.random() < 0.5:
        pitch, bar = _px(rng.uniform(0.1, 0.18), ppm), max(1, _px(0.03, ppm))
        alpha[:, (np.arange(w) % pitch) < bar] = 255
    else:
        pitch, gap = _px(rng.uniform(0.12, 0.2), ppm), max(1, _px(0.02, ppm))
        alpha[:, (np.arange(w) % pitch) >= gap] = 255
        img += 0.1 * rng.uniform(-1, 1, w // max(pitch, 1) + 1)[np.arange(w) // max(pitch, 1)]
    for y in (0.12, 0.5, 0.9):
        r = _px(height_m * y, ppm)
        alpha[r : r + max(2, _px(0.05, ppm))] = 255
    post = _px(rng.uniform(2.0, 3.0), ppm)
    posts = (np.arange(w) % post) < max(2, _px(0.07, ppm))
    alpha[:, posts] = 255
    img[:, posts] = tone * 0.6
    return np.clip(img, 0, 1), alpha


def low_wall(rng: np.random.Generator, width_m: float, height_m: float, ppm: float) -> Texture:
    """Concrete garden wall with slabs, stains and graffiti tags."""
    h, w = _px(height_m, ppm), _px(width_m, ppm)
    img = rng.uniform(0.45, 0.75) + 0.07 * value_noise(rng, (h, w), ppm * 0.7)
    slab = _px(rng.uniform(1.0, 2.5), ppm)
    img[:, (np.arange(w) % slab) < 2] -= 0.2
    img[: max(2, _px(0.08, ppm))] += 0.12
    for _ in range(rng.poisson(width_m / 8)):
        cx, cy = rng.integers(0, w), rng.integers(h // 4, max(h // 4 + 1, h))
        pts = np.column_stack([cx + rng.normal(0, ppm * 0.3, 6), cy + rng.normal(0, ppm * 0.15, 6)])
        cv2.polylines(img, [pts.astype(np.int32)], False, float(rng.uniform(0, 1)), 2)
    return np.clip(img, 0, 1).astype(np.float32), _full(h, w)


def car(rng: np.random.Generator, length_m: float, height_m: float, ppm: float,
        side: bool) -> Texture:
    """A car seen from the side (``side``) or from the front/back; transparent around the body."""
    h, w = _px(height_m, ppm), _px(length_m, ppm)
    paint = rng.choice([rng.uniform(0.05, 0.2), rng.uniform(0.4, 0.6), rng.uniform(0.8, 0.95)])
    img = np.full((h, w), paint, np.float32) + 0.03 * value_noise(rng, (h, w), ppm * 0.5)
    alpha = np.zeros((h, w), np.uint8)
    body_top, sill = _px(height_m * 0.45, ppm), _px(height_m - 0.2, ppm)
    alpha[body_top:sill] = 255
    cab_in = int(w * (0.2 if side else 0.08))
    cab = np.array([[cab_in, body_top], [w - cab_in, body_top], [w - cab_in - w // 10, 0],
                    [cab_in + w // 10, 0]], np.int32)
    cv2.fillPoly(alpha, [cab], 255)
    win = cab.copy()
    win[:, 1] = np.clip(win[:, 1] + np.array([-2, -2, 3, 3]), 0, h)
    win[:, 0] += np.array([4, -4, -4, 4])
    cv2.fillPoly(img, [win], float(rng.uniform(0.05, 0.25)))
    if side:
        cv2.line(img, (w // 2, 0), (w // 2, body_top), float(paint), 3)
        r = _px(0.33, ppm)
        for cx in (int(w * 0.18), int(w * 0.82)):
            cv2.circle(alpha, (cx, h - r), r, 255, -1)
            cv2.circle(img, (cx, h - r), r, 0.06, -1)
            cv2.circle(img, (cx, h - r), r // 2, 0.55, -1)
        img[_px(height_m * 0.62, ppm), w // 4 : w // 4 + w // 12] = 0.9  # door handle
    else:
        for cx in (int(w * 0.15), int(w * 0.85)):
            cv2.circle(img, (cx, _px(height_m * 0.62, ppm)), _px(0.09, ppm), 0.95, -1)
        pw, ph = _px(0.52, ppm), _px(0.11, ppm)
        _glyphs(rng, img, w // 2 - pw // 2, _px(height_m * 0.72, ppm), pw, ph)
    return np.clip(img, 0, 1), alpha


def tree(rng: np.random.Generator, width_m: float, height_m: float, ppm: float) -> Texture:
    """Trunk and a crown of leaf clusters; transparent elsewhere."""
    h, w = _px(height_m, ppm), _px(width_m, ppm)
    img = (0.25 + 0.1 * value_noise(rng, (h, w), ppm * 0.3)).astype(np.float32)
    alpha = np.zeros((h, w), np.uint8)
    tw = 2 * max(2, _px(rng.uniform(0.1, 0.2), ppm))
    crown_base = _px(height_m * rng.uniform(0.3, 0.5), ppm)
    alpha[crown_base:, w // 2 - tw // 2 : w // 2 + tw // 2] = 255
    img[crown_base:, w // 2 - tw // 2 : w // 2 + tw // 2] = rng.uniform(0.15, 0.35) + 0.1 * (
        value_noise(rng, (h - crown_base, tw), 3)
    )
    n = int(60 * width_m * height_m)
    cx = rng.normal(w / 2, w / 5, n).astype(int)
    cy = rng.normal(crown_base * 0.55, crown_base / 4, n).astype(int)
    for x, y in zip(cx, cy, strict=True):
        r = int(rng.integers(max(1, _px(0.05, ppm)), max(2, _px(0.22, ppm))))
        cv2.circle(alpha, (int(x), int(y)), r, 255, -1)
        cv2.circle(img, (int(x), int(y)), r, float(rng.uniform(0.1, 0.5)), -1)
    return np.clip(img, 0, 1), alpha


def signpost(rng: np.random.Generator, width_m: float, height_m: float, ppm: float) -> Texture:
    """A pole with a sign plate near the top."""
    h, w = _px(height_m, ppm), _px(width_m, ppm)
    img = np.full((h, w), rng.uniform(0.3, 0.6), np.float32)
    alpha = np.zeros((h, w), np.uint8)
    pole = max(2, _px(0.08, ppm))
    alpha[:, w // 2 - pole // 2 : w // 2 + pole // 2 + 1] = 255
    ph = _px(rng.uniform(0.4, 0.7), ppm)
    alpha[: ph + 2] = 255
    _glyphs(rng, img, 0, 0, w, ph)
    return np.clip(img, 0, 1), alpha


def person(rng: np.random.Generator, width_m: float, height_m: float, ppm: float) -> Texture:
    """A pedestrian silhouette (a moving occluder)."""
    h, w = _px(height_m, ppm), _px(width_m, ppm)
    img = np.full((h, w), rng.uniform(0.05, 0.8), np.float32)
    alpha = np.zeros((h, w), np.uint8)
    head = max(2, _px(0.11, ppm))
    cv2.circle(alpha, (w // 2, head + 1), head, 255, -1)
    cv2.circle(img, (w // 2, head + 1), head, float(rng.uniform(0.3, 0.7)), -1)
    cv2.ellipse(alpha, (w // 2, int(h * 0.38)), (w // 2 - 1, int(h * 0.22)), 0, 0, 360, 255, -1)
    legs = int(h * 0.55)
    alpha[legs:, w // 2 - w // 4 : w // 2 - 1] = 255
    alpha[legs:, w // 2 + 1 : w // 2 + w // 4] = 255
    img[legs:] = rng.uniform(0.05, 0.5)
    return img, alpha


def sky_panorama(rng: np.random.Generator, sunny: bool, px_per_deg: float = 2.0) -> np.ndarray:
    """Sky luminance over azimuth 0..360 deg (columns) and elevation 60..0 deg (rows)."""
    h, w = int(60 * px_per_deg), int(360 * px_per_deg)
    grad = np.linspace(0.75, 0.92, h, dtype=np.float32)[:, None]
    pad = 64
    noise = value_noise(rng, (h, w + pad), 40, octaves=4)
    ramp = np.linspace(0.0, 1.0, pad, dtype=np.float32)[None, :]
    noise[:, :pad] = noise[:, :pad] * ramp + noise[:, w : w + pad] * (1 - ramp)  # wrap at 360
    clouds = noise[:, :w]
    if sunny:
        img = grad * 0.9 + 0.12 * np.clip(clouds - 0.15, 0, 1)
    else:
        img = np.full_like(grad, 0.8) + 0.05 * clouds
    return np.clip(np.broadcast_to(img, (h, w)), 0, 1).astype(np.float32)
