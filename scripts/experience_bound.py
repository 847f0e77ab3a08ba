"""What a learned layer could give at best: the learned map's gap to the same light, split.

On a map ``swarmloc bench experiences`` taught (its ``--work`` directory keeps
``wSEED-LIGHT-FEATURES/sunny1.swmap``), round 2 of the light is replayed as the benchmark
replays it (client/lab/bench_experience.py ``replays``: DPSO seeds 0..runs-1 from the round's
first image, with the round's odometry, errors after WARMUP frames) on:

- *learned at the truth*: the learned map with every learned image moved to the true place
  of the round-1 frame it came from (what the teaching run's placement costs);
- *every frame at the truth*: the world's sunny1 map with an experience of round 1's first
  ``--frames`` frames at their true places, one image per place (what the teaching run's
  coverage costs besides);

- with ``--fix`` instead, only *learned, placed by the fix*: the learned map with every
  learned image where a learning robot with a GNSS-grade fix would place it (the round's
  ``poses.csv`` positions of the taught frames fused with their odometry, as the learner fuses
  located positions), under the product's rules (what a better position source on the
  learning robot would give);

each under the product's layer rules (``LayerChoice``: a particle's base image stands in for
its place, experiences on the base layer's scale) and, with ``--own``, under the rule of
each particle comparing with the experience image nearest to itself, unscaled (the rule
before the stand-in: ``--own`` monkeypatches ``LayerChoice``, lab only). The benchmark itself
prints the learned map's, the unlearned map's and the same-light map's errors over the same
frames and seeds.

    PYTHONPATH=. python scripts/experience_bound.py /work/expd/w23 cloudy \\
        /work/lab/bw/w23-cloudy-clahe-rootsift+xfeat/sunny1.swmap --own
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from client.dataset import Round, read_round
from client.lab.bench_experience import (
    Replay,
    _features,
    learned_images,
    moved,
    replays,
    source_frames,
)
from client.lab.experiment_cli import map_for
from service.engine.learning import placed
from service.maps import experiences as ex
from service.maps.experiences import NewImage, add_experience
from service.maps.route_map import RouteMap, load_map
from service.vision.features import Features


def own_nearest(self: ex.LayerChoice, m: RouteMap, at: np.ndarray | None = None
                ) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """``LayerChoice.nearest`` with each particle's own nearest experience image (within the
    gap) instead of the one nearest to its base image; the gap rule as the product's."""
    base = ex.base_layers(m)
    gap = ex.GAP_SPACINGS * ex.base_spacing(m)
    layer = self.layer_at(m, at, gap)

    def nearest(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ids, dist = ex.nearest_base(m, positions, base)
        if layer is None:
            return ids, dist
        e_ids, e_dist = m.nearest_in_layer(positions, layer)
        near = (e_dist <= gap)[:, None]
        return np.where(near, e_ids[:, None], ids), np.where(near, e_dist[:, None], dist)
    return nearest


@contextmanager
def own_rule() -> Iterator[None]:
    nearest, scaled = ex.LayerChoice.nearest, ex.LayerChoice.scaled
    ex.LayerChoice.nearest = own_nearest  # type: ignore[method-assign]
    ex.LayerChoice.scaled = lambda self, m, s: s  # type: ignore[method-assign,assignment]
    try:
        yield
    finally:
        ex.LayerChoice.nearest = nearest  # type: ignore[method-assign]
        ex.LayerChoice.scaled = scaled  # type: ignore[method-assign]


def at_truth(learned: RouteMap, truth: np.ndarray, path: Path) -> RouteMap:
    """The learned map with its learned images at the true places of their round-1 frames,
    written to ``path`` and loaded."""
    ids = learned_images(learned)
    return moved(learned, ids, truth[source_frames(learned, ids)], path)


def at_fix(learned: RouteMap, first: Round, path: Path) -> RouteMap:
    """The learned map with its learned images where a learning robot with a GNSS-grade fix
    would place them: the round's ``poses.csv`` positions of the taught frames, fused with
    their odometry as the learner fuses located positions (``learning.placed``), written to
    ``path`` and loaded."""
    ids = learned_images(learned)
    src = source_frames(learned, ids)
    order = np.argsort(src)
    if first.odometry is None:
        raise ValueError(f"round {first.name} has no odometry.csv")
    none = np.zeros((0, 2), np.float32)  # only the positions matter to ``placed``
    fixes = [NewImage(none, none, first.xy[k], str(k)) for k in src[order]]
    taught = placed(fixes, list(src[order]), list(first.odometry[src[order], :2]))
    return moved(learned, ids[order], np.array([f.xy for f in taught], float), path)


def every_frame(sunny: RouteMap, feats: list[Features], truth: np.ndarray, light: str,
                work: Path) -> RouteMap:
    """The sunny map with an experience of every frame of ``feats`` at its true place (one
    image per place, as ``add_experience`` keeps them)."""
    assert sunny.path is not None
    path = work / "sunny1.swmap"
    shutil.copy(sunny.path, path)
    base = load_map(path)
    images = [NewImage.of(f, truth[i], f"bound/{i + 1:06d}", second=base.second is not None)
              for i, f in enumerate(feats)]
    add_experience(base, path, "bound", images, condition=light, robot=None,
                   now=time.time(), budget_bytes=1 << 40)
    return load_map(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("world", type=Path)
    ap.add_argument("light")
    ap.add_argument("learned_map", type=Path)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--own", action="store_true", help="also each particle's own nearest "
                    "experience image, unscaled")
    ap.add_argument("--fix", action="store_true", help="only the learned map with its images "
                    "placed by the round's poses.csv and odometry (a robot with a GNSS-grade "
                    "fix), under the product's rules")
    ap.add_argument("--features", default="clahe-rootsift+xfeat",
                    help="the sunny map's feature type (the learned map's)")
    a = ap.parse_args()
    first, second = (read_round(a.world / f"{a.light}{k}") for k in (1, 2))
    learned = load_map(a.learned_map)
    sunny = map_for(a.world, "sunny1", papers=False, features=a.features)
    test = _features(second, learned, a.frames)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if a.fix:
            m = at_fix(learned, first, work / "fix.swmap")
            ids = learned_images(m)
            truth = first.reference_xy[source_frames(m, ids)]
            off = float(np.mean(np.linalg.norm(m.positions[ids] - truth, axis=1)))
            r = replays(m, second, test, a.runs)
            print(f"{a.world.name} {a.light} learned, placed by the fix ({off:.2f} m from the "
                  f"truth), product rules: {r.mean_error_m:.2f} m, comparisons "
                  f"{r.comparisons:.1f}", flush=True)
            return
        maps = {"learned": learned,
                "learned at the truth": at_truth(learned, first.reference_xy,
                                                 work / "truth.swmap"),
                "every frame at the truth": every_frame(
                    sunny, _features(first, sunny, a.frames), first.reference_xy, a.light,
                    work)}
        n = len(learned_images(maps["every frame at the truth"]))
        print(f"{a.world.name} {a.light}: {len(learned_images(learned))} learned images, "
              f"{n} in the every-frame experience", flush=True)
        for name, m in maps.items():
            rules: list[tuple[str, Replay]] = []
            if name != "learned":  # the benchmark prints it under the product's rules
                rules.append(("product rules", replays(m, second, test, a.runs)))
            if a.own:
                with own_rule():
                    rules.append(("own nearest, unscaled", replays(m, second, test, a.runs)))
            for rule, r in rules:
                print(f"{a.world.name} {a.light} {name}, {rule}: {r.mean_error_m:.2f} m, "
                      f"comparisons {r.comparisons:.1f}", flush=True)


if __name__ == "__main__":
    main()
