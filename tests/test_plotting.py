"""Figures fit for a paper: zoom, box, labelled bounds, legends off the data, error floor."""

import dataclasses

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.legend import Legend

from ofrl_drake.guard import StopReport
from ofrl_drake.plotting import (
    numerical_floor,
    plot_estimation_error_log,
    plot_input,
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
