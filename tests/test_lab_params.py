"""``--param NAME=VALUE`` of the lab commands (``swarmloc experiment``, ``eval-pair``,
``honesty_study``): values reach the strict parameter models with their types."""

from __future__ import annotations

import numpy as np

from client.lab.experiment_cli import param_value, parse_params
from service.estimators.registry import params_for


def test_values_are_typed_as_the_command_line_means_them() -> None:
    assert param_value("false") is False and param_value("True") is True
    assert param_value("3") == 3 and isinstance(param_value("3"), int)
    assert param_value("0.05") == 0.05
    assert param_value("paper") == "paper"


def test_a_switch_given_as_false_turns_it_off() -> None:
    """The strict DPSO model refuses the string 'false'; the parsed value is a bool."""
    p = params_for("dpso", parse_params(["metric_second=false", "v0=0.05"]))
    assert p.metric_second is False and p.v0 == 0.05  # type: ignore[attr-defined]


def test_the_labs_maps_take_a_working_size_and_a_cap(tmp_path, rounds_dir) -> None:
    """`swarmloc experiment --size WxH --max-features N` builds (and keeps apart) a map at
    that working size with that SIFT cap; the default keeps its file name."""
    import shutil

    from client.lab.experiment_cli import map_for

    shutil.copytree(rounds_dir / "sunny1", tmp_path / "sunny1")
    rich = map_for(tmp_path, "sunny1", False, "clahe-rootsift", (160, 120), 50)
    plain = map_for(tmp_path, "sunny1", False, "clahe-rootsift")
    assert rich.path is not None and rich.path.name == "sunny1-160x120-cap50.swmap"
    assert plain.path is not None and plain.path.name == "sunny1.swmap"
    p = rich.feature_params
    assert (p.width, p.height, p.n_features) == (160, 120, 50)  # type: ignore[union-attr]
    assert np.median(np.diff(rich.offsets)) <= 50 < np.median(np.diff(plain.offsets))


def test_the_labs_maps_keep_their_positions_apart(tmp_path, rounds_dir) -> None:
    """Our maps take the fused positions by default; the papers' comparison builds (and
    keeps apart) maps on the recorded ones, for every method alike."""
    import shutil

    from client.lab.experiment_cli import map_for

    shutil.copytree(rounds_dir / "sunny1", tmp_path / "sunny1")
    fused = map_for(tmp_path, "sunny1", False, "clahe-rootsift", (160, 120), 50)
    recorded = map_for(tmp_path, "sunny1", False, "clahe-rootsift", (160, 120), 50,
                       positions="recorded")
    assert recorded.path is not None and recorded.path.name == "sunny1-160x120-cap50-recorded.swmap"
    assert fused.meta["source"]["positions"][0].startswith("fused")
    assert recorded.meta["source"]["positions"] == ["recorded"]
    xy = np.loadtxt(tmp_path / "sunny1" / "poses.csv", delimiter=",", skiprows=1,
                    usecols=(1, 2))
    assert np.allclose(recorded.positions, xy) and not np.allclose(fused.positions, xy)
    assert fused.path is not None
    built = fused.path.stat().st_mtime_ns
    again = map_for(tmp_path, "sunny1", False, "clahe-rootsift", (160, 120), 50)
    assert again.path == fused.path and fused.path.stat().st_mtime_ns == built  # kept


def test_the_experiment_replays_with_the_rounds_odometry_where_asked(tmp_path, rounds_dir
                                                                     ) -> None:
    """`swarmloc experiment --odometry` sends each frame with its round's odometry (other
    estimates than without); a round without odometry.csv is one line, before any map is
    built."""
    import re
    import shutil

    from typer.testing import CliRunner

    from client.cli import app

    for name in ("sunny1", "cloudy1"):
        shutil.copytree(rounds_dir / name, tmp_path / name)
    args = ["experiment", str(tmp_path), "--query", "cloudy1", "--methods", "DPSO-80",
            "--starts", "1", "--warmup", "5", "--no-kidnap", "--size", "160x120",
            "--max-features", "50"]
    rows = []
    for extra in ([], ["--odometry"]):
        out = CliRunner().invoke(app, [*args, *extra])
        assert out.exit_code == 0, out.output
        assert ("with odometry" in out.output) == bool(extra)
        rows.append(re.search(r"^DPSO-80 .*$", out.output, re.M).group(0))  # type: ignore[union-attr]
    assert rows[0] != rows[1]
    (tmp_path / "cloudy1" / "odometry.csv").unlink()
    out = CliRunner().invoke(app, [*args, "--odometry"])
    assert out.exit_code != 0 and "round cloudy1 has no odometry.csv" in out.output


def test_the_world_benches_refuse_bad_seeds_and_missing_rounds_in_one_line(tmp_path) -> None:
    """`swarmloc bench night-places` and `bench experiences`: seeds that are not integers,
    and a world without a round the bench needs, are one line naming the fix, no traceback;
    a world with the rounds passes the check."""
    from typer.testing import CliRunner

    from client.cli import app
    from client.lab.experiment_cli import world_with

    runner = CliRunner()
    out = runner.invoke(app, ["bench", "night-places", str(tmp_path), "--seeds", "0,x"])
    assert out.exit_code == 2 and "comma-separated integers" in out.output
    assert "Traceback" not in out.output
    out = runner.invoke(app, ["bench", "night-places", str(tmp_path), "--seeds", "4"])
    assert out.exit_code == 2 and "has no round sunny1" in out.output
    assert "--seed 4 --rounds sunny1,night1" in out.output
    out = runner.invoke(app, ["bench", "experiences", str(tmp_path), "--seeds", "4",
                              "--conditions", "dusk"])
    assert out.exit_code == 2 and "has no round dusk2" in out.output
    for r in ("sunny1", "night1"):
        (tmp_path / "w4" / r).mkdir(parents=True)
    assert world_with(tmp_path, 4, ["sunny1", "night1"], "sunny1,night1") == tmp_path / "w4"
