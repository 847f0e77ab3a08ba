"""Where local features see nothing at night, do whole images still tell the place?

The rendered night round holds about two grey levels of texture under sensor noise
(docs/research/lighting.md): no local feature survives, and DPSO honestly reports every
frame lost. SeqSLAM (Milford and Wyeth, 2012) localized night and rain along a route from
tiny, patch-normalised images: averaging a frame down to a thumbnail averages the noise away
(an 80 x 60 thumbnail of a 320 x 240 frame averages 16 pixels: sigma / 4), and normalising
each patch takes out the light's gain and offset.

This study measures it on the rendered worlds, without touching the product: each map image
and night frame becomes a thumbnail (``thumbnail``); a frame's place is the map image of the
smallest mean absolute difference, alone or summed along ``sequence`` frames (the frames and
the map advance one image per frame on the rendered rounds, which share their spacing); and
beside it the product's own similarity (the default map, both feature types) on every
``every``-th frame. It prints the share of frames whose best image lies within 3 and 10 m of
the truth, and what chance gives (the share of map images within 3 m of a frame's place).

Where the night round carries the robot's odometry, ``along_odometry`` goes one step further
than SeqSLAM's fixed-speed sum: a forward filter over the map's images in route order (an
HMM on the loop) moves its belief by the wheels' travel between frames and weighs it by each
frame's thumbnail differences, so that evidence adds up along the whole route driven so far.
It gives the whole-image approach every advantage the product's estimators lack (the route
known as a line of images, no kidnap): a bound on what thumbnails and wheels can do at night.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

NEAR_M = 3.0
FAR_M = 10.0


def thumbnail(image: np.ndarray, size: tuple[int, int], block: int) -> np.ndarray:
    """The image (grey or BGR) shrunk to ``size`` (width, height) by area averaging, each
    ``block`` x ``block`` patch normalised to zero mean and unit deviation; flattened
    (float32). ``size`` must be a multiple of ``block`` on both axes."""
    w, h = size
    if w % block or h % block:
        raise ValueError(f"thumbnail size {w}x{h} is not a multiple of the block {block}")
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    small = cv2.resize(grey.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    patches = small.reshape(h // block, block, w // block, block)
    mean = patches.mean(axis=(1, 3), keepdims=True)
    std = patches.std(axis=(1, 3), keepdims=True)
    return ((patches - mean) / (std + 1e-3)).astype(np.float32).ravel()


def differences(frames: np.ndarray, images: np.ndarray) -> np.ndarray:
    """(F, M) mean absolute difference of each frame's thumbnail with each image's."""
    return np.stack([np.abs(images - f).mean(axis=1) for f in frames])


def along_sequence(diff: np.ndarray, length: int) -> np.ndarray:
    """SeqSLAM's sum along the route: entry (i, j) sums ``diff[i - k, j - k]`` over the last
    ``length`` frames (frame and image advancing together; the map wraps around a loop).
    The first ``length - 1`` frames have no full sequence: inf."""
    if length < 1:
        raise ValueError(f"the sequence length must be at least 1, got {length}")
    out = np.full(diff.shape, np.inf)
    if len(diff) < length:
        return out
    acc = np.zeros((len(diff) - length + 1, diff.shape[1]))
    for k in range(length):
        acc += np.roll(diff[length - 1 - k: len(diff) - k], k, axis=1)
    out[length - 1:] = acc
    return out


def along_odometry(diff: np.ndarray, travel: np.ndarray, spacing: float, tau: float,
                   spread: float = 0.15, floor: float = 0.5, uniform: float = 0.02
                   ) -> np.ndarray:
    """(F,) each frame's most probable map image under a forward filter along the route.

    The belief over the map's ``M`` images (in route order; the loop wraps around) starts
    uniform; before frame ``i`` it moves by ``travel[i - 1]`` (m, the odometry's distance
    from frame ``i - 1`` to ``i``) over ``spacing`` (m between map images) images, blurred by
    a Gaussian of ``spread`` x that many images plus ``floor`` images, and mixed with
    ``uniform`` of a uniform belief (a wrong lock can be left); each frame then weighs image
    ``j`` by ``exp(-(diff[i, j] - min_j diff[i]) / tau)``."""
    if tau <= 0 or spacing <= 0:
        raise ValueError(f"tau and spacing must be positive, got {tau} and {spacing}")
    if len(travel) != max(len(diff) - 1, 0):
        raise ValueError(f"{len(travel)} odometry steps for {len(diff)} frames")
    m = diff.shape[1]
    belief = np.full(m, 1.0 / m)
    best = np.empty(len(diff), dtype=int)
    for i, d in enumerate(diff):
        if i:
            mu = float(travel[i - 1]) / spacing
            sigma = spread * mu + floor
            shifts = np.arange(int(np.floor(mu - 4 * sigma)), int(np.ceil(mu + 4 * sigma)) + 1)
            weights = np.exp(-0.5 * ((shifts - mu) / sigma) ** 2)
            weights /= weights.sum()
            moved = weights @ belief[(np.arange(m)[None, :] - shifts[:, None]) % m]
            belief = (1 - uniform) * moved + uniform / m
        belief = belief * np.exp(-(d - d.min()) / tau)
        belief /= belief.sum()
        best[i] = int(belief.argmax())
    return best


@dataclass(frozen=True)
class Tracked:
    """A filter's placement of a round's frames: mean error (m) and the share within 5 m,
    over all frames and from frame ``SETTLED`` on (once the filter has had time to find
    the place)."""

    mean_m: float
    within_5m: float
    settled_mean_m: float
    settled_within_5m: float


SETTLED = 100  # frames


def tracked(best: np.ndarray, image_xy: np.ndarray, frame_xy: np.ndarray) -> Tracked:
    """How far each frame's chosen image (``best``, indices) lies from its true place; a
    round of ``SETTLED`` frames or fewer has its last frame as the settled part."""
    err = np.linalg.norm(image_xy[best] - frame_xy, axis=1)
    late = err[min(SETTLED, len(err) - 1):]
    return Tracked(float(err.mean()), float(np.mean(err < 5.0)), float(late.mean()),
                   float(np.mean(late < 5.0)))


@dataclass(frozen=True)
class Placed:
    """Shares of frames whose best image lies within ``NEAR_M`` and ``FAR_M`` of the truth."""

    near: float
    far: float
    frames: int


def placed(scores: np.ndarray, image_xy: np.ndarray, frame_xy: np.ndarray,
           lower_is_better: bool = True) -> Placed:
    """How well each row's best image (lowest score, or highest) places its frame; rows of
    inf (no full sequence) are left out."""
    ok = np.isfinite(scores).all(axis=1)
    s = scores[ok]
    best = s.argmin(axis=1) if lower_is_better else s.argmax(axis=1)
    err = np.linalg.norm(image_xy[best] - frame_xy[ok], axis=1)
    return Placed(float(np.mean(err < NEAR_M)), float(np.mean(err < FAR_M)), int(ok.sum()))


def chance(image_xy: np.ndarray, frame_xy: np.ndarray) -> float:
    """The share of map images within ``NEAR_M`` of a frame's place, averaged over frames:
    how often a random image would place it."""
    d = np.linalg.norm(frame_xy[:, None, :] - image_xy[None, :, :], axis=2)
    return float(np.mean(d < NEAR_M))


@dataclass(frozen=True)
class WorldResult:
    seed: int
    chance: float
    thumbnails: dict[int, Placed]  # sequence length -> placed
    local: Placed | None  # the map's own similarity (every ``every``-th frame)
    odometry: Tracked | None = None  # thumbnails along the wheels (``along_odometry``)


def study(world: Path, seed: int, map_round: str, query: str, size: tuple[int, int],
          block: int, sequences: list[int], every: int, features: str,
          tau: float = 1.0) -> WorldResult:
    """One world: the map round's images against the query round's frames (and, where the
    query round has ``odometry.csv``, the thumbnails along the wheels with ``tau``). A map of
    rounds joined by '+' keeps the first round's places; each place's difference is the
    least over the rounds' images nearest to it."""
    from client.dataset import read_round
    from client.lab.experiment_cli import map_for
    from service.vision.features import extract

    layers = [read_round(world / r) for r in map_round.split("+") if r]
    night = read_round(world / query)
    image_xy, frame_xy = (np.asarray(layers[0].reference_xy, float),
                          np.asarray(night.reference_xy, float))
    frames = np.stack([thumbnail(night.load_image(i), size, block)
                       for i in range(len(night))])
    diff = np.full((len(night), len(image_xy)), np.inf)
    for layer in layers:  # a map of several rounds: each place's least difference
        images = np.stack([thumbnail(layer.load_image(i), size, block)
                           for i in range(len(layer))])
        xy = np.asarray(layer.reference_xy, float)
        nearest = np.linalg.norm(image_xy[:, None, :] - xy[None, :, :], axis=2).argmin(axis=1)
        diff = np.minimum(diff, differences(frames, images)[:, nearest])
    thumbs = {n: placed(along_sequence(diff, n), image_xy, frame_xy) for n in sequences}
    wheels = None
    if night.odometry is not None:
        spacing = float(np.median(np.linalg.norm(np.diff(image_xy, axis=0), axis=1)))
        travel = np.linalg.norm(np.diff(night.odometry[:, :2], axis=0), axis=1)
        wheels = tracked(along_odometry(diff, travel, spacing, tau), image_xy, frame_xy)
    local = None
    if every > 0:
        m = map_for(world, map_round, papers=False, features=features)
        ids = np.arange(m.n_images)
        picked = np.arange(0, len(night), every)
        sims = np.stack([m.similarity(extract(night.load_image(int(i)), m.feature_params), ids)
                         for i in picked])
        local = placed(sims, np.asarray(m.positions, float), frame_xy[picked],
                       lower_is_better=False)
    return WorldResult(seed, chance(image_xy, frame_xy), thumbs, local, wheels)


def table(results: list[WorldResult], sequences: list[int], features: str) -> str:
    """Per world: best image within 3 m / 10 m of the truth."""
    head = ("| world | chance (3 m) | " + " | ".join(
        f"thumbnails, {'one frame' if n == 1 else f'{n} frames'}" for n in sequences)
        + f" | local features ({features}) | thumbnails along the odometry: mean / within "
        f"5 m, from frame {SETTLED} on |\n|" + "---|" * (4 + len(sequences)))
    rows = []
    for r in results:
        cells = [f"{100 * r.thumbnails[n].near:.0f} / {100 * r.thumbnails[n].far:.0f} %"
                 for n in sequences]
        loc = ("not measured" if r.local is None else
               f"{100 * r.local.near:.0f} / {100 * r.local.far:.0f} % ({r.local.frames} frames)")
        wheels = ("no odometry" if r.odometry is None else
                  f"{r.odometry.mean_m:.1f} m / {100 * r.odometry.within_5m:.0f} %, "
                  f"{r.odometry.settled_mean_m:.1f} m / "
                  f"{100 * r.odometry.settled_within_5m:.0f} %")
        rows.append(f"| seed {r.seed} | {100 * r.chance:.1f} % | " + " | ".join(cells)
                    + f" | {loc} | {wheels} |")
    return "\n".join([head, *rows])
