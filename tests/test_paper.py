"""``swarmloc paper --quick`` on a tiny rendered world, and the batched estimators against the
service's estimators (same seed, one run: the same trajectory)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from client.cli import app
from client.lab import paper_numbers as pn
from client.lab.paper import Lab, frame_sequence, run
from client.lab.paper_engine import NearestGrid, run_batch
from client.lab.world import World

ROUNDS = (("sunny1", 0, "sunny"), ("sunny2", 1, "sunny"), ("cloudy1", 3, "cloudy"),
          ("cloudy2", 4, "cloudy"))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("paper_world")
    world = World(seed=3, length_m=24.0)
    for name, index, cond in ROUNDS:
        world.render_round(root / name, index, cond)
    return root


def test_batched_estimators_reproduce_the_service(tiny: Path) -> None:
    lab = Lab(tiny, threads=1)
    rnd = lab.round("cloudy1")
    m = lab.map("sunny1", True)
    table = lab.table("sunny1", "cloudy1", True)
    grid = NearestGrid(m.positions)
    pts = np.random.default_rng(0).uniform(m.positions.min(0) - 30, m.positions.max(0) + 30,
                                           (5000, 2))
    ids, dist = grid(pts)
    ref_ids, ref_dist = m.nearest(pts)
    assert np.array_equal(ids, ref_ids) and np.allclose(dist, ref_dist)
    assert rnd.t is not None
    dt = float(np.median(np.diff(rnd.t)))
    for est, params in (("dpso", {"variant": "paper"}), ("pf-l", {"n_particles": 300}),
                        ("pf-g", {"n_particles": 100})):
        ref = run(m, table, rnd, est, params, seed=7, start=11)
        frames = frame_sequence(len(rnd), 11)[None]
        got = run_batch(m.positions, lab.gather(table), frames, rnd.reference_xy, est, params,
                        np.random.default_rng(7), dt, nearest=grid)
        np.testing.assert_allclose(got.est_xy[0], ref.est_xy, atol=1e-9, err_msg=est)
        assert np.array_equal(got.comparisons[0], ref.comparisons), est
    # many runs at once: each its own start image, all of them converging on this easy world
    frames = np.stack([frame_sequence(len(rnd), s) for s in range(0, len(rnd), 5)])
    many = run_batch(m.positions, lab.gather(table), frames, rnd.reference_xy, "pf-l", {},
                     np.random.default_rng(1), dt, nearest=grid)
    assert many.est_xy.shape == (len(frames), len(rnd), 2)
    assert np.median(many.errors[:, 10:]) < 5.0


def test_paper_quick_writes_every_table_and_figure(tiny: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    # one process: the worker pool has its own test below
    res = CliRunner().invoke(app, ["paper", str(tiny), "--out", str(out), "--quick",
                                   "--no-progress", "--workers", "1"])
    assert res.exit_code == 0, res.output
    # rows: Tab. 1 two sizes x two variants + four filters; Tab. 2 two variants x two modes;
    # Fig. 4 x three speeds; Tab. 3 a 2 x 1 x 2 grid + two DPSO references; Tab. 4 three
    # scenarios x five methods
    shapes = {"tab1": (8, 7), "tab2": (4, 8), "fig4": (12, 7), "tab3": (6, 8), "tab4": (15, 8)}
    for name, (n_rows, n_cols) in shapes.items():
        doc = json.loads((out / f"{name}.json").read_text())
        assert len(doc["rows"]) == n_rows, name
        assert all(len(r) == n_cols == len(doc["columns"]) for r in doc["rows"]), name
        md = (out / f"{name}.md").read_text()
        assert md.count("\n|") == n_rows + 2, name
    tab1 = {r[0]: r for r in json.loads((out / "tab1.json").read_text())["rows"]}
    assert set(tab1) >= {"DPSO-80 (paper)", "DPSO-80 (product)", "PF-l-300"}
    assert tab1["DPSO-80 (paper)"][1] == pn.TAB1["DPSO-80"][0]
    assert tab1["PF-l-300"][4] == pn.TAB1["PF-l-300"][1]
    for row in tab1.values():
        assert 0 < row[2] < 100 and row[5] > 0  # our error (m) and comparisons per image
    tab4 = json.loads((out / "tab4.json").read_text())["rows"]
    assert {r[0] for r in tab4} == set(pn.TAB4)
    assert any(r[1] == "DPSO-80 (product)" for r in tab4)
    for png in ("fig4_speed", "fig6_kidnap", "fig8_particles", "fig10_comparison", "tab3_grid"):
        img = cv2.imread(str(out / f"{png}.png"))
        assert img is not None and img.shape[0] > 100 and img.shape[1] > 100, png
    meta = json.loads((out / "run.json").read_text())
    assert meta["settings"]["starts"] == 4 and meta["wall_s"] > 0


def test_worker_processes_give_the_numbers_of_one_process(tiny: Path) -> None:
    """Cases in two worker processes, the product's runs split into slices: the same numbers
    as all runs here, in order, and the similarities the workers computed reach the parent."""
    from client.lab.paper import Case, CaseResult, Settings, dpso, merge_results, pf
    from client.lab.paper_pool import Task, run_tasks, tasks_of

    sections = {"t": [Case(pf("l", 100), "sunny1", "cloudy1"),
                      Case(dpso(40, "product"), "sunny1", "cloudy1", speed=2.0)]}
    got: dict[int, dict[int, list[tuple[int, CaseResult]]]] = {}
    filled = {}
    for workers in (1, 2):
        lab = Lab(tiny, threads=1)
        s = Settings(starts=3, product_starts=5, product_chunk=2, warmup=2, workers=workers)
        out: dict[int, list[tuple[int, CaseResult]]] = {}

        def done(t: Task, r: CaseResult, out: dict = out) -> None:
            out.setdefault(t.index, []).append((t.runs[0] if t.runs else 0, r))

        tasks = list(tasks_of(lab, sections, s))
        assert [t.runs for t in tasks] == [None, (0, 2), (2, 4), (4, 5)]
        run_tasks(lab, tasks, s, done)
        got[workers] = out
        filled[workers] = np.isfinite(lab.table("sunny1", "cloudy1", False).table).sum()
    for i in (0, 1):
        one, two = (merge_results([r for _, r in sorted(got[w][i], key=lambda p: p[0])])
                    for w in (1, 2))
        assert len(one.run_error) == (3 if i == 0 else 5)
        np.testing.assert_array_equal(one.run_error, two.run_error)
        np.testing.assert_array_equal(one.run_comparisons, two.run_comparisons)
    assert filled[2] == filled[1] > 0
