"""The place index of a map of two feature types on XFeat against one on RootSIFT.

For a rendered world's sunny map of both types (``clahe-rootsift+xfeat``, built and cached as
``swarmloc experiment`` builds it) and round 2 of a light: per frame, the rank of the first
of the index's top 20 candidates within 3 m of the truth, with the map's index (XFeat since
2026-12-06) and with an index of the same images' RootSIFT features (the index of maps built
before). With ``--replays N``: the mean error of N replays (DPSO seeds 0..N-1) of round 2's
first ``--frames`` images with odometry, scored from frame 20, as ``swarmloc bench
experiences`` replays the unlearned map, with either index.

    PYTHONPATH=. python scripts/place_index_ranks.py data/w0 dusk --replays 3
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from client.dataset import read_round
from client.lab.bench_experience import _features, replays
from client.lab.experiment_cli import map_for
from service.maps.route_map import RouteMap
from service.vision.features import Features
from service.vision.place_index import PlaceIndex, build_place_index

TOP = 20
NEAR_M = 3.0


def ranks(m: RouteMap, index: PlaceIndex, feats: list[Features], truth: np.ndarray
          ) -> np.ndarray:
    """Per frame, the rank of the first candidate within NEAR_M of the truth (TOP: none)."""
    out = np.full(len(feats), TOP)
    for i, f in enumerate(feats):
        ids, _ = index.query(index.frame_codes(f), TOP)
        near = np.flatnonzero(np.linalg.norm(m.positions[ids] - truth[i], axis=1) <= NEAR_M)
        if len(near):
            out[i] = int(near[0])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("light", help="the round-2 light: cloudy, dusk, ...")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--replays", type=int, default=0)
    a = ap.parse_args()
    m = map_for(a.dataset, "sunny1", papers=False, features="clahe-rootsift+xfeat")
    index = m.place_index
    assert index is not None and index.second, "a map of both types indexes its XFeat"
    rootsift = build_place_index(m, np.random.default_rng(0))
    assert rootsift is not None
    rnd = read_round(a.dataset / f"{a.light}2")
    feats = _features(rnd, m, a.frames)
    for name, idx in (("RootSIFT", rootsift), ("XFeat", index)):
        r = ranks(m, idx, feats, rnd.reference_xy)
        line = (f"{a.dataset.name} {a.light} {name:8s}: true place first {np.mean(r == 0):.2f}, "
                f"in top 5 {np.mean(r < 5):.2f}, top 10 {np.mean(r < 10):.2f} of {len(r)} "
                "frames")
        if a.replays:
            m.place_index = idx
            rep = replays(m, rnd, feats, a.replays)
            line += (f"; replays: mean error {rep.mean_error_m:.2f} m, "
                     f"{rep.comparisons:.1f} comparisons per frame")
        print(line, flush=True)
    m.place_index = index


if __name__ == "__main__":
    main()
