"""What an engineer reads from a sweep: designs ranked by the figure of merit, the Pareto
front of accuracy against the cost, and a plot of both."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from endomeasure.study.evaluate import DesignResult
from endomeasure.study.spec import SweepSpec

__all__ = ["ranked", "pareto_front", "plot_sweep"]


def _key(r: DesignResult) -> tuple:
    merit = r.merit
    return (r.success < 1.0, math.inf if math.isnan(merit) else merit, r.index)


def ranked(results: Sequence[DesignResult]) -> list[DesignResult]:
    """Designs whose every draw calibrated first, each group by the merit (lower is
    better), then by index."""
    return sorted(results, key=_key)


def pareto_front(results: Sequence[DesignResult]) -> list[DesignResult]:
    """The designs (every draw calibrated, finite merit and cost) that no other design
    beats in both the merit and the cost (lower is better for both), by cost."""
    pool = [r for r in results if r.success == 1.0 and np.isfinite(r.merit) and np.isfinite(r.cost)]
    pool.sort(key=lambda r: (r.cost, r.merit, r.index))
    front, best = [], math.inf
    for r in pool:
        if r.merit < best:
            front.append(r)
            best = r.merit
    return front


def plot_sweep(spec: SweepSpec, results: Sequence[DesignResult], path: str | Path) -> Path:
    """Left: the merit of every design against its cost, the Pareto front and the target.
    Right: the merit over the first two axes (one axis: against it), the target's contour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    merit = np.array([r.merit for r in results])
    cost = np.array([r.cost for r in results])
    ok = np.array([r.success == 1.0 for r in results])
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.4), constrained_layout=True)
    left.scatter(cost[ok], merit[ok], s=18, c="tab:blue", label="every draw calibrated")
    if (~ok).any():
        left.scatter(
            cost[~ok],
            merit[~ok],
            s=18,
            marker="x",
            c="tab:red",
            label="a draw failed or infeasible",
        )
    front = pareto_front(results)
    if front:
        left.plot(
            [r.cost for r in front],
            [r.merit for r in front],
            "-o",
            c="k",
            ms=4,
            mfc="none",
            label="Pareto front",
        )
    left.axhline(spec.target_pct, ls="--", c="tab:green", label=f"target {spec.target_pct:g} %")
    left.set_xlabel(spec.cost)
    left.set_ylabel("worst 95 % error over draws, %")
    left.set_yscale("log")
    left.legend(fontsize=8)
    values = np.array([r.values for r in results])
    names = spec.axis_names
    if len(names) >= 2:
        sc = right.scatter(
            values[:, 0], values[:, 1], c=np.log10(merit), s=60, marker="s", cmap="viridis_r"
        )
        fig.colorbar(sc, ax=right, label="log10 worst 95 % error, %")
        grid = [a for a in spec.axes[:2] if a.grid is not None]
        if len(grid) == 2 and len(results) == spec.n_designs and not spec.has_random:
            shape = (len(grid[0].grid), len(grid[1].grid))
            zz = merit.reshape(shape)
            if np.isfinite(zz).all() and zz.min() < spec.target_pct < zz.max():
                right.contour(
                    np.array(grid[0].grid),
                    np.array(grid[1].grid),
                    zz.T,
                    levels=[spec.target_pct],
                    colors="tab:green",
                )
        right.set_xlabel(names[0])
        right.set_ylabel(names[1])
    else:
        order = np.argsort(values[:, 0])
        right.plot(values[order, 0], merit[order], "-o")
        right.axhline(spec.target_pct, ls="--", c="tab:green")
        right.set_xlabel(names[0])
        right.set_ylabel("worst 95 % error over draws, %")
        right.set_yscale("log")
    labels = ", ".join(t.label for t in spec.templates)
    depths = ", ".join(f"{z:g}" for z in spec.depths_mm)
    fig.suptitle(
        f"{labels} at {depths} mm: {spec.field_quantile:.0%} of the field, "
        f"{spec.draws} tolerance draw(s) per design",
        fontsize=10,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
