"""The replay report (JSON, Markdown, HTML; PNG plots with the lab extra) and regression
checks against a baseline. The metrics are ``client.runs.run_metrics``."""

from __future__ import annotations

import datetime as dt
import importlib.util
import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from client.dataset import Round
from client.replay import ReplayConfig
from client.report_html import render_html
from client.runs import Run, run_metrics, summarize

SCHEMA = "swarmloc-replay/1"


def build_report(rnd: Round, cfg: ReplayConfig, runs: list[Run], via: str) -> dict[str, Any]:
    per_run = [run_metrics(r) for r in runs]
    return {
        "schema": SCHEMA,
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "round": {"name": rnd.name, "path": str(rnd.path), "images": len(rnd)},
        "via": via,
        "config": asdict(cfg),
        "summary": summarize(per_run),
        "runs": [{"start": r.start, "seed": r.seed, "metrics": m}
                 for r, m in zip(runs, per_run, strict=True)],
    }


# ---- regression check --------------------------------------------------------------------
def compare(report: dict, baseline: dict, tolerance: float = 0.1,
            abs_error_m: float = 0.25) -> list[str]:
    """Regressions of ``report`` against ``baseline`` (empty list: none).

    Accuracy and cost may not get worse by more than ``tolerance`` (relative); the mean error
    also gets ``abs_error_m`` of slack for tiny baselines. Latency is machine-dependent and
    is not compared.
    """
    if baseline.get("schema") != SCHEMA:
        return [f"baseline schema {baseline.get('schema')!r} is not {SCHEMA!r}"]
    new, old = report["summary"], baseline["summary"]
    problems = []
    if new["error_mean_m"] > old["error_mean_m"] * (1 + tolerance) + abs_error_m:
        problems.append(f"mean error {new['error_mean_m']:.2f} m > baseline "
                        f"{old['error_mean_m']:.2f} m (+{100 * tolerance:.0f} %)")
    for key in ("within_5m", "within_2m"):
        if new[key] < old[key] - tolerance:
            problems.append(f"{key} {new[key]:.3f} < baseline {old[key]:.3f} - {tolerance}")
    if new["comparisons_per_frame"] > old["comparisons_per_frame"] * (1 + tolerance):
        problems.append(f"comparisons/frame {new['comparisons_per_frame']:.1f} > baseline "
                        f"{old['comparisons_per_frame']:.1f} (+{100 * tolerance:.0f} %)")
    return problems


# ---- writing -----------------------------------------------------------------------------
def markdown(report: dict) -> str:
    s = report["summary"]
    cfg = report["config"]

    def f(v: Any, fmt: str = ".2f") -> str:
        return "n/a" if v is None else format(v, fmt)

    lines = [
        f"# swarmloc replay: {report['round']['name']} on {cfg['map_name'] or 'default map'}",
        "",
        f"estimator **{cfg['estimator']}**, seed {cfg['seed']}, via `{report['via']}`, "
        f"{s['runs']} run(s), speed {cfg['speed']:g}, kidnap {cfg['kidnap']}",
        "",
        "| metric | value |",
        "|---|---|",
        f"| mean error ± std (m) | {f(s['error_mean_m'])} ± {f(s['error_std_m'])} |",
        f"| median / 95th pct error (m) | {f(s['error_median_m'])} / {f(s['error_p95_m'])} |",
        f"| frames within 2 m / 5 m | {f(100 * s['within_2m'], '.1f')} % / "
        f"{f(100 * s['within_5m'], '.1f')} % |",
        f"| comparisons per frame | {f(s['comparisons_per_frame'], '.1f')} |",
        f"| latency p50 / p95 / p99 (ms) | {f(s['latency_p50_ms'], '.1f')} / "
        f"{f(s['latency_p95_ms'], '.1f')} / {f(s['latency_p99_ms'], '.1f')} |",
        f"| speed error (m/s, tracking) | {f(s['speed_error_mps'])} |",
        f"| recoveries per run | {f(s['recoveries'], '.1f')} |",
    ]
    if "kidnap_recover_frames_median" in s:
        lines.append(f"| kidnap: runs recovered, median frames | {s['kidnap_recovered']}/"
                     f"{s['runs']}, {f(s['kidnap_recover_frames_median'], '.0f')} |")
    lines += ["", "Play the run back in a browser: [report.html](report.html)",
              "", "![route](route.png)", "", "![error](error.png)", "",
              "![comparisons](comparisons.png)", ""]
    return "\n".join(lines)


def write_report(report: dict[str, Any], runs: list[Run], route_xy: np.ndarray, out: Path
                 ) -> list[Path]:
    """report.json, report.md, report.html; the PNG plots too where matplotlib is installed
    (the lab extra)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    (out / "report.md").write_text(markdown(report))
    (out / "report.html").write_text(render_html(report, runs, route_xy))
    files = [out / "report.json", out / "report.md", out / "report.html"]
    if importlib.util.find_spec("matplotlib") is None:  # the light client
        return files
    from client.lab.plots import plot_run

    return [*files, *plot_run(runs[0], route_xy, out)]
