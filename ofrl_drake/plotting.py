"""Publication-ready figures of a closed-loop run (the paper's Figs. 1-5 and c(t)).

Every function takes a :class:`~ofrl_drake.SimulationResult` and returns a
matplotlib ``Figure``; :func:`save_figures` writes them all, as PNG (and PDF or
SVG on request, ``formats``), sized for a page (about 7 in wide) or for a
column of a two-column paper (3.5 in wide, text 8-9 pt, ``size="column"``).

Conventions:

* States, inputs and (when they settle early) the critic weights get two
  panels: the first seconds (the transient, up to :func:`transient_end`) and
  the whole horizon; the zoom is left out when it would cover more than half
  the horizon. At column width the two panels sit one above the other.
* The estimation error has a linear plot and a semilog plot of ``|e_i|``, its
  y-limits read from the data (not from round-off samples near zero).
* The observer box is drawn on the state plots, ``+-lambda_bar`` on the input
  plots, each with a legend entry.
* Axis labels are short (symbol and unit); what the plot is (plant
  coordinates, the cost's definition) goes in its title.
* Legends sit outside the axes (above them, or to the right when there are many
  entries), so they never cover data; one entry per state, input or weight.
  Figures with different panels give each panel its own legend.
* The critic's weights are ``W`` (``W_k`` each), as in ``trajectories.npz``.
* A run stopped by the guard (:mod:`ofrl_drake.guard`) is marked where it
  stopped, with a little room after the mark.
* On log plots, the band below the level where a settled signal only shows
  integration error (:func:`numerical_floor`, the sawtooth of an
  error-controlled integrator) is shaded and labelled, so it is not read as
  behaviour. In ``learning_health``, magnitudes that span less than a decade
  are drawn on a linear axis at least 2 % of their size tall, so round-off is
  not drawn as wiggles.
"""

from __future__ import annotations

import functools
import math
import re
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ParamSpec

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.legend import Legend
from matplotlib.ticker import (
    FixedLocator,
    FuncFormatter,
    LogLocator,
    MaxNLocator,
    NullFormatter,
    NullLocator,
)

from ofrl_drake.atomic import atomic_file
from ofrl_drake.errors import OutputError

if TYPE_CHECKING:  # matplotlib >= 3.10 names the rc keys; the annotation only
    from matplotlib.typing import RcKeyType

    from ofrl_drake.guard import StopReport
    from ofrl_drake.learning_curve import LearningHealth
    from ofrl_drake.simulation import SimulationResult

__all__ = [
    "FIGURE_FORMATS",
    "FIGURE_SIZES",
    "MissingGlyphWarning",
    "numerical_floor",
    "plot_comparison",
    "plot_cost",
    "plot_estimation_error",
    "plot_estimation_error_log",
    "plot_gain_schedule",
    "plot_input",
    "plot_learning_condition",
    "plot_learning_curve",
    "plot_learning_health",
    "plot_overview",
    "plot_state",
    "plot_weights",
    "save_figures",
    "save_png",
    "shade_numerical_floor",
    "transient_end",
]

#: The file formats :func:`save_figures` writes (``formats=``).
FIGURE_FORMATS: tuple[str, ...] = ("png", "pdf", "svg")

#: The figure sizes of :func:`save_figures` and every ``plot_*`` (``size=``):
#: ``"page"`` about 7 in wide, ``"column"`` 3.5 in wide with 8-9 pt text.
FIGURE_SIZES: tuple[str, ...] = ("page", "column")

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

#: Most columns of a legend beside the axes; past what they hold, the entries
#: that matter least are left out and one entry counts them (:func:`_trimmed`).
_SIDE_COLUMNS = 2

#: Most entries of a legend above the axes (column width): six rows of four.
_ABOVE_ENTRIES = 24

#: The ``gid`` of the lines that mark something (the observer box, the input
#: bound, where the run stopped): a trimmed legend keeps their entries.
_ANNOTATION = "ofrl-annotation"

#: A legend row's height in font sizes (math text included), and its borders'.
_ROW_HEIGHT = 1.75
_BORDER = 2.0

#: A linear magnitude axis spans at least this fraction of the data's size.
_MIN_RELATIVE_SPAN = 0.02

#: Room after a stop mark, as a fraction of the run's length.
_STOP_MARGIN = 0.03

Box = tuple[Sequence[float], Sequence[float]]

_P = ParamSpec("_P")


@dataclass(frozen=True)
class _Size:
    """Fonts (points) and panel arrangement of one of :data:`FIGURE_SIZES`."""

    name: str
    column: bool  # panels stacked, 3.5 in wide, legends above the panels
    font: float  # axis labels and tick labels
    legend: float  # a figure's legend
    title: float  # panel titles
    dense: float  # the legends beside (or above) each panel
    tag: float  # the scenario's name in the corner

    def rc(self) -> dict[RcKeyType, Any]:
        return {
            **_STYLE,
            "font.size": self.font,
            "legend.fontsize": self.legend,
            "legend.title_fontsize": self.dense,
            "axes.titlesize": self.title,
        }

    def figsize(
        self, page: tuple[float, float], column: tuple[float, float]
    ) -> tuple[float, float]:
        return column if self.column else page


_SIZES = {
    "page": _Size("page", False, font=10.0, legend=9.0, title=9.0, dense=8.0, tag=7.0),
    "column": _Size("column", True, font=8.5, legend=8.0, title=8.0, dense=8.0, tag=8.0),
}

#: savefig's metadata per format: no creation date, so the same run gives the same file.
_METADATA: dict[str, dict[str, Any]] = {"pdf": {"CreationDate": None}, "svg": {"Date": None}}


def _choice(name: str, value: Any, choices: Sequence[str]) -> str:
    """``value`` if it is one of ``choices``; else :class:`OutputError` naming both."""
    if not isinstance(value, str) or value not in choices:
        raise OutputError(
            f"{name}: unknown value {value!r}; choose one of {', '.join(map(repr, choices))}."
        )
    return value


def _size(size: str) -> _Size:
    return _SIZES[_choice("size", size, FIGURE_SIZES)]


def _formats(formats: Sequence[str]) -> list[str]:
    """``formats`` checked, each once, in order (a single name counts as one)."""
    try:
        names = [formats] if isinstance(formats, str) else list(formats)
    except TypeError:
        raise OutputError(
            f"formats: expected a list of format names, e.g. ['pdf', 'svg']; got {formats!r}."
        ) from None
    if not names:
        raise OutputError(
            f"formats: empty, so no figure would be written; give one or more of "
            f"{', '.join(map(repr, FIGURE_FORMATS))}."
        )
    return list(dict.fromkeys(_choice("formats", f, FIGURE_FORMATS) for f in names))


def _styled(draw: Callable[_P, Figure]) -> Callable[_P, Figure]:
    """Draw under the rc settings of the call's ``size=`` (checked first)."""

    @functools.wraps(draw)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> Figure:
        size = _size(kwargs.get("size", "page"))  # type: ignore[arg-type]
        with plt.rc_context(size.rc()):
            return draw(*args, **kwargs)

    return wrapper


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


def _weight_label(k: int, labels: Sequence[str] | None) -> str:
    """``$W_{k+1}$``, with its basis function when ``labels`` names them."""
    name = _math_label(labels[k]) if labels is not None and k < len(labels) else None
    return rf"$W_{{{k + 1}}}$" + (f" ({name})" if name else "")


def _weight_rank(result: SimulationResult, labels: Sequence[str] | None) -> dict[str, float]:
    """Each weight's legend label to its largest ``|W_k(t)|``: a long legend keeps the largest."""
    W = np.abs(np.asarray(result.W, dtype=float))
    peak = np.nan_to_num(W, nan=0.0).max(axis=0) if W.shape[0] else np.zeros(W.shape[1])
    return {_weight_label(k, labels): float(peak[k]) for k in range(W.shape[1])}


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


def _settled_by(
    t: np.ndarray, signals: np.ndarray, fraction: float, minimum: float, tail: float = 0.25
) -> float:
    """A round time 1.5 times past the last time any column of ``signals`` is unsettled.

    A column is unsettled while ``|s|`` is above ``fraction`` of its peak and
    above twice its level over the last ``tail`` of the run (the 99th
    percentile there, when that is at most half the peak): a signal kept up
    by noise settles when it reaches the noise, not never; one that is still
    large at the end (growing) never settles. At least ``minimum``, at most
    the horizon.
    """
    horizon = float(t[-1]) if t.size else 0.0
    if t.size == 0:
        return 0.0
    mags = np.abs(np.asarray(signals, dtype=float)).reshape(t.size, -1)
    finite = np.where(np.isfinite(mags), mags, 0.0)
    peak = finite.max(axis=0)
    in_tail = t >= t[0] + (1.0 - tail) * (t[-1] - t[0])
    level = np.percentile(finite[in_tail], 99, axis=0) if in_tail.any() else np.zeros_like(peak)
    noise = np.where(2.0 * level <= 0.5 * peak, 2.0 * level, 0.0)  # a signal still large at
    threshold = np.maximum(fraction * peak, noise)  # the end (growing) has no noise floor
    above = np.flatnonzero(np.any(finite > threshold, axis=1))
    last = float(t[above[-1]]) if above.size else 0.0
    return min(horizon, _nice_ceiling(max(minimum, 1.5 * last)))


def transient_end(result: SimulationResult, fraction: float = 0.02, minimum: float = 0.5) -> float:
    """End of the zoomed panel: where x and e have settled.

    1.5 times the last time any ``|x_i|`` or ``|e_i|`` is above ``fraction`` of
    its largest value (and above twice its level over the last quarter of the
    run, so measurement noise does not count as a transient), rounded up, at
    least ``minimum`` seconds, at most the horizon. The figures leave the zoom
    out when it would cover more than half the horizon.
    """
    t = np.asarray(result.t, dtype=float)
    return _settled_by(t, np.concatenate([result.x, result.e], axis=1), fraction, minimum)


def _zoom(t: np.ndarray, end: float) -> float | None:
    """``end`` if a zoom on ``[0, end]`` is worth a panel (at most half the run), else None."""
    horizon = float(t[-1]) if np.size(t) else 0.0
    return end if 0.0 < end <= 0.5 * horizon else None


def _transient_zoom(result: SimulationResult) -> float | None:
    return _zoom(np.asarray(result.t), transient_end(result))


def _transient_figure(
    result: SimulationResult, size: _Size
) -> tuple[float | None, Figure, list[Axes]]:
    """The transient zoom of ``result`` (None: none) and a figure of one panel per window.

    Two panels, the first for ``[0, zoom]`` (:func:`_windows`), when there is a
    zoom; one for the whole run otherwise.
    """
    zoom = _transient_zoom(result)
    fig, axes = _figure(size, 1 if zoom is None else 2)
    return zoom, fig, axes


def _weights_zoom(result: SimulationResult) -> float | None:
    """The zoom on the critic weights when they settle within the first half of the run."""
    t = np.asarray(result.t, dtype=float)
    if t.size == 0:
        return None
    moved = np.asarray(result.W, dtype=float) - np.asarray(result.W, dtype=float)[-1]
    if not np.any(np.abs(moved) > 0):  # weights that never moved have no transient
        return None
    return _zoom(t, _settled_by(t, moved, 0.02, 0.1))


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


def _figure(
    size: _Size,
    panels: int = 1,
    *,
    page: tuple[float, float] = (7.0, 3.0),
    column: tuple[float, float] | None = None,
) -> tuple[Figure, list[Axes]]:
    """A figure of ``panels`` axes: side by side on a page, stacked in a column.

    ``column`` defaults to 3.5 in wide, 2.4 in per panel and 0.6 in for the legend.
    """
    if column is None:
        column = (3.5, 0.6 + 1.8 * panels)
    rows, cols = (panels, 1) if size.column else (1, panels)
    fig, axes = plt.subplots(
        rows, cols, figsize=size.figsize(page, column), layout="constrained", squeeze=False
    )
    return fig, list(axes.flat)


def _entries(axes: Sequence[Axes]) -> tuple[list[Any], list[str]]:
    """The axes' legend handles and labels, each label once, ``_hidden`` ones left out."""
    handles: list[Any] = []
    labels: list[str] = []
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            if lab not in labels and not lab.startswith("_"):
                handles.append(h)
                labels.append(lab)
    return handles, labels


def _side_rows(height_in: float, fontsize: float, title: bool = False) -> int:
    """Legend rows that fit beside axes ``height_in`` inches tall."""
    rows = int((72.0 * height_in / fontsize - _BORDER) // _ROW_HEIGHT) - int(title)
    return max(rows, 2)


def _trimmed(
    handles: list[Any], labels: list[str], room: int, rank: dict[str, float] | None
) -> tuple[list[Any], list[str]]:
    """At most ``room`` entries, in their order: the marks, then the series of highest ``rank``.

    The entries of lines marked :data:`_ANNOTATION` (the observer box, the
    input bound, the stop line) are always kept. Of the series, those of
    highest ``rank`` (label to importance, e.g. a weight's peak ``|W|``; a
    label it does not name counts least) are kept, or the first ones without
    a ``rank``. When entries are left out, the last one kept says how many
    (``and 66 more``), drawn as a blank handle.
    """
    if len(handles) <= room:
        return handles, labels
    from matplotlib.lines import Line2D

    marks = [
        i for i, h in enumerate(handles) if getattr(h, "get_gid", lambda: None)() == _ANNOTATION
    ]
    series = [i for i in range(len(labels)) if i not in marks]
    if rank is not None:
        series.sort(key=lambda i: -rank.get(labels[i], -math.inf))
    chosen = sorted(marks + series[: max(room - 1 - len(marks), 0)])
    more = Line2D([], [], linestyle="none", label="_more")
    return (
        [handles[i] for i in chosen] + [more],
        [labels[i] for i in chosen] + [f"and {len(labels) - len(chosen)} more"],
    )


def _side_legend(
    owner: Figure | Axes,
    handles: list[Any],
    labels: list[str],
    rows: int,
    rank: dict[str, float] | None,
    **kwargs: Any,
) -> Legend:
    """A legend beside the axes in as few columns as hold it, at most :data:`_SIDE_COLUMNS`."""
    handles, labels = _trimmed(handles, labels, rows * _SIDE_COLUMNS, rank)
    ncols = math.ceil(len(handles) / rows)
    return owner.legend(handles, labels, ncols=ncols, **kwargs)


def _fitted(fig: Figure, make: Callable[[int], Legend], count: int) -> Legend:
    """The legend of fewest rows that fits the figure's width, its rows filled evenly.

    ``make(ncols)`` draws it in ``ncols`` columns; of the column counts
    giving those rows, the smallest is taken (4 entries: 2 x 2, not 3 + 1).
    """
    for ncols in range(count, 1, -1):
        legend = make(ncols)
        if legend.get_window_extent().width <= 0.98 * fig.bbox.width:
            even = math.ceil(count / math.ceil(count / ncols))
            if even == ncols:
                return legend
            legend.remove()
            return make(even)
        legend.remove()
    return make(1)


def _legend(
    fig: Figure,
    axes: Sequence[Axes],
    size: _Size,
    *,
    title: str | None = None,
    rank: dict[str, float] | None = None,
) -> None:
    """One legend for the figure, outside the axes: above, or right if long (on a page).

    At column width it is always above, in as many columns as fit. Beside
    the axes it takes as many columns as its entries need (at most
    :data:`_SIDE_COLUMNS`), above them at most :data:`_ABOVE_ENTRIES`; past
    that, series are left out as :func:`_trimmed` says (the lowest ``rank``,
    label to importance, or the last), and the legend says how many.
    """
    handles, labels = _entries(axes)
    if not handles:
        return
    if len(handles) > _MANY and not size.column:
        rows = _side_rows(fig.get_size_inches()[1], size.legend, title is not None)
        _side_legend(fig, handles, labels, rows, rank, loc="outside right upper", title=title)
        return
    handles, labels = _trimmed(handles, labels, _ABOVE_ENTRIES, rank)
    _fitted(
        fig,
        lambda ncols: fig.legend(handles, labels, loc="outside upper center", ncols=ncols),
        len(handles),
    )


def _panel_legend(
    ax: Axes, size: _Size, *, title: str | None = None, rank: dict[str, float] | None = None
) -> None:
    """This panel's legend outside it, with its ``title`` (what the panel shows).

    On a page: the title above the panel, the legend to its right, one entry a
    row (two columns when the panel's height needs them). At column width:
    the legend above the panel in as many columns as fit, titled with
    ``title``. Entries past what that holds are left out as in :func:`_legend`.
    """
    handles, labels = _entries([ax])
    fig = ax.get_figure()
    assert isinstance(fig, Figure)
    if not size.column or not handles:
        if title:
            ax.set_title(title, fontsize=size.title)
        if handles:
            height = fig.get_size_inches()[1] * ax.get_position().height
            _side_legend(
                ax,
                handles,
                labels,
                _side_rows(height, size.dense),
                rank,
                loc="upper left",
                bbox_to_anchor=(1.01, 1.0),
                fontsize=size.dense,
                handlelength=1.5,
                columnspacing=1.0,
            )
        return
    handles, labels = _trimmed(handles, labels, _ABOVE_ENTRIES, rank)
    _fitted(
        fig,
        lambda ncols: ax.legend(
            handles,
            labels,
            loc="lower center",
            bbox_to_anchor=(0.5, 1.0),
            ncols=ncols,
            fontsize=size.dense,
            title=title,
            title_fontsize=size.title,
            handlelength=1.5,
            columnspacing=1.0,
        ),
        len(handles),
    )


def _horizon(t: np.ndarray) -> float:
    return float(t[-1]) if np.size(t) else 0.0


def _whole(ax: Axes, t: np.ndarray, stop: StopReport | None) -> None:
    """x limits of the whole run, with a little room after a stop mark."""
    horizon = _horizon(t)
    if horizon <= 0:
        return
    stopped = stop is not None and not stop.ok
    ax.set_xlim(0.0, horizon * (1.0 + _STOP_MARGIN) if stopped else horizon)


def _windows(
    result: SimulationResult,
    axes: Sequence[Axes],
    size: _Size,
    zoom: float | None,
    note: str = "",
) -> list[str]:
    """x limits and the panels' titles: the first on ``[0, zoom]``, the last the whole run.

    Returns each panel's title (``note`` appended, e.g. ``"plant coordinates"``);
    a lone panel is titled ``note`` only. The caller shows them
    (:func:`_panel_legend` or ``set_title``).
    """
    t = np.asarray(result.t)
    horizon = _horizon(t)
    stop = getattr(result, "stop", None)
    _whole(axes[-1], t, stop)
    for ax in axes:
        ax.set_xlabel(r"time $t$ [s]")
    if size.column:  # 3.5 in: at most six time labels
        for ax in axes:
            ax.xaxis.set_major_locator(MaxNLocator(nbins=5, steps=[1, 2, 2.5, 5, 10]))
    tail = f", {note}" if note else ""
    if len(axes) > 1 and zoom is not None:
        axes[0].set_xlim(0.0, zoom)
        return [f"first {zoom:.3g} s{tail}", f"whole run ({horizon:.3g} s){tail}"]
    return [note] * len(axes)


def _titles(axes: Sequence[Axes], titles: Sequence[str], size: _Size) -> None:
    for ax, title in zip(axes, titles, strict=True):
        if title:
            ax.set_title(title, fontsize=size.title)


def _ylabel(axes: Sequence[Axes], label: str, size: _Size) -> None:
    """The y label on the first panel (side by side) or on each (stacked)."""
    for ax in axes if size.column else axes[:1]:
        ax.set_ylabel(label)


def _mark_stop(
    stop: StopReport | None, axes: Sequence[Axes], *, labelled: int | None = None
) -> None:
    """A vertical line where the guard stopped the run, with a legend entry.

    ``labelled``: the index of the only axes whose line has the entry (all of them if None).
    """
    if stop is None or stop.ok:
        return
    for k, ax in enumerate(axes):
        name = f"run stopped ({stop.status})"
        ax.axvline(
            stop.time,
            color="C3",
            lw=1.3,
            ls=":",
            label=name if labelled is None or k == labelled % len(axes) else "_stop",
            gid=_ANNOTATION,
        )


def _box_lines(ax: Axes, levels: Sequence[float]) -> None:
    """The observer box's bounds at ``levels``, one legend entry for them."""
    for k, bound in enumerate(levels):
        ax.axhline(
            bound,
            color="0.35",
            lw=0.9,
            ls="-.",
            label="observer box" if k == 0 else "_box",
            gid=_ANNOTATION,
        )


def _overview_box(ax: Axes, box: Box | None) -> list[float]:
    """The observer box on the overview's panel of every state; returns its levels.

    One gray pair of lines when every state has the same bounds; otherwise each
    state's bounds in its own color (one band over all of them would put a
    state outside its box inside the band drawn).
    """
    if box is None:
        return []
    lower, upper = (np.asarray(b, dtype=float) for b in box)
    if np.all(lower == lower[0]) and np.all(upper == upper[0]):
        _box_lines(ax, [lower[0], upper[0]])
        return [float(lower[0]), float(upper[0])]
    colors = [line.get_color() for line in ax.get_lines()[::2]]  # x_i, then xhat_i
    for i, bounds in enumerate(zip(lower, upper, strict=True)):
        for bound in bounds:
            ax.axhline(bound, color=colors[i], lw=0.8, ls="-.", alpha=0.8, label="_box")
    ax.plot(
        [],
        [],
        color="0.35",
        lw=0.9,
        ls="-.",
        label="observer box (each state's color)",
        gid=_ANNOTATION,
    )
    return [float(lower.min()), float(upper.max())]


def _stop(result: SimulationResult) -> StopReport | None:
    return getattr(result, "stop", None)


def _autoscale_visible(ax: Axes, t: np.ndarray, data: np.ndarray, extra: Sequence[float]) -> None:
    """y limits from the samples inside the x window (and ``extra`` levels)."""
    lo, hi = ax.get_xlim()
    inside = (t >= lo) & (t <= hi)
    values = np.concatenate([np.ravel(data[inside]), np.asarray(extra, float)])
    values = values[np.isfinite(values)]
    if values.size:
        pad = 0.05 * (values.max() - values.min()) or 0.5
        ax.set_ylim(values.min() - pad, values.max() + pad)


def _log_limits(ax: Axes, magnitudes: np.ndarray) -> None:
    """Log y limits from the data: its 1st percentile (not a round-off sample) to its peak."""
    values = np.asarray(magnitudes, dtype=float).ravel()
    values = values[np.isfinite(values) & (values > 0)]
    if values.size == 0:
        return
    low, high = float(np.percentile(values, 1)), float(values.max())
    if high <= low:
        low, high = high / 10.0, high * 10.0
    # A run stopped near 1e308 would ask for an infinite limit, and matplotlib's log
    # ticks overflow a little below the largest float: keep the axis within 1e+-300.
    top = min(high * 2.0, 1e300)
    ax.set_ylim(min(max(low / 2.0, 1e-300), top / 10.0), top)


def _log_tick(value: float, _position: Any = None) -> str:
    """A log axis' tick: ``50``, ``200`` for plain sizes; 2 x 10^6 in mathtext for the others."""
    if not value > 0:
        return ""
    if 1e-3 <= value < 1e4:
        return f"{value:g}"
    exponent = math.floor(math.log10(value) + 1e-9)
    mantissa = round(value / 10.0**exponent, 6)
    power = f"10^{{{exponent}}}"
    return f"${power}$" if mantissa == 1 else f"${mantissa:g}\\times{power}$"


def _magnitude_axis(ax: Axes, values: np.ndarray) -> None:
    """Log if positive data span a decade or more; else linear with a minimum span.

    On the linear axis the y limits span at least ``_MIN_RELATIVE_SPAN``
    of the data's size, so round-off (a condition number flat to 1e-10) is
    drawn flat, and its tick labels differ.
    """
    data = np.asarray(values, dtype=float).ravel()
    data = data[np.isfinite(data)]
    if data.size == 0:
        return
    lo, hi = float(data.min()), float(data.max())
    if lo > 0 and hi >= 10.0 * lo:
        ax.set_yscale("log")
        ax.set_ylim(lo / 1.5, hi * 1.5)
        if hi < 100.0 * lo:  # few decades: label 1, 2, 5 times a power of ten, nothing else
            ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            ax.yaxis.set_major_formatter(FuncFormatter(_log_tick))
            ax.yaxis.set_minor_formatter(NullFormatter())
        return
    least = _MIN_RELATIVE_SPAN * max(abs(lo), abs(hi))
    if hi - lo < least:
        middle = 0.5 * (lo + hi)
        lo, hi = middle - 0.5 * least, middle + 0.5 * least
    elif hi > lo:
        pad = 0.08 * (hi - lo)
        lo, hi = lo - pad, hi + pad
    else:  # all zero
        lo, hi = -1.0, 1.0
    ax.set_ylim(lo, hi)
    ax.yaxis.set_major_locator(MaxNLocator(nbins=4))


def _symlog_axis(ax: Axes, values: np.ndarray, max_ticks: int = 7) -> None:
    """A symmetric log axis for values of either sign: decades, at most ``max_ticks`` labelled.

    The linear band around 0 reaches the 5th percentile of ``|values|`` (at
    most six decades below the largest), so a small eigenvalue stays visibly
    off 0.
    """
    data = np.abs(np.asarray(values, dtype=float).ravel())
    data = data[np.isfinite(data) & (data > 0)]
    if data.size == 0:
        ax.set_yscale("symlog", linthresh=1.0)
        return
    top = float(data.max())
    linthresh = 10.0 ** math.floor(math.log10(max(float(np.percentile(data, 5)), 1e-6 * top)))
    ax.set_yscale("symlog", linthresh=linthresh)
    raw = np.asarray(values, dtype=float)
    finite = raw[np.isfinite(raw)]
    low = round(math.log10(linthresh))

    def decades(largest: float) -> list[float]:
        if not largest > 0:
            return []
        return [10.0**d for d in range(low, math.ceil(math.log10(largest)) + 1)]

    positive, negative = decades(float(finite.max())), decades(float(-finite.min()))
    ticks = sorted([*(-v for v in negative), 0.0, *positive])
    stride = math.ceil(len(ticks) / max_ticks)
    zero = ticks.index(0.0)
    kept = [v for k, v in enumerate(ticks) if (k - zero) % stride == 0]
    ax.yaxis.set_major_locator(FixedLocator(kept))
    ax.yaxis.set_minor_locator(NullLocator())


@_styled
def plot_state(
    result: SimulationResult, i: int, box: Box | None = None, *, size: str = "page"
) -> Figure:
    """``x_i`` and ``xhat_i`` against time (the paper's Figs. 1 and 2), with the box.

    Left (above, at column width): the transient; right: the whole run. With
    an equilibrium, states are shown in the plant's own coordinates (said in
    the titles), with ``x*_i`` and the box (given relative to x*, as in the
    scenario) shifted by it.

    Raises
    ------
    OutputError
        If ``size`` is not one of :data:`FIGURE_SIZES`.
    """
    sz = _size(size)
    zoom, fig, axes = _transient_figure(result, sz)
    x, xhat = _shown(result, "x")[:, i], _shown(result, "xhat")[:, i]
    x_eq = _equilibrium(result, "x")
    shift = 0.0 if x_eq is None else float(x_eq[i])
    levels = [] if box is None else [box[0][i] + shift, box[1][i] + shift]
    for ax in axes:
        ax.plot(result.t, x, lw=1.6, color="C0", label=rf"$x_{{{i + 1}}}$")
        ax.plot(result.t, xhat, lw=1.4, ls="--", color="C1", label=rf"$\hat{{x}}_{{{i + 1}}}$")
        if x_eq is not None:
            ax.axhline(shift, color="k", lw=0.8, ls=":", label=rf"$x^*_{{{i + 1}}}$ (equilibrium)")
        _box_lines(ax, levels)
    titles = _windows(result, axes, sz, zoom, "" if x_eq is None else "plant coordinates")
    _mark_stop(_stop(result), axes)
    both = np.stack([x, xhat], axis=1)
    for ax in axes:
        _autoscale_visible(ax, result.t, both, levels)
    _titles(axes, titles, sz)
    unit = _unit(result, "state", i)
    _ylabel(axes, rf"$x_{{{i + 1}}}$, $\hat{{x}}_{{{i + 1}}}${unit}", sz)
    _legend(fig, axes, sz)
    return fig


@_styled
def plot_estimation_error(result: SimulationResult, *, size: str = "page") -> Figure:
    """``e = x - xhat`` per component (the paper's Fig. 3): transient and whole run.

    Raises
    ------
    OutputError
        If ``size`` is not one of :data:`FIGURE_SIZES`.
    """
    sz = _size(size)
    zoom, fig, axes = _transient_figure(result, sz)
    for ax in axes:
        for i in range(result.x.shape[1]):
            ax.plot(
                result.t,
                result.e[:, i],
                lw=1.4,
                label=rf"$e_{{{i + 1}}}${_unit(result, 'state', i)}",
            )
    titles = _windows(result, axes, sz, zoom)
    _mark_stop(_stop(result), axes)
    for ax in axes:
        _autoscale_visible(ax, result.t, result.e, [0.0])
    _titles(axes, titles, sz)
    _ylabel(axes, r"$e = x - \hat{x}$" + _unit(result, "state"), sz)
    _legend(fig, axes, sz)
    return fig


def _log_magnitude(values: np.ndarray) -> np.ndarray:
    """``|values|`` with exact zeros (a full-state observer's error) left out of a log plot."""
    mags = np.abs(np.asarray(values, dtype=float))
    return np.where(mags > 0, mags, np.nan)


def _error_log_panel(result: SimulationResult, ax: Axes, units: bool) -> None:
    """``|e_i|`` on a log axis over the whole run, y limits from the data, floor shaded."""
    mags = _log_magnitude(result.e)
    for i in range(result.x.shape[1]):
        unit = _unit(result, "state", i) if units else ""
        ax.semilogy(result.t, mags[:, i], lw=1.3, label=rf"$|e_{{{i + 1}}}|${unit}")
    _log_limits(ax, mags)
    shade_numerical_floor(
        ax, numerical_floor(result.t, result.e), getattr(result, "integrator", {}).get("accuracy")
    )


@_styled
def plot_estimation_error_log(result: SimulationResult, *, size: str = "page") -> Figure:
    """``|e_i|`` on a log scale over the whole run: the observer's convergence rate.

    Exact zeros (a full-state observer) are left out; the y axis starts at
    the data's 1st percentile, so a few round-off samples (an error that is
    exactly 0 at t = 0 but for the last bit) do not stretch it.

    Raises
    ------
    OutputError
        If ``size`` is not one of :data:`FIGURE_SIZES`.
    """
    sz = _size(size)
    fig, (ax,) = _figure(sz, 1, page=(6.0, 3.2), column=(3.5, 2.6))
    _windows(result, [ax], sz, None)
    _error_log_panel(result, ax, units=True)
    _mark_stop(_stop(result), [ax])
    ax.set_ylabel(r"$|e_i| = |x_i - \hat{x}_i|$")
    _legend(fig, [ax], sz)
    return fig


@_styled
def plot_weights(
    result: SimulationResult, labels: Sequence[str] | None = None, *, size: str = "page"
) -> Figure:
    """Critic weights ``W(t)`` (the paper's Fig. 4), legend to the right if many.

    When the weights settle within the first half of the run, a panel zooms
    on that part (as the state plots do on the transient).

    Raises
    ------
    OutputError
        If ``size`` is not one of :data:`FIGURE_SIZES`.
    """
    sz = _size(size)
    zoom = _weights_zoom(result)
    panels = 1 if zoom is None else 2
    fig, axes = _figure(sz, panels, page=(7.0, 3.2), column=(3.5, 1.0 + 1.8 * panels))
    for ax in axes:
        for k in range(result.W.shape[1]):
            ax.plot(result.t, result.W[:, k], lw=1.4, label=_weight_label(k, labels))
    titles = _windows(result, axes, sz, zoom)
    _mark_stop(_stop(result), axes)
    for ax in axes:
        _autoscale_visible(ax, result.t, result.W, [])
    _titles(axes, titles, sz)
    _ylabel(axes, r"critic weights $W$", sz)
    _legend(fig, axes, sz, rank=_weight_rank(result, labels))
    return fig


def _input_levels(result: SimulationResult, input_bound: float | None) -> list[float]:
    """The lines of ``|u - u*| <= lambda_bar`` (``u* = 0`` without an equilibrium)."""
    if input_bound is None:
        return []
    u_eq = _equilibrium(result, "u")
    centers = np.zeros(1) if u_eq is None else np.unique(u_eq)
    return [float(c + s * input_bound) for c in centers for s in (-1, 1)]


def _input_label(result: SimulationResult) -> str:
    return r"input $u$" + _unit(result, "input")


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
            gid=_ANNOTATION,
        )


@_styled
def plot_input(
    result: SimulationResult, input_bound: float | None = None, *, size: str = "page"
) -> Figure:
    """The saturated input ``u(t)`` (the paper's Fig. 5) with ``+-lambda_bar``: transient, run.

    With an equilibrium, ``u`` is in the plant's own coordinates (said in the
    titles) and the bound is drawn around ``u*``.

    Raises
    ------
    OutputError
        If ``size`` is not one of :data:`FIGURE_SIZES`.
    """
    sz = _size(size)
    zoom, fig, axes = _transient_figure(result, sz)
    for ax in axes:
        _input_lines(result, ax, input_bound)
    note = "" if _equilibrium(result, "u") is None else "plant coordinates"
    titles = _windows(result, axes, sz, zoom, note)
    _mark_stop(_stop(result), axes)
    for ax in axes:
        _autoscale_visible(ax, result.t, _shown(result, "u"), _input_levels(result, input_bound))
    _titles(axes, titles, sz)
    _ylabel(axes, _input_label(result), sz)
    _legend(fig, axes, sz)
    return fig


@_styled
def plot_learning_condition(result: SimulationResult, *, size: str = "page") -> Figure:
    """``c(t) = lambda_min((1/N) sum omega omega^T / rho^2)`` (Assumption 2).

    Raises
    ------
    OutputError
        If ``size`` is not one of :data:`FIGURE_SIZES`.
    """
    fig = _one_series(
        result, result.learning_condition, "C3", r"$c(t)$", "learning condition", size
    )
    fig.axes[0].set_ylim(bottom=0)
    return fig


@_styled
def plot_cost(result: SimulationResult, *, size: str = "page") -> Figure:
    """Accumulated cost ``J(t)``, its definition in the title.

    Raises
    ------
    OutputError
        If ``size`` is not one of :data:`FIGURE_SIZES`.
    """
    title = r"$J(t)=\int_0^t Q(x)+U(u)\,d\tau$"
    return _one_series(result, result.cost, "C4", r"cost $J(t)$", title, size)


def _one_series(
    result: SimulationResult, y: np.ndarray, color: str, ylabel: str, title: str, size: str
) -> Figure:
    """One logged scalar over the whole run, in one panel, the stop marked."""
    sz = _size(size)
    fig, (ax,) = _figure(sz, 1, page=(6.0, 3.2), column=(3.5, 2.4))
    ax.plot(result.t, y, lw=1.4, color=color)
    _windows(result, [ax], sz, None)
    _mark_stop(_stop(result), [ax])
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=sz.title)
    _legend(fig, [ax], sz)
    return fig


@_styled
def plot_learning_curve(
    entries: Sequence[dict],
    *,
    optimal_cost: float | None = None,
    lqr_cost: float | None = None,
    size: str = "page",
) -> Figure:
    """The policy in force at each checkpoint, evaluated alone (true state, critic frozen).

    ``entries`` are :func:`ofrl_drake.learning_curve.learning_curve`'s. With
    ``J*`` the axis is ``J / J*``; ``lqr_cost`` adds the LQR policy's cost as
    a reference line. A checkpoint whose policy diverged has no cost: it is
    marked with a cross near the top of the axes (at its time, at no cost
    value), and a curve with no finite cost says so instead of a y axis.

    Raises
    ------
    OutputError
        If ``size`` is not one of :data:`FIGURE_SIZES`.
    """
    sz = _size(size)
    fig, (ax,) = _figure(sz, 1, page=(6.0, 3.4), column=(3.5, 2.6))
    t = np.array([e["t"] for e in entries], dtype=float)
    cost = np.array(
        [np.nan if e["policy_cost"] is None else e["policy_cost"] for e in entries], dtype=float
    )
    relative = optimal_cost is not None and math.isfinite(optimal_cost) and optimal_cost > 0
    scale = float(optimal_cost) if relative and optimal_cost else 1.0
    finite = np.isfinite(cost)
    if np.any(finite):
        ax.plot(t, cost / scale, "o-", lw=1.4, color="C0", label=r"policy in force at $t$")
    if lqr_cost is not None and np.isfinite(lqr_cost):
        ax.axhline(lqr_cost / scale, color="C2", ls="--", lw=1.0, label="LQR policy")
    if relative:
        ax.axhline(1.0, color="k", ls=":", lw=1.0, label=r"$J^*$")
        ax.set_ylabel(r"policy cost $J/J^*$ from $x_0$")
    else:
        ax.set_ylabel(r"policy cost $J$ from $x_0$")
    if np.any(~finite):
        if np.any(finite) or ax.lines:  # room above the costs for the crosses
            low, high = ax.get_ylim()
            ax.set_ylim(low, low + (high - low) / 0.85)
        else:
            ax.set_yticks([])
            ax.text(
                0.5,
                0.5,
                "no checkpoint's policy has a finite cost",
                transform=ax.transAxes,
                ha="center",
                va="center",
                color="0.3",
            )
        ax.plot(
            t[~finite],
            np.full(int(np.sum(~finite)), 0.93),
            "x",
            color="C3",
            ms=8,
            transform=ax.get_xaxis_transform(),
            label="policy diverged (no cost)",
        )
    if t.size and np.ptp(t) == 0:
        ax.set_xlim(t[0] - 1.0, t[0] + 1.0)
    ax.set_xlabel(r"checkpoint time $t$ [s]")
    _legend(fig, [ax], sz)
    return fig


def _eigenvalue_labels(n: int) -> list[str]:
    """``lambda_min ... lambda_max``; with more than four, the middle ones as one entry."""
    if n == 1:
        return [r"$\lambda$"]
    middle = [rf"$\lambda_{{{k + 1}}}$" for k in range(1, n - 1)]
    if n > 4:
        middle = ["other eigenvalues"] + ["_other"] * (n - 3)
    return [r"$\lambda_{\min}$", *middle, r"$\lambda_{\max}$"]


@_styled
def plot_learning_health(
    health: LearningHealth, *, stop: StopReport | None = None, size: str = "page"
) -> Figure:
    """c(t), Gamma's norm and condition, the value's eigenvalues, the linearized loop.

    ``health`` is a :class:`ofrl_drake.learning_curve.LearningHealth`; ``stop``
    the run's :attr:`~ofrl_drake.SimulationResult.stop`, marked on every panel.
    Magnitudes spanning a decade or more are on a log axis, the others on a
    linear one (round-off drawn flat). Policy updates are marked in a strip
    below the panels, by time only: accepted (green ticks) and rejected
    (red crosses). Each panel has its own legend.

    Raises
    ------
    OutputError
        If ``size`` is not one of :data:`FIGURE_SIZES`.
    """
    sz = _size(size)
    kinds = ["c", "norm", "cond"]
    if health.value_eigenvalues is not None:
        kinds.append("eig")
    if health.spectral_abscissa is not None:
        kinds.append("abscissa")
    strip = bool(health.accepted_times or health.rejected_times)
    n = len(kinds)
    fig, axes_array = plt.subplots(
        n + strip,
        1,
        figsize=sz.figsize((6.5, 1.9 * n + 0.5 * strip), (3.5, 0.5 + 1.45 * n + 0.5 * strip)),
        layout="constrained",
        sharex=True,
        squeeze=False,
        gridspec_kw={"height_ratios": [1.0] * n + [0.28] * strip},
    )
    axes: list[Axes] = list(axes_array[:, 0])
    panels = dict(zip(kinds, axes, strict=False))
    t = np.asarray(health.t, dtype=float)
    for kind, series, color, label in (
        ("c", health.learning_condition, "C3", r"$c(t)$"),
        ("norm", health.gamma_norm, "C0", r"$\|\Gamma\|_2$"),
        ("cond", health.gamma_condition, "C1", r"cond$(\Gamma)$"),
    ):
        ax = panels[kind]
        ax.plot(t, series, color=color, lw=1.4)
        _magnitude_axis(ax, series)
        ax.set_ylabel(label)
    if health.value_eigenvalues is not None:
        ax = panels["eig"]
        eig = np.asarray(health.value_eigenvalues, dtype=float)
        labels = _eigenvalue_labels(eig.shape[1])
        for j, label in enumerate(labels):
            middle = 0 < j < eig.shape[1] - 1 and eig.shape[1] > 4
            ax.plot(
                t,
                eig[:, j],
                lw=0.8 if middle else 1.2,
                color="0.6" if middle else None,
                label=label,
            )
        ax.axhline(0.0, color="k", lw=0.6)
        _symlog_axis(ax, eig)
        ax.set_ylabel("eig $P(W)$")
    if health.spectral_abscissa is not None:
        ax = panels["abscissa"]
        ax.plot(t, health.spectral_abscissa, color="C4", lw=1.4, label="policy in force")
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_ylabel(r"abscissa of $A+BK$")
    if strip:
        ax = axes[-1]
        for times, marker, color, label in (
            (health.accepted_times, "|", "C2", "update accepted"),
            (health.rejected_times, "x", "C3", "update rejected"),
        ):
            if times:
                ax.plot(
                    times,
                    np.full(len(times), 0.5),
                    marker,
                    color=color,
                    ls="none",
                    ms=7,
                    transform=ax.get_xaxis_transform(),
                    label=label,
                )
        ax.set_ylim(0.0, 1.0)
        ax.set_yticks([])
        ax.grid(False, axis="y")
        ax.set_ylabel("policy\nupdates", rotation=0, ha="right", va="center")
    _mark_stop(stop, axes, labelled=-1)
    _whole(axes[-1], t, stop)
    axes[-1].set_xlabel(r"time $t$ [s]")
    for ax in axes:
        _panel_legend(ax, sz)
    return fig


@_styled
def plot_comparison(
    results: dict, key: str = "x", component: int = 0, *, size: str = "page"
) -> Figure:
    """One signal of several runs in one plot, e.g. a block swap against the baseline.

    Raises
    ------
    OutputError
        If ``size`` is not one of :data:`FIGURE_SIZES`.
    """
    sz = _size(size)
    first = next(iter(results.values()))
    zoom, fig, axes = _transient_figure(first, sz)
    for ax in axes:
        for label, result in results.items():
            data = getattr(result, key)
            y = data if data.ndim == 1 else data[:, component]
            ax.plot(result.t, y, lw=1.4, label=label)
    _titles(axes, _windows(first, axes, sz, zoom), sz)
    names = {"x": "x", "xhat": r"\hat{x}", "e": "e", "u": "u", "W": "W"}
    if key in names:
        _ylabel(axes, f"${names[key]}_{{{component + 1}}}$", sz)
    else:
        _ylabel(axes, key.replace("_", " "), sz)
    _legend(fig, axes, sz)
    return fig


@_styled
def plot_gain_schedule(
    t: np.ndarray, gains: np.ndarray, failed: np.ndarray, *, size: str = "page"
) -> Figure:
    """Scheduled observer gains L, H and K over time; failed re-solves marked.

    Parameters
    ----------
    t : ndarray, shape (T,)
    gains : ndarray, shape (T, 3 n q)
        The ``observer_gains`` log, ``[vec(L), vec(H), vec(K)]`` row-major.
    failed : ndarray of bool, shape (T,)
        True where the latest re-solve failed (previous gains kept).
    size : {"page", "column"}

    Raises
    ------
    ModelError
        If the columns of ``gains`` are not three equal blocks
        (:func:`~ofrl_drake.observer.unpack_gains`).
    OutputError
        If ``size`` is not one of :data:`FIGURE_SIZES`.
    """
    from ofrl_drake.observer import unpack_gains

    sz = _size(size)
    # Each gain's n q entries as one column of k = n q rows (n and q are not needed).
    k = gains.shape[1] // 3
    parts = [gain[..., 0] for gain in unpack_gains(gains, k, 1)]
    fig, axes = plt.subplots(
        3, 1, sharex=True, figsize=sz.figsize((7.0, 6.4), (3.5, 6.0)), layout="constrained"
    )
    for ax, name, part in zip(axes, ("L", "H", "K"), parts, strict=True):
        for j in range(k):
            ax.step(t, part[:, j], where="post", lw=1.4, label=rf"${name}_{{{j + 1}}}$")
        if np.any(failed):
            ax.plot(t[failed], part[failed, 0], "kx", ms=4, label="re-solve failed")
        ax.set_ylabel(f"gain ${name}$")
        _panel_legend(ax, sz)
    axes[-1].set_xlabel(r"time $t$ [s]")
    return fig


@_styled
def plot_overview(
    result: SimulationResult,
    input_bound: float | None = None,
    box: Box | None = None,
    weight_labels: Sequence[str] | None = None,
    *,
    size: str = "page",
) -> Figure:
    """Four panels: states and estimates (transient, with the box), ``|e_i|`` on a log
    scale, critic weights (their transient when they settle early), input
    (transient, with ``+-lambda_bar``).

    With an equilibrium the states are drawn as ``x - x*`` and ``xhat - x*``
    (the axis says so), so that angles near pi do not flatten the rest; the
    box, given relative to x*, is then drawn as it is. At column width the
    panels are stacked.

    Raises
    ------
    OutputError
        If ``size`` is not one of :data:`FIGURE_SIZES`.
    """
    sz = _size(size)
    rows, cols = (4, 1) if sz.column else (2, 2)
    fig, axes_array = plt.subplots(
        rows, cols, figsize=sz.figsize((10.0, 6.0), (3.5, 9.0)), layout="constrained"
    )
    axes: list[Axes] = list(axes_array.flat)
    t = np.asarray(result.t)
    zoom = _transient_zoom(result)
    horizon = _horizon(t)
    stop = _stop(result)
    whole = f"whole run ({horizon:.3g} s)"
    first = whole if zoom is None else f"first {zoom:.3g} s"
    n = result.x.shape[1]
    relative = _equilibrium(result, "x") is not None

    ax = axes[0]
    for i in range(n):
        (line,) = ax.plot(
            result.t, result.x[:, i], lw=1.5, label=rf"$x_{{{i + 1}}}${_unit(result, 'state', i)}"
        )
        ax.plot(
            result.t,
            result.xhat[:, i],
            lw=1.3,
            ls="--",
            color=line.get_color(),
            label=rf"$\hat{{x}}_{{{i + 1}}}$",
        )
    levels = _overview_box(ax, box)
    ax.set_ylabel(r"$x - x^*$, $\hat{x} - x^*$" if relative else r"$x$, $\hat{x}$")
    if zoom is not None:
        ax.set_xlim(0.0, zoom)
    else:
        _whole(ax, t, stop)
    _autoscale_visible(ax, t, np.concatenate([result.x, result.xhat], axis=1), levels)
    titles = [first]

    ax = axes[1]
    _whole(ax, t, stop)
    _error_log_panel(result, ax, units=False)
    ax.set_ylabel(r"$|x_i - \hat{x}_i|$")
    titles.append(whole)

    ax = axes[2]
    weights_zoom = _weights_zoom(result)
    for k in range(result.W.shape[1]):
        ax.plot(result.t, result.W[:, k], lw=1.3, label=_weight_label(k, weight_labels))
    ax.set_ylabel(r"critic weights $W$")
    if weights_zoom is not None:
        ax.set_xlim(0.0, weights_zoom)
        _autoscale_visible(ax, t, result.W, [])
        titles.append(f"first {weights_zoom:.3g} s")
    else:
        _whole(ax, t, stop)
        titles.append(whole)

    ax = axes[3]
    _input_lines(result, ax, input_bound)
    ax.set_ylabel(_input_label(result))
    if zoom is not None:
        ax.set_xlim(0.0, zoom)
    else:
        _whole(ax, t, stop)
    _autoscale_visible(ax, t, _shown(result, "u"), _input_levels(result, input_bound))
    titles.append(first)

    _mark_stop(stop, axes)
    # A long legend keeps the first states and the largest weights (and the marks).
    ranks = [None, None, _weight_rank(result, weight_labels), None]
    for ax, title, rank in zip(axes, titles, ranks, strict=True):
        ax.set_xlabel(r"time $t$ [s]")
        _panel_legend(ax, sz, title=title, rank=rank)
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
    formats: Sequence[str] = ("png",),
    size: str = "page",
) -> list[Path]:
    """Write every figure of ``result`` into ``directory``; return the paths.

    ``box`` is the observer box ``(lower, upper)``, drawn on the state plots.
    ``learning_curve`` (with ``optimal_cost``, ``lqr_cost``) adds
    ``learning_curve``; ``health`` adds ``learning_health``. Each figure is
    tagged with the scenario's name in its corner.

    Parameters
    ----------
    formats : sequence of str, optional
        Any of :data:`FIGURE_FORMATS` (``"png"``, ``"pdf"``, ``"svg"``): each
        figure is written once per format, ``<name>.<format>``, each file
        whole or not at all. ``dpi`` applies to PNG (and to images inside
        the vector formats). Default PNG only; a single name (``"pdf"``)
        counts as one.
    size : {"page", "column"}, optional
        ``"page"`` (default): about 7 in wide (the overview 10 in), 10 pt
        text. ``"column"``: 3.5 in wide, text 8-9 pt, panels stacked.

    Returns
    -------
    list of pathlib.Path
        Every file written, figure by figure, in the order of ``formats``.

    Raises
    ------
    OutputError
        If ``formats`` is empty, not a list, or names a format not in
        :data:`FIGURE_FORMATS`,
        if ``size`` is not one of :data:`FIGURE_SIZES` (both before anything
        is drawn), or if a file cannot be written.

    Warns
    -----
    MissingGlyphWarning
        Once per figure whose text (the scenario's name) has characters its
        font cannot draw (:func:`save_png`).
    """
    kinds = _formats(formats)
    sz = _size(size)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    # Each figure is drawn, saved and closed in turn: one open at a time, whatever n.
    figures: dict[str, Callable[[], Figure]] = {
        f"state_{i + 1}": functools.partial(plot_state, result, i, box, size=size)
        for i in range(result.x.shape[1])
    }
    figures["estimation_error"] = lambda: plot_estimation_error(result, size=size)
    figures["estimation_error_log"] = lambda: plot_estimation_error_log(result, size=size)
    figures["critic_weights"] = lambda: plot_weights(result, weight_labels, size=size)
    figures["control_input"] = lambda: plot_input(result, input_bound, size=size)
    figures["learning_condition"] = lambda: plot_learning_condition(result, size=size)
    figures["cost"] = lambda: plot_cost(result, size=size)
    figures["overview"] = lambda: plot_overview(result, input_bound, box, weight_labels, size=size)
    if learning_curve:
        figures["learning_curve"] = lambda: plot_learning_curve(
            learning_curve, optimal_cost=optimal_cost, lqr_cost=lqr_cost, size=size
        )
    if health is not None:
        figures["learning_health"] = lambda: plot_learning_health(
            health, stop=_stop(result), size=size
        )
    extra = getattr(result, "extra", {})
    if "observer_gains" in extra:
        failed = extra.get("solve_failed", np.zeros((result.t.size, 1)))[:, 0] > 0.5
        figures["gain_schedule"] = lambda: plot_gain_schedule(
            result.t, extra["observer_gains"], failed, size=size
        )
    title = getattr(result, "scenario_name", "")
    paths: list[Path] = []
    for name, draw in figures.items():
        fig = draw()
        targets = [(directory / f"{name}.{kind}", kind) for kind in kinds]
        with plt.rc_context(sz.rc()):
            if title:  # a footer of its own, clear of the axes' labels and the legends
                fig.supxlabel(title, x=0.998, ha="right", fontsize=sz.tag, color="0.45")
            _save(fig, targets, dpi, stacklevel=3)
        paths.extend(path for path, _ in targets)
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
        The figure's file (the first, when it is written in several formats).
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

#: Fonts embedded as TrueType (Type 42) in PDF and PostScript, not as Type 3,
#: which some publishers' PDF checks refuse.
_VECTOR_FONTS: dict[RcKeyType, Any] = {"pdf.fonttype": 42, "ps.fonttype": 42}


def save_png(fig: Figure, path: Path, dpi: int) -> None:
    """Write ``fig`` to ``path`` as a PNG, whole or not at all, and close it (also on error).

    Characters the font lacks give one :class:`MissingGlyphWarning` for the
    figure; any other warning is issued as it was.

    Warns
    -----
    MissingGlyphWarning
        If the figure's text has characters its font cannot draw.
    """
    _save(fig, [(path, "png")], dpi, stacklevel=3)


def _save(fig: Figure, targets: Sequence[tuple[Path, str]], dpi: int, *, stacklevel: int) -> None:
    """Write ``fig`` to each ``(path, format)``, each whole or not at all; close it.

    One :class:`MissingGlyphWarning` for the figure, however many formats,
    issued ``stacklevel`` frames up from here.
    """
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.filterwarnings("always", _MISSING_GLYPH.pattern, UserWarning)
            with plt.rc_context(_VECTOR_FONTS):
                for path, kind in targets:
                    with atomic_file(path, "wb") as fh:
                        fig.savefig(fh, dpi=dpi, format=kind, metadata=_METADATA.get(kind))
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
        warnings.warn(
            MissingGlyphWarning("".join(missing), fonts, targets[0][0]), stacklevel=stacklevel
        )
