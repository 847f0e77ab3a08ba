"""Lab: may RootSIFT's own distinctiveness vouch for a place on a map of both feature types?

On a map of CLAHE + RootSIFT and XFeat, DPSO judges a place by the fused m's distinctiveness
(service/estimators/lost_detection.py). On a map of long shadows XFeat's chance level, which
the fused m keeps, hides a place RootSIFT alone shows clearly, and DPSO reports right frames
``recovering`` (docs/research/lighting.md, "The low-sun pair and the same light on the other
worlds"). This study replays ``swarmloc experiment``'s four runs (DPSO-80, the same starts
and seeds, no kidnap) with each type's m computed beside the fused one, and lets a frame be
good when RootSIFT's own evidence (with its own background) is good, per ``--rule``:

- ``any``: RootSIFT's evidence alone;
- ``strong``: RootSIFT's distinctiveness at least twice ``distinct_ratio``;
- ``fused2``: RootSIFT's evidence and the fused distinctiveness at least 2.

The service is not changed: the lost detection is patched for the replays only. Prints the
mean and median error, the share within 5 m, the frames more than 10 m off flagged, and the
share of frames ``recovering``; nothing is written.

    PYTHONPATH=. python -m client.lab.vouch_study data/w37 --map lowsun1 --query cloudy1
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from client.dataset import read_round
from client.lab.experiment_cli import _starts, cached_table, map_for
from client.lab.experiments import run
from client.runs import BAD_STATUS, WRONG_M
from service.estimators.lost_detection import DistinctnessMonitor, Evidence
from service.maps.route_map import RouteMap
from service.vision.features import Features

RULES = ("any", "strong", "fused2")
WARMUP = 20


class TypedTable:
    """m(frame q, map image) of a map of both types, each type's kept beside the fused one
    (computed on first use, as ``SimilarityTable`` does)."""

    def __init__(self, m: RouteMap, queries: list[Features]) -> None:
        self.map, self.queries = m, queries
        shape = (len(queries), m.n_images)
        self.first = np.full(shape, np.nan)
        self.second = np.full(shape, np.nan)
        self.frame = 0  # the frame the estimator compares now

    def scores(self, q: int, ids: np.ndarray) -> np.ndarray:
        self.frame = q
        missing = ids[np.isnan(self.first[q, ids])]
        if len(missing):
            a, b = self.map.type_similarities(self.queries[q], missing)
            self.first[q, missing], self.second[q, missing] = a, b
        assert self.map.fusion is not None
        return self.map.fusion.fuse(self.first[q, ids], self.second[q, ids])


def vouches(rule: str, fused: Evidence, first: Evidence, ratio: float) -> bool:
    """Whether RootSIFT's evidence ``first`` makes a frame good under ``rule``."""
    if rule == "strong":
        return first.good and first.distinct >= 2.0 * ratio
    if rule == "fused2":
        return first.good and fused.distinct >= 2.0
    return first.good


@contextmanager
def vouching(table: TypedTable, rule: str | None) -> Iterator[None]:
    """The lost detection patched so that RootSIFT's own evidence may vouch (``rule``; None:
    unpatched). Each monitor gets a twin that judges RootSIFT's m of the same images."""
    original = DistinctnessMonitor.judge
    if rule is None:
        yield
        return
    image_at = {tuple(np.round(p, 6)): i for i, p in enumerate(np.asarray(table.map.positions))}
    if len(image_at) != table.map.n_images:  # the monitor sees positions, not image ids
        raise ValueError(f"map '{table.map.name}': two images share a position; this study "
                         "needs a map of one traversal")
    twins: dict[int, DistinctnessMonitor] = {}

    def judge(self: DistinctnessMonitor, positions: np.ndarray, scores: np.ndarray,
              estimate: np.ndarray, near_m: float) -> Evidence:
        fused = original(self, positions, scores, estimate, near_m)
        ids = np.array([image_at[tuple(np.round(p, 6))] for p in positions], np.int64)
        twin = twins.setdefault(id(self), DistinctnessMonitor(self.min_ratio, self.floor_m,
                                                              self.far_m, self.alpha))
        first = original(twin, positions, table.first[table.frame, ids], estimate, near_m)
        good = fused.good or vouches(rule, fused, first, self.min_ratio)
        return Evidence(fused.best_m, fused.background, max(fused.distinct, first.distinct),
                        good)

    DistinctnessMonitor.judge = judge  # type: ignore[method-assign]
    try:
        yield
    finally:
        DistinctnessMonitor.judge = original  # type: ignore[method-assign]


def replay(table: TypedTable, rnd: Any, rule: str | None, starts: int) -> str:
    errors, wrong, flagged, recovering = [], 0, 0, 0
    with vouching(table, rule):
        for k, s in enumerate(_starts(len(rnd), starts)):
            r = run(table.map, table, rnd, "dpso", None, seed=k, start=s)  # type: ignore[arg-type]
            e, st = r.errors[WARMUP:], np.asarray(r.status)[WARMUP:]
            big = e > WRONG_M
            errors.append(e)
            wrong += int(big.sum())
            flagged += int(np.isin(st[big], list(BAD_STATUS)).sum())
            recovering += int((st == "recovering").sum())
    e = np.concatenate(errors)
    return (f"mean {e.mean():.2f} m, median {np.median(e):.2f} m, within 5 m "
            f"{100 * np.mean(e <= 5):.1f} %, frames > 10 m off flagged {flagged}/{wrong}, "
            f"recovering {100 * recovering / len(e):.1f} %")


def main(dataset: Annotated[Path, typer.Argument(help="rendered world with .maps cached")],
         map_round: Annotated[str, typer.Option("--map")] = "sunny1",
         query: str = "dusk1",
         rule: Annotated[str, typer.Option(help=f"one of {', '.join(RULES)}")] = "fused2",
         starts: int = 4,
         baseline: Annotated[bool, typer.Option(help="also replay unpatched")] = True) -> None:
    if rule not in RULES:
        raise typer.BadParameter(f"unknown rule {rule!r}; choose one of {', '.join(RULES)}")
    m = map_for(dataset, map_round, papers=False, features="clahe-rootsift+xfeat")
    if m.fusion is None:
        raise typer.BadParameter(f"{dataset}: the {map_round} map holds one feature type")
    rnd = read_round(dataset / query)
    table = TypedTable(m, list(cached_table(dataset, m, rnd).queries))
    for which in ((None, rule) if baseline else (rule,)):
        typer.echo(f"{dataset.name} {map_round} -> {query}, {which or 'today'}: "
                   f"{replay(table, rnd, which, starts)}")


if __name__ == "__main__":
    typer.run(main)
