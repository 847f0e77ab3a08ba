"""The lab's one timing helper and one percentile: every benchmark reports with these."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np


def percentile(values: Sequence[float] | np.ndarray, q: float, scale: float = 1.0) -> float:
    """The ``q``-th percentile of ``values`` times ``scale`` (NaN when there are none)."""
    arr = np.asarray(values, float)
    return float(np.percentile(arr, q)) * scale if arr.size else float("nan")


def median_ms(fn: Callable[[], object], repeats: int, cpu: bool = False) -> float:
    """Median time of ``fn()`` over ``repeats`` calls, in ms: wall time, or the calling
    thread's CPU time (``cpu``: robust to other users' load on a shared machine, for
    single-threaded work only, as BLAS worker threads are not counted)."""
    clock = time.thread_time if cpu else time.perf_counter
    times = []
    for _ in range(repeats):
        t0 = clock()
        fn()
        times.append(clock() - t0)
    return percentile(times, 50, 1e3)
