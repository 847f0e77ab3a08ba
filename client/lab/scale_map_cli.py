"""CLI registration of ``swarmloc world long-route`` and ``swarmloc bench scale-map``
(client/lab/world/long_route.py, client/lab/bench_scale_map.py); kept apart so that the CLI's
start-up imports none of their modules."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def register(world_app: typer.Typer, bench_app: typer.Typer) -> None:
    """``world long-route`` on the world group, ``bench scale-map`` on the bench group."""

    @world_app.command("long-route")
    def long_route_cmd(
        out: Annotated[Path, typer.Argument(help="directory for spill/, queries/, maps/")],
        images: Annotated[int, typer.Option(help="map images of the longest map")] = 40_000,
        maps: Annotated[str, typer.Option(help="map sizes to assemble (prefixes of the "
                                                "route)")] = "400,4000,40000",
        seed: int = 0,
        legs: Annotated[int, typer.Option(help="query legs at random places")] = 20,
        leg_frames: Annotated[int, typer.Option(help="frames per query leg")] = 50,
        track_frames: Annotated[int, typer.Option(
            help="frames of the tracking leg in loop 0 (inside the 400-image map)")] = 360,
        workers: Annotated[int, typer.Option(help="rendering processes")] = 1,
    ) -> None:
        """Render a long route of chained street loops (map features, query legs) and
        assemble its maps of the first N images, each with its place index."""
        import time

        import numpy as np

        from client.lab.world.long_route import Leg, LongRoute, assemble_maps, render_long_route
        from service.vision.features import SiftParams

        route = LongRoute(images, seed)
        if track_frames + 20 > min(images, route.per_loop):
            raise typer.BadParameter(f"the tracking leg must fit loop 0 ({route.per_loop} "
                                     "frames)")
        plan = [Leg("track", 0, 20, track_frames)]
        plan += route.plan_legs(legs, leg_frames, np.random.default_rng([seed, 77]))
        params = SiftParams(width=route.camera.width, height=route.camera.height)
        t0 = time.perf_counter()
        typer.echo(f"{route.n_loops} loops of {route.per_loop} images; {len(plan)} legs")

        def tick(k: int) -> None:
            typer.echo(f"loop {k + 1}/{route.n_loops} done, {time.perf_counter() - t0:.0f} s")

        render_long_route(route, out, plan, params, workers, tick)
        sizes = sorted({int(s) for s in maps.split(",") if s.strip()})
        for path in assemble_maps(out, [s for s in sizes if s <= images]):
            typer.echo(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB)")
        typer.echo(f"done in {time.perf_counter() - t0:.0f} s")

    @bench_app.command("scale-map")
    def scale_map_cmd(
        route_dir: Annotated[Path, typer.Argument(help="a 'swarmloc world long-route' dir")],
        sizes: Annotated[str, typer.Option(help="map sizes (route-N.swmap)")]
        = "400,4000,40000",
        server_frames: Annotated[int, typer.Option(
            help="frames sent over HTTP to a service process per size (0: no server)")] = 100,
        relocal: Annotated[bool, typer.Option(
            help="fresh starts and kidnaps on the largest map")] = True,
        baseline: Annotated[bool, typer.Option(
            help="the same relocalisation runs with random placements (no index)")] = False,
    ) -> None:
        """File size, open time, service start-up and RSS, per-frame localizer time and
        comparisons while tracking for each map size; relocalisation on the largest."""
        from client.lab.bench_scale_map import run_bench

        try:
            run_bench(route_dir, sorted(int(s) for s in sizes.split(",") if s.strip()),
                      server_frames, relocal, baseline, typer.echo)
        except FileNotFoundError as exc:
            raise typer.BadParameter(str(exc)) from None
