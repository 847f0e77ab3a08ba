"""CLI registration of ``swarmloc bench experiences`` (client/lab/bench_experience.py); kept
apart so that the CLI's start-up imports none of the benchmark's modules."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def register(bench_app: typer.Typer) -> None:
    """``bench experiences`` on the CLI's bench group."""

    @bench_app.command("experiences")
    def experiences_cmd(
        data: Annotated[Path, typer.Argument(help="folder with one world per seed, DATA/wSEED "
                                                  "(swarmloc world render DATA/wSEED --seed "
                                                  "SEED --rounds sunny1,cloudy1,cloudy2,"
                                                  "dusk1,dusk2)")],
        seeds: Annotated[str, typer.Option(help="worlds, comma-separated")]
        = "0,7,11,23,37,58",
        conditions: Annotated[str, typer.Option(help="lights learned, comma-separated")]
        = "cloudy,dusk",
        frames: Annotated[int, typer.Option(help="images of each round (from its first)")]
        = 10_000,
        budget_mb: Annotated[float, typer.Option(help="SWARMLOC_EXPERIENCE_BUDGET_MB")] = 64.0,
        features: Annotated[str, typer.Option(help="the maps' feature type: clahe-rootsift, "
                                                   "xfeat or clahe-rootsift+xfeat (both)")]
        = "clahe-rootsift",
        work: Annotated[Path, typer.Option(help="where the learning maps are written")]
        = Path("out/experiences"),
        runs: Annotated[int, typer.Option(min=1, help="replays (DPSO seeds) averaged per "
                                                      "unlearned, learned and same-light "
                                                      "case")] = 3,
        odometry: Annotated[bool, typer.Option(help="every run's frames carry their round's "
                                                    "odometry.csv, as swarmloc replay sends "
                                                    "it by default")] = True,
    ) -> None:
        """A sunny map learns one round of another light, then localizes a second round of it:
        errors against the unlearned map and a map in that light, comparisons, file growth."""
        from client.lab.bench_experience import gates_table, run_case, summary, table
        from client.lab.experiment_cli import check_feature_type, parse_seeds, world_with

        check_feature_type(features)

        cases = []
        for seed in parse_seeds(seeds):
            for cond in [c.strip() for c in conditions.split(",") if c.strip()]:
                world = world_with(data, seed, [f"{cond}2"],
                                   "sunny1,cloudy1,cloudy2,dusk1,dusk2")
                cases.append(run_case(world, seed, cond, work, budget_mb, frames, features,
                                      runs, odometry))
                typer.echo(table(cases[-1:]).splitlines()[-1], err=True)
        typer.echo(table(cases))
        typer.echo(gates_table(cases))
        typer.echo(summary(cases))
