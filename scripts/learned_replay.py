"""Round 2 of a light replayed on learned maps as ``swarmloc bench experiences`` replays it
(client/lab/bench_experience.py ``replays``: DPSO seeds 0..runs-1, the round's odometry,
errors after WARMUP frames), without teaching again: the benchmark's *learned* column for the
maps a benchmark run left in its ``--work`` directory, for a change that acts only on maps
with experiences (the teaching run, the unlearned and the same-light maps are unchanged).
Nothing is asserted.

    PYTHONPATH=. python scripts/learned_replay.py /work/expd/w7 dusk \
        WORK/w7-dusk-clahe-rootsift+xfeat/sunny1.swmap
"""

from __future__ import annotations

import argparse
from pathlib import Path

from client.dataset import read_round
from client.lab.bench_experience import _features, replays
from service.maps.route_map import load_map


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("world", type=Path, help="the rendered world (its LIGHT2 round)")
    ap.add_argument("light", help="cloudy or dusk")
    ap.add_argument("maps", type=Path, nargs="+", help="learned maps (.swmap)")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--runs", type=int, default=3)
    a = ap.parse_args()
    second = read_round(a.world / f"{a.light}2")
    for path in a.maps:
        m = load_map(path)
        r = replays(m, second, _features(second, m, a.frames), a.runs)
        print(f"{a.world.name} {a.light} {path}: learned {r.mean_error_m:.3f} m, "
              f"{r.comparisons:.1f} comparisons per frame, on an experience "
              f"{100 * r.on_experience:.0f} %", flush=True)


if __name__ == "__main__":
    main()
