"""The benchmark sections: each returns JSON-ready results.

* :func:`paper_end_to_end` -- ``simulate()`` on the paper scenario, whole,
  against the two numpy right-hand sides under LSODA: the stronger baseline
  (:mod:`benchmarks.precomputed_numpy`, the target's yardstick) and the fused
  one (:mod:`benchmarks.fused_numpy`, the second column);
* :func:`evaluation_overhead` -- one derivative evaluation of the diagram
  against both right-hand sides at the same state;
* :func:`points_scaling`, :func:`basis_scaling`, :func:`state_dimension` --
  how the cost grows with N, L and n;
* :func:`integrators` -- Drake integrators at two accuracies;
* :func:`bellman_math` -- the compiled Bellman extrapolation alone, per call;
* :func:`compile_cost` -- numba's import, first-call compile and cache-load
  times (fresh processes) and its install size;
* :func:`lmi_design` -- the observer LMI through Drake and through cvxpy.

Times are wall-clock seconds, with median, min and max over ``repeats`` runs
after one warm-up run; competing variants run interleaved.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from benchmarks.cases import (
    Reference,
    fused_loop,
    initial_state,
    precomputed_loop,
    reference,
    with_basis,
    with_grid,
    with_integrator,
)
from benchmarks.scaling import ScalingSettings
from benchmarks.timing import Timing, interleaved, measure
from ofrl_drake.scenario import Scenario

__all__ = [
    "BASELINES",
    "BASELINE_METHOD",
    "BASELINE_TOLERANCES",
    "Settings",
    "basis_scaling",
    "bellman_math",
    "block_kinds",
    "compile_cost",
    "evaluation_overhead",
    "integrators",
    "lmi_design",
    "paper_end_to_end",
    "points_scaling",
    "state_dimension",
    "timed",
]

#: The baselines' integrator and its tolerances (rtol, atol).
BASELINE_METHOD = "LSODA"
BASELINE_TOLERANCES = (1e-9, 1e-11)

#: Result key -> how the baseline's loop is built: the stronger baseline
#: first (the targets' yardstick), then the fused one (the second column).
BASELINES = {"precomputed": precomputed_loop, "fused": fused_loop}


@dataclass(frozen=True)
class Settings:
    """What to run and how often.

    Attributes
    ----------
    repeats : int
        Timed runs per case (after one warm-up run).
    point_grids : tuple of tuple of int
        Grid counts of the N-scaling cases.
    basis_degrees : tuple of tuple of int
        Basis degrees of the L-scaling cases.
    integrator_cases : tuple of (str, float, float)
        (scheme, accuracy, log period) of the integrator rows: the paper
        scenario's own log period (0.02 s, about one explicit step, which
        bounds every scheme to at least 1,500 steps) and a coarser one, so
        that implicit schemes are not forced to short steps by the logging.
    overhead_batches, overhead_calls : int
        Interleaved batches, and derivative evaluations per batch, of the
        per-evaluation overhead measurement.
    lmi_cases : tuple of (str, str)
        (backend, solver) pairs.
    bellman_batches, bellman_calls : int
        Batches, and calls per batch, of the Bellman-math measurement (the
        calls shrink with N so that each batch does about the same work).
    scaling : ScalingSettings
        The cart-pole scaling rows (:mod:`benchmarks.scaling`).
    sweep_counts : tuple of int
        Numbers of initial states of the sweep measurement
        (:mod:`benchmarks.sweep`).
    sweep_repeats : int
        Interleaved timed runs of each sweep case.
    """

    repeats: int = 5
    point_grids: tuple[tuple[int, ...], ...] = ((10, 10), (25, 40), (100, 100))
    basis_degrees: tuple[tuple[int, ...], ...] = ((2,), (2, 4))
    integrator_cases: tuple[tuple[str, float, float], ...] = (
        ("runge_kutta3", 1e-4, 0.02),
        ("runge_kutta3", 1e-3, 0.02),
        ("radau3", 1e-3, 0.02),
        ("radau1", 1e-3, 0.02),
        ("implicit_euler", 1e-3, 0.02),
        ("velocity_implicit_euler", 1e-3, 0.02),
        ("runge_kutta3", 1e-3, 0.1),
        ("runge_kutta3", 1e-5, 0.1),
        ("bogacki_shampine3", 1e-4, 0.1),
        ("runge_kutta5", 1e-3, 0.1),
        ("radau3", 1e-3, 0.1),
        ("radau3", 1e-4, 0.1),
        ("radau3", 1e-5, 0.1),
        ("implicit_euler", 1e-3, 0.1),
    )
    overhead_batches: int = 21
    overhead_calls: int = 500
    lmi_cases: tuple[tuple[str, str], ...] = (
        ("drake", "clarabel"),
        ("cvxpy", "clarabel"),
        ("drake", "scs"),
        ("cvxpy", "scs"),
    )
    bellman_batches: int = 21
    bellman_calls: int = 2000
    scaling: ScalingSettings = field(default_factory=ScalingSettings)
    sweep_counts: tuple[int, ...] = (1, 8)
    sweep_repeats: int = 2


# ------------------------------------------------------------------ helpers
def _design(scenario: Scenario) -> Any:
    from ofrl_drake.variants import design_for

    return design_for(scenario)


def _ours(scenario: Scenario) -> Callable[[], Any]:
    from ofrl_drake.simulation import simulate

    return lambda: simulate(scenario, progress=False)


def _solve_baseline(
    kind: str, scenario: Scenario, design: Any, times: np.ndarray | None = None
) -> tuple:
    """Build a baseline's loop (its point data included) and integrate it: ``(loop, sol)``."""
    rtol, atol = BASELINE_TOLERANCES
    loop = BASELINES[kind](scenario, design)
    sol = loop.solve(
        initial_state(scenario, loop),
        scenario.simulation.duration,
        method=BASELINE_METHOD,
        rtol=rtol,
        atol=atol,
        t_eval=times,
    )
    return loop, sol


def _baseline(kind: str, scenario: Scenario, design: Any, times: np.ndarray) -> Callable[[], Any]:
    """The timed baseline run: :func:`_solve_baseline` sampled at ``times``."""
    return lambda: _solve_baseline(kind, scenario, design, times)


def _bare(scenario: Scenario, design: Any, into: list[float]) -> Callable[[], int]:
    """``AdvanceTo`` of the loop with nothing recorded or watched, appended to ``into``.

    The same diagram and integrator as ``simulate()``, but its loggers sample
    only at 0 and at the horizon (``log_period`` is the horizon) and no run
    guard is installed. So the run is not cut at every log time and no Python
    monitor is called after every step: the floor of what logging less, or
    watching the run more cheaply, could save. Each call returns the
    derivative evaluations.
    """
    from pydrake.systems.analysis import ApplySimulatorConfig, Simulator

    from ofrl_drake.diagram import build_closed_loop
    from ofrl_drake.simulation import simulator_config

    duration = scenario.simulation.duration
    loop = build_closed_loop(scenario, design=design, log_period=duration)

    def run() -> int:
        simulator = Simulator(loop.diagram)
        ApplySimulatorConfig(simulator_config(scenario), simulator)
        loop.set_initial_values(simulator.get_mutable_context())
        simulator.Initialize()
        start = time.perf_counter()
        simulator.AdvanceTo(duration)
        into.append(time.perf_counter() - start)
        return int(simulator.get_integrator().get_num_derivative_evaluations())

    return run


def _floor_summary(ours: Timing, advance: list[float], bare: list[float], evals: int) -> dict:
    """The bare loop's ``AdvanceTo``, and ``simulate()`` whole with it in place of its own.

    Per repeat, the floor is ours whole minus ours' ``AdvanceTo`` plus the
    bare ``AdvanceTo`` of the same repeat: the design, build and logs as
    measured, the simulation at its floor.
    """
    floor = [w - a + b for w, a, b in zip(ours.runs, advance, bare, strict=True)]
    return {
        "advance": Timing(tuple(bare)).to_dict(),
        "num_derivative_evaluations": evals,
        "whole": Timing(tuple(floor)).to_dict(),
    }


def _recording(run: Callable[[], Any], into: list[float]) -> Callable[[], Any]:
    """``run`` (a ``simulate()`` call) that also appends each result's ``wall_time`` to ``into``."""

    def recorded() -> Any:
        result = run()
        into.append(result.wall_time)
        return result

    return recorded


def _run_summary(timing: Timing, advance: list[float], result: Any) -> dict:
    """Times, evaluations and steps of repeated ``simulate()`` runs."""
    stats = result.integrator
    evals = stats["num_derivative_evaluations"]
    advance_timing = Timing(tuple(advance))
    return {
        **timing.to_dict(),
        "advance": advance_timing.to_dict(),
        "us_per_evaluation": 1e6 * advance_timing.median / evals,
        "num_derivative_evaluations": evals,
        "num_steps": stats["num_steps"],
        "num_log_samples": int(result.t.size),
        "integrator": stats["scheme"],
        "accuracy": stats["accuracy"],
    }


def _ours_summary(timing: Timing, advance: list[float], result: Any, ref: Reference) -> dict:
    final, worst = ref.errors(result.t, result.W)
    return {**_run_summary(timing, advance, result), "W_final_error": final, "W_max_error": worst}


def _baseline_summary(timing: Timing, run: Any, ref: Reference, steps: int) -> dict:
    loop, sol = run
    W = np.array([loop.weights(z) for z in sol.y.T])
    final, worst = ref.errors(sol.t, W)
    return {
        **timing.to_dict(),
        "us_per_evaluation": 1e6 * timing.median / sol.nfev,
        "num_derivative_evaluations": int(sol.nfev),
        "num_jacobian_evaluations": int(getattr(sol, "njev", 0)),
        "num_steps": steps,
        "integrator": f"scipy {BASELINE_METHOD}",
        "tolerances": list(BASELINE_TOLERANCES),
        "W_final_error": final,
        "W_max_error": worst,
    }


def _baseline_steps(kind: str, scenario: Scenario, design: Any) -> int:
    """LSODA's accepted steps (an untimed run without ``t_eval``)."""
    _, sol = _solve_baseline(kind, scenario, design)
    return int(sol.t.size - 1)


def _compare(
    scenario: Scenario, repeats: int, *, baseline: bool = True, bare: bool = False
) -> dict:
    """Ours (whole ``simulate()``) and, optionally, both baselines, interleaved.

    ``ratio`` is ours over the stronger baseline (``precomputed``), medians of
    the interleaved runs; ``ratio_fused`` the same over the fused baseline;
    ``ratio_of_pairs`` and ``ratio_of_pairs_fused`` are the medians of the
    per-repeat ratios, which a drift in machine load affects less. With
    ``bare``, the loop without per-step logging or guard (:func:`_bare`) runs
    in the same alternation: ``floor`` (:func:`_floor_summary`) and, with the
    baselines, ``ratio_floor``.
    """
    design = _design(scenario)
    ref = reference(scenario, design)
    advance: list[float] = []
    fns: dict[str, Callable[[], Any]] = {"ours": _recording(_ours(scenario), advance)}
    bare_advance: list[float] = []
    if bare:
        fns["bare"] = _bare(scenario, design, bare_advance)
    if baseline:
        for kind in BASELINES:
            fns[kind] = _baseline(kind, scenario, design, ref.times)
    timings, results = interleaved(fns, repeats)
    out = {"ours": _ours_summary(timings["ours"], advance[-repeats:], results["ours"], ref)}
    if bare:
        out["floor"] = _floor_summary(
            timings["ours"], advance[-repeats:], bare_advance[-repeats:], results["bare"]
        )
        if baseline:
            floor = out["floor"]["whole"]["median"]
            out["ratio_floor"] = floor / timings["precomputed"].median
    if baseline:
        for kind in BASELINES:
            steps = _baseline_steps(kind, scenario, design)
            out[kind] = _baseline_summary(timings[kind], results[kind], ref, steps)
            suffix = "" if kind == "precomputed" else f"_{kind}"
            out[f"ratio{suffix}"] = timings["ours"].median / timings[kind].median
            pairs = [a / b for a, b in zip(timings["ours"].runs, timings[kind].runs, strict=True)]
            out[f"ratio_of_pairs{suffix}"] = float(np.median(pairs))
    return out


# ----------------------------------------------------------------- sections
def paper_end_to_end(scenario: Scenario, settings: Settings) -> dict:
    """The paper scenario: whole ``simulate()`` against both baselines, interleaved.

    The bare loop (:func:`_bare`) runs in the same alternation, for the floor
    of the overhead levers (``floor``, ``ratio_floor``).
    """
    out = _compare(scenario, settings.repeats, bare=True)
    design_timing, _ = measure(lambda: _design(scenario), settings.repeats)
    out["design"] = design_timing.to_dict()
    advance = out["ours"]["advance"]["median"]
    out["ratio_simulation_only"] = advance / out["precomputed"]["median"]
    out["ratio_simulation_only_fused"] = advance / out["fused"]["median"]
    return out


_STATE_SLOTS = ("plant", "observer", "critic", "gamma", "running_cost")


def _diagram_state(loop: Any, context: Any, z: np.ndarray) -> np.ndarray:
    """The diagram's continuous state for the fused state ``z = [x, xhat, W, vec(Gamma), J]``.

    The plant, observer and critic blocks write their own state through their
    setters; Gamma's block holds its upper triangle. ``context`` is left at
    the state.
    """
    from ofrl_drake.bellman import pack_symmetric

    n, L = loop.parts.system.n, loop.parts.basis.size
    x, xhat, W, Gamma, J = np.split(z, np.cumsum([n, n, L, L * L]))
    sub = {slot: loop.blocks[slot].GetMyMutableContextFromRoot(context) for slot in _STATE_SLOTS}
    loop.plant.set_state(sub["plant"], x)
    loop.observer.set_estimated_state(sub["observer"], xhat)
    loop.critic.set_weights(sub["critic"], W)
    sub["gamma"].SetContinuousState(pack_symmetric(Gamma.reshape(L, L)))
    sub["running_cost"].SetContinuousState(J)
    return context.get_continuous_state_vector().CopyToVector()


def _fused_layout(loop: Any, context: Any) -> np.ndarray:
    """The time derivatives of the diagram at ``context``, in the fused layout."""
    from ofrl_drake.bellman import unpack_symmetric

    rates = {
        slot: loop.blocks[slot]
        .EvalTimeDerivatives(loop.blocks[slot].GetMyContextFromRoot(context))
        .CopyToVector()
        for slot in _STATE_SLOTS
    }
    rates["gamma"] = unpack_symmetric(rates["gamma"]).ravel()
    return np.concatenate([rates[slot] for slot in _STATE_SLOTS])


def evaluation_overhead(scenario: Scenario, settings: Settings) -> dict:
    """Microseconds per derivative evaluation: the diagram against both right-hand sides.

    The diagram is evaluated as an integrator does it: the continuous state is
    set (invalidating every cached value), then the time derivatives are
    computed. Two states alternate; all three see the same states. Many
    short interleaved batches (``settings.overhead_batches`` of
    ``settings.overhead_calls`` calls each) keep bursts of load on a shared
    machine from landing on one method only; medians and minima are reported.
    ``overhead_us`` is the diagram minus the stronger baseline's right-hand
    side, ``overhead_us_fused`` minus the fused one.
    """
    calls = settings.overhead_calls
    from ofrl_drake.diagram import build_closed_loop

    design = _design(scenario)
    loop = build_closed_loop(scenario, design=design)
    diagram = loop.diagram
    context = diagram.CreateDefaultContext()
    derivatives = diagram.AllocateTimeDerivatives()
    baselines = {kind: build(scenario, design) for kind, build in BASELINES.items()}
    z0 = initial_state(scenario, baselines["fused"])
    z1 = z0.copy()
    z1[: 2 * len(scenario.x0)] *= 0.5  # another plant and observer state
    fused_states = (z0, z1)
    states = tuple(_diagram_state(loop, context, z) for z in fused_states)

    def diagram_calls() -> None:
        for k in range(calls):
            context.SetContinuousState(states[k & 1])
            diagram.CalcTimeDerivatives(context, derivatives)

    def rhs_calls(rhs: Callable[[float, np.ndarray], np.ndarray]) -> Callable[[], None]:
        def run() -> None:
            for k in range(calls):
                rhs(0.0, fused_states[k & 1])

        return run

    fns = {"diagram": diagram_calls}
    fns.update({kind: rhs_calls(b.rhs) for kind, b in baselines.items()})
    timings, _ = interleaved(fns, settings.overhead_batches)
    difference = 0.0
    for z, zf in zip(states, fused_states, strict=True):
        context.SetContinuousState(z)
        ours = _fused_layout(loop, context)
        for b in baselines.values():
            difference = max(difference, float(np.abs(ours - b.rhs(0.0, zf)).max()))
    out: dict[str, Any] = {}
    for key, timing in timings.items():
        out[f"{key}_us"] = 1e6 * timing.median / calls
        out[f"{key}_min_us"] = 1e6 * timing.min / calls
    for kind in BASELINES:
        suffix = "" if kind == "precomputed" else f"_{kind}"
        out[f"overhead_us{suffix}"] = out["diagram_us"] - out[f"{kind}_us"]
        out[f"overhead_min_us{suffix}"] = out["diagram_min_us"] - out[f"{kind}_min_us"]
    out.update(
        {
            "calls": calls,
            "batches": settings.overhead_batches,
            "num_states": int(states[0].size),
            "max_derivative_difference": difference,
        }
    )
    return out


def points_scaling(scenario: Scenario, settings: Settings) -> list[dict]:
    """Cost against the number N of extrapolation points."""
    rows = []
    for counts in settings.point_grids:
        case = with_grid(scenario, list(counts))
        row = {"N": int(np.prod(counts)), "grid": list(counts)}
        row.update(_compare(case, settings.repeats))
        rows.append(row)
    return rows


def basis_scaling(scenario: Scenario, settings: Settings) -> list[dict]:
    """Cost against the basis size L."""
    from ofrl_drake.basis import PolynomialBasis

    rows = []
    for degrees in settings.basis_degrees:
        case = with_basis(scenario, list(degrees))
        size = PolynomialBasis(len(scenario.x0), list(degrees)).size
        row = {"degrees": list(degrees), "L": size}
        row.update(_compare(case, settings.repeats))
        rows.append(row)
    return rows


def state_dimension(scenarios: list[Scenario], settings: Settings) -> list[dict]:
    """Cost for each scenario (the n = 2 paper example, the n = 4 MIMO one)."""
    rows = []
    for case in scenarios:
        row = {"scenario": case.name, "n": len(case.x0)}
        row.update(_compare(case, settings.repeats))
        rows.append(row)
    return rows


def block_kinds(scenarios: list[Scenario], settings: Settings) -> list[dict]:
    """Each scenario with the C++ symbolic blocks and with the Python blocks, interleaved.

    ``simulate()`` with the observer design given (computed once, its time
    reported apart): the plant, observer and controller are
    ``SymbolicVectorSystem`` blocks or Python ``LeafSystem`` blocks
    (``simulation.blocks``); the other four blocks are the same. No baseline:
    the multibody scenarios have no hand-written fused loop.
    """
    from ofrl_drake.simulation import simulate

    rows = []
    for scenario in scenarios:
        design_timing, design = measure(lambda s=scenario: _design(s), 1, warmup=0)
        advance: dict[str, list[float]] = {"symbolic": [], "python": []}
        fns = {}
        for kind in advance:
            case = dataclasses.replace(
                scenario, simulation=dataclasses.replace(scenario.simulation, blocks=kind)
            )
            run = functools.partial(simulate, case, design=design, progress=False)
            fns[kind] = _recording(run, advance[kind])
        timings, results = interleaved(fns, settings.repeats)
        row: dict[str, Any] = {
            "scenario": scenario.name,
            "n": len(scenario.x0),
            "design_seconds": design_timing.median,
        }
        for kind, timing in timings.items():
            row[kind] = _run_summary(timing, advance[kind][-settings.repeats :], results[kind])
        row["python_over_symbolic"] = timings["python"].median / timings["symbolic"].median
        rows.append(row)
    return rows


def integrators(scenario: Scenario, settings: Settings) -> list[dict]:
    """Drake integrators on the paper scenario (no baseline run; W against the reference)."""
    design = _design(scenario)
    ref = reference(scenario, design)
    rows = []
    for scheme, accuracy, log_period in settings.integrator_cases:
        case = with_integrator(scenario, scheme, accuracy, log_period)
        advance: list[float] = []
        timing, result = measure(_recording(_ours(case), advance), settings.repeats)
        row = {"integrator": scheme, "accuracy": accuracy, "log_period": log_period}
        row.update(_ours_summary(timing, advance[-settings.repeats :], result, ref))
        rows.append(row)
    return rows


def bellman_math(scenario: Scenario, settings: Settings) -> list[dict]:
    """Microseconds per Bellman extrapolation (both sums) at each N of ``point_grids``.

    This is the math a derivative evaluation of the Bellman block does:
    :meth:`~ofrl_drake.bellman.Extrapolator.sums_into` at the scenario's
    initial weights, into preallocated arrays, called from Python as the
    block calls it.
    """
    from ofrl_drake.basis import PolynomialBasis
    from ofrl_drake.bellman import Extrapolator, point_features
    from ofrl_drake.diagram import extrapolation_points
    from ofrl_drake.examples import make_system

    system = make_system(scenario.system)
    basis = PolynomialBasis(system.n, scenario.critic.basis_degrees)
    Q = np.asarray(scenario.cost.Q, dtype=float)
    r = np.asarray(scenario.cost.R, dtype=float)
    W = np.asarray(scenario.critic.W0, dtype=float)
    rows = []
    for counts in settings.point_grids:
        case = with_grid(scenario, list(counts))
        features = point_features(system, basis, extrapolation_points(case), Q)
        extrapolator = Extrapolator(features, r, case.input_bound, case.critic.nu)
        N = features.num_points
        calls = max(1, settings.bellman_calls * 100 // N)

        out = extrapolator.empty_sums()

        def batch(
            extrapolator: Extrapolator = extrapolator, calls: int = calls, out: Any = out
        ) -> None:
            for _ in range(calls):
                extrapolator.sums_into(W, out.critic_sum, out.gain_sum)

        timing, _ = measure(batch, settings.bellman_batches)
        rows.append(
            {
                "N": int(N),
                "calls": calls,
                "batches": settings.bellman_batches,
                "us_per_call": 1e6 * timing.median / calls,
                "us_per_call_min": 1e6 * timing.min / calls,
            }
        )
    return rows


_COMPILE_SCRIPT = """
import json, sys, time
t0 = time.perf_counter()
import numba
t1 = time.perf_counter()
import ofrl_drake
from benchmarks.cases import with_duration
t2 = time.perf_counter()
scenario = with_duration(ofrl_drake.load_scenario(sys.argv[1]), 0.1)
ofrl_drake.simulate(scenario, progress=False)
t3 = time.perf_counter()
ofrl_drake.simulate(scenario, progress=False)
t4 = time.perf_counter()
print(json.dumps({"import_numba": t1 - t0, "import_ofrl_drake": t2 - t1,
                  "first_simulate": t3 - t2, "second_simulate": t4 - t3}))
"""


def compile_cost(scenario_path: str) -> dict:
    """numba's fixed costs, each in a fresh Python process.

    ``cold``: an empty kernel cache (``NUMBA_CACHE_DIR`` set to a new
    folder), so the first ``simulate()`` (0.1 s of the scenario) compiles
    every kernel; ``warm``: the same folder again, so the kernels are loaded
    from the cache. ``compile_s`` is cold minus warm first-call time. The
    install size is what the ``numba`` and ``llvmlite`` distributions put on
    disk.
    """
    import importlib.metadata
    import json
    import os
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        env["PYTHONPATH"] = os.pathsep.join(
            p for p in (str(root), os.environ.get("PYTHONPATH", "")) if p
        )
        for label in ("cold", "warm"):
            done = subprocess.run(
                [sys.executable, "-c", _COMPILE_SCRIPT, scenario_path],
                env=env,
                cwd=root,
                capture_output=True,
                text=True,
                check=True,
            )
            out[label] = json.loads(done.stdout.strip().splitlines()[-1])
    out["compile_s"] = out["cold"]["first_simulate"] - out["warm"]["first_simulate"]
    sizes = {}
    for dist in ("numba", "llvmlite"):
        files = importlib.metadata.distribution(dist).files or []
        sizes[dist] = sum(f.locate().stat().st_size for f in files if f.locate().is_file())
    out["install_bytes"] = sizes
    out["versions"] = {d: importlib.metadata.version(d) for d in ("numba", "llvmlite")}
    return out


def lmi_design(scenarios: list[Scenario], settings: Settings) -> list[dict]:
    """The observer LMI through each (backend, solver), Jacobian bounds precomputed."""
    from ofrl_drake.design import design_observer
    from ofrl_drake.errors import OfrlError
    from ofrl_drake.jacobian_bounds import jacobian_bounds
    from ofrl_drake.plants import resolve_system

    rows = []
    for scenario in scenarios:
        system = resolve_system(scenario)
        o = scenario.observer
        box = (np.asarray(o.box.lower, float), np.asarray(o.box.upper, float))
        options: dict[str, Any] = {"jacobian_method": o.jacobian_method}
        if hasattr(o, "formulation"):
            options["formulation"] = o.formulation
        bounds = jacobian_bounds(system, box, o.jacobian_method)
        for backend, solver in settings.lmi_cases:
            row: dict[str, Any] = {"scenario": scenario.name, "backend": backend, "solver": solver}

            solve = functools.partial(
                design_observer,
                system,
                box,
                scenario.input_bound,
                o.alpha,
                bounds=bounds,
                solver=solver,
                backend=backend,
                **options,
            )
            try:
                timing, design = measure(solve, settings.repeats)
            except OfrlError as err:
                row.update({"failed": f"{type(err).__name__}: {err}"})
                rows.append(row)
                continue
            row.update(timing.to_dict())
            row.update(
                {
                    "solve_time": design.solve_time,
                    "status": design.status,
                    "certified": bool(design.is_certified),
                    "max_eigenvalue": float(design.max_eigenvalue),
                    "gain_norm": float(design.gain_norm),
                }
            )
            rows.append(row)
    return rows


def timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    """``(seconds, fn())``: how long a whole section took."""
    start = time.perf_counter()
    value = fn()
    return time.perf_counter() - start, value
