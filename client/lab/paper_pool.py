"""The protocol's cases in worker processes (``Settings.workers``), or in this process.

A task is one case (the papers' DPSO and the filters: all runs at once, one random generator,
so a case is not split) or a slice of the product DPSO's runs of one case (independent runs,
seed ``seed + k`` for the k-th run wherever it runs: the numbers do not depend on the split or
the number of workers). Each worker keeps its own ``Lab``; similarity tables travel with the
tasks: a task carries the parent's current table of its round pair, the worker fills what it
lacks from it, and returns the entries it computed, which the parent merges. So a similarity
is computed at most once per round pair unless two tasks in flight need it at the same time.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from client.lab.paper import Case, CaseResult, Lab, Settings, fill_missing, run_case, starts_of


@dataclass(frozen=True)
class Task:
    section: str
    index: int  # the case's position in its section
    case: Case
    seed: int
    runs: tuple[int, int] | None = None  # product DPSO: this slice of the case's runs


def tasks_of(lab: Lab, sections: dict[str, list[Case]], s: Settings,
             skip: Collection[tuple[str, int]] = ()) -> Iterator[Task]:
    """Every task in protocol order but the cases in ``skip`` (section, index); case k (over
    all sections) has seed ``s.seed + 1000 k``."""
    k = 0
    for name, cases in sections.items():
        for i, case in enumerate(cases):
            seed = s.seed + 1000 * k
            k += 1
            if (name, i) in skip:
                continue
            if case.method.batched:
                yield Task(name, i, case, seed)
                continue
            n = len(starts_of(len(lab.round(case.query)), s.product_starts))
            step = max(1, s.product_chunk)
            for lo in range(0, n, step):
                yield Task(name, i, case, seed, (lo, min(n, lo + step)))


_WORKER: dict[str, Lab] = {}  # the worker process's Lab (set by ``_init``)


def _init(dataset: str) -> None:
    _WORKER["lab"] = Lab(Path(dataset), threads=1)


def _work(task: Task, s: Settings, known: np.ndarray
          ) -> tuple[Task, CaseResult, np.ndarray, np.ndarray]:
    """Run a task in a worker: its result and the (flat index, value) entries it computed."""
    lab = _WORKER["lab"]
    c = task.case
    table = lab.table(c.map_round, c.query, c.method.papers_features)
    fill_missing(table.table, known)
    before = np.isnan(table.table)
    res = run_case(lab, c, s, task.seed, task.runs)
    new = np.flatnonzero(before & ~np.isnan(table.table))
    return task, res, new, table.table.ravel()[new]


def run_tasks(lab: Lab, tasks: Sequence[Task], s: Settings,
              done: Callable[[Task, CaseResult], None]) -> None:
    """Run the tasks (``s.workers`` processes; 1: here, in order); ``done`` gets each result
    in the parent as it arrives, after its new similarities are merged into ``lab``."""
    if s.workers <= 1:
        for t in tasks:
            done(t, run_case(lab, t.case, s, t.seed, t.runs))
        return
    todo = list(tasks)
    pending: set[Future[tuple[Task, CaseResult, np.ndarray, np.ndarray]]] = set()
    ctx = get_context("spawn")  # no fork of a process with threads (BLAS, numba, the pool)
    with ProcessPoolExecutor(s.workers, mp_context=ctx, initializer=_init,
                             initargs=(str(lab.dataset),)) as pool:
        while todo or pending:
            while todo and len(pending) < s.workers + 1:  # tables go out as filled as now
                t = todo.pop(0)
                c = t.case
                known = lab.table(c.map_round, c.query, c.method.papers_features).table
                pending.add(pool.submit(_work, t, s, known))
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                t, res, idx, vals = fut.result()
                c = t.case
                lab.table(c.map_round, c.query, c.method.papers_features).table.ravel()[idx] \
                    = vals
                done(t, res)
