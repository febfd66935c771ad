"""Publication-ready figures of a closed-loop run (the paper's Figs. 1-5 and c(t)).

Every function takes a :class:`~ofrl_drake.SimulationResult` and returns a
matplotlib ``Figure``; :func:`save_figures` writes them all as PNG.

Conventions, so the figures go into a paper unedited:

* States and inputs get two panels: the first seconds (the transient, up to
  :func:`transient_end`) and the whole horizon.
* The estimation error has a linear plot and a semilog plot of ``|e_i|``.
* The observer box is drawn on the state plots, ``+-lambda_bar`` on the input
  plots, each with a legend entry.
* Legends sit outside the axes (above them, or to the right when there are many
  entries), so they never cover data; one entry per state, input or weight.
* A run stopped by the guard (:mod:`ofrl_drake.guard`) is marked where it stopped.
* On log plots, the band below the level where a settled signal only shows
  integration error (:func:`numerical_floor`, the sawtooth of an
  error-controlled integrator) is shaded and labelled, so it is not read as
  behaviour.
"""

from __future__ import annotations

import functools
import re
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from ofrl_drake.atomic import atomic_file

if TYPE_CHECKING:  # matplotlib >= 3.10 names the rc keys; the annotation only
    from matplotlib.typing import RcKeyType

    from ofrl_drake.learning_curve import LearningHealth
    from ofrl_drake.simulation import SimulationResult

__all__ = [
    "MissingGlyphWarning",
    "numerical_floor",
    "plot_comparison",
    "plot_cost",
    "plot_estimation_error",
    "plot_estimation_error_log",
    "plot_gain_schedule",
    "plot_input",
    "plot_learning_condition",
    "plot_overview",
    "plot_state",
    "plot_weights",
    "save_figures",
    "save_png",
    "shade_numerical_floor",
    "transient_end",
]

_STYLE: dict[RcKeyType, Any] = {
    "figure.figsize": (6.0, 3.4),
    "axes.grid": True,
    "grid.alpha": 0.3,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "font.size": 10,
    "legend.frameon": False,
    "legend.fontsize": 9,
}

#: Legends with more entries than this go to the right of the axes, one per row.
_MANY = 4

Box = tuple[Sequence[float], Sequence[float]]


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


def _shown(result: SimulationResult, key: str) -> np.ndarray:
    """``x``, ``xhat`` or ``u`` in the plant's own coordinates (a run with an equilibrium)."""
    original = getattr(result, "original", None)
    return getattr(result, key) if original is None else original(key)


def _equilibrium(result: SimulationResult, key: str) -> np.ndarray | None:
    return getattr(result, f"{key}_equilibrium", None)


def _unit(result: SimulationResult, key: str, i: int | None = None) -> str:
    """`` [m]`` for entry ``i`` of ``x``/``e`` (``key="state"``) or ``u`` (``"input"``).

    With ``i`` None, the unit shared by every entry, if there is one. Empty
    when the model does not know its units (e.g. the paper's dimensionless toy).
    """
    units = getattr(result, f"{key}_units", None)
    if not units:
        return ""
    chosen = set(units) if i is None else {units[i]}
    return f" [{chosen.pop()}]" if len(chosen) == 1 and "" not in chosen else ""


def transient_end(result: SimulationResult, fraction: float = 0.02, minimum: float = 0.5) -> float:
    """End of the zoomed panel: where x and e have settled.

    1.5 times the last time any ``|x_i|`` or ``|e_i|`` is above ``fraction`` of
    its largest value, at least ``minimum`` seconds, at most the horizon.
    """
    t = np.asarray(result.t)
    horizon = float(t[-1]) if t.size else 0.0
    signals = np.abs(np.concatenate([result.x, result.e], axis=1))
    peak = np.nanmax(signals, axis=0) if t.size else np.zeros(0)
    above = np.flatnonzero(np.any(signals > fraction * peak, axis=1))
    last = float(t[above[-1]]) if above.size else 0.0
    return min(horizon, _nice_ceiling(max(minimum, 1.5 * last)))


def _nice_ceiling(value: float) -> float:
    """``value`` rounded up to 1, 1.5, 2, 2.5, 3, 4, 5, 6, 8 or 10 times a power of ten."""
    if not value > 0:
        return value
    scale = 10.0 ** np.floor(np.log10(value))
    for step in (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0):
        if value <= step * scale * (1 + 1e-12):
            return float(step * scale)
    return float(10 * scale)  # pragma: no cover - the loop always returns


def numerical_floor(
    t: np.ndarray, values: np.ndarray, tail: float = 0.25, drop: float = 1e-3
) -> float | None:
    """The level under which a settled signal shows only integration error, or None.

    A signal has reached its numerical floor when, over the last ``tail`` of the
    horizon, it is below ``drop`` times its peak and no longer decays (its
    largest value over the last half of that window is at least half the one
    over the first half): what is left is the sawtooth of an
    error-controlled integrator. The floor is then the largest value over the
    window. A signal that still decays, or never settles, has none.

    Parameters
    ----------
    t : ndarray, shape (T,)
    values : ndarray, shape (T,) or (T, k)
        Magnitudes (e.g. ``|e_i|`` or ``||x||``); several columns share one floor.
    tail : float, optional
        The fraction of the horizon, at its end, read for the floor (default
        the last quarter).
    drop : float, optional
        How far below its peak a signal must be to count as settled (default
        ``1e-3`` of the peak).

    Returns
    -------
    float or None
        The floor, or None for fewer than 8 samples, a non-finite value, a
        window without samples, or a signal that still decays or never settled.
    """
    t = np.asarray(t, dtype=float)
    mags = np.abs(np.asarray(values, dtype=float)).reshape(t.size, -1)
    if t.size < 8 or not np.all(np.isfinite(mags)):
        return None
    start = t[0] + (1.0 - tail) * (t[-1] - t[0])
    middle = t[0] + (1.0 - tail / 2) * (t[-1] - t[0])
    first, last = mags[(t >= start) & (t < middle)], mags[t >= middle]
    if first.size == 0 or last.size == 0:
        return None
    level, peak = float(max(first.max(), last.max())), float(mags.max())
    if peak == 0.0 or level == 0.0 or level > drop * peak or last.max() < 0.5 * first.max():
        return None
    return level


def _power_of_ten(value: float) -> str:
    """``1e-4`` -> ``"$10^{-4}$"``; other numbers as ``%g``."""
    exponent = np.log10(value)
    if np.isclose(exponent, round(exponent), rtol=0, atol=1e-9):
        return f"$10^{{{round(exponent)}}}$"
    return f"{value:g}"


def shade_numerical_floor(ax: Axes, floor: float | None, accuracy: float | None = None) -> None:
    """Shade a log axis below ``floor`` and label it as integrator accuracy."""
    if floor is None:
        return
    bottom = min(ax.get_ylim()[0], floor / 10.0)
    note = f" (accuracy {_power_of_ten(accuracy)})" if accuracy else ""
    ax.axhspan(
        bottom,
        floor,
        color="0.88",
        zorder=0,
        lw=0,
        label=f"integrator error floor{note}",
    )
    ax.set_ylim(bottom=bottom)


def _figure(panels: int = 1, *, width: float = 7.0, height: float = 3.0) -> tuple[Figure, list]:
    with plt.rc_context(_STYLE):
        fig, axes = plt.subplots(
            1, panels, figsize=(width, height), layout="constrained", squeeze=False
        )
    return fig, list(axes[0])


def _legend(fig: Figure, axes: Sequence[Axes], *, title: str | None = None) -> None:
    """One legend for the figure, outside the axes: above, or right if long."""
    handles, labels = [], []
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            if lab not in labels and not lab.startswith("_"):
                handles.append(h)
                labels.append(lab)
    if not handles:
        return
    with plt.rc_context(_STYLE):
        if len(handles) > _MANY:
            fig.legend(handles, labels, loc="outside right upper", ncols=1, title=title)
        else:
            fig.legend(handles, labels, loc="outside upper center", ncols=len(handles))


def _windows(result: SimulationResult, axes: Sequence[Axes]) -> None:
    """Zoom the first axes on the transient; the last shows the whole horizon."""
    horizon = float(result.t[-1]) if result.t.size else 0.0
    zoom = transient_end(result)
    if len(axes) > 1 and zoom > 0:
        axes[0].set_xlim(0.0, zoom)
        axes[0].set_title(f"first {zoom:.3g} s", fontsize=9)
        axes[-1].set_title(f"whole run ({horizon:.3g} s)", fontsize=9)
    if horizon > 0:
        axes[-1].set_xlim(0.0, horizon)
    for ax in axes:
        ax.set_xlabel(r"time $t$ [s]")


def _mark_stop(result: SimulationResult, axes: Sequence[Axes]) -> None:
    """A vertical line where the guard stopped the run, with a legend entry."""
    stop = getattr(result, "stop", None)
    if stop is None or stop.ok:
        return
    for ax in axes:
        ax.axvline(stop.time, color="C3", lw=1.0, ls=":", label=f"run stopped ({stop.status})")


def _autoscale_visible(ax: Axes, t: np.ndarray, data: np.ndarray, extra: Sequence[float]) -> None:
    """y limits from the samples inside the x window (and ``extra`` levels)."""
    lo, hi = ax.get_xlim()
    inside = (t >= lo) & (t <= hi)
    values = np.concatenate([np.ravel(data[inside]), np.asarray(extra, float)])
    values = values[np.isfinite(values)]
    if values.size:
        pad = 0.05 * (values.max() - values.min()) or 0.5
        ax.set_ylim(values.min() - pad, values.max() + pad)


def plot_state(result: SimulationResult, i: int, box: Box | None = None) -> Figure:
    """``x_i`` and ``xhat_i`` against time (the paper's Figs. 1 and 2), with the box.

    Left: the transient; right: the whole run. With an equilibrium, states are
    shown in the plant's own coordinates, with ``x*_i`` and the box (given
    relative to x*, as in the scenario) shifted by it.
    """
    fig, axes = _figure(2)
    x, xhat = _shown(result, "x")[:, i], _shown(result, "xhat")[:, i]
    x_eq = _equilibrium(result, "x")
    shift = 0.0 if x_eq is None else float(x_eq[i])
    levels = [] if box is None else [box[0][i] + shift, box[1][i] + shift]
    for ax in axes:
        ax.plot(result.t, x, lw=1.6, color="C0", label=rf"$x_{{{i + 1}}}$")
        ax.plot(result.t, xhat, lw=1.4, ls="--", color="C1", label=rf"$\hat{{x}}_{{{i + 1}}}$")
        if x_eq is not None:
            ax.axhline(shift, color="k", lw=0.8, ls=":", label=rf"$x^*_{{{i + 1}}}$ (equilibrium)")
        if box is not None:
            for k, bound in enumerate(levels):
                ax.axhline(
                    bound,
                    color="0.35",
                    lw=0.9,
                    ls="-.",
                    label="observer box" if k == 0 else "_box",
                )
    _windows(result, axes)
    _mark_stop(result, axes)
    both = np.stack([x, xhat], axis=1)
    for ax in axes:
        _autoscale_visible(ax, result.t, both, levels)
    where = "" if x_eq is None else " (plant coordinates)"
    axes[0].set_ylabel(rf"state $x_{{{i + 1}}}$ and estimate{where}{_unit(result, 'state', i)}")
    _legend(fig, axes)
    return fig


def plot_estimation_error(result: SimulationResult) -> Figure:
    """``e = x - xhat`` per component (the paper's Fig. 3): transient and whole run."""
    fig, axes = _figure(2)
    for ax in axes:
        for i in range(result.x.shape[1]):
            ax.plot(
                result.t,
                result.e[:, i],
                lw=1.4,
                label=rf"$e_{{{i + 1}}}${_unit(result, 'state', i)}",
            )
    _windows(result, axes)
    _mark_stop(result, axes)
    for ax in axes:
        _autoscale_visible(ax, result.t, result.e, [0.0])
    axes[0].set_ylabel(r"estimation error $e = x - \hat{x}$" + _unit(result, "state"))
    _legend(fig, axes)
    return fig


def _log_magnitude(values: np.ndarray) -> np.ndarray:
    """``|values|`` with exact zeros (a full-state observer's error) left out of a log plot."""
    mags = np.abs(np.asarray(values, dtype=float))
    return np.where(mags > 0, mags, np.nan)


def plot_estimation_error_log(result: SimulationResult) -> Figure:
    """``|e_i|`` on a log scale over the whole run: the observer's convergence rate.

    Exact zeros (a full-state observer) are left out.
    """
    fig, (ax,) = _figure(1, width=6.0, height=3.2)
    for i in range(result.x.shape[1]):
        ax.semilogy(
            result.t,
            _log_magnitude(result.e[:, i]),
            lw=1.3,
            label=rf"$|e_{{{i + 1}}}|${_unit(result, 'state', i)}",
        )
    _windows(result, [ax])
    _mark_stop(result, [ax])
    shade_numerical_floor(
        ax, numerical_floor(result.t, result.e), getattr(result, "integrator", {}).get("accuracy")
    )
    ax.set_ylabel(r"$|e_i| = |x_i - \hat{x}_i|$")
    _legend(fig, [ax])
    return fig


def plot_weights(result: SimulationResult, labels: Sequence[str] | None = None) -> Figure:
    """Critic weights ``W(t)`` (the paper's Fig. 4), legend to the right if many."""
    fig, (ax,) = _figure(1, width=7.0, height=3.2)
    for k in range(result.W.shape[1]):
        name = _math_label(labels[k]) if labels is not None else None
        label = rf"$\hat{{W}}_{{{k + 1}}}$" + (f" ({name})" if name else "")
        ax.plot(result.t, result.W[:, k], lw=1.4, label=label)
    _windows(result, [ax])
    _mark_stop(result, [ax])
    ax.set_ylabel(r"critic weights $\hat{W}_c$")
    _legend(fig, [ax])
    return fig


def _input_levels(result: SimulationResult, input_bound: float | None) -> list[float]:
    """The lines of ``|u - u*| <= lambda_bar`` (``u* = 0`` without an equilibrium)."""
    if input_bound is None:
        return []
    u_eq = _equilibrium(result, "u")
    centers = np.zeros(1) if u_eq is None else np.unique(u_eq)
    return [float(c + s * input_bound) for c in centers for s in (-1, 1)]


def _input_label(result: SimulationResult) -> str:
    unit = _unit(result, "input")
    if _equilibrium(result, "u") is None:
        return r"control input $u$" + unit
    return r"input $u$ ($|u - u^*| \leq \bar\lambda$)" + unit


def _input_lines(result: SimulationResult, ax: Axes, input_bound: float | None) -> None:
    u = _shown(result, "u")
    for k in range(u.shape[1]):
        ax.plot(
            result.t,
            u[:, k],
            lw=1.4,
            color=f"C{k}",
            label=rf"$u_{{{k + 1}}}${_unit(result, 'input', k)}",
        )
    around = "" if _equilibrium(result, "u") is None else "u^* "
    for j, level in enumerate(_input_levels(result, input_bound)):
        ax.axhline(
            level,
            color="k",
            lw=0.8,
            ls=":",
            label=rf"${around}\pm\bar{{\lambda}}$, $\bar{{\lambda}} = {input_bound:g}$"
            if j == 0 and around
            else (rf"$\pm\bar{{\lambda}} = \pm{input_bound:g}$" if j == 0 else "_bound"),
        )


def plot_input(result: SimulationResult, input_bound: float | None = None) -> Figure:
    """The saturated input ``u(t)`` (the paper's Fig. 5) with ``+-lambda_bar``: transient, run."""
    fig, axes = _figure(2)
    for ax in axes:
        _input_lines(result, ax, input_bound)
    _windows(result, axes)
    _mark_stop(result, axes)
    for ax in axes:
        _autoscale_visible(ax, result.t, _shown(result, "u"), _input_levels(result, input_bound))
    axes[0].set_ylabel(_input_label(result))
    _legend(fig, axes)
    return fig


def plot_learning_condition(result: SimulationResult) -> Figure:
    """``c(t) = lambda_min((1/N) sum omega omega^T / rho^2)`` (Assumption 2)."""
    fig, (ax,) = _figure(1, width=6.0, height=3.2)
    ax.plot(result.t, result.learning_condition, lw=1.4, color="C3")
    _windows(result, [ax])
    _mark_stop(result, [ax])
    ax.set_ylabel(r"learning condition $c(t)$")
    ax.set_ylim(bottom=0)
    _legend(fig, [ax])
    return fig


def plot_cost(result: SimulationResult) -> Figure:
    """Accumulated cost ``J(t)``."""
    fig, (ax,) = _figure(1, width=6.0, height=3.2)
    ax.plot(result.t, result.cost, lw=1.4, color="C4")
    _windows(result, [ax])
    _mark_stop(result, [ax])
    ax.set_ylabel(r"cost $J(t)=\int_0^t Q(x)+U(u)\,d\tau$")
    _legend(fig, [ax])
    return fig


def plot_learning_curve(
    entries: Sequence[dict],
    *,
    optimal_cost: float | None = None,
    lqr_cost: float | None = None,
) -> Figure:
    """The policy in force at each checkpoint, evaluated alone (true state, critic frozen).

    ``entries`` are :func:`ofrl_drake.learning_curve.learning_curve`'s. With
    ``J*`` the axis is ``J / J*``; ``lqr_cost`` adds the LQR policy's cost as
    a reference line. A checkpoint whose policy diverged is marked at the top.
    """
    fig, (ax,) = _figure(1, width=6.0, height=3.4)
    t = np.array([e["t"] for e in entries], dtype=float)
    cost = np.array([np.nan if e["policy_cost"] is None else e["policy_cost"] for e in entries])
    scale = optimal_cost if optimal_cost is not None and np.isfinite(optimal_cost) else 1.0
    ax.plot(t, cost / scale, "o-", lw=1.4, color="C0", label="policy in force at t")
    if lqr_cost is not None and np.isfinite(lqr_cost):
        ax.axhline(lqr_cost / scale, color="C2", ls="--", lw=1.0, label="LQR policy")
    if scale != 1.0:
        ax.axhline(1.0, color="k", ls=":", lw=1.0, label=r"$J^*$")
        ax.set_ylabel(r"policy cost $J/J^*$ from $x_0$")
    else:
        ax.set_ylabel(r"policy cost $J$ from $x_0$")
    diverged = ~np.isfinite(cost)
    if np.any(diverged):
        top = np.nanmax(cost / scale) if np.any(~diverged) else 1.0
        ax.plot(t[diverged], np.full(diverged.sum(), top), "x", color="C3", label="diverged")
    ax.set_xlabel("checkpoint time t [s]")
    _legend(fig, [ax])
    return fig


def plot_learning_health(health: LearningHealth) -> Figure:
    """c(t), Gamma's norm and condition, the value's eigenvalues, the linearized loop.

    ``health`` is a :class:`ofrl_drake.learning_curve.LearningHealth`. Policy
    updates are marked on the last panel: accepted (green ticks) and rejected
    (red crosses).
    """
    panels = 3 + (health.value_eigenvalues is not None) + (health.spectral_abscissa is not None)
    with plt.rc_context(_STYLE):
        fig, axes = plt.subplots(
            panels, 1, figsize=(6.5, 1.9 * panels), layout="constrained", sharex=True
        )
    axes = list(np.atleast_1d(axes))
    ax = axes[0]
    ax.semilogy(health.t, np.maximum(health.learning_condition, 1e-300), color="C3")
    ax.set_ylabel(r"$c(t)$")
    ax = axes[1]
    ax.semilogy(health.t, health.gamma_norm, color="C0")
    ax.set_ylabel(r"$\|\Gamma\|_2$")
    ax = axes[2]
    ax.semilogy(health.t, health.gamma_condition, color="C1")
    ax.set_ylabel(r"cond$(\Gamma)$")
    k = 3
    if health.value_eigenvalues is not None:
        ax = axes[k]
        ax.plot(health.t, health.value_eigenvalues, lw=1.0)
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_yscale("symlog", linthresh=1e-2)
        ax.set_ylabel("eig $P(W)$")
        k += 1
    if health.spectral_abscissa is not None:
        ax = axes[k]
        ax.plot(health.t, health.spectral_abscissa, color="C4", label="policy in force")
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_ylabel(r"abscissa of $A+BK$")
    last = axes[-1]
    for i, times in enumerate((health.accepted_times, health.rejected_times)):
        if times:
            marker, color = ("|", "C2") if i == 0 else ("x", "C3")
            label = "update accepted" if i == 0 else "update rejected"
            y = np.full(len(times), last.get_ylim()[1])
            last.plot(times, y, marker, color=color, ls="none", ms=8, label=label)
    last.set_xlabel("t [s]")
    _legend(fig, axes)
    return fig


def plot_comparison(results: dict, key: str = "x", component: int = 0) -> Figure:
    """One signal of several runs in one plot, e.g. a block swap against the baseline."""
    fig, axes = _figure(2)
    first = next(iter(results.values()))
    for ax in axes:
        for label, result in results.items():
            data = getattr(result, key)
            y = data if data.ndim == 1 else data[:, component]
            ax.plot(result.t, y, lw=1.4, label=label)
    _windows(first, axes)
    names = {"x": "x", "xhat": r"\hat{x}", "e": "e", "u": "u", "W": r"\hat{W}"}
    if key in names:
        axes[0].set_ylabel(f"${names[key]}_{{{component + 1}}}$")
    else:
        axes[0].set_ylabel(key.replace("_", " "))
    _legend(fig, axes)
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

    Raises
    ------
    ModelError
        If the columns of ``gains`` are not three equal blocks
        (:func:`~ofrl_drake.observer.unpack_gains`).
    """
    from ofrl_drake.observer import unpack_gains

    # Each gain's n q entries as one column of k = n q rows (n and q are not needed).
    k = gains.shape[1] // 3
    parts = [gain[..., 0] for gain in unpack_gains(gains, k, 1)]
    with plt.rc_context(_STYLE):
        fig, axes = plt.subplots(3, 1, sharex=True, figsize=(7.0, 6.4), layout="constrained")
    for ax, name, part in zip(axes, ("L", "H", "K"), parts, strict=True):
        for j in range(k):
            ax.step(t, part[:, j], where="post", lw=1.4, label=rf"${name}_{{{j + 1}}}$")
        if np.any(failed):
            ax.plot(t[failed], part[failed, 0], "kx", ms=4, label="re-solve failed")
        ax.set_ylabel(f"gain ${name}$")
        with plt.rc_context(_STYLE):
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), ncols=1, fontsize=8)
    axes[-1].set_xlabel(r"time $t$ [s]")
    return fig


def plot_overview(
    result: SimulationResult, input_bound: float | None = None, box: Box | None = None
) -> Figure:
    """Four panels: states and estimates (transient, with the box), ``|e_i|`` on a log
    scale, critic weights, input (transient, with ``+-lambda_bar``)."""
    with plt.rc_context(_STYLE):
        fig, axes = plt.subplots(2, 2, figsize=(10.0, 6.0), layout="constrained")
    zoom = transient_end(result)
    horizon = float(result.t[-1]) if result.t.size else 0.0
    n = result.x.shape[1]

    ax = axes[0, 0]
    x, xhat = _shown(result, "x"), _shown(result, "xhat")
    if _equilibrium(result, "x") is not None:
        box = None  # its bounds differ per state in the plant's coordinates: see state_i.png
    for i in range(n):
        (line,) = ax.plot(
            result.t, x[:, i], lw=1.5, label=rf"$x_{{{i + 1}}}${_unit(result, 'state', i)}"
        )
        ax.plot(
            result.t,
            xhat[:, i],
            lw=1.3,
            ls="--",
            color=line.get_color(),
            label=rf"$\hat{{x}}_{{{i + 1}}}$",
        )
    if box is not None:
        for k, bound in enumerate((min(box[0]), max(box[1]))):
            ax.axhline(bound, color="0.35", lw=0.9, ls="-.", label="box" if k == 0 else "_box")
    where = "" if _equilibrium(result, "x") is None else ", plant coordinates"
    ax.set_ylabel(f"state (solid), estimate (dashed){where}")
    ax.set_title(f"first {zoom:.3g} s", fontsize=9)
    if zoom > 0:
        ax.set_xlim(0.0, zoom)
    _autoscale_visible(
        ax,
        result.t,
        np.concatenate([x, xhat], axis=1),
        [] if box is None else [min(box[0]), max(box[1])],
    )

    ax = axes[0, 1]
    for i in range(n):
        ax.semilogy(result.t, _log_magnitude(result.e[:, i]), lw=1.3, label=rf"$|e_{{{i + 1}}}|$")
    ax.set_ylabel(r"$|x_i - \hat{x}_i|$")
    ax.set_title(f"whole run ({horizon:.3g} s)", fontsize=9)
    shade_numerical_floor(
        ax, numerical_floor(result.t, result.e), getattr(result, "integrator", {}).get("accuracy")
    )

    ax = axes[1, 0]
    for k in range(result.W.shape[1]):
        ax.plot(result.t, result.W[:, k], lw=1.3, label=rf"$\hat{{W}}_{{{k + 1}}}$")
    ax.set_ylabel(r"critic weights $\hat{W}_c$")
    ax.set_title(f"whole run ({horizon:.3g} s)", fontsize=9)

    ax = axes[1, 1]
    _input_lines(result, ax, input_bound)
    ax.set_ylabel(_input_label(result))
    ax.set_title(f"first {zoom:.3g} s", fontsize=9)
    if zoom > 0:
        ax.set_xlim(0.0, zoom)
    _autoscale_visible(ax, result.t, _shown(result, "u"), _input_levels(result, input_bound))
    if horizon > 0:
        axes[0, 1].set_xlim(0.0, horizon)
        axes[1, 0].set_xlim(0.0, horizon)
    _mark_stop(result, list(axes.flat))
    for ax in axes.flat:
        ax.set_xlabel(r"time $t$ [s]")
        with plt.rc_context(_STYLE):
            ax.legend(
                loc="upper left",
                bbox_to_anchor=(1.01, 1.0),
                ncols=1,
                fontsize=8,
                handlelength=1.5,
            )
    return fig


def save_figures(
    result: SimulationResult,
    directory: str | Path,
    *,
    input_bound: float | None = None,
    weight_labels: Sequence[str] | None = None,
    box: Box | None = None,
    dpi: int = 200,
    learning_curve: Sequence[dict] | None = None,
    optimal_cost: float | None = None,
    lqr_cost: float | None = None,
    health: LearningHealth | None = None,
) -> list[Path]:
    """Write every figure of ``result`` as PNG into ``directory``; return the paths.

    ``box`` is the observer box ``(lower, upper)``, drawn on the state plots.
    ``learning_curve`` (with ``optimal_cost``, ``lqr_cost``) adds
    ``learning_curve.png``; ``health`` adds ``learning_health.png``. Each
    figure is titled with the scenario's name.

    Warns
    -----
    MissingGlyphWarning
        Once per figure whose text (the scenario's name) has characters its
        font cannot draw (:func:`save_png`).
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    # Each figure is drawn, saved and closed in turn: one open at a time, whatever n.
    figures: dict[str, Callable[[], Figure]] = {
        f"state_{i + 1}": functools.partial(plot_state, result, i, box)
        for i in range(result.x.shape[1])
    }
    figures["estimation_error"] = lambda: plot_estimation_error(result)
    figures["estimation_error_log"] = lambda: plot_estimation_error_log(result)
    figures["critic_weights"] = lambda: plot_weights(result, weight_labels)
    figures["control_input"] = lambda: plot_input(result, input_bound)
    figures["learning_condition"] = lambda: plot_learning_condition(result)
    figures["cost"] = lambda: plot_cost(result)
    figures["overview"] = lambda: plot_overview(result, input_bound, box)
    if learning_curve:
        figures["learning_curve"] = lambda: plot_learning_curve(
            learning_curve, optimal_cost=optimal_cost, lqr_cost=lqr_cost
        )
    if health is not None:
        figures["learning_health"] = lambda: plot_learning_health(health)
    extra = getattr(result, "extra", {})
    if "observer_gains" in extra:
        failed = extra.get("solve_failed", np.zeros((result.t.size, 1)))[:, 0] > 0.5
        figures["gain_schedule"] = lambda: plot_gain_schedule(
            result.t, extra["observer_gains"], failed
        )
    title = getattr(result, "scenario_name", "")
    paths = []
    for name, draw in figures.items():
        fig = draw()
        if title:  # in the corner, clear of the legends above the axes
            fig.text(0.998, 0.002, title, ha="right", va="bottom", fontsize=7, color="0.45")
        path = directory / f"{name}.png"
        save_png(fig, path, dpi)
        paths.append(path)
    return paths


class MissingGlyphWarning(UserWarning):
    """A figure's text has characters its font lacks; they are drawn as empty boxes.

    :func:`save_png` warns once per figure, in place of matplotlib's warning
    for every character at every drawing pass (a scenario named in CJK script
    printed about 40 of them per run).

    Attributes
    ----------
    characters : str
        The missing characters, each once, in the order they were drawn.
    fonts : str
        The font(s) matplotlib looked in, as it names them (``DejaVu Sans``).
    path : pathlib.Path
        The figure's file.
    """

    def __init__(self, characters: str, fonts: str, path: Path) -> None:
        super().__init__(
            f"{Path(path).name}: the font ({fonts}) has no glyph for {characters!r}, drawn as "
            "empty boxes; use other characters, or set matplotlib's font.family to a font "
            "that has them."
        )
        self.characters = characters
        self.fonts = fonts
        self.path = Path(path)

    def __reduce__(self) -> tuple[type[MissingGlyphWarning], tuple[str, str, Path]]:
        return type(self), (self.characters, self.fonts, self.path)


#: matplotlib's warning for one character its font lacks (``Glyph 20498 (\N{CJK UNIFIED
#: IDEOGRAPH-5012}) missing from font(s) DejaVu Sans.``).
_MISSING_GLYPH = re.compile(r"Glyph (\d+) \(.*\) missing from font\(s\) (.+?)\.?$")


def save_png(fig: Figure, path: Path, dpi: int) -> None:
    """Write ``fig`` to ``path`` as a PNG, whole or not at all, and close it (also on error).

    Characters the font lacks give one :class:`MissingGlyphWarning` for the
    figure; any other warning is issued as it was.

    Warns
    -----
    MissingGlyphWarning
        If the figure's text has characters its font cannot draw.
    """
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.filterwarnings("always", _MISSING_GLYPH.pattern, UserWarning)
            with atomic_file(path, "wb") as fh:
                fig.savefig(fh, dpi=dpi, format="png")
    finally:
        plt.close(fig)
    missing: dict[str, None] = {}  # in the order drawn, each once
    fonts = ""
    for caught_warning in caught:
        glyph = _MISSING_GLYPH.match(str(caught_warning.message))
        if glyph is not None and issubclass(caught_warning.category, UserWarning):
            missing[chr(int(glyph.group(1)))] = None
            fonts = glyph.group(2)
        else:
            warnings.warn_explicit(
                caught_warning.message,
                caught_warning.category,
                caught_warning.filename,
                caught_warning.lineno,
                source=caught_warning.source,
            )
    if missing:
        warnings.warn(MissingGlyphWarning("".join(missing), fonts, path), stacklevel=2)
