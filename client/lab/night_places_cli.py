"""CLI registration of ``swarmloc bench night-places`` (client/lab/night_places.py); kept
apart so that the CLI's start-up imports none of the study's modules."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def register(bench_app: typer.Typer) -> None:
    """``bench night-places`` on the CLI's bench group."""

    @bench_app.command("night-places")
    def night_places_cmd(
        data: Annotated[Path, typer.Argument(help="folder with one world per seed, DATA/wSEED "
                                                  "(swarmloc world render DATA/wSEED --seed "
                                                  "SEED --rounds sunny1,night1)")],
        seeds: Annotated[str, typer.Option(help="worlds, comma-separated")]
        = "0,7,11,23,37,58",
        map_round: Annotated[str, typer.Option("--map", help="the map's round, or rounds "
                                                              "joined by '+' (layers)")]
        = "sunny1",
        query: Annotated[str, typer.Option(help="the round placed")] = "night1",
        size: Annotated[str, typer.Option(help="thumbnail WIDTHxHEIGHT")] = "64x48",
        block: Annotated[int, typer.Option(min=1, help="patch normalised (pixels of the "
                                                       "thumbnail)")] = 8,
        sequences: Annotated[str, typer.Option(help="sequence lengths, comma-separated "
                                                    "(1: each frame alone)")] = "1,10,20",
        every: Annotated[int, typer.Option(min=0, help="the local features on every this "
                                                       "many frames (0: not measured)")] = 6,
        features: Annotated[str, typer.Option(help="the map's feature type for the local "
                                                   "features' column")]
        = "clahe-rootsift+xfeat",
        tau: Annotated[float, typer.Option(min=1e-6, help="the filter along the odometry: a "
                                                          "frame weighs an image by exp(-(its "
                                                          "difference - the least) / tau)")]
        = 1.0,
    ) -> None:
        """Whole-image thumbnails (SeqSLAM) against local features: the share of a round's
        frames whose best map image lies within 3 / 10 m of the truth, per world; where the
        round has odometry.csv, the thumbnails along the wheels (a forward filter over the
        map's images in route order): mean error and share within 5 m."""
        from client.lab.experiment_cli import check_feature_type, parse_seeds, world_with
        from client.lab.night_places import study, table

        check_feature_type(features)
        try:
            w, h = (int(v) for v in size.lower().split("x"))
        except ValueError:
            raise typer.BadParameter(f"size {size!r} is not WIDTHxHEIGHT") from None
        if w % block or h % block:
            raise typer.BadParameter(f"size {size} is not a multiple of the block {block}")
        lengths = [int(n) for n in sequences.split(",") if n.strip()]
        if not lengths or min(lengths) < 1:
            raise typer.BadParameter("sequence lengths must be 1 or more")
        results = []
        for seed in parse_seeds(seeds):
            rounds = [*(r for r in map_round.split("+") if r), query]  # as study() reads it
            world = world_with(data, seed, rounds, ",".join(rounds))
            results.append(study(world, seed, map_round, query, (w, h), block, lengths,
                                 every, features, tau))
            typer.echo(table(results[-1:], lengths, features).splitlines()[-1], err=True)
        typer.echo(table(results, lengths, features))
