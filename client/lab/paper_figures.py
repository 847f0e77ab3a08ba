"""The figures' analogues as PNGs (matplotlib, imported when a figure is drawn)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from client.lab import paper_numbers as pn
from client.lab.paper import CaseResult
from client.lab.paper_tables import pooled


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=80, bbox_inches="tight")
    tmp.replace(path)
    _plt().close(fig)
    return path


def fig4(res: Sequence[CaseResult], path: Path) -> Path:
    """Error against simulated speed, adaptive and non-adaptive, both DPSO variants."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    lines: dict[str, list[tuple[float, float]]] = {}
    for r in res:
        lines.setdefault(r.case.method.label, []).append((r.case.speed, pooled([r])[0]))
    for label, pts in lines.items():
        pts.sort()
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-" if "non" not in label else "s--",
                label=label)
    ax.set_xscale("log", base=2)
    ax.set_xlabel("simulated speed (x original)")
    ax.set_ylabel("mean error (m)")
    ax.set_title("Fig. 4: error at simulated speeds (sunny1 vs cloudy1)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    return _save(fig, path)


def fig6(res: Sequence[CaseResult], path: Path) -> Path:
    """Mean error per iteration in the kidnapped run."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    for r in res:
        if r.case.kidnap:
            ax.plot(r.error_curve, label=f"{r.case.method.label}", lw=1)
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("mean error over runs (m)")
    ax.set_title("Fig. 6: kidnapped robot (sunny1 vs cloudy1)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    return _save(fig, path)


def fig8(res: Sequence[CaseResult], path: Path) -> Path:
    """Error and comparisons against the number of particles, ours and the paper's."""
    plt = _plt()
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    labels = [r.case.method.label for r in res]
    x = np.arange(len(res))
    ours = [pooled([r]) for r in res]
    paper = [pn.TAB1.get(lbl.split(" (")[0], (np.nan, np.nan)) for lbl in labels]
    for ax, k, pk, name in ((a, 0, 0, "mean error (m)"), (b, 2, 1, "comparisons per image")):
        ax.bar(x - 0.2, [o[k] for o in ours], 0.4, label="ours")
        ax.bar(x + 0.2, [p[pk] for p in paper], 0.4, label="paper")
        ax.set_xticks(x, labels, rotation=60, ha="right", fontsize=7)
        ax.set_ylabel(name)
        ax.legend(fontsize=7)
    fig.suptitle("Fig. 8: particle counts (sunny1 vs cloudy1)")
    return _save(fig, path)


def fig10(res: Sequence[CaseResult], scenarios: dict[str, list[tuple[str, str]]],
          path: Path) -> Path:
    """Tab. 4 as bars: per scenario and method, ours against the paper's."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    methods = list(dict.fromkeys(r.case.method.label for r in res))
    width = 0.8 / (len(methods) + 1)
    for ax, k, pk, name in ((axes[0], 0, 0, "mean error (m)"),
                            (axes[1], 2, 2, "comparisons per image")):
        for j, meth in enumerate(methods):
            vals, errs = [], []
            for pairs in scenarios.values():
                sel = [r for r in res if r.case.method.label == meth
                       and (r.case.map_round, r.case.query) in set(pairs)]
                p = pooled(sel)
                vals.append(p[k])
                errs.append(p[1] if k == 0 else 0.0)
            ax.bar(np.arange(len(scenarios)) + j * width, vals, width, yerr=errs, label=meth,
                   capsize=2)
        ax.set_xticks(np.arange(len(scenarios)) + 0.4, list(scenarios), fontsize=8)
        for i, scen in enumerate(scenarios):
            for j, meth in enumerate(methods):
                ref = pn.TAB4[scen].get(meth.split(" (")[0])
                if ref:
                    ax.plot([i + (j - 0.4) * width, i + (j + 0.4) * width], [ref[pk]] * 2,
                            "k-", lw=1.5)
        ax.set_ylabel(name)
    axes[0].legend(fontsize=7)
    fig.suptitle("Fig. 10: ours (bars) against the paper (black ticks)")
    return _save(fig, path)


def fig3_grid(res: Sequence[CaseResult], path: Path) -> Path:
    """Tab. 3 as a heat map: ours beside the paper's, sigma_rot x (sigma_acc, v_init)."""
    plt = _plt()
    keys = []
    for r in res:
        p = dict(r.case.method.params)
        v = int(r.case.method.label.split("v=")[1].split("vR")[0])
        keys.append((round(p["sigma_rot_deg"]), float(p["sigma_acc"]), v, pooled([r])[0]))
    rots = sorted({k[0] for k in keys})
    cols = sorted({(k[1], k[2]) for k in keys}, key=lambda c: (-c[0], c[1]))
    ours = np.full((len(rots), len(cols)), np.nan)
    paper = np.full_like(ours, np.nan)
    for rot, acc, v, e in keys:
        i, j = rots.index(rot), cols.index((acc, v))
        ours[i, j] = e
        paper[i, j] = pn.TAB3.get((rot, acc, v), np.nan)
    fig, axes = plt.subplots(1, 2, figsize=(12, 3.5))
    for ax, data, name in ((axes[0], ours, "ours"), (axes[1], paper, "paper")):
        im = ax.imshow(data, aspect="auto", cmap="viridis_r")
        ax.set_yticks(range(len(rots)), [f"{r}°" for r in rots])
        ax.set_xticks(range(len(cols)), [f"{a:g}\n{v}vR" for a, v in cols], fontsize=6)
        ax.set_title(f"Tab. 3 PF-l-300 mean error (m): {name}")
        fig.colorbar(im, ax=ax)
    return _save(fig, path)
