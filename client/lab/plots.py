"""PNG plots of a replay (route, error over time, comparisons); matplotlib, the lab extra."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from client.runs import Run, episodes


def plot_run(run: Run, route_xy: np.ndarray, out: Path) -> list[Path]:
    """route.png, error.png, comparisons.png of one run in ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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

    status = run.status
    colors = {"initializing": "0.85", "recovering": "#f7c6c6", "lost": "#f08080"}
    fig, ax = plt.subplots(figsize=(9, 3.2))
    for s, c in colors.items():
        for start, n in episodes(np.array(status) == s):
            ax.axvspan(start - 0.5, start + n - 0.5, color=c, lw=0,
                       label=s if start == episodes(np.array(status) == s)[0][0] else None)
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
    ax.plot(run.comparisons, "b-", lw=0.9)
    ax.set_xlabel("frame")
    ax.set_ylabel("comparisons")
    paths.append(out / "comparisons.png")
    fig.savefig(paths[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)
    return paths
