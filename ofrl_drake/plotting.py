"""Publication-ready figures of a closed-loop run (the paper's Figs. 1-5 and c(t)).

Every function takes a :class:`~ofrl_drake.SimulationResult` and returns a
matplotlib ``Figure``; :func:`save_figures` writes them all as PNG.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

__all__ = [
    "plot_comparison",
    "plot_cost",
    "plot_estimation_error",
    "plot_gain_schedule",
    "plot_input",
    "plot_learning_condition",
    "plot_overview",
    "plot_state",
    "plot_weights",
    "save_figures",
]

_STYLE = {
    "figure.figsize": (6.0, 3.4),
    "axes.grid": True,
    "grid.alpha": 0.3,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "font.size": 10,
    "legend.frameon": False,
}


def _math_label(label: str) -> str:
    """``"x1^2 x2"`` -> ``"$x_{1}^{2} x_{2}$"`` for mathtext."""
    return (
        "$"
        + re.sub(
            r"x(\d+)(?:\^(\d+))?",
            lambda m: f"x_{{{m[1]}}}" + (f"^{{{m[2]}}}" if m[2] else ""),
            label,
        )
        + "$"
    )


def _shown(result, key: str) -> np.ndarray:
    """``x``, ``xhat`` or ``u`` in the plant's own coordinates (a run with an equilibrium)."""
    original = getattr(result, "original", None)
    return getattr(result, key) if original is None else original(key)


def _equilibrium(result, key: str) -> np.ndarray | None:
    return getattr(result, f"{key}_equilibrium", None)


def _axes(title: str | None = None) -> tuple[Figure, plt.Axes]:
    with plt.rc_context(_STYLE):
        fig, ax = plt.subplots(constrained_layout=True)
    if title:
        ax.set_title(title)
    ax.set_xlabel(r"time $t$ [s]")
    return fig, ax


def plot_state(result, i: int) -> Figure:
    """``x_i`` and ``xhat_i`` against time (the paper's Figs. 1 and 2)."""
    fig, ax = _axes()
    ax.plot(result.t, _shown(result, "x")[:, i], lw=1.6, label=rf"$x_{{{i + 1}}}$")
    xhat = _shown(result, "xhat")[:, i]
    ax.plot(result.t, xhat, lw=1.4, ls="--", label=rf"$\hat{{x}}_{{{i + 1}}}$")
    ax.set_ylabel(rf"state $x_{{{i + 1}}}$")
    x_eq = _equilibrium(result, "x")
    if x_eq is not None:
        ax.axhline(x_eq[i], color="k", lw=0.8, ls=":", label=rf"$x^*_{{{i + 1}}}$ (equilibrium)")
        ax.set_ylabel(rf"state $x_{{{i + 1}}}$ (plant coordinates)")
    ax.legend()
    return fig


def plot_estimation_error(result) -> Figure:
    """``e = x - xhat`` per component (the paper's Fig. 3)."""
    fig, ax = _axes()
    for i in range(result.x.shape[1]):
        ax.plot(result.t, result.e[:, i], lw=1.4, label=rf"$e_{{{i + 1}}}$")
    ax.set_ylabel(r"estimation error $x - \hat{x}$")
    ax.legend(ncol=min(4, result.x.shape[1]))
    return fig


def plot_weights(result, labels: Sequence[str] | None = None) -> Figure:
    """Critic weights ``W(t)`` (the paper's Fig. 4)."""
    fig, ax = _axes()
    L = result.W.shape[1]
    for k in range(L):
        name = _math_label(labels[k]) if labels is not None else None
        label = rf"$\hat{{W}}_{{{k + 1}}}$" + (f" ({name})" if name else "")
        ax.plot(result.t, result.W[:, k], lw=1.4, label=label)
    ax.set_ylabel(r"critic weights $\hat{W}_c$")
    ax.legend(ncol=min(3, L), fontsize=8)
    return fig


def plot_input(result, input_bound: float | None = None) -> Figure:
    """The saturated input ``u(t)`` (the paper's Fig. 5), with the bound."""
    fig, ax = _axes()
    u = _shown(result, "u")
    for k in range(u.shape[1]):
        ax.plot(result.t, u[:, k], lw=1.4, label=rf"$u_{{{k + 1}}}$")
    u_eq = _equilibrium(result, "u")
    if input_bound is not None:
        centers = np.zeros(u.shape[1]) if u_eq is None else np.unique(u_eq)
        for c in centers:
            for s in (-1, 1):
                ax.axhline(c + s * input_bound, color="k", lw=0.8, ls=":")
    bound = r"input $u$ ($|u - u^*| \leq \bar\lambda$)"
    ax.set_ylabel(r"control input $u$" if u_eq is None else bound)
    ax.legend()
    return fig


def plot_learning_condition(result) -> Figure:
    """``c(t) = lambda_min((1/N) sum omega omega^T / rho^2)`` (Assumption 2)."""
    fig, ax = _axes()
    ax.plot(result.t, result.learning_condition, lw=1.4, color="C3")
    ax.set_ylabel(r"learning condition $c(t)$")
    ax.set_ylim(bottom=0)
    return fig


def plot_cost(result) -> Figure:
    """Accumulated cost ``J(t)``."""
    fig, ax = _axes()
    ax.plot(result.t, result.cost, lw=1.4, color="C4")
    ax.set_ylabel(r"cost $J(t)=\int_0^t Q(x)+U(u)\,d\tau$")
    return fig


def plot_comparison(results: dict, key: str = "x", component: int = 0) -> Figure:
    """One signal of several runs in one plot, e.g. a block swap against the baseline."""
    fig, ax = _axes()
    for label, result in results.items():
        data = getattr(result, key)
        y = data if data.ndim == 1 else data[:, component]
        ax.plot(result.t, y, lw=1.4, label=label)
    names = {"x": "x", "xhat": r"\hat{x}", "e": "e", "u": "u", "W": r"\hat{W}"}
    if key in names:
        ax.set_ylabel(f"${names[key]}_{{{component + 1}}}$")
    else:
        ax.set_ylabel(key.replace("_", " "))
    ax.legend()
    return fig


def plot_gain_schedule(t: np.ndarray, gains: np.ndarray, failed: np.ndarray) -> Figure:
    """Scheduled observer gains L, H and K over time; failed re-solves marked.

    Parameters
    ----------
    t : ndarray, shape (T,)
    gains : ndarray, shape (T, 3 n q)
        The ``observer_gains`` log, ``[vec(L), vec(H), vec(K)]`` row-major.
    failed : ndarray of bool, shape (T,)
        True where the latest re-solve failed (previous gains kept).
    """
    k = gains.shape[1] // 3
    with plt.rc_context(_STYLE):
        fig, axes = plt.subplots(3, 1, sharex=True, figsize=(6.0, 6.4), constrained_layout=True)
    for ax, (name, block) in zip(axes, (("L", 0), ("H", 1), ("K", 2)), strict=True):
        part = gains[:, block * k : (block + 1) * k]
        for j in range(k):
            ax.step(t, part[:, j], where="post", lw=1.4, label=rf"${name}_{{{j + 1}}}$")
        if np.any(failed):
            ax.plot(t[failed], part[failed, 0], "kx", ms=4, label="re-solve failed")
        ax.set_ylabel(f"gain ${name}$")
        ax.legend(fontsize=8, ncol=min(k + 1, 4))
    axes[-1].set_xlabel(r"time $t$ [s]")
    return fig


def plot_overview(result, input_bound: float | None = None) -> Figure:
    """Four panels: states and estimates, estimation error, weights, input."""
    with plt.rc_context({**_STYLE, "figure.figsize": (9.0, 6.0)}):
        fig, axes = plt.subplots(2, 2, sharex=True, constrained_layout=True)
    ax = axes[0, 0]
    x, xhat = _shown(result, "x"), _shown(result, "xhat")
    for i in range(result.x.shape[1]):
        (line,) = ax.plot(result.t, x[:, i], lw=1.5, label=rf"$x_{{{i + 1}}}$")
        ax.plot(
            result.t,
            xhat[:, i],
            lw=1.3,
            ls="--",
            color=line.get_color(),
            label=rf"$\hat{{x}}_{{{i + 1}}}$",
        )
    ax.set_ylabel(
        "state and estimate"
        if _equilibrium(result, "x") is None
        else "state and estimate (plant coordinates)"
    )
    ax.legend(ncol=2, fontsize=8)
    ax = axes[0, 1]
    for i in range(result.x.shape[1]):
        ax.plot(result.t, result.e[:, i], lw=1.3, label=rf"$e_{{{i + 1}}}$")
    ax.set_ylabel(r"error $x-\hat{x}$")
    ax.legend(fontsize=8)
    ax = axes[1, 0]
    for k in range(result.W.shape[1]):
        ax.plot(result.t, result.W[:, k], lw=1.3, label=rf"$\hat{{W}}_{{{k + 1}}}$")
    ax.set_ylabel(r"critic weights $\hat{W}_c$")
    ax.legend(ncol=3, fontsize=8)
    ax = axes[1, 1]
    u = _shown(result, "u")
    for k in range(u.shape[1]):
        ax.plot(result.t, u[:, k], lw=1.3, label=rf"$u_{{{k + 1}}}$")
    if input_bound is not None:
        u_eq = _equilibrium(result, "u")
        for c in np.zeros(1) if u_eq is None else np.unique(u_eq):
            for s in (-1, 1):
                ax.axhline(c + s * input_bound, color="k", lw=0.8, ls=":")
    ax.set_ylabel("control input $u$")
    for ax in axes[1]:
        ax.set_xlabel(r"time $t$ [s]")
    for ax in axes.flat:
        ax.grid(True, alpha=0.3)
    return fig


def save_figures(
    result,
    directory: str | Path,
    *,
    input_bound: float | None = None,
    weight_labels: Sequence[str] | None = None,
    dpi: int = 200,
) -> list[Path]:
    """Write every figure of ``result`` as PNG into ``directory``; return the paths."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    figures = {f"state_{i + 1}": plot_state(result, i) for i in range(result.x.shape[1])}
    figures["estimation_error"] = plot_estimation_error(result)
    figures["critic_weights"] = plot_weights(result, weight_labels)
    figures["control_input"] = plot_input(result, input_bound)
    figures["learning_condition"] = plot_learning_condition(result)
    figures["cost"] = plot_cost(result)
    figures["overview"] = plot_overview(result, input_bound)
    extra = getattr(result, "extra", {})
    if "observer_gains" in extra:
        failed = extra.get("solve_failed", np.zeros((result.t.size, 1)))[:, 0] > 0.5
        figures["gain_schedule"] = plot_gain_schedule(result.t, extra["observer_gains"], failed)
    paths = []
    for name, fig in figures.items():
        path = directory / f"{name}.png"
        fig.savefig(path, dpi=dpi)
        plt.close(fig)
        paths.append(path)
    return paths
