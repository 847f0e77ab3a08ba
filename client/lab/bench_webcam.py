"""``swarmloc bench webcam-night``: correct matches between day and night photos of fixed
cameras (the tilde webcams, ``../shared/textures/tilde_webcam``), one feature type against
another.

Each scene is one folder of photos taken by one fixed camera, so the pixel correspondence
between any two of its photos is the identity. Per scene, every photo is brought to one working
size (aspect kept, about ``area`` pixels) and classified by its mean grey there: night below
``night_max``, day at or above the scene's median (the photos in between are neither). For every
day-night pair, a feature type's own matches (what its similarity counts: the symmetric ratio
test for RootSIFT, ``service.vision.metric_pose.match_pairs``; mutual nearest neighbours with
the cosine gate for XFeat, ``service.vision.mnn_matcher.mnn_pairs``) are correct when their
keypoints lie within ``tolerance_px`` of each other. The result is the share of pairs with at
least 10, 20 and 50 correct matches.

The photos are licensed for research only: this module reads them where they are and prints
numbers; nothing of them is copied.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from client.dataset import imread_gray
from service.api.round_format import IMAGE_SUFFIXES
from service.vision.features import (
    DEFAULT_DELTA,
    Features,
    SiftParams,
    extract,
    named_params,
    to_working_size,
)
from service.vision.metric_pose import match_pairs
from service.vision.mnn_matcher import mnn_pairs
from service.vision.xfeat import XFeatParams

if TYPE_CHECKING:
    from service.vision.features import FeatureParams

NIGHT_MAX = 80.0  # mean grey below this: a night photo
TOLERANCE_PX = 3.0  # a match is correct when its keypoints lie this close (identity)
THRESHOLDS = (10, 20, 50)  # correct matches a pair needs to count


@dataclass(frozen=True)
class Scene:
    name: str
    photos: int
    size: tuple[int, int]  # working size (width, height)
    night: tuple[str, ...]  # file names
    day: tuple[str, ...]

    @property
    def pairs(self) -> int:
        return len(self.night) * len(self.day)


@dataclass
class WebcamBench:
    scenes: list[Scene]
    correct: dict[str, list[int]] = field(default_factory=dict)  # per feature type, per pair
    per_scene: dict[tuple[str, str], list[int]] = field(default_factory=dict)

    def share(self, kind: str, at_least: int, scene: str | None = None) -> float:
        """Share of day-night pairs with at least ``at_least`` correct matches (nan: none)."""
        c = np.asarray(self.correct[kind] if scene is None else self.per_scene[(scene, kind)])
        return float(np.mean(c >= at_least)) if len(c) else float("nan")


def working_size(width: int, height: int, area: int) -> tuple[int, int]:
    """(width, height) of about ``area`` pixels with the photo's aspect."""
    s = (area / (width * height)) ** 0.5
    return max(32, round(width * s)), max(32, round(height * s))


def own_matches(params: FeatureParams, a: Features, b: Features
                ) -> tuple[np.ndarray, np.ndarray]:
    """The feature type's own matches (those its similarity m counts) between two frames."""
    if isinstance(params, XFeatParams):
        return mnn_pairs(a.codes, b.codes, params.min_cos, params.max_ratio)
    return match_pairs(a.codes, b.codes, DEFAULT_DELTA)


def correct_matches(params: FeatureParams, a: Features, b: Features,
                    tolerance_px: float = TOLERANCE_PX) -> int:
    """Matches whose keypoints lie within ``tolerance_px`` under the identity."""
    ia, ib = own_matches(params, a, b)
    if not len(ia):
        return 0
    return int(np.sum(np.linalg.norm(a.keypoints[ia] - b.keypoints[ib], axis=1)
                      <= tolerance_px))


def scene_folders(root: Path) -> list[Path]:
    if not root.is_dir():
        raise ValueError(f"{root} is not a folder of scene folders")
    scenes = sorted(p for p in root.iterdir() if p.is_dir() and _photos(p))
    if not scenes:
        raise ValueError(f"{root} has no scene folder with PNG or JPEG photos")
    return scenes


def _photos(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def classify(means: Sequence[float], night_max: float = NIGHT_MAX
             ) -> tuple[list[int], list[int]]:
    """(night, day) indices: night below ``night_max``, day at or above the median; a scene
    whose median is itself below ``night_max`` has no day."""
    med = float(np.median(means))
    night = [i for i, m in enumerate(means) if m < night_max]
    day = [i for i, m in enumerate(means) if m >= max(med, night_max)]
    return night, day


def bench_webcam(root: Path, kinds: Sequence[str] = ("clahe-rootsift", "xfeat"),
                 area: int = 640 * 360, night_max: float = NIGHT_MAX,
                 tolerance_px: float = TOLERANCE_PX) -> WebcamBench:
    """Correct matches of every day-night pair of every scene under ``root``."""
    out = WebcamBench([], {k: [] for k in kinds})
    for folder in scene_folders(root):
        files = _photos(folder)
        grays = []
        for f in files:
            g = imread_gray(f)
            if g is None:
                raise ValueError(f"{f} does not decode as an image")
            grays.append(g)
        size = working_size(grays[0].shape[1], grays[0].shape[0], area)
        shape = SiftParams(width=size[0], height=size[1])
        means = [float(to_working_size(g, shape).mean()) for g in grays]
        night, day = classify(means, night_max)
        scene = Scene(folder.name, len(files), size, tuple(files[i].name for i in night),
                      tuple(files[i].name for i in day))
        out.scenes.append(scene)
        for kind in kinds:
            params = named_params(kind, *size)
            feats = {i: extract(grays[i], params) for i in night + day}
            counts = [correct_matches(params, feats[n], feats[d], tolerance_px)
                      for n in night for d in day]
            out.correct[kind].extend(counts)
            out.per_scene[(scene.name, kind)] = counts
    return out


def report(b: WebcamBench, say: Callable[[str], object] = print) -> None:
    """The scenes, then the shares per feature type and their ratio (second over first)."""
    say("| scene | photos | working size | night | day | pairs |")
    say("|---|---|---|---|---|---|")
    for s in b.scenes:
        say(f"| {s.name} | {s.photos} | {s.size[0]}x{s.size[1]} | {len(s.night)} | "
            f"{len(s.day)} | {s.pairs} |")
    say("")
    cols = " | ".join(f"share >= {t}" for t in THRESHOLDS)
    say(f"| features | scene | pairs | {cols} | median correct |")
    say("|---|---|---|" + "---|" * len(THRESHOLDS) + "---|")
    for kind, counts in b.correct.items():
        rows = [("all", counts)] + [(s.name, b.per_scene[(s.name, kind)]) for s in b.scenes
                                    if s.pairs]
        for scene, c in rows:
            shares = " | ".join(f"{b.share(kind, t, None if scene == 'all' else scene):.3f}"
                                for t in THRESHOLDS)
            med = f"{np.median(c):.0f}" if len(c) else "n/a"
            say(f"| {kind} | {scene} | {len(c)} | {shares} | {med} |")
    kinds = list(b.correct)
    if len(kinds) == 2:
        base, other = kinds
        ratios = []
        for t in THRESHOLDS:
            s0, s1 = b.share(base, t), b.share(other, t)
            ratios.append(f">= {t}: {s1 / s0:.2f}" if s0 > 0 else f">= {t}: n/a")
        say(f"ratio {other} / {base} of the shares: " + ", ".join(ratios))
