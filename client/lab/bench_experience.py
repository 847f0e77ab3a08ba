"""Experience maps in the lab: a sunny map learns a cloudy (or dusk) round, then localizes another.

For each rendered world and condition C (``cloudy`` or ``dusk``), in process (the service's
``Localizer`` and ``Learner``, as ``process_frame`` calls them), runs from each round's first
image (the learning session one, the others averaged over ``runs`` DPSO seeds), errors scored
after ``WARMUP`` frames:

- *unlearned*: the sunny1 map, round C2;
- *learn*: the sunny1 map, round C1 replayed by a session with ``learn`` (its experience is
  written into the map when the session ends);
- *learned*: the learned map, round C2;
- *same light*: the C1 map (recorded in that light), round C2.

Printed: mean errors, learned / unlearned and learned / same-light ratios, comparisons per
frame before and after learning, the images learned and the map file's growth against the
budget. Benchmarks print numbers; nothing here asserts.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from client.dataset import Round, read_round
from client.runs import odometry_poses
from service.engine.learning import LearnPath, path_gate
from service.engine.localization_service import LocalizationService
from service.engine.localizer import Localizer
from service.maps.experiences import (
    GAP_SPACINGS,
    base_spacing,
    experience_layers,
    experience_list,
)
from service.maps.route_map import RouteMap, load_map, save_map
from service.settings import Settings
from service.vision.features import Features, extract

WARMUP = 20  # frames of global convergence before errors are scored


@dataclass(frozen=True)
class Replay:
    mean_error_m: float
    comparisons: float  # per frame
    frames: int
    on_experience: float = 0.0  # share of the scored frames matched with an experience


@dataclass(frozen=True)
class Case:
    seed: int
    condition: str
    unlearned: Replay
    learned: Replay
    same_light: Replay
    learned_images: int
    taught: int
    file_growth_bytes: int
    budget_bytes: int
    learn_s: float
    coverage: float  # share of round 2's frames within GAP_SPACINGS of a learned image
    placed_m: float  # mean distance of the learned images from the truth (round 1's frames)
    gates: dict[str, int]  # the teaching session's frames, taught and stopped by each gate


def _features(rnd: Round, m: RouteMap, frames: int) -> list[Features]:
    return [extract(rnd.load_image(i), m.feature_params) for i in range(min(frames, len(rnd)))]


def replay(m: RouteMap, rnd: Round, feats: list[Features], *, seed: int = 0,
           teach: tuple[LocalizationService, str] | None = None,
           odometry: bool = True) -> Replay:
    """One run from the round's first image (features extracted once per round and shared by
    its runs). ``teach``: (service, condition), the run is a learning session of the service:
    each estimate goes to its learner, as ``process_frame`` does, and the session's images are
    written into the map when the run ends. ``odometry``: each frame carries the round's
    odometry (``odometry.csv``), as ``swarmloc replay`` sends it by default."""
    loc = Localizer(m, seed=seed)
    dt = float(np.median(np.diff(rnd.t))) if rnd.t is not None and len(rnd) > 1 else 1.0
    if odometry and rnd.odometry is None:
        raise ValueError(f"round {rnd.name} has no odometry.csv: render it again, or run "
                         "without odometry")
    poses = odometry_poses(rnd.odometry if odometry else None, np.arange(len(feats)))
    est, comps, on = [], [], []
    path: LearnPath = []
    for i, f in enumerate(feats):
        e = loc.step(f, t=i * dt, odom=poses[i])
        if teach is not None:
            svc = teach[0]
            path, stopped = path_gate(path, e, svc.settings.learn_accuracy_m)
            svc.learner.observe("teacher", 0.0, teach[1], m, f, e, stopped, poses[i])
        est.append((e.x, e.y))
        comps.append(e.comparisons)
        on.append(e.experience is not None)
    err = np.linalg.norm(np.array(est) - rnd.reference_xy[: len(est)], axis=1)[WARMUP:]
    return Replay(float(err.mean()), float(np.mean(comps)), len(est),
                  float(np.mean(on[WARMUP:])) if len(on) > WARMUP else 0.0)


def replays(m: RouteMap, rnd: Round, feats: list[Features], n: int,
            odometry: bool = True) -> Replay:
    """``n`` runs (DPSO seeds 0..n-1) from the round's first image, averaged: one run's
    error swings by tens of per cent where the light is hard."""
    runs = [replay(m, rnd, feats, seed=k, odometry=odometry) for k in range(n)]
    return Replay(float(np.mean([r.mean_error_m for r in runs])),
                  float(np.mean([r.comparisons for r in runs])), runs[0].frames,
                  float(np.mean([r.on_experience for r in runs])))


def teach(service: LocalizationService, base: RouteMap, rnd: Round, condition: str,
          frames: int, odometry: bool = True) -> dict[str, int]:
    """The learning session: ``rnd``'s first ``frames`` frames replayed on ``base`` (the
    service's map) with ``learn``, then ended, so that its images are written into the map
    (``service.get_map`` loads the new version). Returns the session's gate counts."""
    replay(base, rnd, _features(rnd, base, frames), teach=(service, condition),
           odometry=odometry)
    stats = service.learner.stats("teacher")
    service.learner.flush("teacher", end=True)  # the session ends: its images are written
    service.writer.wait()
    return stats


def moved(m: RouteMap, ids: np.ndarray, xy: np.ndarray, path: Path) -> RouteMap:
    """A copy of ``m`` with images ``ids`` at ``xy`` (lab ablations of where learned images
    sit), written to ``path`` and loaded."""
    pos = np.array(m.positions, float)
    pos[ids] = xy
    return load_map(save_map(dataclasses.replace(m, positions=pos), path))


def learned_images(m: RouteMap) -> np.ndarray:
    """Ids of the map's experience images."""
    return np.flatnonzero(np.isin(np.asarray(m.layers), list(experience_layers(m).values())))


def covered(m: RouteMap, truth: np.ndarray) -> np.ndarray:
    """Per true position: whether a learned image lies within ``GAP_SPACINGS`` map spacings
    (all False for a map without experiences)."""
    ids = learned_images(m)
    if not len(ids):
        return np.zeros(len(truth), bool)
    d = np.min(np.linalg.norm(truth[:, None, :] - m.positions[ids][None, :, :], axis=2), axis=1)
    return d <= GAP_SPACINGS * base_spacing(m)


def source_frames(m: RouteMap, ids: np.ndarray) -> np.ndarray:
    """The round-1 frame (index) each learned image ``ids`` came from: a learned image is named
    ``EXPERIENCE/SEQ``, SEQ the session's frame counted from 1."""
    return np.array([int(m.image_names[int(i)].rsplit("/", 1)[1]) - 1 for i in ids], int)


def learned_fit(m: RouteMap, first: Round, second: Round, frames: int) -> tuple[float, float]:
    """(coverage, placed): the share of round 2's first ``frames`` frames whose true place lies
    within ``GAP_SPACINGS`` map spacings of a learned image, and the mean distance of the
    learned images from the true place of the round-1 frames they came from."""
    ids = learned_images(m)
    if not len(ids):
        return 0.0, float("nan")
    coverage = float(np.mean(covered(m, second.reference_xy[:frames])))
    truth = first.reference_xy[source_frames(m, ids)]
    placed = float(np.mean(np.linalg.norm(m.positions[ids] - truth, axis=1)))
    return coverage, placed


def run_case(dataset: Path, seed: int, condition: str, work: Path, budget_mb: float,
             frames: int, features: str = "clahe-rootsift", runs: int = 1,
             odometry: bool = True) -> Case:
    """One world and condition: the four runs above, ``frames`` images of each round;
    ``features``: the maps' feature type (``clahe-rootsift+xfeat``: both, fused); ``runs``:
    the unlearned, learned and same-light replays each averaged over that many DPSO seeds
    (the learning session is one run, as a robot's); ``odometry``: every run's frames carry
    their round's odometry."""
    from client.lab.experiment_cli import map_for

    sunny = map_for(dataset, "sunny1", papers=False, features=features)
    same = map_for(dataset, f"{condition}1", papers=False, features=features)
    first, second = (read_round(dataset / f"{condition}{k}") for k in (1, 2))
    maps_dir = work / f"w{seed}-{condition}-{features}"
    shutil.rmtree(maps_dir, ignore_errors=True)
    maps_dir.mkdir(parents=True)
    assert sunny.path is not None
    shutil.copy(sunny.path, maps_dir / "sunny1.swmap")
    service = LocalizationService(Settings(maps_dir=maps_dir, session_store="memory",
                                           experience_budget_mb=budget_mb))
    base = service.get_map("sunny1")
    before = (maps_dir / "sunny1.swmap").stat().st_size
    test_feats = _features(second, base, frames)
    unlearned = replays(base, second, test_feats, runs, odometry)
    same_light = replays(same, second, test_feats, runs, odometry)
    t0 = time.perf_counter()
    stats = teach(service, base, first, condition, frames, odometry)
    learn_s = time.perf_counter() - t0
    m = service.get_map("sunny1")
    learned = replays(m, second, test_feats, runs, odometry)
    images = sum(int(e["images"]) for e in experience_list(m))
    growth = (maps_dir / "sunny1.swmap").stat().st_size - before
    coverage, placed = learned_fit(m, first, second, frames)
    service.close()
    print(f"seed {seed} {condition}: learning gates {stats}; coverage {coverage:.2f}, learned "
          f"images {placed:.2f} m from the truth, frames on an experience "
          f"{learned.on_experience:.2f}", flush=True)
    return Case(seed, condition, unlearned, learned, same_light, images,
                stats.get("taught", 0), growth, int(budget_mb * 1024 * 1024), learn_s,
                coverage, placed, stats)


def table(cases: list[Case]) -> str:
    head = ("| world | light | unlearned | learned | same light | learned / unlearned | "
            "learned / same light | comp. before | comp. after | growth | images | "
            "file growth (budget) |\n|" + "---|" * 12)
    rows = []
    for c in cases:
        rows.append(
            f"| seed {c.seed} | {c.condition} | {c.unlearned.mean_error_m:.2f} | "
            f"**{c.learned.mean_error_m:.2f}** | {c.same_light.mean_error_m:.2f} | "
            f"x{c.learned.mean_error_m / c.unlearned.mean_error_m:.2f} | "
            f"x{c.learned.mean_error_m / c.same_light.mean_error_m:.2f} | "
            f"{c.unlearned.comparisons:.1f} | {c.learned.comparisons:.1f} | "
            f"{100 * (c.learned.comparisons / c.unlearned.comparisons - 1):+.0f} % | "
            f"{c.learned_images} | {c.file_growth_bytes / 1e6:.1f} MB "
            f"({c.budget_bytes / 1e6:.0f} MB) |")
    return "\n".join([head, *rows])


GATES = ("confident", "path", "appearance", "located", "place")


def gates_table(cases: list[Case]) -> str:
    """The teaching session's frames: stopped by each gate (learning.py), taught, bridged by
    the wheels (of the stopped ones); the learned images' coverage of round 2 and distance
    from the truth; round 2's frames matched with an experience."""
    head = ("| world | light | frames | " + " | ".join(GATES) + " | taught | bridged | "
            "coverage | learned images from the truth | frames on the experience |\n|"
            + "---|" * 13)
    rows = [f"| seed {c.seed} | {c.condition} | {c.gates.get('seen', 0)} | "
            + " | ".join(str(c.gates.get(g, 0)) for g in GATES)
            + f" | {c.gates.get('taught', 0)} | {c.gates.get('bridged', 0)} | "
            f"{100 * c.coverage:.0f} % | {c.placed_m:.2f} m | "
            f"{100 * c.learned.on_experience:.0f} % |" for c in cases]
    return "\n".join([head, *rows])


def summary(cases: list[Case]) -> str:
    lines = []
    for cond in sorted({c.condition for c in cases}):
        cs = [c for c in cases if c.condition == cond]
        u = np.mean([c.unlearned.mean_error_m for c in cs])
        le = np.mean([c.learned.mean_error_m for c in cs])
        s = np.mean([c.same_light.mean_error_m for c in cs])
        g = np.mean([c.learned.comparisons / c.unlearned.comparisons - 1 for c in cs])
        lines.append(f"{cond}: mean over {len(cs)} worlds: unlearned {u:.2f} m, learned "
                     f"{le:.2f} m (x{le / u:.2f}), same light {s:.2f} m (learned x{le / s:.2f}); "
                     f"comparisons {100 * g:+.0f} %")
    return "\n".join(lines)
