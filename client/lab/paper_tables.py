"""Fig. 4 and Tab. 1-4 as tables (Markdown and JSON), the papers' numbers beside ours."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from client.lab import paper_numbers as pn
from client.lab.paper import CaseResult


@dataclass
class Table:
    name: str  # file stem, e.g. "tab1"
    title: str
    columns: list[str]
    rows: list[list[Any]]  # numbers (float | int | None) or strings
    notes: str = ""

    def as_json(self) -> dict[str, Any]:
        return {"name": self.name, "title": self.title, "columns": self.columns,
                "rows": [[_json(v) for v in r] for r in self.rows], "notes": self.notes}

    def markdown(self) -> str:
        head = "| " + " | ".join(self.columns) + " |"
        sep = "|" + "|".join("---" if i == 0 else "---:" for i in range(len(self.columns))) + "|"
        body = ["| " + " | ".join(_cell(v) for v in r) + " |" for r in self.rows]
        out = [f"### {self.title}", "", head, sep, *body]
        if self.notes:
            out += ["", self.notes]
        return "\n".join(out) + "\n"


def _json(v: Any) -> Any:
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _cell(v: Any) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return "–" if not math.isfinite(v) else f"{v:.2f}"
    return str(v)


def _pm(mean: float | None, std: float | None) -> str:
    if mean is None or not math.isfinite(mean):
        return "–"
    return f"{mean:.2f} ± {std:.2f}" if std is not None and math.isfinite(std) else f"{mean:.2f}"


def pooled(results: Sequence[CaseResult]) -> tuple[float, float, float, int]:
    """(mean error, std of per-run mean errors, mean comparisons, runs) over all runs."""
    if not results:
        return float("nan"), float("nan"), float("nan"), 0
    err = np.concatenate([r.run_error for r in results])
    comp = np.concatenate([r.run_comparisons for r in results])
    return float(err.mean()), float(err.std()), float(comp.mean()), len(err)


def _base(label: str) -> str:
    """'DPSO-80 (paper)' -> 'DPSO-80': the papers' name of a method."""
    return label.split(" (")[0]


def tab1(res: Sequence[CaseResult]) -> Table:
    rows = []
    for r in res:
        err, std, comp, runs = pooled([r])
        paper = pn.TAB1.get(_base(r.case.method.label), (None, None))
        rows.append([r.case.method.label, paper[0], err, std, paper[1], comp, runs])
    return Table("tab1", "Tab. 1 / Fig. 8: swarm size and particle count, sunny1 (map) vs "
                 "cloudy1", ["method", "paper err (m)", "ours err (m)", "ours std (m)",
                             "paper comp/img", "ours comp/img", "runs"], rows)


def tab2(res: Sequence[CaseResult]) -> Table:
    groups: dict[str, dict[bool, CaseResult]] = {}
    for r in res:
        groups.setdefault(r.case.method.label, {})[r.case.kidnap] = r
    rows = []
    for label, g in groups.items():
        mode = "non-adaptive" if "non-adaptive" in label else "adaptive"
        ps = pn.TAB2[(mode, "standard")]
        pk = pn.TAB2[(mode, "kidnapped")]
        e0, s0, _, n0 = pooled([g[False]]) if False in g else pooled([])
        e1, s1, _, _ = pooled([g[True]]) if True in g else pooled([])
        back = g[True].recovered if True in g else np.zeros(0)
        ok = back[np.isfinite(back)]
        rows.append([label, _pm(*ps), _pm(e0, s0), _pm(*pk), _pm(e1, s1),
                     f"{len(ok)}/{len(back)}", float(np.median(ok)) if len(ok) else None, n0])
    return Table("tab2", "Tab. 2 / Fig. 6: standard and kidnapped case, sunny1 vs cloudy1",
                 ["method", "paper standard (m)", "ours standard (m)", "paper kidnapped (m)",
                  "ours kidnapped (m)", "ours back within 5 m", "median frames to recover",
                  "runs"], rows,
                 "Kidnapping at the middle of the run (image index + n/2). Errors are means of "
                 "per-run mean errors ± their std over runs.")


def fig4(res: Sequence[CaseResult]) -> Table:
    rows = []
    for r in res:
        err, std, comp, runs = pooled([r])
        rows.append([r.case.method.label, r.case.speed, None, err, std, comp, runs])
    return Table("fig4", "Fig. 4: error at simulated speeds, sunny1 vs cloudy1",
                 ["method", "speed", "paper err (m)", "ours err (m)", "ours std (m)",
                  "ours comp/img", "runs"], rows,
                 "Speed k > 1: every k-th image; 1/r: each image r times. The paper gives "
                 "Fig. 4 as a plot only (no numbers to copy).")


def tab3(res: Sequence[CaseResult], dpso_ref: Sequence[CaseResult] = ()) -> Table:
    rows = []
    for r in res:
        p = dict(r.case.method.params)
        rot, acc = round(p["sigma_rot_deg"]), float(p["sigma_acc"])
        v = int(r.case.method.label.split("v=")[1].split("vR")[0])
        err, _, comp, runs = pooled([r])
        rows.append([r.case.method.label, rot, f"{acc:g}", v, pn.TAB3.get((rot, acc, v)), err,
                     comp, runs])
    for r in dpso_ref:
        err, _, comp, runs = pooled([r])
        rows.append([r.case.method.label, None, None, None,
                     pn.TAB1[_base(r.case.method.label)][0], err, comp, runs])
    return Table("tab3", "Tab. 3: PF-l-300 grid search over sigma_rot, sigma_acc, v_init, "
                 "sunny1 vs cloudy1", ["method", "sigma_rot (deg)", "sigma_acc",
                                       "v_init (v_R)", "paper err (m)", "ours err (m)",
                                       "ours comp/img", "runs"], rows,
                 "The last rows are DPSO-80 on the same case for reference (paper: Tab. 1).")


def tab4(res: Sequence[CaseResult], scenarios: dict[str, list[tuple[str, str]]]) -> Table:
    rows = []
    for scen, pairs in scenarios.items():
        pairset = set(pairs)
        by_method: dict[str, list[CaseResult]] = {}
        for r in res:
            if (r.case.map_round, r.case.query) in pairset:
                by_method.setdefault(r.case.method.label, []).append(r)
        for label, rs in by_method.items():
            err, std, comp, runs = pooled(rs)
            paper = pn.TAB4[scen].get(_base(label))
            rows.append([scen, label, _pm(paper[0], paper[1]) if paper else "–", _pm(err, std),
                         paper[2] if paper else None, comp, len(rs), runs])
    return Table("tab4", "Tab. 4 / Fig. 10: particle filters against DPSO, all round pairs",
                 ["scenario", "method", "paper err (m)", "ours err (m)", "paper comp/img",
                  "ours comp/img", "cases", "runs"], rows,
                 "± is the std of per-run mean errors over all runs of the scenario (the "
                 "paper: 'deviations refer to full rounds').")


def case_records(res: Sequence[CaseResult]) -> list[dict[str, Any]]:
    """Every case's raw per-run numbers (to redraw tables and figures without rerunning)."""
    return [{"method": r.case.method.label, "estimator": r.case.method.estimator,
             "params": dict(r.case.method.params), "map": r.case.map_round,
             "query": r.case.query, "speed": r.case.speed, "kidnap": r.case.kidnap,
             "run_error": [_json(float(x)) for x in r.run_error],
             "run_comparisons": [_json(float(x)) for x in r.run_comparisons],
             "error_curve": [_json(float(x)) for x in r.error_curve],
             "recovered": [_json(float(x)) for x in r.recovered],
             "seconds": round(r.seconds, 2)} for r in res]


def write_text(path: Path, text: str) -> Path:
    """Write atomically (temp + fsync + rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    tmp.replace(path)
    return path


def write(table: Table, out: Path) -> list[Path]:
    """``out/NAME.md`` and ``out/NAME.json``, each written atomically."""
    return [write_text(out / f"{table.name}{suffix}", text)
            for suffix, text in ((".md", table.markdown()),
                                 (".json", json.dumps(table.as_json(), indent=1)))]
