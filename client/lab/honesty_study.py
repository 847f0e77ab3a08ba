"""Which frames far off are reported ``tracking``, and what the lost detection saw there.

Replays ``swarmloc experiment``'s runs (``client.lab.experiments.run``, the same starts and
seeds, the world's cached map and similarity table, read only: nothing is written) and records
per frame the error, the status, ``accuracy_m`` and the lost detection's evidence (best m near
the reported place, the far images' background, distinctiveness, good). For each frame more
than ``WRONG_M`` off that is not flagged it prints where it lies in its excursion (the run of
consecutive frames more than ``WRONG_M`` off) and the evidence of the frames around it.

    PYTHONPATH=. python -m client.lab.honesty_study data/w7 --query dusk1 \
        --features clahe-rootsift+xfeat [--param lost_frames=2] [--csv out.csv]
"""

from __future__ import annotations

import csv
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from client.runs import BAD_STATUS, WRONG_M, Run, run_metrics
from service.estimators.lost_detection import Evidence
from service.estimators.multi_swarm_dpso import MultiSwarmDPSO
from service.estimators.odometry import LocatedGate

app = typer.Typer(add_completion=False)


@contextmanager
def recorded_evidence() -> Iterator[tuple[list[Evidence], list[tuple[np.ndarray, Any]],
                                           list[int]]]:
    """The evidence each DPSO frame's status used, ``good`` as the status counted it (after a
    map of two types' vouching: the monitors' ``judge`` runs once per type, so the evidence is
    taken where the status counts it; before, the two types' verdicts alternated in the list)
    and every ``_located`` call (the image estimate it was given, the located camera or None)
    while inside, in call order (one each per DPSO frame), and one entry per located frame a
    ``LocatedGate`` held back."""
    seen: list[Evidence] = []
    placed: list[tuple[np.ndarray, Any]] = []
    held: list[int] = []
    counts_good = MultiSwarmDPSO._counts_good
    located = MultiSwarmDPSO._located
    admit = LocatedGate.admit

    def spy(self: MultiSwarmDPSO, ev: Evidence) -> bool:
        ok = counts_good(self, ev)
        seen.append(replace(ev, good=ok))
        return ok

    def spy_admit(self: LocatedGate, where: Any, *args: Any) -> bool:
        ok = admit(self, where, *args)
        if not ok:
            held.append(1)
        return ok

    def spy_located(self: MultiSwarmDPSO, fitness: Any, status: Any, pos: np.ndarray,
                    *args: Any) -> Any:
        out = located(self, fitness, status, pos, *args)
        placed.append((np.array(pos, float), None if out is None else out[0]))
        return out

    MultiSwarmDPSO._counts_good = spy  # type: ignore[method-assign]
    MultiSwarmDPSO._located = spy_located  # type: ignore[method-assign,assignment]
    LocatedGate.admit = spy_admit  # type: ignore[method-assign,assignment]
    try:
        yield seen, placed, held
    finally:
        MultiSwarmDPSO._counts_good = counts_good  # type: ignore[method-assign]
        MultiSwarmDPSO._located = located  # type: ignore[method-assign]
        LocatedGate.admit = admit  # type: ignore[method-assign]


def excursions(wrong: np.ndarray) -> list[tuple[int, int]]:
    """(first frame, length) of each stretch of consecutive True."""
    out, start = [], None
    for i, w in enumerate([*wrong.tolist(), False]):
        if w and start is None:
            start = i
        elif not w and start is not None:
            out.append((start, i - start))
            start = None
    return out


def _table(dataset: Path, m: Any, rnd: Any, features: str, query: str) -> Any:
    """``cached_table``, with the query round's features kept in /tmp between runs of this
    script (extraction dominates its time)."""
    import pickle

    from client.lab.experiment_cli import cached_table

    keep = Path("/tmp") / f"honesty-{dataset.resolve().name}-{query}-{features}.pkl"
    if not keep.is_file():
        table = cached_table(dataset, m, rnd)
        keep.write_bytes(pickle.dumps(table.queries))
        return table
    return cached_table(dataset, m, rnd, pickle.loads(keep.read_bytes()))


def _refused(dataset: Path, m: Any, query: str, rule: str, fused: np.ndarray) -> np.ndarray:
    """The table of a two-type map under another fusion ``rule`` (set on ``m`` in memory):
    each type's m from the single-type maps' cached tables (the same matchers, the same
    values), completed from the recorded rule's fused values where those invert exactly
    (``mean-affine`` above its clip at 0); NaN (computed on use) elsewhere."""
    from client.lab.experiment_cli import table_path
    from service.maps.route_map import load_map
    from service.vision.fusion import Fusion

    old = Fusion.from_dict(m.meta["fusion"])
    singles = []
    for name in ("sunny1", "sunny1-xfeat"):
        single = load_map(dataset / ".maps" / f"{name}.swmap")
        path = table_path(dataset, single, query)
        singles.append(np.load(path) if path.is_file() else np.full(fused.shape, np.nan))
    first, second = singles
    if old.rule == "mean-affine":
        k = 2 * fused - old.first_chance + old.slope * old.second_chance  # = m1 + slope m2
        ok = fused > 0
        second = np.where(ok & np.isnan(second), (k - first) / old.slope, second)
        first = np.where(ok & np.isnan(first), k - old.slope * second, first)
    m.meta["fusion"] = {**m.meta["fusion"], "rule": rule}
    m.__dict__.pop("fusion", None)  # a cached_property: parsed again with the new rule
    new = Fusion.from_dict(m.meta["fusion"])
    return np.asarray(new.fuse(first, second), np.float64)


@app.command()
def main(
    dataset: Annotated[Path, typer.Argument(help="rendered world with .maps cached")],
    map_round: Annotated[str, typer.Option("--map")] = "sunny1",
    query: str = "dusk1",
    features: str = "clahe-rootsift+xfeat",
    starts: int = 4,
    warmup: int = 20,
    seed: int = 0,
    param: Annotated[list[str] | None, typer.Option(help="DPSO parameter NAME=VALUE")] = None,
    against: Annotated[list[str] | None, typer.Option(
        help="NAME=VALUE: also replay with this parameter changed, on the same table")] = None,
    rule: Annotated[str | None, typer.Option(
        help="replay a two-type map with this fusion rule instead of the one it records "
             "(its table recomposed from the single-type maps' cached tables)")] = None,
    csv_out: Annotated[Path | None, typer.Option("--csv")] = None,
    context: Annotated[int, typer.Option(help="frames shown before each unflagged one")] = 3,
    disagree_m: Annotated[float, typer.Option(
        help="also print what a report-only rule would give: a tracked frame located farther "
             "than this from the images' estimate reported 'recovering', its accuracy_m "
             "widened to the distance (positions untouched)")] = 8.0,
) -> None:
    from client.dataset import read_round
    from client.lab.experiment_cli import map_for, parse_params

    params_v = parse_params(param)
    m = map_for(dataset, map_round, False, features)
    rnd = read_round(dataset / query)
    table = _table(dataset, m, rnd, features, query)  # read; never saved here
    if rule is not None:
        table.table = _refused(dataset, m, query, rule, table.table)
    fusion = m.meta.get("fusion")
    typer.echo(f"{dataset} {map_round} vs {query}, {features}, fusion "
               f"{fusion.get('rule') if isinstance(fusion, dict) else '-'}")
    variants = [params_v] + [{**params_v, **parse_params([x])} for x in against or []]
    for n, pv in enumerate(variants):
        rows = _study(m, table, rnd, pv, starts, warmup, seed, context)
        typer.echo(what_if(rows, warmup, disagree_m))
        if csv_out is not None and rows:
            out = csv_out if n == 0 else csv_out.with_suffix(f".{n}.csv")
            with out.open("w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=list(rows[0]))
                w.writeheader()
                w.writerows(rows)


def what_if(rows: list[dict[str, Any]], warmup: int, disagree_m: float) -> str:
    """Honesty and calibration as recorded, and with a tracked frame located more than
    ``disagree_m`` from the images' estimate reported ``recovering`` (accuracy_m at least
    that distance): a report-only rule, the positions (so the errors) unchanged."""
    out = []
    for rule in (False, True):
        honest, calib, flagged, wrong_n, wrong_flagged = [], [], 0, 0, 0
        for k in sorted({r["run"] for r in rows}):
            rr = [r for r in rows if r["run"] == k and r["i"] >= warmup]
            err = np.array([r["err"] for r in rr])
            status = np.array([r["status"] for r in rr])
            acc = np.array([r["acc"] for r in rr])
            jump = np.array([r["jump"] for r in rr])
            if rule:
                far = (jump > disagree_m) & (status == "tracking")  # NaN: not located
                flagged += int(far.sum())
                status = np.where(far, "recovering", status)
                acc = np.where(far, np.maximum(acc, jump), acc)
            bad, wrong = np.isin(status, BAD_STATUS), err > WRONG_M
            wrong_n += int(wrong.sum())
            wrong_flagged += int((bad & wrong).sum())
            if wrong.any():
                honest.append(float(bad[wrong].mean()))
            tracked = status == "tracking"
            if tracked.any():
                calib.append(float(np.mean(err[tracked] <= acc[tracked])))
        h = f"{100 * np.mean(honest):.1f} %" if honest else "-"
        out.append(f"honest {h} ({wrong_flagged}/{wrong_n} frames), calib "
                   f"{100 * np.mean(calib):.1f} %" + (f", {flagged} frames newly flagged"
                                                      if rule else ""))
    return f"what-if, located > {disagree_m:g} m from the images' estimate: {out[0]} -> {out[1]}"


def _study(m: Any, table: Any, rnd: Any, params_v: dict[str, Any], starts: int, warmup: int,
           seed: int, context: int) -> list[dict[str, Any]]:
    from client.lab.experiment_cli import _starts, metrics
    from client.lab.experiments import run

    typer.echo(f"params {params_v}")
    runs: list[Run] = []
    rows: list[dict[str, Any]] = []
    for k, s in enumerate(_starts(len(rnd), starts)):
        with recorded_evidence() as (evs, placed, held):
            r = run(m, table, rnd, "dpso", params_v or None, seed=seed + k, start=s)
        runs.append(r)
        typer.echo(f"run {k}: {len(held)} located frames held back by the gate")
        err = r.errors
        for i in range(len(err)):
            ev = evs[i]
            img_pos, cam = placed[i]
            jump = float("nan") if cam is None else float(np.linalg.norm(cam - img_pos))
            img_err = float(np.linalg.norm(img_pos - r.true_xy[i]))
            cam_err = float("nan") if cam is None else float(np.linalg.norm(cam - r.true_xy[i]))
            rows.append({"run": k, "i": i, "frame": int(r.frames[i]), "err": float(err[i]),
                         "x": float(r.est_xy[i, 0]), "y": float(r.est_xy[i, 1]),
                         "true_x": float(r.true_xy[i, 0]), "true_y": float(r.true_xy[i, 1]),
                         "jump": jump, "img_err": img_err, "cam_err": cam_err,
                         "status": r.status[i], "acc": float(r.accuracy_m[i]),
                         "best_m": ev.best_m, "bg": ev.background, "distinct": ev.distinct,
                         "good": ev.good, "vouched": ev.vouched,
                         "located": bool(r.located is not None and r.located[i])})
        mt = run_metrics(r, warmup)
        wrong = err[warmup:] > WRONG_M
        admits = np.isin(np.array(r.status[warmup:]), BAD_STATUS)
        typer.echo(f"run {k} (start {s}): mean {mt['error_mean_m']:.2f} m, wrong "
                   f"{int(wrong.sum())}, flagged {int((wrong & admits).sum())}, honesty "
                   f"{mt['honesty']}")
        for a, n in excursions(wrong):
            a += warmup
            typer.echo(f"  excursion frames {a}..{a + n - 1} ({n}): statuses "
                       f"{[x[0] for x in r.status[a:a + n]]}")
            for j in range(max(warmup, a - context), a + n):
                row = rows[len(rows) - len(err) + j]
                typer.echo(f"    {j:4d} err {row['err']:6.1f} {row['status']:11s} "
                           f"acc {row['acc']:5.1f} best {row['best_m']:.4f} bg "
                           f"{row['bg']:.4f} distinct {row['distinct']:6.2f} good "
                           f"{int(row['good'])}{'v' if row['vouched'] else ' '} located "
                           f"{int(row['located'])} jump "
                           f"{row['jump']:5.1f} image estimate off {row['img_err']:5.1f}")
    t = metrics(runs, warmup)
    typer.echo(f"summary {params_v}: mean {t['error_mean_m']:.2f} median "
               f"{t['error_median_m']:.2f} within 5 m {100 * t['within_5m']:.1f} % calib "
               f"{100 * (t['calibration'] or 0):.1f} % honest {t['honesty']} recovering "
               f"{100 * t['bad_status_share']:.1f} %")
    return rows


if __name__ == "__main__":
    app()
