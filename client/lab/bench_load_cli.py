"""CLI registration of ``swarmloc bench load`` and ``bench fuzz`` (client/lab/bench_load.py);
kept apart so that the CLI's start-up imports none of the benchmark's modules."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def register(bench_app: typer.Typer) -> None:
    """``bench load`` and ``bench fuzz`` on the CLI's bench group."""

    @bench_app.command("load")
    def load_cmd(
        round_dir: Annotated[Path, typer.Argument(help="round whose frames are sent")],
        maps_dir: Annotated[Path, typer.Option(help="maps the service loads")] = Path("maps"),
        robots: Annotated[str, typer.Option(help="robot counts")] = "1,4,16,64",
        frames: Annotated[int, typer.Option(help="frames per robot")] = 20,
        transports: Annotated[str, typer.Option(help="http,zenoh")] = "http,zenoh",
        via: Annotated[str | None, typer.Option(
            help="transports to compare, of http, zenoh, local (in process, no transport: "
                 "the baseline of the frames/s ratios); replaces --transports")] = None,
        soak: Annotated[int, typer.Option(help="soak: frames in all (0: none)")] = 0,
        soak_robots: Annotated[int, typer.Option(help="robots of the soak")] = 8,
        soak_transport: Annotated[str, typer.Option(help="http or zenoh")] = "http",
        soak_reconnect: Annotated[bool, typer.Option(
            help="soak robots open new connections every block")] = False,
        fairness: Annotated[int, typer.Option(help="heavy sessions beside a light robot "
                                                   "(0: no fairness run)")] = 0,
        heavy_particles: Annotated[int, typer.Option(help="particles of a heavy session")]
        = 5000,
    ) -> None:
        """Load (frames/s, p50/p99, errors, drops, the service's CPU and RSS per robot count
        and transport; with local among --via, transport/local frames/s), soak, fairness."""
        from client.lab.bench_load import bench_fairness, bench_load, bench_soak

        counts = [int(x) for x in robots.split(",") if x.strip()]
        chosen = [t.strip() for t in (via or transports).split(",") if t.strip()]
        unknown = [t for t in chosen if t not in ("http", "zenoh", "local")]
        if unknown:
            raise typer.BadParameter(f"unknown transport(s) {unknown}: use http, zenoh, local")
        if counts:
            bench_load(maps_dir, round_dir, counts, frames, chosen)
        if soak:
            bench_soak(maps_dir, round_dir, soak, soak_robots, transport=soak_transport,
                       reconnect=soak_reconnect)
        if fairness:
            bench_fairness(maps_dir, round_dir, fairness, heavy_particles, max(frames, 30))

    @bench_app.command("fuzz")
    def fuzz_cmd(
        minutes: Annotated[float, typer.Option(help="about how long to fuzz")] = 5.0,
        seed: Annotated[int | None, typer.Option(help="hypothesis seed")] = None,
    ) -> None:
        """The suite's fuzzers (hypothesis on the parsers, schemathesis on a real server)
        with more examples; exit code 1 on a failure."""
        from client.lab.bench_load import bench_fuzz

        raise typer.Exit(bench_fuzz(minutes, seed))
