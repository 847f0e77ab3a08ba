"""Replay metrics, the JSON/Markdown/PNG report, and regression checks against a baseline."""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from client.dataset import Round
from client.experiments import frames_until_within
from client.replay import ReplayConfig, ReplayRun
from client.report_html import render_html

SCHEMA = "swarmloc-replay/1"
BAD_STATUS = ("recovering", "lost")


def _episodes(flags: np.ndarray) -> list[tuple[int, int]]:
    """(start, length) of runs of True."""
    out, start = [], None
    for i, f in enumerate(flags):
        if f and start is None:
            start = i
        elif not f and start is not None:
            out.append((start, i - start))
            start = None
    if start is not None:
        out.append((start, len(flags) - start))
    return out


def run_metrics(run: ReplayRun) -> dict[str, Any]:
    err = run.errors
    status = np.array([e.status for e in run.estimates])
    comps = np.array([e.comparisons for e in run.estimates], float)
    speed = np.array([e.speed for e in run.estimates])
    tracking = status == "tracking"
    true_speed = run.true_speed
    bad = np.isin(status, BAD_STATUS)
    episodes = _episodes(bad)
    converged = frames_until_within(err, 0)
    m: dict[str, Any] = {
        "frames": len(err),
        "error_mean_m": float(err.mean()),
        "error_std_m": float(err.std()),
        "error_median_m": float(np.median(err)),
        "error_p95_m": float(np.percentile(err, 95)),
        "within_2m": float(np.mean(err <= 2.0)),
        "within_5m": float(np.mean(err <= 5.0)),
        "comparisons_per_frame": float(comps.mean()),
        "latency_p50_ms": float(np.percentile(run.latency_ms, 50)),
        "latency_p95_ms": float(np.percentile(run.latency_ms, 95)),
        "latency_p99_ms": float(np.percentile(run.latency_ms, 99)),
        "speed_true_mps": float(np.median(true_speed)),
        "speed_error_mps": float(np.mean(np.abs(speed[tracking] - true_speed[tracking])))
        if tracking.any() else None,
        "speed_error_rel": float(abs(np.median(speed[tracking]) / np.median(true_speed) - 1))
        if tracking.any() and np.median(true_speed) > 0 else None,
        "status_frames": {s: int(np.sum(status == s)) for s in sorted(set(status.tolist()))},
        "recoveries": len(episodes),
        "recovery_frames_median": float(np.median([n for _, n in episodes])) if episodes
        else 0.0,
        "converged_after_frames": converged,
    }
    if run.kidnap:
        m["kidnap_recover_frames"] = frames_until_within(err, len(err) // 2)
    return m


_AGG_KEYS = ("error_mean_m", "error_std_m", "error_median_m", "error_p95_m", "within_2m",
             "within_5m", "comparisons_per_frame", "latency_p50_ms", "latency_p95_ms",
             "latency_p99_ms", "speed_error_mps", "speed_error_rel", "recoveries")


def summarize(per_run: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {"runs": len(per_run)}
    for k in _AGG_KEYS:
        vals = [r[k] for r in per_run if r.get(k) is not None]
        out[k] = float(np.mean(vals)) if vals else None
    if per_run and "kidnap_recover_frames" in per_run[0]:
        rec = [r["kidnap_recover_frames"] for r in per_run]
        out["kidnap_recovered"] = sum(r is not None for r in rec)
        done = [r for r in rec if r is not None]
        out["kidnap_recover_frames_median"] = float(np.median(done)) if done else None
    return out


def build_report(rnd: Round, cfg: ReplayConfig, runs: list[ReplayRun], via: str) -> dict:
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


def plot(runs: list[ReplayRun], route_xy: np.ndarray, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = runs[0]
    paths = []
    fig, ax = plt.subplots(figsize=(7, 6))
    ax.plot(route_xy[:, 0], route_xy[:, 1], color="0.8", lw=6, label="map images")
    ax.plot(run.true_xy[:, 0], run.true_xy[:, 1], "g-", lw=1.2, label="truth")
    est = run.est_xy
    ax.plot(est[:, 0], est[:, 1], "r.", ms=2.5, label="estimate")
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.legend(loc="best")
    ax.set_title(f"run from image {run.start}")
    paths.append(out / "route.png")
    fig.savefig(paths[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)

    status = [e.status for e in run.estimates]
    colors = {"initializing": "0.85", "recovering": "#f7c6c6", "lost": "#f08080"}
    fig, ax = plt.subplots(figsize=(9, 3.2))
    for s, c in colors.items():
        for start, n in _episodes(np.array(status) == s):
            ax.axvspan(start - 0.5, start + n - 0.5, color=c, lw=0,
                       label=s if start == _episodes(np.array(status) == s)[0][0] else None)
    ax.plot(run.errors, "k-", lw=0.9, label="position error")
    if run.kidnap:
        ax.axvline(len(run.errors) // 2, color="tab:blue", ls="--", lw=1, label="kidnapping")
    ax.set_xlabel("frame")
    ax.set_ylabel("error (m)")
    top = float(np.percentile(run.errors, 99)) if len(run.errors) else 1.0
    ax.set_ylim(0, max(10.0, 1.1 * top))  # rare far-off frames are cut, not squashing the rest
    ax.legend(loc="upper right", fontsize=8)
    paths.append(out / "error.png")
    fig.savefig(paths[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(9, 2.8))
    ax.plot([e.comparisons for e in run.estimates], "b-", lw=0.9)
    ax.set_xlabel("frame")
    ax.set_ylabel("comparisons")
    paths.append(out / "comparisons.png")
    fig.savefig(paths[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)
    return paths


def write_report(report: dict, runs: list[ReplayRun], route_xy: np.ndarray, out: Path
                 ) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    (out / "report.md").write_text(markdown(report))
    (out / "report.html").write_text(render_html(report, runs, route_xy))
    return [out / "report.json", out / "report.md", out / "report.html",
            *plot(runs, route_xy, out)]
