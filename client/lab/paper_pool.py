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
from dataclasses import dataclass, replace
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from client.lab.paper import (
    SC_QUERY,
    Case,
    CaseResult,
    Lab,
    Settings,
    driven_speed,
    fill_missing,
    merge_results,
    protocol,
    run_case,
    same_cases,
    starts_of,
    with_driven_speed,
)


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
    from threadpoolctl import threadpool_limits

    threadpool_limits(1, "blas")  # the workers share the cores: one BLAS thread each
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


def run_protocol(lab: Lab, rounds: Sequence[str], s: Settings,
                 on_section: Callable[[str, list[CaseResult]], None] | None = None,
                 progress: bool = True) -> dict[str, list[CaseResult]]:
    """Run every case (``s.workers`` processes) with a progress bar; ``on_section`` gets each
    finished section in protocol order, and Tab. 4 so far after every fifth case of it."""
    from tqdm import tqdm

    sections = protocol(rounds, s)
    sections["tab3"] = with_driven_speed(sections["tab3"], driven_speed(lab.round(SC_QUERY)))
    copies = same_cases(sections)
    skip = {c for cs in copies.values() for c in cs}
    tasks = list(tasks_of(lab, sections, s, skip))
    parts_left: dict[tuple[str, int], int] = dict.fromkeys(skip, 1)
    for t in tasks:
        parts_left[t.section, t.index] = parts_left.get((t.section, t.index), 0) + 1
    parts: dict[tuple[str, int], list[tuple[int, CaseResult]]] = {}
    out: dict[str, list[CaseResult]] = {}
    order = list(sections)
    bar = tqdm(total=len(parts_left), desc="paper cases", unit="case", disable=not progress)

    def finished(name: str) -> list[CaseResult]:
        return [merge_results([r for _, r in sorted(parts[name, i], key=lambda p: p[0])])
                for i in range(len(sections[name])) if parts_left[name, i] == 0]

    def done(t: Task, res: CaseResult) -> None:
        key = (t.section, t.index)
        parts.setdefault(key, []).append((t.runs[0] if t.runs else 0, res))
        parts_left[key] -= 1
        if parts_left[key]:
            return
        bar.update()
        if key in copies:  # the same case elsewhere in the protocol: the same runs
            merged = merge_results([r for _, r in sorted(parts[key], key=lambda p: p[0])])
            for sec, i in copies[key]:
                parts[sec, i] = [(0, replace(merged, case=sections[sec][i]))]
                parts_left[sec, i] = 0
                bar.update()
        bar.set_postfix_str(f"{t.section}: {t.case.method.label} {t.case.map_round}/"
                            f"{t.case.query}")
        while order and all(parts_left[order[0], i] == 0 for i in range(len(sections[order[0]]))):
            name = order.pop(0)
            out[name] = finished(name)
            lab.save()
            if on_section is not None:
                on_section(name, out[name])
        if t.section == "tab4" and "tab4" in order and on_section is not None:
            so_far = finished("tab4")
            if len(so_far) % 5 == 0:
                lab.save()
                on_section("tab4", so_far)  # partial Tab. 4 after each round pair's worth

    run_tasks(lab, tasks, s, done)
    bar.close()
    return out
