"""The place-sequence test's synthetic start over many DPSO seeds, with its honesty.

Runs ``tests/test_place_sequence.py``'s ``_search`` (a DPSO on a line of 400 images with weak
matches, a look-alike stretch 60 m ahead, odometry and no camera yaw) for seeds 0..N-1, with
the place sequence and without it, and prints per case the frames 20-59 within 3 m of the
robot, those more than 20 m off, and those reported ``tracking`` more than 10 m off (with
the runs that had any).

    PYTHONPATH=. python scripts/sequence_starts.py [N]     # N: 24 by default
"""

from __future__ import annotations

import sys

from tests.test_place_sequence import _search


def main(argv: list[str]) -> None:
    n = int(argv[0]) if argv else 24
    for frames in (8, 0):
        runs = [_search(frames, seed) for seed in range(n)]
        print(f"sequence_frames={frames}: within 3 m {sum(r[0] for r in runs)}/{40 * n}, "
              f"> 20 m off {sum(r[1] for r in runs)}, tracking > 10 m off "
              f"{sum(r[2] for r in runs)} frames in {sum(r[2] > 0 for r in runs)} of {n} runs",
              flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
