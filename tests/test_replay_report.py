"""Replay through each transport, metrics, reports, plots and the baseline check."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest

from client.replay import ReplayConfig, replay
from client.report import build_report, compare, run_metrics, write_report
from client.transports import HttpClient, LocalClient, ZenohClient

LENGTH = 40


@pytest.fixture(scope="module")
def reports(server, sunny2) -> dict:
    cfg = ReplayConfig("small", "dpso", {}, seed=3, start=10, length=LENGTH)
    clients = {"http": HttpClient(server["url"]),
               "zenoh": ZenohClient([server["zenoh"]], mode="peer"),
               "local": LocalClient(server["maps"])}
    out = {}
    try:
        for name, c in clients.items():
            runs = replay(c, sunny2, cfg, robot_id=f"replay-{name}")
            out[name] = (runs, build_report(sunny2, cfg, runs, name))
    finally:
        for c in clients.values():
            c.close()
    return out


def test_transports_give_the_same_metrics(reports) -> None:
    keys = ("error_mean_m", "error_median_m", "error_p95_m", "within_2m", "within_5m",
            "comparisons_per_frame", "speed_error_mps", "recoveries")
    local = reports["local"][1]["summary"]
    for name in ("http", "zenoh"):
        s = reports[name][1]["summary"]
        assert {k: s[k] for k in keys} == {k: local[k] for k in keys}
    assert local["error_mean_m"] < 5.0 and local["comparisons_per_frame"] > 0
    assert reports["http"][1]["summary"]["latency_p50_ms"] > 0


def test_report_files_and_plots(reports, tmp_path: Path, small_map) -> None:
    runs, report = reports["local"]
    files = write_report(report, runs, small_map.positions, tmp_path)
    data = json.loads((tmp_path / "report.json").read_text())
    assert data["schema"] == "swarmloc-replay/1" and data["runs"][0]["metrics"]["frames"] == LENGTH
    assert "mean error" in (tmp_path / "report.md").read_text()
    for name in ("route.png", "error.png", "comparisons.png"):
        img = cv2.imread(str(tmp_path / name))
        assert img is not None and img.shape[0] > 100 and img.std() > 5
    assert len(files) == 6


def test_baseline_catches_a_worse_configuration(reports, server, sunny2) -> None:
    _, good = reports["local"]
    assert compare(good, good) == []
    # a deliberately worse DPSO: a handful of particles without random perturbation, the
    # estimate from the particles alone (the images' place would rescue even 4 particles)
    worse_cfg = ReplayConfig("small", "dpso", {"n_particles": 4, "phi0": 0.0,
                                               "quantum_ratio": 0.0,
                                               "estimate_image_radius_m": 0.0},
                             seed=3, start=10, length=LENGTH)
    client = LocalClient(server["maps"])
    runs = replay(client, sunny2, worse_cfg, robot_id="worse")
    worse = build_report(sunny2, worse_cfg, runs, "local")
    problems = compare(worse, good, tolerance=0.1)
    assert worse["summary"]["error_mean_m"] > good["summary"]["error_mean_m"]
    assert any("mean error" in p for p in problems)


def test_metrics_of_a_kidnapped_run(server, sunny2) -> None:
    cfg = ReplayConfig("small", "dpso", {}, seed=1, start=0, kidnap=True, length=len(sunny2))
    c = LocalClient(server["maps"])
    runs = replay(c, sunny2, cfg)
    m = run_metrics(runs[0])
    assert m["recoveries"] >= 1
    assert m["kidnap_recover_frames"] is not None and m["kidnap_recover_frames"] < len(sunny2) // 2
    assert m["status_frames"].get("recovering", 0) > 0
