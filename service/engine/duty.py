"""Background work that leaves the CPU to the robots' frames: after each piece of work, rest
so that the work takes at most ``duty`` of the time (map builds, geometry warm-up)."""

from __future__ import annotations

import time


def rest(started: float, duty: float) -> None:
    """Sleep after a piece of work begun at ``started`` (``time.perf_counter()``) so that it
    took ``duty`` (0 < duty <= 1) of the time since; duty 1: no rest."""
    if duty < 1.0:
        time.sleep((time.perf_counter() - started) * (1.0 - duty) / duty)
