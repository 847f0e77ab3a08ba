"""Round 2 of a light against a learned map, its errors split by the experience's coverage.

The learned run of ``swarmloc bench experiences`` (client/lab/bench_experience.py ``replay``:
DPSO seed 0 from the round's first image, timestamps at the round's median spacing, errors
scored after WARMUP frames) on a map the benchmark already taught (its ``--work`` directory
keeps ``wSEED-LIGHT-FEATURES/sunny1.swmap``), so a change to how experiences are *used* is
measured without teaching again (the teaching session runs on the map without experiences:
it does not depend on that code). Prints the mean error over all scored frames, over those
within two map spacings of a learned image (*covered*) and the others (*gap*), comparisons
per frame and the share of frames matched with the experience; ``--unlearned`` also runs the
world's sunny1 map, ``--per-frame`` prints every frame, ``--no-scale`` leaves the layers
unscaled (``LayerChoice.scaled``: the ablation in docs/research/lighting.md).

    PYTHONPATH=. python scripts/experience_split.py /tmp/expd/w0 dusk2 \\
        /tmp/expd/work/w0-dusk-clahe-rootsift+xfeat/sunny1.swmap --frames 200
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from client.dataset import read_round
from client.lab.bench_experience import WARMUP, covered
from client.lab.experiment_cli import map_for
from service.engine.localizer import Localizer
from service.maps.experiences import LayerChoice
from service.maps.route_map import RouteMap, load_map
from service.vision.features import extract


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("world", type=Path)
    ap.add_argument("round")
    ap.add_argument("learned_map", type=Path)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--unlearned", action="store_true")
    ap.add_argument("--per-frame", action="store_true")
    ap.add_argument("--no-scale", action="store_true")
    ap.add_argument("--features", default="clahe-rootsift+xfeat",
                    help="the unlearned map's feature type (the learned map's)")
    a = ap.parse_args()
    if a.no_scale:
        LayerChoice.scaled = lambda self, m, s: s  # type: ignore[method-assign,assignment]
    learned = load_map(a.learned_map)
    rnd = read_round(a.world / a.round)
    n = min(a.frames, len(rnd))
    feats = [extract(rnd.load_image(i), learned.feature_params) for i in range(n)]
    dt = float(np.median(np.diff(rnd.t))) if rnd.t is not None and len(rnd) > 1 else 1.0
    truth = rnd.reference_xy[:n]
    cov = covered(learned, truth)
    maps: list[tuple[str, RouteMap]] = [("learned", learned)]
    if a.unlearned:
        maps.append(("unlearned", map_for(a.world, "sunny1", papers=False,
                                          features=a.features)))
    for name, m in maps:
        loc = Localizer(m, seed=0)
        est, comps, on = [], [], []
        for i, f in enumerate(feats):
            e = loc.step(f, t=i * dt)
            est.append((e.x, e.y))
            comps.append(e.comparisons)
            on.append(e.experience is not None)
            if a.per_frame:
                print(name, i, f"{np.hypot(e.x - truth[i][0], e.y - truth[i][1]):.2f} m",
                      "covered" if cov[i] else "gap", e.status, e.experience, flush=True)
        err = np.linalg.norm(np.array(est) - truth, axis=1)[WARMUP:]
        c = cov[WARMUP:]
        print(f"{a.world.name} {a.round} {name}: mean {err.mean():.2f} m, covered "
              f"{err[c].mean() if c.any() else float('nan'):.2f} m ({c.sum()} frames), gap "
              f"{err[~c].mean() if (~c).any() else float('nan'):.2f} m ({(~c).sum()}), "
              f"comparisons {np.mean(comps):.1f}, on the experience {np.mean(on[WARMUP:]):.2f}",
              flush=True)


if __name__ == "__main__":
    main()
