"""Gains re-solved along the trajectory, held in discrete state."""

import dataclasses

import numpy as np
import pytest

from ofrl_drake import ScenarioError, simulate
from ofrl_drake.scenario import validate_scenario


def _scheduled(scenario, **observer):
    return dataclasses.replace(
        scenario,
        observer=dataclasses.replace(scenario.observer, **observer),
        simulation=dataclasses.replace(scenario.simulation, duration=3.0),
    )


def test_gains_are_resolved_and_logged(paper_scenario, paper_design):
    s = _scheduled(paper_scenario, schedule_period=1.0, schedule_half_width=[1.0, 1.0])
    r = simulate(s, design=paper_design, progress=False)
    gains, failed = r.extra["observer_gains"], r.extra["solve_failed"][:, 0]
    assert gains.shape == (r.t.size, 6)  # vec L, vec H, vec K with n = 2, q = 1
    before = r.t < 1.0 - 1e-9
    np.testing.assert_allclose(
        gains[before, :2], np.tile(paper_design.L.ravel(), (before.sum(), 1))
    )
    # A smaller box around the estimate needs a smaller gain than the design on [-2, 2]^2.
    assert np.linalg.norm(gains[-1, :2]) < 0.9 * np.linalg.norm(paper_design.L)
    assert not failed.any()
    assert np.linalg.norm(r.e[-1]) < 1e-3


def test_failed_resolves_keep_the_previous_gains(paper_scenario, paper_design):
    # No design certifies alpha = 500 on these boxes: every re-solve fails.
    s = _scheduled(paper_scenario, schedule_period=1.0, alpha=500.0)
    r = simulate(s, design=paper_design, progress=False)
    failed = r.extra["solve_failed"][:, 0]
    assert failed[r.t < 1.0 - 1e-9].max() == 0.0
    assert failed[r.t > 1.0 + 1e-9].min() == 1.0
    np.testing.assert_allclose(r.extra["observer_gains"][-1, :2], paper_design.L.ravel())


def test_schedule_cannot_pin_gains(paper_scenario):
    s = _scheduled(
        paper_scenario, schedule_period=1.0, L=[[1.0], [1.0]], H=[[0.0], [0.0]], K=[[0.0], [0.0]]
    )
    with pytest.raises(
        ScenarioError, match=r"observer\.schedule_period: scheduled gains are re-designed"
    ):
        validate_scenario(s)


def test_bad_half_width(paper_scenario):
    s = _scheduled(paper_scenario, schedule_period=1.0, schedule_half_width=[1.0, -1.0])
    with pytest.raises(ScenarioError, match=r"observer\.schedule_half_width: entries must be > 0"):
        validate_scenario(s)


def test_every_gain_in_force_rechecks_in_numpy_from_the_logs(paper_scenario, paper_design):
    """P, box and gains of each design in force are logged; numpy re-certifies them."""
    from ofrl_drake.design import ObserverDesign
    from ofrl_drake.examples import make_system
    from ofrl_drake.observer import unpack_gains

    s = _scheduled(paper_scenario, schedule_period=1.0, schedule_half_width=[1.0, 1.0])
    r = simulate(s, design=paper_design, progress=False)
    system = make_system("two_state")
    n, q = system.n, system.q
    P, cert, box = (
        r.extra["lyapunov_matrix"],
        r.extra["certificate"][:, 0],
        r.extra["certified_box"],
    )
    L, H, K = unpack_gains(r.extra["observer_gains"], n, q)
    np.testing.assert_allclose(P[0], paper_design.P.ravel(), rtol=0, atol=0)
    # One sample per design in force: before the first re-solve, and after each one.
    for t in (0.5, 1.5, 2.5):
        k = int(np.argmin(np.abs(r.t - t)))
        recheck = ObserverDesign.from_gains(
            system,
            (box[k, :n], box[k, n:]),
            s.input_bound,
            s.observer.alpha,
            L=L[k],
            H=H[k],
            K=K[k],
            P=P[k].reshape(n, n),
            jacobian_method=s.observer.jacobian_method,
            formulation=s.observer.formulation,
        )
        assert recheck.is_certified
        assert recheck.max_eigenvalue == pytest.approx(cert[k], rel=1e-6, abs=1e-9)
        assert cert[k] < 0
    assert len({tuple(row) for row in box}) == 3  # three different boxes were in force


def test_each_resolve_is_bounded_by_the_runs_wall_time(paper_scenario, paper_design, monkeypatch):
    import ofrl_drake.design as design_module
    from ofrl_drake.errors import WallTimeExceeded

    s = _scheduled(paper_scenario, schedule_period=1.0, schedule_half_width=[1.0, 1.0])
    s = dataclasses.replace(s, simulation=dataclasses.replace(s.simulation, max_wall_time=120.0))
    limits = []

    def out_of_time(*args, **kwargs):
        limits.append(kwargs["time_limit"])
        raise WallTimeExceeded("the observer LMI ran out of its time limit", step="LMI solve")

    monkeypatch.setattr(design_module, "design_observer", out_of_time)
    r = simulate(s, design=paper_design, progress=False)
    # Each re-solve got the run's budget; one that runs out keeps the gains in force
    # and counts as failed, and the run goes on.
    assert limits == [120.0, 120.0] and r.status == "ok"
    assert r.extra["solve_failed"][-1, 0] == 1.0
    np.testing.assert_array_equal(r.extra["solve_counts"][-1], [2.0, 2.0])
    np.testing.assert_allclose(r.extra["observer_gains"][-1, :2], paper_design.L.ravel())


def _observer(design, **given):
    from ofrl_drake.examples import make_system
    from ofrl_drake.systems import ScheduledThreeGainObserver

    arguments = {"period": 1.0, "half_width": [1.0, 1.0], "input_bound": 3.0, "alpha": 0.5}
    return ScheduledThreeGainObserver(make_system("two_state"), design, **(arguments | given))


@pytest.mark.parametrize(
    ("given", "message"),
    [
        ({"period": np.inf}, r"^ScheduledThreeGainObserver: period must be finite; got inf\."),
        ({"period": np.nan}, r"^ScheduledThreeGainObserver: period must be finite; got nan\."),
        ({"period": 0.0}, r"^ScheduledThreeGainObserver: period must be > 0; got 0\.0\."),
        ({"period": "1"}, r"^ScheduledThreeGainObserver: period must be a number; got '1'\."),
        (
            {"half_width": [np.nan, 1.0]},
            r"^ScheduledThreeGainObserver: half_width must be finite; got \[nan, 1\.0\]\.",
        ),
        (
            {"half_width": [np.inf, 1.0]},
            r"^ScheduledThreeGainObserver: half_width must be finite; got \[inf, 1\.0\]\.",
        ),
        (
            {"half_width": [1.0, -1.0]},
            r"^ScheduledThreeGainObserver: half_width must have entries > 0; got \[1\.0, -1\.0\]",
        ),
        (
            {"half_width": [1.0, 1.0, 1.0]},
            r"^ScheduledThreeGainObserver: half_width must have length 2; got 3\.",
        ),
        (
            {"half_width": "wide"},
            r"^ScheduledThreeGainObserver: half_width must be numeric; got 'wide'\.",
        ),
        ({"alpha": -0.5}, r"^ScheduledThreeGainObserver: alpha must be >= 0; got -0\.5\."),
        ({"alpha": "0.5"}, r"^ScheduledThreeGainObserver: alpha must be a number; got '0\.5'\."),
        (
            {"input_bound": np.inf},
            r"^ScheduledThreeGainObserver: input_bound must be finite; got inf\.",
        ),
        (
            {"design_options": {"solvr": "scs"}},
            r"^ScheduledThreeGainObserver: design_options has unknown key 'solvr'; "
            r"use keyword arguments of design_observer: .*'solver'",
        ),
        (
            {"design_options": {"alpha": 1.0}},
            r"^ScheduledThreeGainObserver: design_options has unknown key 'alpha'; ",
        ),
        (
            {"design_options": [("solver", "scs")]},
            r"^ScheduledThreeGainObserver: design_options must be a dict of keyword arguments",
        ),
    ],
)
def test_bad_arguments_are_named_up_front(paper_design, given, message):
    """Not a block that re-solves forever on a bad box, nor fails every re-solve quietly."""
    from ofrl_drake.errors import ModelError

    with pytest.raises(ModelError, match=message):
        _observer(paper_design, **given)


def test_the_blocks_own_unpacking_reads_the_layout_of_unpack_gains(mimo_scenario):
    """The per-evaluation ``_unpack`` reads the gains inline: pinned to ``unpack_gains``."""
    from ofrl_drake.examples import make_system
    from ofrl_drake.observer import pack_gains, unpack_gains
    from ofrl_drake.systems import ScheduledThreeGainObserver
    from ofrl_drake.variants import design_for

    system = make_system("coupled_two_state")  # n = 4, q = 2, m = 2: row-major order shows
    n, q, m = system.n, system.q, system.m
    design = design_for(mimo_scenario)
    block = ScheduledThreeGainObserver(
        system, design, period=1.0, half_width=[1.0] * n, input_bound=3.0, alpha=0.5
    )
    context = block.CreateDefaultContext()
    # What the block logs is pack_gains of the design in force.
    logged = block.get_observer_gains_output_port().Eval(context)
    np.testing.assert_array_equal(logged, pack_gains(design.L, design.H, design.K))
    # Any gains and bounds written into the state are read back as unpack_gains reads them.
    rng = np.random.default_rng(3)
    packed = rng.normal(size=3 * n * q)
    Mf1, Mg1, Mg2 = rng.normal(size=(n, n)), rng.normal(size=(n, n, m)), rng.normal(size=(n, n, m))
    context.get_mutable_discrete_state(block._gains_index).SetFromVector(packed)
    context.get_mutable_discrete_state(block._bounds_index).SetFromVector(
        np.concatenate([Mf1.ravel(), Mg1.ravel(), Mg2.ravel()])
    )
    got = block._unpack(context)
    for name, want in zip("LHK", unpack_gains(packed, n, q), strict=True):
        np.testing.assert_array_equal(getattr(got, name), want)
    for name, want in (("Mf1", Mf1), ("Mg1", Mg1), ("Mg2", Mg2)):
        np.testing.assert_array_equal(getattr(got, name), want)


def test_a_subclass_is_named_in_the_initial_state_message(paper_design):
    """The initial state's message names the block like its other arguments' messages."""
    # Before: "ScheduledThreeGainObserver: initial_state" was written out, for a subclass too.
    from ofrl_drake.errors import ModelError
    from ofrl_drake.examples import make_system
    from ofrl_drake.systems import ScheduledThreeGainObserver

    class MyObserver(ScheduledThreeGainObserver):
        pass

    arguments = {"period": 1.0, "half_width": [1.0, 1.0], "input_bound": 3.0, "alpha": 0.5}
    system = make_system("two_state")
    with pytest.raises(ModelError, match=r"^MyObserver: initial_state must have length 2; got 3"):
        MyObserver(system, paper_design, initial_state=[0.0, 0.0, 0.0], **arguments)
    with pytest.raises(ModelError, match=r"^MyObserver: half_width must have length 2; got 3"):
        MyObserver(system, paper_design, **(arguments | {"half_width": [1.0] * 3}))


def test_the_gain_schedule_plot_reads_the_log_with_unpack_gains():
    """Its three panels are L, H and K; a log that is not three equal blocks is refused."""
    # Before: 7 columns were read as three blocks of 2, the last column dropped unseen.
    import matplotlib.pyplot as plt

    from ofrl_drake.errors import ModelError
    from ofrl_drake.plotting import plot_gain_schedule

    t = np.linspace(0.0, 1.0, 5)
    gains = np.arange(30.0).reshape(5, 6)  # n q = 2: L = columns 0-1, H = 2-3, K = 4-5
    fig = plot_gain_schedule(t, gains, np.zeros(5, dtype=bool))
    try:
        for ax, first in zip(fig.axes[:3], (0, 2, 4), strict=True):
            lines = ax.get_lines()
            np.testing.assert_array_equal(lines[0].get_ydata(), gains[:, first])
            np.testing.assert_array_equal(lines[1].get_ydata(), gains[:, first + 1])
    finally:
        plt.close(fig)
    with pytest.raises(ModelError, match=r"observer_gains must have 3 n q = 6 entries .*\(5, 7\)"):
        plot_gain_schedule(t, np.zeros((5, 7)), np.zeros(5, dtype=bool))
