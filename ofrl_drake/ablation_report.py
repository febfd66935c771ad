"""The report of an ablation sweep: ``ablation.md`` and ``figures/``.

:func:`write_report` turns the rows of :func:`ofrl_drake.ablation.ablate` into

* ``ablation.md``: mean and standard deviation of every metric per variant,
  ``J*`` per initial state, and the runs that failed;
* ``figures/optimality_ratio.png``: ``J / J*`` per variant, a box plot with the
  individual runs on top;
* ``figures/trajectories.png``: the state of every variant from the scenario's
  own ``x0``, one panel per state component.

Figures are drawn on ``matplotlib.figure.Figure`` objects (no pyplot state) and
saved at 150 dpi or more.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from ofrl_drake.ablation import load_run
from ofrl_drake.ablation_metrics import settling_time
from ofrl_drake.atomic import atomic_write_text
from ofrl_drake.optimal import Trajectory
from ofrl_drake.plotting import _power_of_ten, numerical_floor, save_png

__all__ = [
    "REPORT_METRICS",
    "plot_optimality_ratio",
    "plot_trajectories",
    "summary_table",
    "write_report",
]

#: Column of ``ablation.csv`` -> heading in ``ablation.md``.
REPORT_METRICS = {
    "cost": "J",
    "optimality_ratio": "J/J*",
    "final_state_norm": "\\|x(T)\\|",
    "settling_time": "settling time [s]",
    "rms_estimation_error": "rms \\|x - xhat\\|",
    "min_learning_condition": "min c(t)",
    "time_outside_box": "time outside box [s]",
    "initial_policy_ratio": "policy(0)/J*",
    "final_policy_ratio": "policy(T)/J*",
    "wall_time": "wall time [s]",
}

DPI = 150


def _stats(values: Sequence[float]) -> tuple[float, float, bool]:
    """Mean, sample standard deviation and whether non-finite values were dropped."""
    arr = np.asarray(values, dtype=float)
    finite = arr[np.isfinite(arr)]
    dropped = finite.size < arr.size
    if finite.size == 0:
        return math.nan, math.nan, dropped
    std = float(np.std(finite, ddof=1)) if finite.size > 1 else math.nan
    return float(np.mean(finite)), std, dropped


def _cell(mean: float, std: float, dropped: bool) -> str:
    if not math.isfinite(mean):
        return "n/a"
    text = f"{mean:.4g}" if not math.isfinite(std) else f"{mean:.4g} ± {std:.2g}"
    return text + (" †" if dropped else "")


def summary_table(rows: Sequence[Mapping[str, Any]], variants: Sequence[str]) -> str:
    """The per-variant table of ``ablation.md`` (Markdown), mean ± std of each metric."""
    head = ["variant", "runs", "ok", *REPORT_METRICS.values()]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name in variants:
        mine = [r for r in rows if r["variant"] == name]
        ok = sum(r["status"] == "ok" for r in mine)
        cells = [_cell(*_stats([r[c] for r in mine])) for c in REPORT_METRICS]
        lines.append("| " + " | ".join([name, str(len(mine)), str(ok), *cells]) + " |")
    return "\n".join(lines)


def _key(row: Mapping[str, Any]) -> tuple[str, str]:
    """A row's (variant, initial state)."""
    return row["variant"], row["initial_state"]


def _optimal_table(rows: Sequence[Mapping[str, Any]]) -> str:
    lines = ["| initial state x0 | J* |", "|---|---|"]
    seen: dict[str, float] = {}
    for r in rows:
        seen.setdefault(r["initial_state"], r["optimal_cost"])
    for label, value in seen.items():
        shown = f"{value:.6g}" if math.isfinite(value) else "not converged"
        lines.append(f"| {label} | {shown} |")
    return "\n".join(lines)


def plot_optimality_ratio(rows: Sequence[Mapping[str, Any]], variants: Sequence[str]) -> Figure:
    """``J / J*`` per variant: a box plot with every run as a dot."""
    fig = Figure(figsize=(7.0, 0.45 * len(variants) + 1.4), layout="constrained")
    ax = fig.add_subplot()
    data = []
    for name in variants:
        vals = np.asarray([r["optimality_ratio"] for r in rows if r["variant"] == name], float)
        data.append(vals[np.isfinite(vals)])
    positions = np.arange(1, len(variants) + 1)
    filled = [i for i, d in enumerate(data) if d.size]
    if filled:
        ax.boxplot(
            [data[i] for i in filled],
            positions=positions[filled],
            orientation="horizontal",
            widths=0.6,
            showfliers=False,
        )
    for pos, d in zip(positions, data, strict=True):
        if d.size:
            ax.plot(d, np.full(d.size, pos), "o", ms=4, alpha=0.7, color="C1")
        else:
            ax.text(1.0, float(pos), "  no J/J*", va="center", fontsize=8, color="0.4")
    ax.axvline(1.0, color="0.3", lw=1, ls="--")
    ax.set_yticks(positions, list(variants))
    ax.invert_yaxis()
    ax.set_xlabel(r"$J / J^*$ (1 = optimal)")
    ax.grid(True, axis="x", alpha=0.3)
    return fig


def _at_floor(t: np.ndarray, norm: np.ndarray) -> int | None:
    """Index from which a run's ``norm`` shows only integration error, or None.

    The first sample at or below the run's own floor
    (:func:`~ofrl_drake.plotting.numerical_floor`); None when the run has no
    floor (it still decays, or never settled).
    """
    floor = numerical_floor(t, norm)
    if floor is None:
        return None
    below = np.flatnonzero(norm <= floor)
    return int(below[0]) if below.size else None


def _log_magnitude(values: np.ndarray) -> tuple[np.ndarray, bool]:
    """``values`` with exact zeros as NaN (a log axis cannot draw them); whether any were."""
    zero = values == 0.0
    return np.where(zero, np.nan, values), bool(np.any(zero))


def _window(start: float, end: float) -> str:
    return f"t = {start:g} to {end:.4g} s"


#: Alpha of the part of a run's ``|x|`` that is only integrator error.
FLOOR_ALPHA = 0.3


def plot_trajectories(
    runs_dir: str | os.PathLike[str],
    variants: Sequence[str],
    initial_state: str,
    optimum: Trajectory | None = None,
    equilibrium: Sequence[float] | None = None,
    accuracy: float | None = None,
) -> Figure:
    """Each variant's state from one initial state (saved runs).

    One panel per state component, zoomed on the transient (until every run has
    settled, :func:`~ofrl_drake.ablation_metrics.settling_time`), and a last
    panel with ``|x(t)|`` on a log scale over the whole horizon; the titles name
    the time window of each. The optimal trajectory behind ``J*``, if given, is
    drawn dashed in black. With an ``equilibrium`` x* the runs are in
    ``x - x*``, and the axes say so. The legend sits outside the axes.

    On the log panel, each run that ends on its own integrator error floor
    (:func:`~ofrl_drake.plotting.numerical_floor`) is drawn faded, in its own
    colour, from the first time it reaches that floor; the legend names the
    integrator's ``accuracy`` if given. The floor is per run, not a band across
    the axes: the runs of one sweep end on different floors, and some (a linear
    loop, the true state fed back) decay cleanly through the others' floors to
    round-off, which a band at the highest floor would label integration
    error. The lower y-limit is the smallest positive value drawn; exact zeros
    cannot be drawn on a log axis, and the panel's title says so when a run has
    any (no value is clipped).
    """
    runs = {name: run for name in variants if (run := load_run(runs_dir, name, initial_state))}
    curves = [(name, run["t"], run["x"]) for name, run in runs.items()]
    if optimum is not None:
        curves.append(("optimal (J*)", optimum.t, optimum.x))
    n = curves[0][2].shape[1] if curves else 1
    fig = Figure(figsize=(9.0, 2.2 * (n + 1) + 0.6), layout="constrained")
    axes = fig.subplots(n + 1, 1, squeeze=False)[:, 0]
    horizon, settled = 0.0, 0.0
    smallest, zeros, faded = math.inf, [], False
    for k, (name, t, x) in enumerate(curves):
        optimal = name == "optimal (J*)"
        style = {"color": "k", "ls": "--"} if optimal else {"color": f"C{k % 10}"}
        for i in range(n):
            axes[i].plot(t, x[:, i], lw=1.3, label=name, **style)
        norm, has_zero = _log_magnitude(np.linalg.norm(x, axis=1))
        if has_zero:
            zeros.append(name)
        positive = norm[np.isfinite(norm)]
        smallest = min(smallest, float(positive.min()) if positive.size else math.inf)
        # The sawtooth a settled run ends in is the integrator's error, not behaviour.
        start = None if optimal else _at_floor(t, np.linalg.norm(x, axis=1))
        end = norm.size if start is None else start + 1
        axes[n].semilogy(t[:end], norm[:end], lw=1.1, **style)
        if start is not None:
            axes[n].semilogy(t[start:], norm[start:], lw=0.9, alpha=FLOOR_ALPHA, **style)
            faded = True
        horizon = max(horizon, float(t[-1]))
        ts = settling_time(t, x)
        settled = max(settled, ts if math.isfinite(ts) else float(t[-1]))
    zoom = min(horizon, 1.5 * settled) if settled > 0 else horizon
    for i in range(n):
        label = rf"$x_{i + 1}$" if equilibrium is None else rf"$x_{i + 1} - x^*_{i + 1}$"
        axes[i].set_ylabel(label)
        axes[i].set_xlim(0.0, zoom or 1.0)
    axes[n].set_ylabel(r"$\|x\|$" if equilibrium is None else r"$\|x - x^*\|$")
    axes[n].set_xlim(0.0, horizon or 1.0)
    if math.isfinite(smallest):
        axes[n].set_ylim(bottom=10.0 ** math.floor(math.log10(smallest)))
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.set_xlabel(r"time $t$ [s]")
    title = f"state from x0 = {initial_state}"
    if equilibrium is not None:
        title = f"state relative to x* = {list(equilibrium)}, from x0 - x* = {initial_state}"
    window = "the whole horizon" if zoom >= horizon else "the transient"
    axes[0].set_title(f"{title}; state panels {_window(0.0, zoom or 1.0)} ({window})", fontsize=10)
    log_title = f"norm on a log scale, {_window(0.0, horizon or 1.0)} (the whole horizon)"
    if zeros:
        log_title += f"; exact zeros not drawn ({', '.join(zeros)})"
    axes[n].set_title(log_title, fontsize=9)
    handles, labels = axes[0].get_legend_handles_labels()
    if faded:
        note = f", accuracy {_power_of_ten(accuracy)}" if accuracy else ""
        handles.append(Line2D([], [], color="0.3", lw=2.0, alpha=FLOOR_ALPHA))
        labels.append(f"faded: at the run's integrator\nerror floor (log panel{note})")
    if handles:
        fig.legend(handles, labels, loc="outside right upper", fontsize=8, frameon=False)
    return fig


def write_report(
    out: str | os.PathLike[str],
    rows: Sequence[Mapping[str, Any]],
    variants: Sequence[str],
    *,
    scenario_name: str,
    x0_label: str,
    duration: float,
    solver: str = "SNOPT",
    optimum: Trajectory | None = None,
    equilibrium: Sequence[float] | None = None,
    accuracy: float | None = None,
) -> list[Path]:
    """Write ``ablation.md`` and the figures into ``out``; return the paths written.

    Parameters
    ----------
    out : str or Path
        The sweep's directory (holding ``runs/`` from :func:`~ofrl_drake.ablation.ablate`).
    rows : sequence of dict
        The sweep's rows.
    variants : sequence of str
        Variant names, in table order.
    scenario_name : str
    x0_label : str
        ``initial_state`` label of the scenario's own ``x0`` (for the
        trajectory figure, which draws the saved runs of the rows of ``rows``
        from it).
    duration : float
        The horizon of J and J*.
    solver : str
        Solver of J*, for the text.
    optimum : Trajectory, optional
        The optimal trajectory from the scenario's ``x0``, drawn with the variants.
    equilibrium : sequence of float, optional
        The scenario's x*: states and initial states are then ``x - x*``.
    accuracy : float, optional
        The integrator accuracy of the runs, named on the shaded error floor.
    """
    out = Path(out)
    figures = out / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    failed = [r for r in rows if r["status"] != "ok"]
    states = list(dict.fromkeys(r["initial_state"] for r in rows))
    text = [
        f"# Ablation: {scenario_name}",
        "",
        f"{len(rows)} runs: {len(variants)} variants from {len(states)} initial states, "
        f"horizon {duration:g} s. J* is the optimal cost over the same horizon with "
        f"|u_k| <= lambda_bar (direct collocation, {solver}). Cells are mean ± sample "
        "standard deviation over the initial states; † marks a cell that left out "
        "non-finite values (a run that never settled, or a failed one).",
        "",
        summary_table(rows, variants),
        "",
    ]
    if equilibrium is not None:
        text += [
            f"States and initial states are relative to the equilibrium x* = "
            f"{list(equilibrium)} (the method's coordinates x - x*).",
            "",
        ]
    text += [
        "## Optimal cost per initial state",
        "",
        _optimal_table(rows),
        "",
        "## Runs that did not finish with status ok",
        "",
    ]
    if failed:
        text += ["| variant | initial state | status |", "|---|---|---|"]
        text += [
            f"| {r['variant']} | {r['initial_state']} | {r['status'].replace('|', '/')} |"
            for r in failed
        ]
    else:
        text.append("None.")
    text += [
        "",
        "Figures: `figures/optimality_ratio.png` (J/J* per variant), "
        "`figures/trajectories.png` (state of every variant from the scenario's x0).",
        "",
    ]
    md = out / "ablation.md"
    atomic_write_text(md, "\n".join(text))
    ratio = figures / "optimality_ratio.png"
    save_png(plot_optimality_ratio(rows, variants), ratio, DPI)
    traj = figures / "trajectories.png"
    # Only the runs of rows in the table: a file in runs/ without its row is no run of this sweep.
    in_table = {_key(r) for r in rows}
    drawn = [v for v in variants if (v, x0_label) in in_table]
    trajectories = plot_trajectories(out / "runs", drawn, x0_label, optimum, equilibrium, accuracy)
    save_png(trajectories, traj, DPI)
    return [md, ratio, traj]
