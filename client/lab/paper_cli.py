"""``swarmloc paper DATASET --out DIR``: the journal's Fig. 4 and Tab. 1-4 in full protocol."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import os
import time
from pathlib import Path
from typing import Annotated, Any

import typer


def paper(
    dataset: Annotated[Path, typer.Argument(help="dataset with sunny1-3 and cloudy1-3")],
    out: Annotated[Path, typer.Option(help="directory for the tables (.md, .json) and PNGs")],
    quick: Annotated[bool, typer.Option(help="smoke version: few start images, small grid, "
                                              "one round pair per scenario")] = False,
    starts: Annotated[int | None, typer.Option(
        help="start images per case for the papers' DPSO and the filters (0 = every test "
             "image, the papers' protocol)")] = None,
    product_starts: Annotated[int | None, typer.Option(
        help="start images per case for the product's DPSO (one run at a time; default 24)")
    ] = None,
    warmup: Annotated[int | None, typer.Option(help="frames not scored (global start)")] = None,
    seed: int = 0,
    threads: Annotated[int, typer.Option(help="similarity computations in parallel threads "
                                            "(without worker processes)")] = 2,
    workers: Annotated[int, typer.Option(help="cases in parallel worker processes "
                                            "(1: all in this process)")] = 2,
    progress: Annotated[bool, typer.Option(help="progress bar over the cases")] = True,
) -> None:
    """Fig. 4, Tab. 1/Fig. 8, Tab. 2/Fig. 6, Tab. 3, Tab. 4/Fig. 10: tables as Markdown and
    JSON with the papers' numbers beside ours (the faithful papers' DPSO and the product's
    DPSO in each), figures as PNG, settings and wall time in run.json."""
    from client.lab import paper_figures as figs
    from client.lab import paper_tables as tabs
    from client.lab.paper import Lab, Settings, iter_rounds, protocol, tab4_pairs
    from client.lab.paper_pool import run_protocol

    s = Settings.quick() if quick else Settings()
    given = (("starts", starts), ("product_starts", product_starts), ("warmup", warmup))
    over: dict[str, Any] = {k: v for k, v in given if v is not None}
    s = dataclasses.replace(s, seed=seed, threads=threads, workers=workers, **over)
    rounds = list(iter_rounds(dataset))
    need = {"sunny1", "cloudy1"}
    if not need <= set(rounds):
        raise typer.BadParameter(f"{dataset} needs rounds {sorted(need)}; it has {rounds}")
    scen = tab4_pairs(rounds, s.pair_limit)
    lab = Lab(dataset, s.threads)
    t0 = time.time()
    started = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    written: list[str] = []
    done: dict[str, list] = {}

    def on_section(name: str, res: list) -> None:
        done[name] = res
        if name == "tab1":
            table = tabs.tab1(res)
            written.append(str(figs.fig8(res, out / "fig8_particles.png")))
        elif name == "tab2":
            table = tabs.tab2(res)
            written.append(str(figs.fig6(res, out / "fig6_kidnap.png")))
        elif name == "fig4":
            table = tabs.fig4(res)
            written.append(str(figs.fig4(res, out / "fig4_speed.png")))
        elif name == "tab3":
            ref = [r for r in done.get("tab1", []) if r.case.method.label.startswith("DPSO-80 ")]
            table = tabs.tab3(res, ref)
            written.append(str(figs.fig3_grid(res, out / "tab3_grid.png")))
        else:
            table = tabs.tab4(res, scen)
            written.append(str(figs.fig10(res, scen, out / "fig10_comparison.png")))
        written.extend(str(p) for p in tabs.write(table, out))
        tabs.write_text(out / f"cases-{name}.json", json.dumps(tabs.case_records(res)))
        if name != "tab4" or len(res) == len(sections.get("tab4", res)):
            typer.echo(f"\n{table.markdown()}")

    sections = protocol(rounds, s)
    run_protocol(lab, rounds, s, on_section, progress)
    wall = time.time() - t0
    import resource

    cpu = sum(getattr(resource.getrusage(who), f) for who in (resource.RUSAGE_SELF,
              resource.RUSAGE_CHILDREN) for f in ("ru_utime", "ru_stime"))
    opts = "".join(f" --{k.replace('_', '-')} {v}" for k, v in over.items())
    meta = {"command": f"swarmloc paper {dataset} --out {out}" + (" --quick" if quick else "")
            + opts,
            "started_utc": started, "wall_s": round(wall, 1),
            "cpu_s": round(cpu, 1),  # this process and its workers, user + system
            "load_average": list(os.getloadavg()), "cpus": os.cpu_count(),
            "settings": dataclasses.asdict(s), "rounds": rounds,
            "case_seconds": {k: round(sum(r.seconds for r in v), 1) for k, v in done.items()},
            "files": written}
    (out / "run.json").write_text(json.dumps(meta, indent=1))
    typer.echo(f"wall time {wall / 60:.1f} min, CPU time {cpu / 60:.1f} min (this process and "
               f"its workers), load average {os.getloadavg()[0]:.2f}; "
               f"wrote {len(written)} files to {out}")
