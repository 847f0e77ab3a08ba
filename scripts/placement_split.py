"""Where a teaching run places its images, split along and across the path, and what each part
of that error costs round 2.

A sunny map learns round 1 of a light as ``swarmloc bench experiences`` teaches it
(client/lab/bench_experience.py ``replay`` with ``teach``: the round's odometry, one run from
its first image). Each learned image is compared with the true place of the round-1 frame it
came from: its error along the path and across it, the share of that error the sunny map's own
image there carries, and the *pull*: the error across the path towards the sunny map's lane
(positive: placed nearer the sunny lane than the robot drove). Located frames (gate 4) and
frames bridged by the wheels are printed apart, and the located ones also by the geometry that
located them (RootSIFT's or XFeat's) before the placement aligns them to the odometry.

Round 2 is then replayed as the benchmark replays it (``replays``: DPSO seeds 0..runs-1, with
odometry, errors after WARMUP frames) on the learned map and on copies with every learned
image moved: ``along`` (its error along the path removed, across kept), ``across`` (the
reverse) and ``truth`` (both removed). ``--radius SPACINGS``: the learner's reach for the
map's images (gates 3 and 4; the product's is ``GAP_SPACINGS``, 2). Lab only: it
monkeypatches the learner to record which geometry located a frame. Nothing is asserted.

    PYTHONPATH=. python scripts/placement_split.py /work/expd/w23 cloudy --replay all
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from client.dataset import read_round
from client.lab.bench_experience import (
    _features,
    learned_images,
    moved,
    replays,
    source_frames,
    teach,
)
from client.lab.experiment_cli import map_for
from service.engine import learning
from service.engine.localization_service import LocalizationService
from service.maps.experiences import GAP_SPACINGS, NewImage
from service.maps.route_map import RouteMap, load_map
from service.settings import Settings
from service.vision.features import Features
from service.vision.map_geometry import MapGeometry
from service.vision.metric_pose import Offset

VARIANTS = ("learned", "along", "across", "truth")


class Recorder:
    """Which geometry located each taught frame (the learner's located position, bit for bit,
    names it) and the located positions before the placement."""

    def __init__(self) -> None:
        self.kind: dict[tuple[float, float], str] = {}
        self.raw: dict[str, tuple[np.ndarray, bool]] = {}  # image name -> (xy, located)
        self._last: list[str] = []

    def install(self, second: MapGeometry | None) -> None:
        locate, located, placed = MapGeometry.locate, learning.Learner._located, \
            learning.placed
        rec = self

        def locate_spy(geo: MapGeometry, *a: Any, **k: Any) -> Offset | None:
            off = locate(geo, *a, **k)
            if off is not None:
                rec._last.append("xfeat" if geo is second else "rootsift")
            return off

        def located_spy(learner: learning.Learner, m: RouteMap, features: Features,
                        xy: np.ndarray) -> tuple[np.ndarray | None, float | None]:
            rec._last.clear()
            at, heading = located(learner, m, features, xy)
            if at is not None and rec._last:
                rec.kind[(float(at[0]), float(at[1]))] = rec._last[-1]
            return at, heading

        def placed_spy(images: list[NewImage], seqs: list[int],
                       odometry: list[np.ndarray | None], known: list[bool] | None = None,
                       context: learning.Context | None = None) -> list[NewImage]:
            ks = [True] * len(images) if known is None else list(known)
            for f, ok in zip(images, ks, strict=True):
                rec.raw[f.name] = (np.array(f.xy, float), bool(ok))
            return placed(images, seqs, odometry, known, context)

        MapGeometry.locate = locate_spy  # type: ignore[method-assign,assignment]
        learning.Learner._located = located_spy  # type: ignore[method-assign,assignment]
        learning.placed = placed_spy


def frame_axes(ref: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The unit direction of travel and its left normal at each of ``frames`` of a round."""
    tan = np.gradient(ref, axis=0)[frames]
    tan /= np.linalg.norm(tan, axis=1, keepdims=True)
    return tan, np.column_stack([-tan[:, 1], tan[:, 0]])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("world", type=Path)
    ap.add_argument("light")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--radius", type=float, default=GAP_SPACINGS,
                    help="the learner's reach for the map's images, in map spacings")
    ap.add_argument("--replay", default="",
                    help=f"comma list of {', '.join(VARIANTS)}, or all")
    ap.add_argument("--features", default="clahe-rootsift+xfeat")
    a = ap.parse_args()
    first, second = (read_round(a.world / f"{a.light}{k}") for k in (1, 2))
    sunny = map_for(a.world, "sunny1", papers=False, features=a.features)
    sunny_ref = read_round(a.world / "sunny1").reference_xy
    learning.GAP_SPACINGS = a.radius
    rec = Recorder()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        assert sunny.path is not None
        shutil.copy(sunny.path, work / "sunny1.swmap")
        svc = LocalizationService(Settings(maps_dir=work, session_store="memory"))
        base = svc.get_map("sunny1")
        rec.install(base.second_geometry)
        stats = teach(svc, base, first, a.light, a.frames)
        svc.close()
        m = load_map(work / "sunny1.swmap")
        ids = learned_images(m)
        src = source_frames(m, ids)
        ref = first.reference_xy
        truth = ref[src]
        tan, nrm = frame_axes(ref, src)
        err = m.positions[ids] - truth
        along, across = (err * tan).sum(1), (err * nrm).sum(1)
        near = np.argmin(np.linalg.norm(truth[:, None] - sunny.positions[None], axis=2), axis=1)
        side = np.sign(((truth - sunny.positions[near]) * nrm).sum(1))  # the robot's lane side
        pull = -side * across
        lane = np.abs(((truth - sunny.positions[near]) * nrm).sum(1))
        own = sunny.positions[near] - sunny_ref[near]  # the sunny image's own position error
        raw = [rec.raw.get(m.image_names[int(i)]) for i in ids]
        located = np.array([r is None or r[1] for r in raw])
        print(f"{a.world.name} {a.light}: {len(ids)} learned images ({int(located.sum())} "
              f"located, {int((~located).sum())} bridged); gates {stats}")
        print(f"  placed {np.linalg.norm(err, axis=1).mean():.2f} m from the truth: |along| "
              f"{np.abs(along).mean():.2f}, |across| {np.abs(across).mean():.2f}; the robot "
              f"drove {lane.mean():.2f} m beside the sunny lane; pull towards it: located "
              f"{pull[located].mean():+.2f}, bridged "
              f"{pull[~located].mean() if (~located).any() else float('nan'):+.2f}")
        print(f"  the sunny images there {np.linalg.norm(own, axis=1).mean():.2f} m from the "
              f"truth; learned error less theirs {np.linalg.norm(err - own, axis=1).mean():.2f}")
        for kind in ("rootsift", "xfeat"):
            rows = [(k, r[0]) for k, r in enumerate(raw) if r is not None and r[1]
                    and rec.kind.get((float(r[0][0]), float(r[0][1]))) == kind]
            if not rows:
                continue
            k = np.array([q for q, _ in rows])
            e = np.array([xy for _, xy in rows]) - truth[k]
            print(f"  located by {kind}: {len(k)} frames, before the placement "
                  f"{np.linalg.norm(e, axis=1).mean():.2f} m from the truth, pull "
                  f"{np.mean(-side[k] * (e * nrm[k]).sum(1)):+.2f}, |along| "
                  f"{np.abs((e * tan[k]).sum(1)).mean():.2f}")
        wanted = VARIANTS if a.replay == "all" else [v for v in a.replay.split(",") if v]
        test = _features(second, m, a.frames) if wanted else []
        for v in wanted:
            xy = {"along": truth + across[:, None] * nrm, "across": truth + along[:, None] * tan,
                  "truth": truth}.get(v)
            mm = m if xy is None else moved(m, ids, xy, work / f"{v}.swmap")
            r = replays(mm, second, test, a.runs)
            print(f"  round 2, {v}: {r.mean_error_m:.2f} m, comparisons {r.comparisons:.1f}",
                  flush=True)


if __name__ == "__main__":
    main()
