"""Figures fit for a paper: zoom, box, labelled bounds, legends off the data, error floor."""

import dataclasses
import math
import re
import warnings
from unittest import mock

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.legend import Legend
from matplotlib.text import Text

from ofrl_drake import plotting
from ofrl_drake.errors import OutputError
from ofrl_drake.guard import StopReport
from ofrl_drake.learning_curve import LearningHealth
from ofrl_drake.plotting import (
    numerical_floor,
    plot_comparison,
    plot_cost,
    plot_estimation_error,
    plot_estimation_error_log,
    plot_input,
    plot_learning_condition,
    plot_learning_curve,
    plot_learning_health,
    plot_overview,
    plot_state,
    plot_weights,
    save_figures,
    transient_end,
)
from ofrl_drake.simulation import SimulationResult


def _result(n=2, m=1, L=3, T=30.0, samples=1501, sawtooth=1e-6):
    """A synthetic run: x and e decay at 3/s onto a sawtooth floor of ``sawtooth``."""
    t = np.linspace(0.0, T, samples)
    decay = np.exp(-3.0 * t)[:, None]
    saw = sawtooth * (1.0 + (t % 2.0) / 2.0)[:, None]
    x = np.maximum(decay * np.linspace(1.0, 2.0, n), saw)
    e = np.maximum(decay * np.linspace(0.5, 1.5, n), saw)
    return SimulationResult(
        t=t,
        x=x,
        xhat=x - e,
        W=np.tile(np.linspace(0.1, 1.0, L), (samples, 1)),
        W_policy=np.tile(np.linspace(0.1, 1.0, L), (samples, 1)),
        Gamma=np.tile(np.eye(L), (samples, 1, 1)),
        u=-2.5 * np.tile(decay, (1, m)),
        learning_condition=np.full(samples, 0.1),
        cost=1.0 - decay[:, 0],
        integrator={"accuracy": 1e-4},
    )


def _legends(fig):
    return [*fig.legends, *(ax.get_legend() for ax in fig.axes if ax.get_legend() is not None)]


def _assert_legends_outside_axes(fig):
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    legends = _legends(fig)
    assert legends, "the figure has no legend"
    for legend in legends:
        box = legend.get_window_extent(renderer)
        for ax in fig.axes:
            overlap = box.intersection(box, ax.get_window_extent(renderer))
            assert overlap is None or overlap.width * overlap.height < 1.0, (
                f"legend {[t.get_text() for t in legend.get_texts()]} covers an axes"
            )


def _labels(fig):
    return [text.get_text() for legend in _legends(fig) for text in legend.get_texts()]


def test_numerical_floor_is_the_settled_sawtooth_not_a_decay():
    r = _result(sawtooth=1e-6)
    assert numerical_floor(r.t, r.e) == pytest.approx(2e-6, rel=1e-2)
    still_decaying = _result(sawtooth=0.0)
    assert numerical_floor(still_decaying.t, still_decaying.e) is None
    slow = np.exp(-0.5 * r.t)  # halves every 1.4 s: still decaying over the tail
    assert numerical_floor(r.t, slow) is None
    never_settles = 1.0 + np.sin(r.t)
    assert numerical_floor(r.t, never_settles) is None


def test_transient_end_is_a_round_number_past_the_transient():
    r = _result()
    end = transient_end(r)
    # |x| and |e| fall below 2 % of their peak near t = ln(50)/3 = 1.3 s.
    assert end == 2.0
    assert end < r.t[-1]


def test_state_plot_zooms_draws_the_box_and_keeps_its_legend_off_the_data():
    r = _result()
    fig = plot_state(r, 0, box=([-2.0, -2.0], [2.0, 2.0]))
    zoom, whole = fig.axes
    assert zoom.get_xlim() == (0.0, 2.0)
    assert whole.get_xlim() == (0.0, 30.0)
    levels = {tuple(line.get_ydata()) for line in zoom.get_lines() if line.get_linestyle() == "-."}
    assert levels == {(-2.0, -2.0), (2.0, 2.0)}
    assert _labels(fig) == ["$x_{1}$", r"$\hat{x}_{1}$", "observer box"]
    _assert_legends_outside_axes(fig)


def test_input_plot_labels_the_bound_once_and_every_input():
    r = _result(n=4, m=2)
    fig = plot_input(r, input_bound=3.0)
    assert _labels(fig) == ["$u_{1}$", "$u_{2}$", r"$\pm\bar{\lambda} = \pm3$"]
    _assert_legends_outside_axes(fig)


def test_semilog_error_plot_shades_the_integrator_floor():
    r = _result()
    fig = plot_estimation_error_log(r)
    (ax,) = fig.axes
    assert ax.get_yscale() == "log"
    assert _labels(fig) == [
        "$|e_{1}|$",
        "$|e_{2}|$",
        r"integrator error floor (accuracy $10^{-4}$)",
    ]
    _assert_legends_outside_axes(fig)


def test_many_weights_get_a_legend_beside_the_axes():
    r = _result(n=4, L=10)
    fig = plot_weights(r, labels=[f"x{i}^2" for i in range(1, 11)])
    assert len(_labels(fig)) == 10
    _assert_legends_outside_axes(fig)


def test_overview_of_a_mimo_run_has_one_entry_per_input_and_no_legend_on_data():
    r = _result(n=4, m=2, L=10)
    fig = plot_overview(r, input_bound=3.0, box=([-2.0] * 4, [2.0] * 4))
    input_axes = fig.axes[3]
    entries = [t.get_text() for t in input_axes.get_legend().get_texts()]
    assert entries == ["$u_{1}$", "$u_{2}$", r"$\pm\bar{\lambda} = \pm3$"]
    assert all(isinstance(lg, Legend) for lg in _legends(fig))
    _assert_legends_outside_axes(fig)


def test_a_stopped_run_is_marked_and_its_figures_are_written(tmp_path):
    r = _result(T=0.5, samples=26)
    r.stop = StopReport(
        "diverged", "x_1 = 30 left the abort box", 0.5, [30.0, 1.0], [0.0, 0.0], 0.1
    )
    fig = plot_state(r, 0)
    assert "run stopped (diverged)" in _labels(fig)
    one_sample = dataclasses.replace(
        r,
        **{k: getattr(r, k)[:1] for k in ("t", "x", "xhat", "W", "Gamma", "u")},
        learning_condition=r.learning_condition[:1],
        cost=r.cost[:1],
    )
    one_sample.stop = dataclasses.replace(r.stop, time=0.0)
    paths = save_figures(one_sample, tmp_path, input_bound=3.0, box=([-2.0] * 2, [2.0] * 2))
    assert {p.name for p in paths} >= {"state_1.png", "estimation_error_log.png", "overview.png"}
    assert all(p.stat().st_size > 0 for p in paths)


def test_axes_carry_the_models_units_and_none_when_unknown():
    r = dataclasses.replace(
        _result(n=4), state_units=("m", "rad", "m/s", "rad/s"), input_units=("N",)
    )
    assert plot_state(r, 0).axes[0].get_ylabel().endswith("[m]")
    assert plot_state(r, 3).axes[0].get_ylabel().endswith("[rad/s]")
    assert plot_input(r, 3.0).axes[0].get_ylabel().endswith("[N]")
    assert "$u_{1}$ [N]" in _labels(plot_input(r, 3.0))
    labels = _labels(plot_estimation_error_log(r))
    assert "$|e_{2}|$ [rad]" in labels and "$|e_{3}|$ [m/s]" in labels
    assert "$x_{1}$ [m]" in _labels(plot_overview(r, 3.0))
    # The paper's toy is dimensionless: no brackets anywhere.
    plain = _result(n=2)
    assert "[" not in plot_state(plain, 0).axes[0].get_ylabel()
    assert "[" not in plot_input(plain, 3.0).axes[0].get_ylabel()


def test_summary_records_the_units():
    r = dataclasses.replace(_result(n=2), state_units=("rad", "rad/s"), input_units=("N·m",))
    assert r.summary()["units"] == {"state": ["rad", "rad/s"], "input": ["N·m"]}
    assert "units" not in _result(n=2).summary()


def test_figures_are_drawn_one_at_a_time_and_none_is_left_open(tmp_path, monkeypatch):
    # Drawing every figure first had 21 open at once for n = 12 (matplotlib warns at 20).
    from matplotlib.figure import Figure

    open_at_save = []
    save = Figure.savefig

    def counting_save(fig, *args, **kwargs):
        open_at_save.append(len(plt.get_fignums()))
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", counting_save)
    plt.close("all")
    r = _result(n=12, T=0.5, samples=26)
    paths = save_figures(r, tmp_path, input_bound=3.0)
    assert len(paths) == len(open_at_save) == 19  # 12 states and 7 other figures
    assert max(open_at_save) == 1 and plt.get_fignums() == []


# --- figures for a paper: labels that fit, honest axes, formats and sizes ---------------

CART_POLE_EQ = np.array([0.0, math.pi, 0.0, 0.0])


def _cart_pole_like(T=20.0, samples=1001):
    """Four states with units about x* = (0, pi, 0, 0), ten weights settling by 0.3 s."""
    r = _result(n=4, m=1, L=10, T=T, samples=samples)
    settle = np.exp(-15.0 * r.t)[:, None]
    W = np.linspace(-200.0, 700.0, 10) * (1.0 + 0.4 * settle)
    return dataclasses.replace(
        r,
        W=W,
        W_policy=W,
        x_equilibrium=CART_POLE_EQ,
        u_equilibrium=np.zeros(1),
        state_units=("m", "rad", "m/s", "rad/s"),
        input_units=("N",),
        scenario_name="cart_pole_real_world",
    )


def _health(t, *, accepted=(), rejected=()):
    """Learning health like cart_pole's: cond(Gamma) flat up to round-off, eig of both signs."""
    rng = np.random.default_rng(0)
    return LearningHealth(
        t=t,
        learning_condition=0.031 + 0.013 * np.exp(-t),  # less than a decade: linear
        gamma_norm=50.0 + 550.0 * (1.0 - np.exp(-t / 5.0)),  # 50..600: log
        gamma_condition=42048.8 * (1.0 + 1e-10 * rng.standard_normal(t.size)),  # round-off
        value_eigenvalues=np.column_stack(
            [-100.0 + 100.05 * (1 - np.exp(-t)), np.full_like(t, 3.0), 30.0 + 0 * t, 1e4 + 0 * t]
        ),
        spectral_abscissa=np.full_like(t, -0.69),
        accepted_times=list(accepted),
        rejected_times=list(rejected),
    )


def _texts(fig):
    """Every non-empty text ``fig`` draws (labels, ticks in view, titles, legends, notes)."""
    drawn = []
    draw = Text.draw

    def recording(text, renderer):
        if text.get_visible() and text.get_text().strip():
            drawn.append(text)
        return draw(text, renderer)

    with mock.patch.object(Text, "draw", recording):
        fig.canvas.draw()
    return drawn


def _all_figures(r, size):
    t = r.t
    kw = {} if size == "page" else {"size": size}  # the page is the default
    entries = [{"t": 0.0, "policy_cost": 12.0}, {"t": 10.0, "policy_cost": None}]
    return {
        "state": plot_state(r, 1, box=([-2.0] * 4, [2.0] * 4), **kw),
        "error": plot_estimation_error(r, **kw),
        "error_log": plot_estimation_error_log(r, **kw),
        "weights": plot_weights(r, [f"x{i}^2" for i in range(1, 11)], **kw),
        "input": plot_input(r, 50.0, **kw),
        "condition": plot_learning_condition(r, **kw),
        "cost": plot_cost(r, **kw),
        "overview": plot_overview(
            r,
            50.0,
            ([-2.0] * 4, [2.0] * 4),
            **kw,
            **({"weight_labels": [f"x{i} x{i}" for i in range(1, 11)]} if kw else {}),
        ),
        "curve": plot_learning_curve(entries, optimal_cost=10.0, lqr_cost=11.0, **kw),
        "health": plot_learning_health(_health(t, rejected=[2.0, 4.0]), **kw),
    }


@pytest.mark.parametrize("size", ["page", "column"])
def test_every_label_fits_inside_its_figure(size):
    # "state x2 and estimate (plant coordinates) [rad]" was taller than the 3 in
    # figure and read "ate x2 and estimate (plant coordinates) [ra".
    r = _cart_pole_like()
    for name, fig in _all_figures(r, size).items():
        box = fig.bbox
        for text in _texts(fig):
            extent = text.get_window_extent()
            inside = (
                extent.x0 >= box.x0 - 1.0
                and extent.y0 >= box.y0 - 1.0
                and extent.x1 <= box.x1 + 1.0
                and extent.y1 <= box.y1 + 1.0
            )
            assert inside, f"{name} ({size}): {text.get_text()!r} is cut off at {extent}"
        plt.close(fig)


def test_plant_coordinates_go_in_the_title_and_the_y_label_stays_short():
    r = _cart_pole_like()
    for ax in plot_state(r, 1).axes:
        assert ax.get_ylabel() in ("", r"$x_{2}$, $\hat{x}_{2}$ [rad]")
        assert "plant coordinates" in ax.get_title()
    assert "plant coordinates" in plot_input(r, 50.0).axes[0].get_title()


def test_column_size_is_3_5_in_wide_with_8_to_9_pt_text_and_legends_off_the_data():
    r = _cart_pole_like()
    for name, fig in _all_figures(r, "column").items():
        assert fig.get_figwidth() == pytest.approx(3.5), name
        sizes = {round(t.get_fontsize(), 2) for t in _texts(fig)}
        assert min(sizes) >= 8.0 and max(sizes) <= 9.0, f"{name}: font sizes {sorted(sizes)}"
        if _legends(fig):
            _assert_legends_outside_axes(fig)
        plt.close(fig)
    # The page size is today's: 7 x 3 in for a state, 10 x 6 in for the overview.
    assert plot_state(_result(), 0).get_size_inches() == pytest.approx((7.0, 3.0))
    assert plot_overview(_result()).get_size_inches() == pytest.approx((10.0, 6.0))


def test_magnitudes_within_a_decade_are_linear_and_round_off_is_drawn_flat():
    t = np.linspace(0.0, 20.0, 1001)
    fig = plot_learning_health(_health(t))
    c_ax, norm_ax, cond_ax, eig_ax, _ = fig.axes
    fig.canvas.draw()
    assert c_ax.get_yscale() == "linear"  # 0.031..0.044: not a log axis
    assert norm_ax.get_yscale() == "log"  # 50..600
    assert cond_ax.get_yscale() == "linear"
    labels = [t.get_text() for t in cond_ax.get_yticklabels() if t.get_text()]
    assert len(labels) >= 2 and len(set(labels)) == len(labels), labels
    # 1e-10 relative noise spans under 1 % of the panel (it spanned all of it).
    lo, hi = cond_ax.get_ylim()
    data = cond_ax.get_lines()[0].get_ydata()
    assert (data.max() - data.min()) / (hi - lo) < 0.01
    # eig P(W) from -100 to 1e4: at most 8 tick labels (the symlog axis had 13).
    assert eig_ax.get_yscale() == "symlog"
    eig_labels = [t.get_text() for t in eig_ax.get_yticklabels() if t.get_text()]
    assert 3 <= len(eig_labels) <= 8, eig_labels
    plt.close(fig)


def test_policy_updates_are_a_strip_by_time_and_each_panel_has_its_own_legend():
    t = np.linspace(0.0, 20.0, 1001)
    fig = plot_learning_health(_health(t, accepted=[1.0], rejected=[2.0, 4.0]))
    assert fig.legends == []  # no figure legend far from its panel
    strip = fig.axes[-1]
    marks = {line.get_label(): line for line in strip.get_lines()}
    assert set(marks) == {"update accepted", "update rejected"}
    for line in marks.values():
        assert line.get_transform() is strip.get_xaxis_transform()  # y in axes coordinates
        assert np.all((line.get_ydata() > 0.0) & (line.get_ydata() < 1.0))
    assert list(marks["update rejected"].get_xdata()) == [2.0, 4.0]
    # No update mark on the spectral abscissa's data axis.
    abscissa = fig.axes[-2]
    assert abscissa.get_lines()[0].get_label() == "policy in force"
    assert not any("update" in line.get_label() for line in abscissa.get_lines())
    for ax in fig.axes:
        legend = ax.get_legend()
        if legend is None:
            continue
        own = {line.get_label() for line in ax.get_lines()}
        assert {text.get_text() for text in legend.get_texts()} <= own
    eig_legend = fig.axes[3].get_legend()
    assert [t.get_text() for t in eig_legend.get_texts()] == [
        r"$\lambda_{\min}$",
        r"$\lambda_{2}$",
        r"$\lambda_{3}$",
        r"$\lambda_{\max}$",
    ]
    _assert_legends_outside_axes(fig)
    plt.close(fig)


def test_a_diverged_checkpoint_is_marked_by_time_not_at_an_invented_cost():
    fig = plot_learning_curve([{"t": 0.0, "policy_cost": None}])
    (ax,) = fig.axes
    (mark,) = [line for line in ax.get_lines() if "diverged" in line.get_label()]
    assert mark.get_transform() is ax.get_xaxis_transform()
    assert list(ax.get_yticks()) == []  # no cost scale for a curve without a cost
    assert any("finite cost" in t.get_text() for t in ax.texts)
    # Beside finite costs, the cross sits above them, in axes coordinates.
    fig = plot_learning_curve(
        [{"t": 0.0, "policy_cost": 4.0}, {"t": 1.0, "policy_cost": None}], optimal_cost=2.0
    )
    (ax,) = fig.axes
    (mark,) = [line for line in ax.get_lines() if "diverged" in line.get_label()]
    assert mark.get_transform() is ax.get_xaxis_transform()
    assert list(mark.get_xdata()) == [1.0]
    plt.close("all")


@pytest.mark.parametrize(
    ("optimal_cost", "ratio"), [(1.0, True), (0.0, False), (math.nan, False), (None, False)]
)
def test_the_learning_curve_is_over_j_star_when_j_star_is_positive(optimal_cost, ratio):
    """Before: a J* of exactly 1 was taken for 'no J*' (the axis said J, no J* line), and
    a J* of 0 divided the costs by it."""
    entries = [{"t": 0.0, "policy_cost": 4.0}, {"t": 1.0, "policy_cost": 2.0}]
    (ax,) = plot_learning_curve(entries, optimal_cost=optimal_cost).axes
    assert ("J/J^*" in ax.get_ylabel()) is ratio
    assert (r"$J^*$" in [line.get_label() for line in ax.get_lines()]) is ratio
    np.testing.assert_array_equal(ax.get_lines()[0].get_ydata(), [4.0, 2.0])
    plt.close("all")


def test_the_zoom_is_dropped_past_half_the_run_and_noise_is_no_transient():
    # x settles at about 13 s of 20: a "first 20 s" zoom was the whole run again.
    r = _result(T=20.0, samples=1001)
    slow = np.exp(-0.3 * r.t)[:, None] * np.array([1.0, 2.0])
    late = dataclasses.replace(r, x=slow, xhat=slow - r.e)
    assert transient_end(late) > 10.0
    fig = plot_state(late, 0)
    assert len(fig.axes) == 1 and fig.axes[0].get_xlim() == (0.0, 20.0)
    # e decays in 1 s onto measurement noise of 1 % of its peak: the zoom ends
    # near the decay, not at the horizon (noise was read as a transient).
    rng = np.random.default_rng(1)
    noisy_e = r.e + 0.01 * rng.standard_normal(r.e.shape)
    noisy = dataclasses.replace(r, xhat=r.x - noisy_e)
    assert transient_end(noisy) <= 3.0
    zoom, whole = plot_state(noisy, 0).axes
    assert zoom.get_xlim()[1] <= 3.0 and whole.get_xlim() == (0.0, 20.0)
    plt.close("all")


def test_the_log_error_axis_starts_at_the_data_not_at_a_round_off_sample():
    r = _result(T=20.0, samples=1001, sawtooth=0.0)
    e = 1e-3 * (1.5 + np.sin(r.t))[:, None] * np.ones(2)  # 5e-4 .. 2.5e-3
    e[0, 1] = 1e-17  # x0 and xhat0 agree in x2 but for the last bit
    fig = plot_estimation_error_log(dataclasses.replace(r, xhat=r.x - e))
    (ax,) = fig.axes
    assert ax.get_yscale() == "log"
    assert ax.get_ylim()[0] > 1e-5, ax.get_ylim()  # reached 1e-17
    plt.close(fig)


def test_weights_that_settle_early_get_a_zoom_and_the_overview_names_them():
    r = _cart_pole_like()
    labels = [f"x{i}^2" for i in range(1, 11)]
    fig = plot_weights(r, labels)
    zoom, whole = fig.axes  # W settles within 0.3 s of 20 s
    assert 0.3 <= zoom.get_xlim()[1] <= 1.0 and whole.get_xlim() == (0.0, 20.0)
    entries = [
        t.get_text() for t in plot_overview(r, 50.0, None, labels).axes[2].get_legend().get_texts()
    ]
    assert entries[0] == "$W_{1}$ ($x_{1}^{2}$)"
    # Weights still moving over the run, or never moving, keep one panel.
    drifting = _result(L=3)
    drifting.W = drifting.W + drifting.t[:, None]
    assert len(plot_weights(drifting).axes) == 1
    assert len(plot_weights(_result(L=3)).axes) == 1
    plt.close("all")


def test_the_overview_draws_states_about_the_equilibrium_and_says_so():
    r = _cart_pole_like()
    ax = plot_overview(r, 50.0, ([-2.0] * 4, [2.0] * 4)).axes[0]
    np.testing.assert_allclose(ax.get_lines()[2].get_ydata(), r.x[:, 1])  # x2 - pi, not x2
    assert "x^*" in ax.get_ylabel()
    assert "observer box" in [t.get_text() for t in ax.get_legend().get_texts()]
    plt.close("all")


def test_the_overview_draws_each_states_own_box():
    """Before: one band from the smallest lower to the largest upper bound (the cart's
    +-2 m) over every state, so a pole angle 1.3 rad off looked inside its +-0.4 rad box."""
    r = _cart_pole_like()
    lower, upper = [-2.0, -0.4, -1.5, -1.5], [2.0, 0.4, 1.5, 1.5]
    ax = plot_overview(r, 50.0, (lower, upper)).axes[0]
    states = ax.get_lines()[:8:2]
    for i, state in enumerate(states):
        levels = sorted(
            line.get_ydata()[0]
            for line in ax.get_lines()[8:]
            if line.get_label() == "_box" and line.get_color() == state.get_color()
        )
        assert levels == [lower[i], upper[i]], i
    assert "observer box (each state's color)" in [
        t.get_text() for t in ax.get_legend().get_texts()
    ]
    plt.close("all")


def test_a_stop_mark_has_room_after_it_and_learning_health_marks_it():
    r = _result(T=2.0, samples=101)
    r.stop = StopReport("diverged", "x_1 left the abort box", 2.0, [30.0, 1.0], [0.0, 0.0], 0.1)
    whole = plot_state(r, 0).axes[-1]
    assert whole.get_xlim()[1] > 2.0 * 1.02  # the line is not on the right edge
    fig = plot_learning_health(_health(r.t), stop=r.stop)
    stops = [line for ax in fig.axes for line in ax.get_lines() if line.get_xdata()[0] == 2.0]
    assert len(stops) == len(fig.axes)
    assert "run stopped (diverged)" in _labels(fig)
    assert fig.axes[-1].get_xlim()[1] > 2.0 * 1.02
    plt.close("all")


def test_the_weights_are_W_in_every_figure():
    r = _result(n=2, L=3)
    figures = [plot_weights(r), plot_overview(r), plot_comparison({"a": r, "b": r}, "W")]
    texts = [t.get_text() for fig in figures for t in _texts(fig)]
    assert not [t for t in texts if r"\hat{W}" in t or r"\hat W" in t]
    assert "$W_{1}$" in texts and r"critic weights $W$" in texts
    plt.close("all")


def test_the_learning_plots_are_public():
    assert {"plot_learning_curve", "plot_learning_health"} <= set(plotting.__all__)
    assert plotting.FIGURE_FORMATS == ("png", "pdf", "svg")
    assert plotting.FIGURE_SIZES == ("page", "column")


def test_save_figures_writes_every_format_and_size(tmp_path):
    from matplotlib.image import imread

    r = _result(T=5.0, samples=251)
    r.scenario_name = "toy"
    default = save_figures(r, tmp_path / "default")
    assert {p.suffix for p in default} == {".png"} and len(default) == 9
    assert imread(tmp_path / "default" / "state_1.png").shape[:2] == (
        600,
        1400,
    )  # 7 x 3 in, 200 dpi
    paths = save_figures(r, tmp_path / "all", formats=("png", "pdf", "svg"), size="column")
    assert len(paths) == 3 * len(default)
    assert {p.stem for p in paths} == {p.stem for p in default}
    assert all(p.is_file() and p.stat().st_size > 0 for p in paths)
    assert (tmp_path / "all" / "overview.pdf").read_bytes().startswith(b"%PDF")
    assert "<svg" in (tmp_path / "all" / "overview.svg").read_text()[:1000]
    assert imread(tmp_path / "all" / "state_1.png").shape[1] == 700  # 3.5 in at 200 dpi
    assert not list((tmp_path / "all").glob(".*"))  # no temporary file left
    # The same run gives the same PDF (no creation date inside).
    again = save_figures(r, tmp_path / "again", formats=["pdf"], size="column")
    assert [p.name for p in again] == [p.name for p in paths if p.suffix == ".pdf"]
    assert (tmp_path / "again" / "cost.pdf").read_bytes() == (
        tmp_path / "all" / "cost.pdf"
    ).read_bytes()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            {"formats": ("png", "jpg")},
            r"formats: unknown value 'jpg'; choose one of 'png', 'pdf', 'svg'",
        ),
        ({"formats": ()}, r"formats: empty, so no figure would be written"),
        ({"formats": None}, r"formats: expected a list of format names.*got None"),
        ({"size": "poster"}, r"size: unknown value 'poster'; choose one of 'page', 'column'"),
        ({"size": None}, r"size: unknown value None"),
    ],
)
def test_an_unknown_format_or_size_is_refused_before_anything_is_written(tmp_path, kwargs, message):
    with pytest.raises(OutputError, match=message):
        save_figures(_result(T=1.0, samples=51), tmp_path / "figs", **kwargs)
    assert not (tmp_path / "figs").exists()
    with pytest.raises(OutputError, match=r"size: unknown value 'A4'"):
        plot_state(_result(), 0, size="A4")


def _inside_figure(fig):
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for legend in _legends(fig):
        box = legend.get_window_extent(renderer)
        assert box.x0 >= -1 and box.y0 >= -1, [t.get_text() for t in legend.get_texts()]
        assert box.x1 <= fig.bbox.width + 1 and box.y1 <= fig.bbox.height + 1, (
            f"legend {[t.get_text() for t in legend.get_texts()][-3:]} runs off the figure"
        )


@pytest.mark.parametrize("size", ["page", "column"])
def test_long_legends_keep_the_largest_weights_and_fit_the_figure(size):
    # Before: the quadrotor's 78 weights and 24 state entries were one legend column
    # each, cut off at the figure's edge, over the next panel, and matplotlib warned
    # "constrained_layout not applied because axes sizes collapsed to zero".
    r = _result(n=12, m=4, L=78)
    scale = np.where(np.arange(78) % 7 == 3, 50.0, 1.0)  # every 7th weight from W4 is large
    stop = StopReport("diverged", "x_1 left the abort box", 20.0, [0.0] * 12, [0.0] * 12, 1.0)
    r = dataclasses.replace(r, W=r.W * scale, W_policy=r.W_policy * scale, stop=stop)
    labels = [f"x{k}" for k in range(1, 79)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the layout warning included
        figures = {
            "weights": plot_weights(r, labels, size=size),
            "overview": plot_overview(r, 3.0, ([-2.0] * 12, [2.0] * 12), labels, size=size),
        }
        for fig in figures.values():
            _assert_legends_outside_axes(fig)
            _inside_figure(fig)
    states = [t.get_text() for t in figures["overview"].axes[0].get_legend().get_texts()]
    assert "observer box" in states and re.fullmatch(r"and \d+ more", states[-1]), states
    big = [k for k in range(78) if k % 7 == 3]  # 12 of them: kept, whatever the room
    for entries in (
        [t.get_text() for t in figures["overview"].axes[2].get_legend().get_texts()],
        _labels(figures["weights"]),
    ):
        kept = [w for w in entries if w.startswith("$W")]
        assert re.fullmatch(r"and \d+ more", entries[-1]), entries
        assert len(kept) + int(entries[-1].split()[1]) == 78
        assert all(any(w.startswith(rf"$W_{{{k + 1}}}$ ") for w in kept) for k in big), kept
        assert "run stopped (diverged)" in entries  # what is not a weight is kept
    assert "run stopped (diverged)" in states
    for fig in figures.values():
        plt.close(fig)


@pytest.mark.parametrize("size", ["page", "column"])
def test_a_trimmed_legend_without_a_ranking_keeps_the_stop_line(size):
    # Before: legends of series in order (|e_i|, e_i) kept their first entries and cut
    # the stop line, drawn last, once a run had about 17 states or more.
    n = 24
    stop = StopReport("diverged", "x_1 left the abort box", 20.0, [0.0] * n, [0.0] * n, 1.0)
    r = dataclasses.replace(_result(n=n, m=1, L=3), stop=stop)
    figures = [
        plot_overview(r, 3.0, ([-2.0] * n, [2.0] * n), size=size),
        plotting.plot_estimation_error(r, size=size),
        plotting.plot_estimation_error_log(r, size=size),
    ]
    trimmed = 0
    for fig in figures:
        texts = _labels(fig)
        trimmed += any(re.fullmatch(r"and \d+ more", t) for t in texts)
        assert "run stopped (diverged)" in texts, texts
        plt.close(fig)
    assert trimmed >= 2  # the overview and the error plot at least
