"""CLI registration of ``swarmloc bench frame`` (client/lab/bench_frame.py); kept apart so
that the CLI's start-up imports none of the benchmark's modules."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, cast

import typer

if TYPE_CHECKING:
    from service.api.models import Matcher


def register(bench_app: typer.Typer) -> None:
    """``bench frame`` on the CLI's bench group."""

    @bench_app.command("frame")
    def frame_cmd(
        round_dir: Annotated[Path, typer.Argument(help="round whose frames are sent")],
        maps_dir: Annotated[Path, typer.Option(help="maps the service loads (one map, or "
                                                    "one named demo)")] = Path("maps"),
        frames: Annotated[int, typer.Option(help="frames per path, after the warm-up")] = 100,
        warmup: Annotated[int, typer.Option(help="frames of global convergence not "
                                                 "counted")] = 10,
        via: Annotated[str, typer.Option(help="transports beside in-process")] = "http,zenoh",
        seed: int = 0,
        matcher: Annotated[str, typer.Option(help="the service's matcher(s), comma-separated "
                                                  "(auto, exact, words): one run each, in turn")]
        = "auto",
        warm_geometry: Annotated[bool, typer.Option(
            help="the service builds its maps' geometry structures before the frames (as it "
                 "does after start-up, SWARMLOC_WARM_GEOMETRY); off: frames build them")]
        = True,
    ) -> None:
        """Per-frame cost breakdown (decode, extraction, localizer step, serialisation,
        transport) in process and through each transport, with the issue's ratios."""
        from client.lab.bench_frame import bench_frame, report
        from service.api.models import MATCHERS

        transports = tuple(t.strip() for t in via.split(",") if t.strip())
        unknown = [t for t in transports if t not in ("http", "zenoh")]
        if unknown:
            raise typer.BadParameter(f"unknown transport(s) {unknown}: use http and/or zenoh")
        matchers = [m.strip() for m in matcher.split(",") if m.strip()]
        bad = [m for m in matchers if m not in MATCHERS]
        if bad or not matchers:
            raise typer.BadParameter(f"unknown matcher(s) {bad}: use {', '.join(MATCHERS)}")
        runs = [bench_frame(maps_dir, round_dir, frames, warmup, seed, transports,
                            matcher=cast("Matcher", m), warm_geometry=warm_geometry)
                for m in matchers]
        for b in runs:
            report(b)
        for b in runs:
            typer.echo(f"matcher {b.matcher}: step / extraction p50 = {b.step_ratio:.2f}")

    @bench_app.command("first-frame")
    def first_frame_cmd(
        frames: Annotated[int, typer.Option(min=2, help="frames sent by the robot")] = 20,
        unwritable: Annotated[bool, typer.Option(
            help="a kernel cache directory that cannot be made (compiled at each start)")]
        = False,
    ) -> None:
        """The first frame after a fresh install and start (``swarmloc serve`` from a copy of
        the package, an empty kernel cache) beside the later ones, over HTTP."""
        from client.lab.bench_first_frame import bench_first_frame, report

        report(bench_first_frame(frames, unwritable), typer.echo)

    @bench_app.command("geometry")
    def geometry_cmd(
        dataset: Annotated[Path, typer.Argument(help="dataset with the rounds (and the "
                                                     "camera: dataset.json or calib.txt)")],
        map_round: Annotated[str, typer.Option("--map", help="round used as the map")]
        = "sunny1",
        query: Annotated[str, typer.Option(help="round whose frames are localized")]
        = "cloudy1",
        frames: Annotated[int, typer.Option(help="frames timed, after the warm-up")] = 200,
        warmup: Annotated[int, typer.Option(help="frames of global convergence not "
                                                 "counted")] = 20,
        seed: int = 0,
    ) -> None:
        """Per-frame cost of locating frames between map images (two-view geometry): the
        localizer step with and without it, interleaved on the same frames, and its parts."""
        from client.lab.bench_geometry import bench_geometry, report

        try:
            b = bench_geometry(dataset, map_round, query, frames, warmup, seed)
        except ValueError as exc:
            raise typer.BadParameter(str(exc)) from None
        report(b)

    @bench_app.command("feature-types")
    def feature_types_cmd(
        dataset: Annotated[Path, typer.Argument(help="dataset with the rounds")],
        map_round: Annotated[str, typer.Option("--map", help="round used as the map")]
        = "sunny1",
        query: Annotated[str, typer.Option(help="comma-separated query rounds")]
        = "sunny2,cloudy1",
        types: Annotated[str, typer.Option(help="rootsift, orb (500 features), orbN (N), akaze")]
        = "rootsift,orb,akaze",
        methods: Annotated[str, typer.Option(help="lab method names")] = "DPSO-80,PF-l-300",
        starts: Annotated[int, typer.Option(help="runs from evenly spaced start images")] = 3,
        warmup: Annotated[int, typer.Option(help="frames of global convergence not scored")]
        = 20,
        cache: Annotated[Path | None, typer.Option(
            help="folder for the map, descriptors and similarity tables (default: none, "
                 "the map from DATASET/.maps)")] = None,
    ) -> None:
        """ORB and AKAZE (Hamming) against CLAHE + RootSIFT: mean error of DPSO-80 and
        PF-l-300, comparisons, extraction and matching time, time per frame."""
        from client.lab.feature_study import akaze_available, header, study

        kinds = [t.strip() for t in types.split(",") if t.strip()]
        if "akaze" in kinds and not akaze_available():
            typer.echo("AKAZE skipped: this OpenCV has none (it is in the contrib build)")
            kinds.remove("akaze")
        chosen = [m for m in methods.split(",") if m]
        typer.echo(f"{dataset} map {map_round}; {starts} runs per method; CPU ms of one "
                   "thread; frame ms = extraction + comparisons x ms/comparison")
        typer.echo(header(chosen))
        study(dataset, map_round, [q for q in query.split(",") if q], kinds, chosen, starts,
              warmup, cache)
