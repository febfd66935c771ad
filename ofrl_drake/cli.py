"""The ``ofrl-drake`` command-line tool.

Subcommands::

    ofrl-drake run SCENARIO --out DIR              simulate, write logs, figures, graph
    ofrl-drake design-observer SCENARIO --out F    certified observer gains as JSON
    ofrl-drake verify-observer SCENARIO            falsify the design against the dynamics
    ofrl-drake ablate SCENARIO --out DIR           every variant vs the optimum, on Dask
    ofrl-drake montecarlo SCENARIO --runs N --out DIR  N noise seeds (and sampled truths)
    ofrl-drake plot RUN_DIR [--out DIR]            redraw a run's figures from its files

Exit codes (docs/cli.md has the table): 0 success; 1 internal error (a bug:
please report it); 2 bad input, printed on one line (``error: ...``); 3 ``run``
stopped early because the run diverged or timed out, or its learning curve ran
out of ``--max-wall`` (its output folder is written and says so); 4
``verify-observer`` found a counterexample to the design's decay claim
(printed in one line); 130 interrupted (SIGINT). Nothing partial is written:
outputs are built in a temporary sibling and renamed into place. The exception
is ``ablate`` and ``montecarlo``, whose rows stream into their table as runs
finish so that ``--resume`` can complete an interrupted sweep (one that stops
before its first row removes what it wrote).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib
import json
import math
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from ofrl_drake import __version__
from ofrl_drake.atomic import (
    atomic_write_text,
    check_output_folder,
    check_output_target,
    check_writable,
    ensure_parent,
    output_lock,
    sigint_handled_here,
    sigint_held,
    umask_mode,
)
from ofrl_drake.errors import OfrlError, OutputError, one_line
from ofrl_drake.limits import (
    CHECKPOINTS_FIX,
    INITIAL_STATES_FIX,
    MAX_CHECKPOINTS,
    MAX_INITIAL_STATES,
    MAX_RUNS,
    RUNS_FIX,
)

if TYPE_CHECKING:  # annotations only: the commands import what they run when they run
    from ofrl_drake.design import ObserverDesign
    from ofrl_drake.model import ControlAffineSystem
    from ofrl_drake.verification import VerificationReport

__all__ = [
    "FIGURES_MARKER",
    "FIGURE_INPUTS_KEY",
    "OUTPUT_MARKER",
    "FigureInputs",
    "OutputError",
    "atomic_directory",
    "check_figures_directory",
    "check_output_directory",
    "main",
    "save_run_figures",
]

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_BAD_INPUT = 2
EXIT_STOPPED = 3
EXIT_FALSIFIED = 4
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143


#: Written into every output folder of ``run``; only such folders are replaced.
OUTPUT_MARKER = ".ofrl_drake_output"

#: Written into every output folder of ``plot``; only such folders (and a run's own
#: :data:`FIGURES_FOLDER`) are replaced.
FIGURES_MARKER = ".ofrl_drake_figures"

#: The resolved scenario as run, in every output folder of ``run``.
SCENARIO_FILE = "scenario.yaml"

#: The folder of a run's figures, in every output folder of ``run`` (``plot``'s default ``--out``).
FIGURES_FOLDER = "figures"

#: Where the docs explain a falsified observer design, and a state outside its box.
CERTIFICATE_DOCS = (
    "(why: docs/theory.md, 'What the observer certificate does, and does not, prove')"
)
VALIDITY_DOCS = "(why: docs/theory.md, 'Where the certificate holds')"

#: The entry of ``summary.json`` where ``run`` writes what its figures need of the
#: scenario (:class:`FigureInputs`), so that ``plot`` needs neither the scenario nor its plant.
FIGURE_INPUTS_KEY = "figure_inputs"


def check_output_directory(target: Path) -> Path:
    """Resolve ``target`` and refuse to replace anything ``run`` did not write.

    ``target`` may be absent, an empty folder, or the output of an earlier
    ``run`` (it holds :data:`OUTPUT_MARKER`).
    """
    target = _check_output_place(check_output_target(target, folder=True))
    check_output_folder(target, marker=OUTPUT_MARKER, command="run")
    return check_writable(target)


def check_figures_directory(target: Path, run_dir: Path) -> Path:
    """Resolve ``plot``'s ``--out`` for the run folder ``run_dir``; refuse what it may not replace.

    ``target`` may be absent, an empty folder, a folder an earlier ``plot``
    wrote (it holds :data:`FIGURES_MARKER`), or the :data:`FIGURES_FOLDER` of
    ``run_dir`` itself, which ``run`` drew. Nothing directly inside another
    run folder (one holding :data:`OUTPUT_MARKER`): its figures are its own.

    Raises
    ------
    OutputError
        If ``target`` is a file, a link, a filesystem root, the current folder
        or one holding it, ``run_dir`` or a folder holding it, a folder inside
        another run folder, someone else's non-empty folder, or cannot be
        written.
    """
    run_dir = Path(run_dir).expanduser().resolve()
    target = _check_output_place(check_output_target(target, folder=True))
    if target == run_dir or target in run_dir.parents:
        raise OutputError(
            f"--out: {target} is the run folder or holds it, which the figures would "
            f"replace; name another folder (default RUN_DIR/{FIGURES_FOLDER})."
        )
    if target.parent != run_dir and (target.parent / OUTPUT_MARKER).is_file():
        raise OutputError(
            f"--out: {target} is inside {target.parent}, the folder of another run, whose "
            f"files are its own; name a folder outside it (default RUN_DIR/{FIGURES_FOLDER})."
        )
    if target != run_dir / FIGURES_FOLDER:
        check_output_folder(target, marker=FIGURES_MARKER, command="plot")
    return check_writable(target)


def _check_output_place(target: str | Path) -> Path:
    """Resolve the output folder ``target``; refuse a filesystem root and the current folder.

    Every folder output (``run``, ``ablate``, ``montecarlo``) goes through it:
    ``--out .`` (or a folder holding the current one) would write into, or
    replace, the folder the command was started in.

    Raises
    ------
    OutputError
        If ``target`` is a filesystem root, the current folder or one holding it.
    """
    target = Path(target).expanduser().resolve()
    if target == target.parent:
        raise OutputError(f"--out: {target} is a filesystem root; name an output folder.")
    if target == Path.cwd().resolve() or target in Path.cwd().resolve().parents:
        raise OutputError(
            f"--out: {target} is the current folder or holds it; name an output folder below it."
        )
    return target


def _remove_stale_partials(target: Path) -> None:
    """Remove ``.NAME.partial-PID.*`` folders beside ``target`` whose process is gone.

    A run killed by SIGKILL (or a power cut) cannot clean up its temporary
    folder; the next run into the same ``--out`` does. Folders of a live
    process are left alone.
    """
    for stale in target.parent.glob(f".{target.name}.partial-*"):
        try:
            pid = int(stale.name.split(".partial-", 1)[1].split(".", 1)[0])
        except ValueError:
            continue
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            shutil.rmtree(stale, ignore_errors=True)
        except PermissionError:
            continue


@contextlib.contextmanager
def atomic_directory(target: Path, run_dir: Path | None = None) -> Iterator[Path]:
    """Yield a temporary folder that replaces ``target`` only on success.

    The folder is built beside ``target`` and renamed into place, so a failure
    at any point leaves ``target`` as it was and no temporary folder behind. The
    temporary folder's name holds ``partial`` and the process id. Without
    ``run_dir`` it is ``run``'s output (:func:`check_output_directory` says
    which folders it may replace; it gets :data:`OUTPUT_MARKER`); with it,
    ``plot``'s figures of that run folder (:func:`check_figures_directory`,
    :data:`FIGURES_MARKER`).
    """
    if run_dir is None:
        target, command, marker = check_output_directory(target), "run", OUTPUT_MARKER
    else:
        target, command = check_figures_directory(target, run_dir), "plot"
        marker = FIGURES_MARKER
    ensure_parent(target)
    _remove_stale_partials(target)
    try:
        # "partial" and the pid mark the folder as unfinished; a later run removes it if the
        # process is gone (SIGKILL cannot be caught).
        prefix = f".{target.name}.partial-{os.getpid()}."
        tmp = Path(tempfile.mkdtemp(prefix=prefix, dir=target.parent))
    except OSError as err:
        raise OutputError(f"--out: cannot write in {target.parent} ({err.strerror}).") from None
    backup = target.with_name(f".{target.name}.old")
    try:
        tmp.chmod(umask_mode(0o777))
        yield tmp
        (tmp / marker).write_text(f"written by ofrl-drake {command}\n")
        shutil.rmtree(backup, ignore_errors=True)
        if target.exists():
            target.rename(backup)
        tmp.rename(target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if backup.exists() and not target.exists():
            backup.rename(target)
        raise
    shutil.rmtree(backup, ignore_errors=True)


def _write_animation(scenario, result, folder: Path) -> str | None:
    """``animation.html`` of a multibody scenario's run; a note if Meshcat cannot start.

    Written only for ``plant.multibody`` scenarios whose model has geometry.
    """
    plant = scenario.plant
    if plant is None or not plant.multibody:
        return None
    from ofrl_drake.animation import MeshcatUnavailable, animation_html

    x = result.original("x")
    try:
        html = animation_html(plant.multibody, result.t, x[:, : x.shape[1] // 2])
    except MeshcatUnavailable as err:
        return f"note: Meshcat cannot start ({err}); no animation.html written."
    if html is not None:
        (folder / "animation.html").write_text(html)
    return None


def _with_max_wall(scenario: Any, seconds: float | None) -> Any:
    """``scenario`` with ``simulation.max_wall_time`` set from ``--max-wall``."""
    if seconds is None:
        return scenario
    if not seconds > 0 or seconds == float("inf"):
        raise OfrlError(f"--max-wall: must be a finite number of seconds > 0; got {seconds}.")
    simulation = dataclasses.replace(scenario.simulation, max_wall_time=float(seconds))
    return dataclasses.replace(scenario, simulation=simulation)


def _outside_box_warning(scenario: Any) -> str | None:
    """One line if x0 or xhat0 starts outside the observer box, else None."""
    import numpy as np

    from ofrl_drake.scenario import abort_box

    lower = np.asarray(scenario.observer.box.lower, float)
    upper = np.asarray(scenario.observer.box.upper, float)
    outside = [
        f"{name} = {list(value)}"
        for name, value in (("x0", scenario.x0), ("xhat0", scenario.xhat0))
        if np.any((np.asarray(value) < lower) | (np.asarray(value) > upper))
    ]
    if not outside:
        return None
    alo, ahi = abort_box(scenario)
    stops = any(
        np.any((np.asarray(v) < alo) | (np.asarray(v) > ahi)) for v in (scenario.x0, scenario.xhat0)
    )
    tail = (
        "; it is outside the abort box too, so the run stops at t = 0 (widen "
        "simulation.abort_box to run it anyway)"
        if stops
        else ""
    )
    return (
        f"warning: {' and '.join(outside)} outside the observer box "
        f"[{lower.tolist()}, {upper.tolist()}]: the observer certificate does not apply{tail}."
    )


def _strict_json(data: Any) -> str:
    """``data`` as strict JSON text (NaN and infinities as ``null``), with a final newline."""
    from ofrl_drake.checks import json_ready

    return json.dumps(json_ready(data), indent=2, allow_nan=False) + "\n"


def _not_regulated(details: dict[str, Any]) -> str:
    """One line saying why a run that ended ``ok`` did not reach its target."""
    from ofrl_drake.ablation_metrics import regulation_shortfall

    why = regulation_shortfall(
        details["final_error"], details["tolerance"], details["inside_observer_box"]
    )
    return (
        f"warning: the run did not regulate: {why or details['status']} "
        "(simulation.regulation_tolerance, a fraction of the observer box's half-width; "
        "summary.json -> regulation)."
    )


def _learning_report(args: argparse.Namespace, loop: Any, result: Any, started: float) -> Any:
    """The learning curve and health of ``run`` (``--checkpoints``, ``--optimal``).

    The curve shares ``simulation.max_wall_time`` (``--max-wall``) with the
    simulation, which began at ``started`` (``time.monotonic()``): when it is
    used up, the report has no curve and says why (``curve_stop``), and
    ``run`` stops with exit 3 (:func:`_run`).
    """
    from ofrl_drake.errors import WallTimeExceeded
    from ofrl_drake.learning_curve import learning_report

    optimal_cost = None
    budget = loop.parts.scenario.simulation.max_wall_time
    if args.optimal:
        from ofrl_drake.optimal import optimal_control

        before = time.monotonic() - started  # what the run used before J* began
        try:
            solved = optimal_control(
                loop.parts.scenario,
                solver=args.solver,
                deadline=None if budget is None else started + budget,
            )
        except WallTimeExceeded as err:  # the run is whole; its curve would have no budget left
            where = (
                f"the run had used {before:.3g} s of it before J* began (the simulation and "
                "the checks after it)"
                if budget is not None and before >= budget
                else one_line(err)
            )
            curve = (
                ", so no checkpoint of the learning curve was evaluated"
                if args.checkpoints > 0
                else ""
            )
            stop = (
                f"J* (--optimal) did not finish within max_wall_time (--max-wall) = {budget:g} "
                f"s: {where}{curve}; allow more wall time (a larger --max-wall) or run without "
                "--optimal"
            )
            report = learning_report(loop, result, checkpoints=0)
            return dataclasses.replace(report, curve_stop=stop)
        result.reports["optimal"] = solved.to_dict()  # J*, its solver, grid and status
        if solved.converged:
            optimal_cost = solved.cost
        else:
            print(
                f"note: J* {solved.status}; the learning curve has no optimality ratios.",
                file=sys.stderr,
            )
    try:
        return learning_report(
            loop,
            result,
            checkpoints=args.checkpoints,
            optimal_cost=optimal_cost,
            max_wall_time=budget,
            started=None if budget is None else started,
        )
    except WallTimeExceeded as err:  # the run's outputs are kept; the curve is not
        report = learning_report(loop, result, checkpoints=0, optimal_cost=optimal_cost)
        return dataclasses.replace(report, curve_stop=one_line(err))


def _cmd_run(args: argparse.Namespace) -> int:
    """``run``, holding the output's lock (:func:`ofrl_drake.atomic.output_lock`).

    numpy's overflow warnings are off: a state that overflows (``x0 = [1e300,
    1e300]``, a huge disturbance) printed ``RuntimeWarning: overflow
    encountered`` and its source line, while the run itself reports it: a
    state that is not finite, or outside the abort box, stops the run as
    ``diverged`` (exit 3, ``summary.json`` -> ``status``, ``stop``).
    """
    import numpy as np

    check_output_directory(Path(args.out))
    with output_lock(Path(args.out).expanduser().resolve()), np.errstate(over="ignore"):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    import numpy as np

    from ofrl_drake.diagram import build_closed_loop
    from ofrl_drake.graph import render_diagram
    from ofrl_drake.learning_curve import LEARNING_HEALTH_FILE
    from ofrl_drake.scenario import dump_scenario, load_scenario
    from ofrl_drake.simulation import simulate

    if args.checkpoints < 0:
        raise OfrlError(
            f"--checkpoints: must be an integer >= 0 (0 switches the learning curve off); "
            f"got {args.checkpoints}."
        )
    if args.solver is not None and not args.optimal:
        raise OfrlError(f"--solver {args.solver}: chooses the solver of J*; pass --optimal too.")
    _check_solver(args.solver)
    scenario = _with_max_wall(load_scenario(args.scenario), args.max_wall)
    check_output_directory(Path(args.out))  # fail before the work, not after
    warning = _outside_box_warning(scenario)
    if warning:
        print(warning, file=sys.stderr)
    if args.optimal:  # before the design and the run, not after them
        from ofrl_drake.errors import ModelError
        from ofrl_drake.optimal import require_traceable
        from ofrl_drake.plants import resolve_system

        try:
            require_traceable(resolve_system(scenario))
        except ModelError as err:
            raise ModelError(f"--optimal: {err} Run without --optimal.") from err
    loop = build_closed_loop(scenario)
    started = time.monotonic()  # --max-wall: the simulation and the learning curve share it
    result = simulate(scenario, loop=loop, progress=None if not args.quiet else False)
    budget = loop.parts.scenario.simulation.max_wall_time
    verification, unverified = _verify(loop.design, loop.parts.system, budget, started)
    if verification is not None and result.design is not None:
        result.design = {**result.design, "verification": verification.to_dict()}
    if unverified is not None:
        result.reports["verification_stop"] = unverified
    learning = _learning_report(args, loop, result, started)
    result.reports.update(learning.to_dict())
    figure_inputs = FigureInputs.of(scenario)
    result.reports[FIGURE_INPUTS_KEY] = figure_inputs.to_dict()
    out = Path(args.out)
    with atomic_directory(out) as tmp:
        result.save(tmp)
        with open(tmp / LEARNING_HEALTH_FILE, "wb") as fh:
            np.savez(fh, **learning.health.arrays())
        (tmp / SCENARIO_FILE).write_text(dump_scenario(loop.resolved_scenario()))
        save_run_figures(result, figure_inputs, learning, tmp / FIGURES_FOLDER)
        if loop.design is not None:
            design = loop.design.to_dict()
            if verification is not None:
                design["verification"] = verification.to_dict()
            (tmp / "observer_design.json").write_text(_strict_json(design))
        graph = render_diagram(loop.diagram, tmp)
        animation_note = _write_animation(scenario, result, tmp)
    args.written = out
    if animation_note:
        print(animation_note, file=sys.stderr)
    stop = result.stop
    no_curve = (
        ""
        if learning.curve_stop is None or args.checkpoints == 0
        else ", without the learning curve (out of --max-wall; summary.json -> learning_curve_stop)"
    )
    if stop is not None and result.stopped is not None:
        print(
            f"stopped: {result.stopped}; wrote {out} with the logs up "
            f"to t = {stop.time:.6g} s{no_curve}",
            file=sys.stderr,
        )
        return EXIT_STOPPED
    if graph.suffix == ".dot":
        print(
            f"note: Graphviz 'dot' not found; wrote {out / graph.name} instead of "
            "diagram.svg (install with `apt-get install -y graphviz`)."
        )
    if result.validity is not None and not result.validity.valid:
        print(f"{result.validity.warning()} {VALIDITY_DOCS}", file=sys.stderr)
    elif result.validity is not None and not result.validity.box_checked:
        print(f"note: {result.validity.note}.", file=sys.stderr)
    if loop.design is not None and not loop.design.is_decay_certified:
        print(
            f"note: the observer gains satisfy the {loop.design.formulation!r} LMI but not "
            "the sound decay certificate (is_decay_certified is false); use "
            "formulation: polytopic for a guarantee. See docs/theory.md.",
            file=sys.stderr,
        )
    if verification is not None and loop.design is not None:  # verified only with a design
        line = verification.verdict(
            loop.design.is_decay_certified, loop.design.bounds_are_guaranteed
        )
        print(f"observer: {line}" + (f" {CERTIFICATE_DOCS}" if verification.falsified else ""))
    elif unverified is not None and learning.curve_stop is not None:  # the curve's line is last
        print(f"note: {unverified}.", file=sys.stderr)
    s = result.summary()
    if not s["regulated"]:
        print(_not_regulated(s["regulation"]), file=sys.stderr)
    distance = "|x(T)|" if result.x_equilibrium is None else "|x(T) - x*|"
    print(
        f"wrote {out}: {distance} = {s['final_state_norm']:.3g}, "
        f"|e(T)| = {s['final_estimation_error_norm']:.3g}, J(T) = {s['final_cost']:.4g}, "
        f"simulated in {s['wall_time']:.2f} s, {time.perf_counter() - args.started:.1f} s in all"
    )
    if learning.curve_stop is not None:  # the run is whole and reported above; its curve is not
        print(
            f"stopped: timeout: {learning.curve_stop.rstrip('.')}; wrote {out} with the whole "
            f"run{no_curve}",
            file=sys.stderr,
        )
        return EXIT_STOPPED
    if unverified is not None:  # the run is whole and reported above; its verification is not
        print(
            f"stopped: timeout: {unverified}; wrote {out} with the whole run, without the "
            "observer's verification (summary.json -> verification_stop)",
            file=sys.stderr,
        )
        return EXIT_STOPPED
    return EXIT_OK


@dataclasses.dataclass(frozen=True)
class FigureInputs:
    """What a run's figures need of its scenario, beside the run's own files.

    ``run`` writes it into ``summary.json`` (:data:`FIGURE_INPUTS_KEY`),
    ``plot`` reads it back (:meth:`read`): neither the scenario nor its
    plant's code is needed to redraw a run.

    Attributes
    ----------
    input_bound : float
        ``lambda_bar``, drawn as ``+-lambda_bar`` on the input.
    inputs : int
        The number of inputs ``m`` (``u`` of the run has ``m`` columns).
    box_lower, box_upper : tuple of float
        The observer box, drawn on the states (``n`` entries each).
    basis_degrees : tuple of int
        The critic's basis (``critic.basis_degrees``), which names the weights.
    """

    input_bound: float
    inputs: int
    box_lower: tuple[float, ...]
    box_upper: tuple[float, ...]
    basis_degrees: tuple[int, ...]

    @classmethod
    def of(cls, scenario: Any) -> FigureInputs:
        """The figure inputs of a loaded, validated ``scenario``."""
        box = scenario.observer.box
        return cls(
            input_bound=float(scenario.input_bound),
            inputs=len(scenario.cost.R),
            box_lower=tuple(float(v) for v in box.lower),
            box_upper=tuple(float(v) for v in box.upper),
            basis_degrees=tuple(int(d) for d in scenario.critic.basis_degrees),
        )

    def to_dict(self) -> dict[str, Any]:
        """For ``summary.json`` -> :data:`FIGURE_INPUTS_KEY`."""
        return {
            "input_bound": self.input_bound,
            "inputs": self.inputs,
            "observer_box": {"lower": list(self.box_lower), "upper": list(self.box_upper)},
            "basis_degrees": list(self.basis_degrees),
        }

    @classmethod
    def from_dict(cls, data: Any) -> FigureInputs:
        """The inputs :meth:`to_dict` wrote (also the same keys of a scenario file).

        Raises
        ------
        TypeError, ValueError, KeyError
            If an entry is missing or of the wrong type, ``input_bound`` is
            not a number > 0, ``inputs`` or a degree not an integer >= 1, or
            the box's corners are not finite numbers of one length, lower
            below upper.
        """
        from ofrl_drake.checks import number_from_json, object_from_json, vector_from_json

        data = object_from_json(data)
        box = object_from_json(data["observer_box"])
        lower, upper = vector_from_json(box["lower"]), vector_from_json(box["upper"])
        input_bound = number_from_json(data["input_bound"])
        if not (math.isfinite(input_bound) and input_bound > 0):
            raise ValueError(f"input_bound {input_bound} is not a number > 0")
        if not (
            len(lower) == len(upper) >= 1
            and all(math.isfinite(v) for v in (*lower, *upper))
            and all(lo < hi for lo, hi in zip(lower, upper, strict=True))
        ):
            raise ValueError(
                f"the observer box {lower} to {upper} is not finite corners of one length, "
                "lower below upper"
            )
        degrees = data["basis_degrees"]
        if not (
            isinstance(degrees, list)
            and degrees
            and all(type(k) is int and k >= 1 for k in [data["inputs"], *degrees])
        ):
            raise ValueError("inputs and basis_degrees are integers >= 1 (a list of them)")
        return cls(
            input_bound=input_bound,
            inputs=data["inputs"],
            box_lower=tuple(lower),
            box_upper=tuple(upper),
            basis_degrees=tuple(degrees),
        )

    @classmethod
    def read(cls, run_dir: Path, result: Any) -> FigureInputs:
        """The figure inputs of the run folder ``run_dir``, checked against its run ``result``.

        From ``summary.json`` -> :data:`FIGURE_INPUTS_KEY` (``result.reports``);
        a folder written before ``run`` wrote it gives them from its
        :data:`SCENARIO_FILE`, read as data (its plant is not loaded), whose
        ``name`` must be the run's.

        Raises
        ------
        RunFolderError
            If neither holds them, one cannot be read (not YAML, an entry
            missing or of the wrong type), the scenario file is another
            scenario's, or they do not fit the run's arrays: a box of
            another length than the columns of ``x``, another number of
            inputs than the columns of ``u``, a basis of another size than
            the columns of ``W``. The message names the file, both values and
            the fix.
        """
        from ofrl_drake.basis import PolynomialBasis
        from ofrl_drake.errors import ModelError, RunFolderError
        from ofrl_drake.simulation import SUMMARY_FILE, TRAJECTORIES_FILE, summary_entry

        if FIGURE_INPUTS_KEY in result.reports:
            source = run_dir / SUMMARY_FILE
            inputs = summary_entry(source, result.reports, FIGURE_INPUTS_KEY, cls.from_dict)
        else:
            source = run_dir / SCENARIO_FILE
            inputs = _scenario_figure_inputs(source, result.scenario_name)
        assert inputs is not None  # the key is there, or the scenario file gave them
        n, m, L = result.x.shape[1], result.u.shape[1], result.W.shape[1]
        try:
            size = PolynomialBasis(n, list(inputs.basis_degrees)).size
        except ModelError as err:
            raise RunFolderError(
                f"{source}: the critic basis of degrees {list(inputs.basis_degrees)} is not one "
                f"a run could have used ({err}); the file was edited or comes from another "
                "run: run the scenario again."
            ) from None
        basis = f"the critic basis of degrees {list(inputs.basis_degrees)} has {size} terms"
        for theirs, ours, columns, said in (
            (
                len(inputs.box_lower),
                n,
                "x",
                f"the observer box has {len(inputs.box_lower)} entries",
            ),
            (inputs.inputs, m, "u", f"the scenario has {inputs.inputs} inputs"),
            (size, L, "W", basis),
        ):
            if theirs != ours:
                raise RunFolderError(
                    f"{source}: {said}, but {columns} in {TRAJECTORIES_FILE} has {ours} columns; "
                    "the files are of two runs, or one is damaged: write the run again "
                    "(ofrl-drake run SCENARIO --out NEW_DIR)."
                )
        return inputs


def _scenario_figure_inputs(path: Path, name: str) -> FigureInputs:
    """:class:`FigureInputs` from a run folder's scenario file, read as data (no plant loaded).

    Raises
    ------
    RunFolderError
        If the file is missing, too large, not YAML, not the scenario
        ``name``, or lacks an entry (or has one of the wrong type).
    """
    import yaml

    from ofrl_drake.errors import RunFolderError
    from ofrl_drake.scenario import MAX_SCENARIO_BYTES, check_yaml

    fix = "write the run again (ofrl-drake run SCENARIO --out NEW_DIR)"
    if not path.is_file():
        raise RunFolderError(
            f"RUN_DIR: {path}: no such file, and {path.parent / 'summary.json'} has no "
            f"{FIGURE_INPUTS_KEY} (a run written before it was saved there), so {path.parent} "
            "is not the --out folder of ofrl-drake run (which writes the scenario it ran "
            "there); name one."
        )
    if path.stat().st_size > MAX_SCENARIO_BYTES:
        raise RunFolderError(f"{path}: larger than a scenario file may be; {fix}.")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise RunFolderError(f"{path}: cannot be read ({err}); {fix}.") from None
    try:
        check_yaml(path, text, error=RunFolderError)
        data = yaml.safe_load(text)
    except RunFolderError as err:
        raise RunFolderError(f"{str(err).rstrip('.')}; {fix}.") from None
    except yaml.YAMLError as err:
        why = one_line(err, 200)
        raise RunFolderError(f"{path}: not valid YAML ({why}); {fix}.") from None
    if not isinstance(data, dict):
        raise RunFolderError(
            f"{path}: a YAML {type(data).__name__}, not a scenario's mapping of keys; {fix}."
        )
    if data.get("name") != name:
        raise RunFolderError(
            f"{path}: the scenario {data.get('name')!r}, but summary.json holds a run of "
            f"{name!r}; the files are of two runs: {fix}."
        )
    try:
        return FigureInputs.from_dict(
            {
                "input_bound": data["input_bound"],
                "inputs": len(data["cost"]["R"]),
                "observer_box": data["observer"]["box"],
                "basis_degrees": data["critic"]["basis_degrees"],
            }
        )
    except (TypeError, ValueError, KeyError) as err:
        raise RunFolderError(
            f"{path}: the input bound, cost.R, observer.box or critic.basis_degrees cannot "
            f"be read ({err}); {fix}."
        ) from None


def save_run_figures(
    result: Any,
    inputs: FigureInputs,
    learning: Any,
    directory: Path,
    *,
    formats: Sequence[str] = ("png",),
    size: str = "page",
) -> list[Path]:
    """Every figure of a run into ``directory``: what ``run`` draws and ``plot`` redraws.

    Parameters
    ----------
    result : SimulationResult
        The run, as simulated or as read back (:meth:`~ofrl_drake.SimulationResult.load`).
    inputs : FigureInputs
        What the figures need of the scenario it ran (:meth:`FigureInputs.of`,
        or :meth:`FigureInputs.read`): the input bound, the observer box and
        the critic's basis.
    learning : LearningReport or None
        Its learning curve and health (:func:`ofrl_drake.learning_curve.learning_report`,
        or :meth:`~ofrl_drake.learning_curve.LearningReport.load`); None: neither figure.
    directory : Path
    formats, size
        As for :func:`ofrl_drake.plotting.save_figures`.

    Returns
    -------
    list of Path
        Every file written.
    """
    from ofrl_drake.basis import PolynomialBasis
    from ofrl_drake.plotting import save_figures

    basis = PolynomialBasis(result.x.shape[1], list(inputs.basis_degrees))
    return save_figures(
        result,
        directory,
        input_bound=inputs.input_bound,
        weight_labels=basis.labels(),
        box=(list(inputs.box_lower), list(inputs.box_upper)),
        learning_curve=None if learning is None else learning.curve,
        optimal_cost=None if learning is None else learning.optimal_cost,
        lqr_cost=None if learning is None else learning.lqr_policy_cost,
        health=None if learning is None else learning.health,
        formats=formats,
        size=size,
    )


def _cmd_plot(args: argparse.Namespace) -> int:
    """``plot``, holding the run folder's lock shared and ``--out``'s exclusive.

    ``run`` holds the run folder's lock exclusive while it writes that folder
    (:func:`ofrl_drake.atomic.output_lock`): a run folder being written is
    refused, not read half-way, and a run into a folder ``plot`` reads is
    refused too; two plots of one run may read it together.
    """
    run_dir = _run_folder(args.run_dir)
    out = run_dir / FIGURES_FOLDER if args.out is None else Path(args.out)
    target = check_figures_directory(out, run_dir)
    with output_lock(run_dir, "RUN_DIR", shared=True), output_lock(target):
        return _plot(args, run_dir, target)


def _run_folder(run_dir: str) -> Path:
    """``plot``'s RUN_DIR, resolved; refused unless a folder.

    Raises
    ------
    RunFolderError
        If ``run_dir`` is empty or not a folder.
    """
    from ofrl_drake.errors import RunFolderError

    if not run_dir:
        raise RunFolderError("RUN_DIR: the path is empty; name the --out folder of a run.")
    path = Path(run_dir).expanduser().resolve()
    if not path.is_dir():
        raise RunFolderError(
            f"RUN_DIR: {run_dir} is not a folder; name the --out folder of ofrl-drake run."
        )
    return path


def _plot(args: argparse.Namespace, run_dir: Path, target: Path) -> int:
    from ofrl_drake.learning_curve import LearningReport
    from ofrl_drake.simulation import SimulationResult

    result = SimulationResult.load(run_dir)
    inputs = FigureInputs.read(run_dir, result)
    learning = LearningReport.load(run_dir, result)
    formats = list(dict.fromkeys(args.format or ["png"]))
    with atomic_directory(target, run_dir) as tmp:
        written = save_run_figures(result, inputs, learning, tmp, formats=formats, size=args.size)
    args.written = target
    names = sorted({path.stem for path in written})
    print(
        f"wrote {target}: {len(names)} figures ({', '.join(formats)}, "
        f"{args.size} size) of {run_dir}"
    )
    return EXIT_OK


def _check_output_file(out: str, scenario: str) -> Path:
    """Check the ``--out FILE`` of ``design-observer`` and ``verify-observer`` before the work.

    The file is written after the design (seconds to minutes): a path that
    cannot take it is refused first. So is the scenario file itself
    (``design-observer same.yaml --out same.yaml`` replaced the scenario with
    JSON), also through a link or under another spelling.

    Raises
    ------
    OutputError
        If ``out`` is the scenario file, not a regular file (a folder, a link,
        a device: :func:`ofrl_drake.atomic.check_output_target`), or cannot be
        created (:func:`ofrl_drake.atomic.check_writable`).
    """
    target = check_output_target(out)
    try:
        same = target.exists() and os.path.samefile(target, scenario)
    except OSError:  # the scenario cannot be read: load_scenario names it
        same = False
    if same:
        raise OutputError(
            f"--out: {out} is the scenario file {scenario}; the JSON would replace the "
            "scenario. Name another file for the output."
        )
    return check_writable(target)


def _scenario_design(
    args: argparse.Namespace, out: str | None
) -> tuple[Any, ControlAffineSystem, ObserverDesign]:
    """The scenario, system and observer design of ``design-observer`` and ``verify-observer``.

    ``out`` (the ``--out`` file, None for none) is checked after the scenario
    is read and before the design: fail before the work, not after.

    Raises
    ------
    OfrlError
        From :func:`_with_max_wall`, :func:`_check_output_file` (``OutputError``),
        loading the scenario, resolving its system or designing.
    """
    from ofrl_drake.plants import resolve_system
    from ofrl_drake.scenario import load_scenario
    from ofrl_drake.variants import design_for

    scenario = _with_max_wall(load_scenario(args.scenario), args.max_wall)
    if out is not None:
        _check_output_file(out, args.scenario)  # fail before the work, not after
    system = resolve_system(scenario)
    return scenario, system, design_for(scenario, system)


def _cmd_design_observer(args: argparse.Namespace) -> int:
    from ofrl_drake.verification import verify_observer

    _, system, design = _scenario_design(args, args.out)
    verification = verify_observer(design, system)  # the fast check shown next to every design
    data = design.to_dict()
    data["verification"] = verification.to_dict()
    atomic_write_text(Path(args.out), _strict_json(data))
    args.written = args.out
    print(
        f"wrote {args.out}: alpha = {design.alpha}, ||L|| = {design.gain_norm:.4g}, "
        f"max certificate eigenvalue = {design.max_eigenvalue:.3g}"
    )
    print(
        f"observer: {verification.verdict(design.is_decay_certified, design.bounds_are_guaranteed)}"
    )
    return EXIT_OK


def _verify(
    design: ObserverDesign | None,
    system: ControlAffineSystem,
    budget: float | None = None,
    started: float = 0.0,
) -> tuple[VerificationReport | None, str | None]:
    """The fast falsification attempt shown next to every design, or why there is none.

    ``(None, None)`` without a design. With ``budget`` (``--max-wall``, counted
    from ``started``, a ``time.monotonic()`` reading) the search stops when it
    is spent: ``(None, why)``.
    """
    if design is None:
        return None, None
    from ofrl_drake.errors import WallTimeExceeded
    from ofrl_drake.verification import verify_observer

    deadline = None if budget is None else started + budget
    try:
        return verify_observer(design, system, deadline=deadline), None
    except WallTimeExceeded as err:
        return None, (
            f"the observer's verification did not finish within max_wall_time (--max-wall) = "
            f"{budget:g} s: {one_line(err)}; allow more wall time (a larger --max-wall)"
        )


def _cmd_verify_observer(args: argparse.Namespace) -> int:
    from ofrl_drake.verification import verify_observer

    scenario, system, design = _scenario_design(args, args.out or None)
    report = verify_observer(design, system, samples=args.samples, seed=args.seed)
    if args.out:
        data = {
            "scenario": scenario.name,
            "verification": report.to_dict(),
            "observer_design": design.to_dict(),
        }
        atomic_write_text(Path(args.out), _strict_json(data))
        args.written = args.out
    print(
        f"{scenario.name}: "
        f"{report.verdict(design.is_decay_certified, design.bounds_are_guaranteed)}"
    )
    return EXIT_FALSIFIED if report.falsified else EXIT_OK


#: Seconds past ``--scheduler-timeout`` left to distributed to report a failed connection
#: itself (its own message names the cause) before the connection is abandoned.
CONNECT_GRACE = 1.0


def _check_scheduler_address(scheduler: str, error: type[OfrlError]) -> None:
    """Refuse a ``--scheduler`` that is not the address of a dask scheduler, before connecting.

    Raises
    ------
    OfrlError
        (``error``: the command's own class) If ``scheduler`` has no port, an
        unknown scheme, or a port outside 1-65535.
    """
    from distributed.comm import registry
    from distributed.comm.addressing import get_address_host_port, parse_address

    try:
        registry.get_backend(parse_address(scheduler)[0])
        port = get_address_host_port(scheduler)[1]
        if not 0 < port < 65536:
            raise ValueError(f"port {port} is not in 1-65535")
    except (ValueError, TypeError) as err:
        raise error(
            f"--scheduler: {scheduler!r} is not a scheduler address ({err}); give "
            "tcp://HOST:PORT of a running dask scheduler."
        ) from None


def _connect(scheduler: str, wait: float, error: type[OfrlError]) -> Any:
    """A ``distributed.Client`` of ``scheduler``, within ``wait`` seconds or not at all.

    distributed bounds the TCP connection by ``timeout``, not the handshake
    after it: a server that accepts and stays silent (an HTTP server, a
    scheduler that hangs) held ``Client`` forever, and one that sends
    something else (an SSH banner) read as a message of exabytes
    (``MemoryError``). So the scheduler is asked first by an asynchronous
    client, in an event loop of its own (in a thread, which ends with it),
    given ``wait`` seconds and :data:`CONNECT_GRACE`: on time or not, that
    client is closed, and nothing of it is left running or registered as
    dask's default client. Only a scheduler that answered it is connected
    to, by the ``Client`` returned.

    Raises
    ------
    OfrlError
        (``error``) If no dask scheduler answered at ``scheduler`` in time, or
        connecting raised anything at all; naming the address and the cause.
    """
    import asyncio

    from distributed import Client

    async def ask() -> None:
        client = Client(scheduler, asynchronous=True, timeout=wait, set_as_default=False)
        try:
            await asyncio.wait_for(client, wait + CONNECT_GRACE)
        except asyncio.TimeoutError as err:  # ours (no text), or distributed's own
            raise (_NoAnswer() if not str(err) else err) from None
        finally:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(client.close(), CONNECT_GRACE)

    failed: list[BaseException] = []

    def probe() -> None:
        try:
            asyncio.run(ask())
        except Exception as err:  # whatever the server sent: the command's one-line error
            failed.append(err)

    # A thread of its own, as the caller may be in an event loop (asyncio.run refuses one).
    thread = threading.Thread(target=probe, name="ofrl-drake connect", daemon=True)
    thread.start()
    thread.join()  # bounded: wait + CONNECT_GRACE, then CONNECT_GRACE to close
    try:
        if not failed:
            return Client(scheduler, timeout=wait)
    except Exception as err:
        failed.append(err)
    cause = failed[0]
    if isinstance(cause, _NoAnswer):
        why = f"no dask scheduler answered after {wait:g} s"
    elif isinstance(cause, (OSError, TimeoutError)):
        why = one_line(cause)
    else:
        text = one_line(cause, 200)
        why = f"what answered there is not a dask scheduler: {type(cause).__name__}: {text}"
    raise error(
        f"--scheduler: cannot connect to {scheduler} within --scheduler-timeout {wait:g} s "
        f"({why}); start a dask scheduler there, check the address (a dask scheduler's port, "
        "not another server's), or raise --scheduler-timeout."
    ) from None


class _NoAnswer(Exception):
    """No dask scheduler answered :func:`_connect` in time."""


@contextlib.contextmanager
def _sigint_kept_from_children() -> Iterator[None]:
    """Hold SIGINT while the block starts processes, which never receive it.

    A terminal's Ctrl-C goes to the whole process group: Dask's worker
    processes, interrupted mid-start (``Fatal Python error:
    init_import_site``) or mid-task, printed dozens of lines of tracebacks
    beside the command's one line. In the block, SIGINT is blocked in this
    thread's signal mask; the threads started in it (the cluster's event loop,
    the threads that start each worker, and restart it later) inherit the
    mask, and the processes they start keep it across ``exec``, so the
    workers leave the interrupt to the command, which closes them. The
    command itself loses no SIGINT: one that comes in the block (the cluster's
    start, seconds) is held (:func:`~ofrl_drake.atomic.sigint_held`) and raised as
    ``KeyboardInterrupt`` when the block ends. (Ignoring SIGINT in the block,
    which the workers would inherit as well, would drop that Ctrl-C: the sweep
    went on to its end.) Outside the main thread, or with SIGINT ignored (the
    workers inherit that), the block runs as is (:func:`~ofrl_drake.atomic.sigint_handled_here`).
    """
    if not sigint_handled_here():
        yield
        return
    from multiprocessing import resource_tracker

    # Started now, not by the block's first process: starting it unblocks SIGINT in the
    # thread that starts it, and every thread that thread starts inherits its mask.
    resource_tracker.ensure_running()
    with sigint_held():
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            yield
        finally:  # a SIGINT the mask kept pending is delivered here, to sigint_held's handler
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)


@contextlib.contextmanager
def _dask_client(
    scheduler: str | None,
    workers: int | None,
    wait: float = 60.0,
    error: type[OfrlError] = OfrlError,
) -> Iterator[object]:
    """A client of the cluster at ``scheduler``, or of an embedded ``LocalCluster``.

    ``wait`` seconds (``--scheduler-timeout``) bound both the connection to
    ``scheduler`` (:func:`_connect`) and, with what is left of them, the wait
    for its first worker; then the command stops with exit 2. The workers of
    a ``LocalCluster`` never get SIGINT (:func:`_sigint_kept_from_children`):
    a Ctrl-C stops the command, which closes them, without a line of theirs.

    Raises
    ------
    OfrlError
        (``error``: the command's own class) If ``scheduler`` is not an address,
        cannot be reached within ``wait`` seconds, or has no worker by then.
    """
    import logging

    from distributed import Client, LocalCluster

    if scheduler:
        deadline = time.monotonic() + wait
        _check_scheduler_address(scheduler, error)
        with _connect(scheduler, wait, error) as client:
            try:
                # Dask waits forever for timeout=0: at least a moment, which finds a worker
                # already there.
                client.wait_for_workers(1, timeout=max(deadline - time.monotonic(), 0.01))
            except TimeoutError:
                raise error(
                    f"--scheduler: no worker joined {scheduler} within {wait:g} s; start one "
                    f"(dask worker {scheduler}) or raise --scheduler-timeout."
                ) from None
            yield client
        return
    if workers is None:
        workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
        workers = workers or os.cpu_count() or 1
    logging_was = logging.root.manager.disable
    cluster = contextlib.ExitStack()  # closes the client, then the cluster
    try:
        with _sigint_kept_from_children():
            local = cluster.enter_context(
                LocalCluster(
                    n_workers=workers,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                    # No dashboard; its HTTP server on any free local port, not 8787, which
                    # another cluster may hold ("warning: Port 8787 is already in use").
                    scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                    silence_logs=logging.ERROR,
                )
            )
            client = cluster.enter_context(Client(local))
        yield client
    except BaseException:
        # Closing a cluster whose tasks were cut short (Ctrl-C) logs distributed's errors
        # (lost workers, cancelled tasks): the command prints its own line instead.
        logging.disable(logging.CRITICAL)
        raise
    finally:
        try:
            # A Ctrl-C while the cluster closes is raised after it, not in the middle (a
            # cluster left half-closed for Python's exit to close, with a traceback).
            with sigint_held():
                cluster.close()
        finally:
            logging.disable(logging_was)


def _locked(command: Any) -> Any:
    """``command(args)`` holding the lock of ``args.out`` (:func:`ofrl_drake.atomic.output_lock`).

    Two sweeps into one folder (two ``--resume`` at once) would write the same
    rows twice; the second is refused instead.
    """

    def run(args: argparse.Namespace) -> int:
        out = check_output_target(args.out, folder=True)
        _check_output_place(out)  # as run does: not the current folder, not a root
        with output_lock(out):
            return command(args)

    run.__doc__ = command.__doc__
    return run


def _run_sweep(
    args: argparse.Namespace,
    sweep: Callable[[Any], list[dict]],
    table: Path,
    error: type[OfrlError],
    report: Callable[[list[dict]], int],
) -> int:
    """``sweep(client)`` (serially with ``--workers 0``, else on Dask), then ``report(rows)``.

    Returns ``report``'s exit code. An interrupt (SIGINT, SIGTERM), in the
    sweep or in its report (the figures, ``J*``), keeps the rows finished in
    ``table`` and returns the exit code, after one line saying how to resume.
    ``error`` is the command's exception class, for a scheduler that cannot
    be used (:func:`_dask_client`). An interrupt Python swallowed in the
    sweep or its report is one too (:func:`_interrupts_not_swallowed`).
    """
    try:
        with _interrupts_not_swallowed():
            if args.workers == 0 and not args.scheduler:
                rows = sweep(None)
            else:
                with _dask_client(
                    args.scheduler, args.workers, args.scheduler_timeout, error
                ) as client:
                    rows = sweep(client)
            return report(rows)
    except KeyboardInterrupt as err:
        what = "terminated (SIGTERM)" if isinstance(err, Terminated) else "interrupted"
        kept = (
            f"finished rows are in {table}; rerun with --resume to complete the sweep"
            if table.exists()
            else "no output written"  # stopped before the sweep wrote anything
        )
        _print_error(f"error: {what}; {kept}")
        return EXIT_TERMINATED if isinstance(err, Terminated) else EXIT_INTERRUPTED


def _cmd_ablate(args: argparse.Namespace) -> int:
    from ofrl_drake.ablation import ablate
    from ofrl_drake.ablation_grid import (
        AblationError,
        default_variants,
        initial_state_label,
        load_variants,
        sample_initial_states,
    )
    from ofrl_drake.ablation_report import summary_table, write_report
    from ofrl_drake.optimal import OptimalCostCache, solver_name
    from ofrl_drake.scenario import load_scenario

    if args.workers is not None and args.workers < 0:
        raise AblationError(f"--workers: must be >= 0; got {args.workers}.")
    _check_solver(args.solver)
    scenario = _with_max_wall(load_scenario(args.scenario), args.max_wall)
    variants = load_variants(args.variants) if args.variants else default_variants(scenario)
    states = sample_initial_states(scenario, args.initial_states, args.seed)
    out = Path(args.out)
    if args.retry_failed and not args.resume:
        raise AblationError("--retry-failed: reruns failed rows of a sweep; pass --resume too.")
    options = {
        "out": out,
        "resume": args.resume,
        "seed": args.seed,
        "retry_failed": args.retry_failed,
        "solver": args.solver,
    }

    def report(rows: list[dict]) -> int:
        x0_label = initial_state_label(scenario.x0)
        optimum = OptimalCostCache(out / "optimal", solver=args.solver).get(scenario, scenario.x0)
        write_report(
            out,
            rows,
            [v.name for v in variants],
            scenario_name=scenario.name,
            x0_label=x0_label,
            duration=scenario.simulation.duration,
            optimum=optimum.trajectory if optimum is not None else None,
            equilibrium=scenario.equilibrium.x if scenario.equilibrium is not None else None,
            accuracy=scenario.simulation.accuracy,
            solver=solver_name(args.solver).upper(),
        )
        ok = sum(r["status"] == "ok" for r in rows)
        print(summary_table(rows, [v.name for v in variants]))
        print(
            f"wrote {out}: {len(rows)} runs ({ok} ok), ablation.csv, ablation.md, "
            "figures/optimality_ratio.png, figures/trajectories.png"
        )
        return EXIT_OK

    return _run_sweep(
        args,
        lambda client: ablate(scenario, variants, states, client, **options),
        out / "ablation.csv",
        AblationError,
        report,
    )


def _cmd_montecarlo(args: argparse.Namespace) -> int:
    from ofrl_drake.monte_carlo import (
        MonteCarloError,
        montecarlo,
        montecarlo_table,
        write_montecarlo_report,
    )
    from ofrl_drake.scenario import load_scenario

    if args.workers is not None and args.workers < 0:
        raise MonteCarloError(f"--workers: must be >= 0; got {args.workers}.")
    _check_solver(args.solver)
    scenario = _with_max_wall(load_scenario(args.scenario), args.max_wall)
    out = Path(args.out)
    options = {
        "mass_spread": args.mass_spread,
        "out": out,
        "resume": args.resume,
        "solver": args.solver,
    }

    def report(rows: list[dict]) -> int:
        write_montecarlo_report(out, rows, scenario.name)
        print(montecarlo_table(rows), end="")
        good = sum(r["status"] == "ok" and r["regulated"] == "true" for r in rows)
        envelope = ", figures/envelope.png" if (out / "figures" / "envelope.png").is_file() else ""
        print(
            f"wrote {out}: {len(rows)} runs ({good} ok and regulated), montecarlo.csv, "
            f"montecarlo.md{envelope}"
        )
        return EXIT_OK

    return _run_sweep(
        args,
        lambda client: montecarlo(scenario, args.runs, args.seed, client=client, **options),
        out / "montecarlo.csv",
        MonteCarloError,
        report,
    )


def _positive_seconds(text: str) -> float:
    """``--scheduler-timeout``'s value: a finite number of seconds > 0.

    Dask waits without a deadline for ``timeout=0`` and never times out on
    NaN, so both (and negative or infinite values) are refused while parsing,
    before any scheduler is contacted.
    """
    try:
        seconds = float(text)
    except ValueError:
        seconds = float("nan")
    if not (seconds > 0 and math.isfinite(seconds)):
        raise argparse.ArgumentTypeError(
            f"must be a finite number of seconds > 0 to wait for a worker, e.g. 60; got {text!r}"
        )
    return seconds


def _count_at_most(most: int, fix: str) -> Callable[[str], int]:
    """An argparse type: a whole number of at most ``most``, refused while parsing.

    A huge count (``--runs 1000000000``) would allocate gigabytes, or run for
    days, before anything is written; it is refused in one line naming the
    value, the limit and ``fix``. Not-a-number reads as argparse's own
    ``invalid int value``; the lower bound is each command's own check.
    """

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
        if value > most:
            raise argparse.ArgumentTypeError(f"{value} is more than the limit of {most}; {fix}")
        return value

    return parse


def _check_solver(solver: str | None) -> None:
    """Refuse an unknown or unavailable ``--solver`` before any work, naming the option."""
    if solver is None:
        return
    from ofrl_drake.optimal import solver_name

    try:
        solver_name(solver)
    except OfrlError as err:
        raise OfrlError(f"--solver: {one_line(err)}") from None


def _solver_option(parser: argparse.ArgumentParser, when: str) -> None:
    parser.add_argument(
        "--solver",
        metavar="NAME",
        help=f"the nonlinear-programming solver of J* ({when}): snopt or ipopt (default: "
        "snopt when available; ipopt settles a J* too small for snopt's tolerances)",
    )


def _scheduler_timeout_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scheduler-timeout",
        type=_positive_seconds,
        default=60.0,
        metavar="SECONDS",
        help="wait at most this long for a worker of --scheduler (seconds > 0; default 60)",
    )


def _design_wall_option(command: argparse.ArgumentParser) -> None:
    command.add_argument(
        "--max-wall",
        type=float,
        metavar="SECONDS",
        help="stop the design (Jacobian bounds, then the LMI solve) after this much wall "
        "time, with exit 2 and no output; overrides simulation.max_wall_time",
    )


class _OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line, ``error: ...``, and exit 2.

    argparse's own prints the usage (several lines) and ``PROG: error: ...``;
    every other bad input of ``ofrl-drake`` is one line naming the fix.
    """

    def error(self, message: str) -> NoReturn:
        text = " ".join(message.split())
        self.exit(EXIT_BAD_INPUT, f"error: {text}; see {self.prog} --help\n")


def _parser() -> argparse.ArgumentParser:
    parser = _OneLineParser(
        prog="ofrl-drake",
        description="Output-feedback model-based RL control as Drake block diagrams.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_OneLineParser)

    run = sub.add_parser("run", help="simulate a scenario; write logs, figures and graph")
    run.add_argument("scenario", help="scenario YAML file, e.g. diagrams/two_state_paper.yaml")
    run.add_argument("--out", required=True, help="output directory (replaced atomically)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.add_argument(
        "--max-wall",
        type=float,
        metavar="SECONDS",
        help="stop with status timeout (exit 3) after this much wall time; overrides "
        "simulation.max_wall_time",
    )
    run.add_argument(
        "--checkpoints",
        type=_count_at_most(MAX_CHECKPOINTS, CHECKPOINTS_FIX),
        default=10,
        metavar="K",
        help="evaluate the policy in force at K + 1 times 0, T/K, ..., T, true state fed "
        f"back, for the learning curve (default 10; 0 switches it off; at most {MAX_CHECKPOINTS})",
    )
    run.add_argument(
        "--optimal",
        action="store_true",
        help="also solve for J* (direct collocation) and report the learning curve as J/J*",
    )
    _solver_option(run, "with --optimal")
    run.set_defaults(func=_cmd_run)

    design = sub.add_parser("design-observer", help="certified observer gains as JSON")
    design.add_argument("scenario", help="scenario YAML file")
    design.add_argument("--out", required=True, help="output JSON file")
    _design_wall_option(design)
    design.set_defaults(func=_cmd_design_observer)

    verify = sub.add_parser(
        "verify-observer",
        help="falsify the observer design against the true error dynamics "
        "(exit 4 on a counterexample)",
    )
    verify.add_argument("scenario", help="scenario YAML file")
    verify.add_argument(
        "--samples", type=int, default=10_000, metavar="N", help="sampled points (default 10000)"
    )
    verify.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the samples")
    verify.add_argument("--out", metavar="FILE.json", help="also write the report as JSON")
    _design_wall_option(verify)
    verify.set_defaults(func=_cmd_verify_observer)

    ab = sub.add_parser(
        "ablate", help="every variant from several initial states, against the optimal cost"
    )
    ab.add_argument("scenario", help="scenario YAML file")
    ab.add_argument(
        "--out", required=True, metavar="DIR", help="output directory (rows stream into it)"
    )
    ab.add_argument(
        "--variants",
        metavar="FILE.yaml",
        help="variants as {name: {slot: choice}}; default: baseline and every single-slot swap",
    )
    ab.add_argument(
        "--initial-states",
        type=_count_at_most(MAX_INITIAL_STATES, INITIAL_STATES_FIX),
        default=0,
        metavar="K",
        help="states sampled in the observer box, besides the scenario's x0 (default 0; "
        f"at most {MAX_INITIAL_STATES})",
    )
    ab.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the samples")
    _solver_option(ab, "of every initial state")
    ab.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="workers of the embedded Dask LocalCluster (default: one per core; "
        "0 runs serially without Dask)",
    )
    ab.add_argument(
        "--scheduler", metavar="ADDRESS", help="use the Dask cluster at tcp://HOST:PORT"
    )
    ab.add_argument(
        "--resume", action="store_true", help="keep the rows in DIR/ablation.csv; run the rest"
    )
    ab.add_argument(
        "--retry-failed",
        action="store_true",
        help="with --resume, also run again the rows whose status is not ok",
    )
    ab.add_argument(
        "--max-wall",
        type=float,
        metavar="SECONDS",
        help="stop each run after this much wall time (status timeout in its row); "
        "overrides simulation.max_wall_time",
    )
    _scheduler_timeout_option(ab)
    ab.set_defaults(func=_locked(_cmd_ablate))

    mc = sub.add_parser(
        "montecarlo",
        help="run a scenario under N noise seeds (and sampled truths); success rate and statistics",
    )
    mc.add_argument("scenario", help="scenario YAML file")
    mc.add_argument(
        "--runs",
        type=_count_at_most(MAX_RUNS, RUNS_FIX),
        required=True,
        metavar="N",
        help=f"number of runs (at most {MAX_RUNS})",
    )
    mc.add_argument(
        "--seed", type=int, default=0, metavar="S", help="run k uses measurement seed S + k"
    )
    mc.add_argument(
        "--mass-spread",
        type=float,
        default=0.0,
        metavar="F",
        help="scale each body mass of a multibody truth by U[1 - F, 1 + F] per run (default 0)",
    )
    _solver_option(mc, "of the nominal problem")
    mc.add_argument("--out", required=True, help="output folder (rows streamed as runs finish)")
    mc.add_argument("--resume", action="store_true", help="complete the sweep in --out")
    mc.add_argument("--workers", type=int, metavar="W", help="local Dask workers (0: serial)")
    mc.add_argument("--scheduler", metavar="ADDR", help="tcp://HOST:PORT of a Dask scheduler")
    mc.add_argument(
        "--max-wall", type=float, metavar="SECONDS", help="stop each run after this wall time"
    )
    _scheduler_timeout_option(mc)
    mc.set_defaults(func=_locked(_cmd_montecarlo))

    plot = sub.add_parser(
        "plot", help="redraw a run's figures from its saved files, without simulating"
    )
    plot.add_argument("run_dir", metavar="RUN_DIR", help="the --out folder of ofrl-drake run")
    plot.add_argument(
        "--out",
        metavar="DIR",
        help=f"output folder, replaced atomically (default RUN_DIR/{FIGURES_FOLDER}, where "
        "run drew them)",
    )
    plot.add_argument(
        "--format",
        nargs="+",
        action="extend",  # --format pdf --format svg: both (a default list would be extended)
        type=_figure_choice("FIGURE_FORMATS"),
        metavar="FORMAT",
        help="file formats: one or more of png, pdf, svg (default png)",
    )
    plot.add_argument(
        "--size",
        type=_figure_choice("FIGURE_SIZES"),
        default="page",
        help="page (about 7 in wide, as run draws them) or column (3.5 in); default page",
    )
    plot.set_defaults(func=_cmd_plot)
    return parser


def _figure_choice(choices: str) -> Callable[[str], str]:
    """An argparse type: one of ``ofrl_drake.plotting``'s ``choices`` (a constant's name).

    matplotlib is imported only when the option is given, not for every command.
    """

    def parse(text: str) -> str:
        from ofrl_drake import plotting

        allowed = getattr(plotting, choices)
        if text not in allowed:
            raise argparse.ArgumentTypeError(
                f"unknown value {text!r}; choose one of {', '.join(allowed)}"
            )
        return text

    return parse


#: Modules each command needs, imported with SIGINT held (:func:`~ofrl_drake.atomic.sigint_held`).
_COMMAND_MODULES = {
    "run": (
        "ofrl_drake.diagram",
        "ofrl_drake.graph",
        "ofrl_drake.plotting",
        "ofrl_drake.simulation",
    ),
    "plot": (
        "ofrl_drake.learning_curve",
        "ofrl_drake.plotting",
        "ofrl_drake.simulation",
    ),
    "ablate": (
        "ofrl_drake.ablation",
        "ofrl_drake.ablation_report",
        "ofrl_drake.simulation",
        "distributed",
    ),
}
#: What any other command imports first: enough to initialize pydrake.
_DEFAULT_MODULES = ("ofrl_drake.diagram",)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Python next runs, so it unwinds like Ctrl-C: nothing partial."""


def _raise_terminated(signum: int, frame: Any) -> None:
    raise Terminated


def _user_code_frame(err: BaseException) -> Any:
    """The innermost frame of ``err``'s traceback in the user's own code, or None.

    A frame is the user's when its file is an absolute path to a file that
    exists, neither in ofrl_drake, nor in an installed package
    (``site-packages``, ``dist-packages``), nor in Python's standard library:
    e.g. the module of a plant named ``module:callable``, whose ``f`` raised
    during a run. Compiled (Cython) frames name their source relative to the
    package that was built (``numpy/random/bit_generator.pyx``), and
    ``<frozen ...>`` or ``<string>`` name no file: neither is the user's.
    """
    import sysconfig
    import traceback

    package = Path(__file__).resolve().parent
    stdlib = Path(sysconfig.get_paths()["stdlib"]).resolve()
    for frame in reversed(traceback.extract_tb(err.__traceback__)):
        if not os.path.isabs(frame.filename) or not os.path.isfile(frame.filename):
            continue
        path = Path(frame.filename).resolve()
        if package in path.parents or stdlib in path.parents:
            continue
        if {"site-packages", "dist-packages"} & set(path.parts):
            continue
        return frame
    return None


def _user_frame_behind(err: BaseException) -> Any:
    """The innermost frame of the user's own code behind ``err``, or None.

    ``err`` is an ofrl_drake error that may wrap one raised in the user's code
    (``system: 'rp.py:make_plant' raised ModelError: f(x) failed at the probe
    point ...``): the wrapped exceptions are its ``__cause__`` and its
    ``__context__`` (kept by ``raise ... from None``, which only hides it from
    tracebacks). The deepest one with a frame of the user's
    (:func:`_user_code_frame`) names it: the line that failed, or the line of
    the user's code that called ofrl_drake with the bad value.
    """
    chain: list[BaseException] = []
    current: BaseException | None = err
    while current is not None and all(current is not seen for seen in chain):
        chain.append(current)
        current = current.__cause__ or current.__context__
    for exc in reversed(chain):
        frame = _user_code_frame(exc)
        if frame is not None:
            return frame
    return None


@contextlib.contextmanager
def _drake_warnings_only() -> Iterator[None]:
    """Drake's log at WARNING while a command runs, unless configured otherwise.

    pydrake logs at INFO by default, and its solvers say so at every solve
    (``Clarabel returns MaxTime``, ``SCS returns code 2``): lines on stderr
    beside the command's own, which the command reports itself.
    """
    import logging

    logger = logging.getLogger("drake")
    level = logger.level
    if level in (logging.NOTSET, logging.INFO):
        logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


def _print_error(line: str) -> None:
    """Print the command's one error line on stderr, on a line of its own.

    On a terminal, a progress bar cut short (Ctrl-C mid-run) is still on the
    last line, without its newline: the line is blanked first, so the error
    does not run on from the bar (``0.0 serror: interrupted``).
    """
    if sys.stderr.isatty():
        try:
            columns = os.get_terminal_size(sys.stderr.fileno()).columns
        except (OSError, ValueError):
            columns = 0
        line = "\r" + " " * ((columns or 80) - 1) + "\r" + line
    print(line, file=sys.stderr)


class _WarningLines:
    """``warnings.showwarning`` while a command runs: a Python warning is one line.

    Python's own prints two, the second the source line that warned (``return
    ControlAffineSystem(f, g, ...)``). Here each is ``warning: MESSAGE`` on
    stderr, and a message already shown is not shown again. A figure font's
    missing characters (:class:`ofrl_drake.plotting.MissingGlyphWarning`, one
    per figure) are gathered for :meth:`glyph_note`, one line for them all.
    """

    def __init__(self) -> None:
        self.shown: set[str] = set()
        self.glyphs: dict[str, None] = {}  # in the order drawn, each once
        self.fonts: dict[str, None] = {}

    def __call__(
        self,
        message: Warning | str,
        category: type[Warning],
        filename: str,
        lineno: int,
        file: Any = None,
        line: str | None = None,
    ) -> None:
        plotting = sys.modules.get("ofrl_drake.plotting")  # imported if it drew a figure
        if plotting is not None and isinstance(message, plotting.MissingGlyphWarning):
            self.glyphs.update(dict.fromkeys(message.characters))
            self.fonts[message.fonts] = None
            return
        text = f"warning: {one_line(message)}"
        if text not in self.shown:
            self.shown.add(text)
            print(text, file=sys.stderr if file is None else file)

    def glyph_note(self) -> None:
        """One line naming every character the figures' font lacked, if any."""
        if self.glyphs:
            print(
                f"note: the figures' font ({', '.join(self.fonts)}) has no glyph for "
                f"{''.join(self.glyphs)!r}, drawn as empty boxes; use other characters "
                "in the scenario's name (and variant names), or set matplotlib's font.family "
                "to a font that has them.",
                file=sys.stderr,
            )


#: Seconds after a swallowed interrupt (:func:`_interrupts_not_swallowed`) before its
#: signal is sent again: time for Python to leave the callback that swallowed it.
RESIGNAL_DELAY = 0.01


@contextlib.contextmanager
def _interrupts_not_swallowed() -> Iterator[None]:
    """A Ctrl-C (or SIGTERM) raised where Python cannot raise it comes again, in the block.

    A ``KeyboardInterrupt`` that lands in a weakref callback or a ``__del__``
    (frequent while Dask's or matplotlib's objects are released) is "ignored":
    Python printed ``Exception ignored in: <function WeakSet...>`` and a
    traceback, and the command went on to its end, exit 0. Here it is
    recorded, and its signal sent to the main thread again
    :data:`RESIGNAL_DELAY` later (not from the hook, which it would interrupt
    in turn), so the command stops as for any Ctrl-C. If the block ends
    first, the signal is not sent (after the block nothing may interrupt the
    caller): the recorded interrupt is raised as the block ends, unless one
    is on its way out of it already. Other unraisable exceptions are reported
    as before.
    """
    previous = sys.unraisablehook
    main_thread = threading.main_thread().ident
    lock = threading.Lock()
    timers: list[threading.Timer] = []
    pending: list[KeyboardInterrupt] = []  # recorded, its signal not sent again yet
    open_ = [True]  # the block has not ended: a timer may still send the signal

    def send_again() -> None:
        with lock:
            if not (open_[0] and pending) or main_thread is None:
                return
            interrupt = pending.pop()
            pending.clear()
            signum = signal.SIGTERM if isinstance(interrupt, Terminated) else signal.SIGINT
            signal.pthread_kill(main_thread, signum)

    def hook(unraisable: Any) -> None:
        interrupt = unraisable.exc_value
        if not isinstance(interrupt, KeyboardInterrupt):
            previous(unraisable)
            return
        with lock:
            pending.append(interrupt)
            again = threading.Timer(RESIGNAL_DELAY, send_again)
            again.name = "ofrl-drake interrupt again"
            again.daemon = True
            timers.append(again)
        again.start()

    sys.unraisablehook = hook
    cutting_short = False
    try:
        yield
    except KeyboardInterrupt:
        cutting_short = True
        raise
    finally:
        sys.unraisablehook = previous
        with lock:
            open_[0] = False
            for timer in timers:
                timer.cancel()
            recorded = pending[-1] if pending else None
        for timer in timers:  # cancelled: each ends at once
            timer.join()
        if recorded is not None and not cutting_short:
            raise Terminated() if isinstance(recorded, Terminated) else KeyboardInterrupt()


def _written_before(args: argparse.Namespace | None) -> str:
    """What an interrupted command leaves: nothing, or the output it wrote in full first.

    A command sets ``args.written`` once its output is in place (the rename of
    its atomic write); an interrupt after that, in what it prints, said "no
    output written" beside the file it had just replaced.
    """
    written = getattr(args, "written", None)
    if written is None:
        return "no output written"
    return f"{written} was written in full before it"


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``ofrl-drake``; returns the exit code.

    While the command runs, Python warnings are printed as one line each
    (:class:`_WarningLines`), SIGTERM raises :class:`Terminated` (in the main
    thread) and an interrupt Python would swallow stops the command
    (:func:`_interrupts_not_swallowed`); ``warnings.showwarning``, SIGTERM's
    handler and ``sys.unraisablehook`` are as they were on return.
    """

    started = time.perf_counter()
    # SIGTERM's handler before main's, restored on return; None: not set (not the main thread)
    sigterm: Any = None
    if threading.current_thread() is threading.main_thread():
        # signal.signal returns None for a handler not set from Python: the default one
        sigterm = signal.signal(signal.SIGTERM, _raise_terminated) or signal.SIG_DFL
    lines = _WarningLines()
    showwarning = warnings.showwarning
    warnings.showwarning = lines
    args: argparse.Namespace | None = None
    try:
        args = _parser().parse_args(argv)
        args.started = started
        if getattr(args, "out", None) == "":
            raise OutputError("--out: the path is empty; name an output file or folder.")
        with sigint_held():
            for module in _COMMAND_MODULES.get(args.command, _DEFAULT_MODULES):
                importlib.import_module(module)
        with _drake_warnings_only(), _interrupts_not_swallowed():
            code = args.func(args)
        if code in (EXIT_OK, EXIT_STOPPED):  # the figures were drawn: the run was not cut short
            lines.glyph_note()
        return code
    except OfrlError as err:
        frame = _user_frame_behind(err)
        where = "" if frame is None else f" (at {frame.filename}:{frame.lineno}, in {frame.name})"
        _print_error(f"error: {one_line(err)}{where}")
        return EXIT_BAD_INPUT
    except Terminated:
        _print_error(f"error: terminated (SIGTERM); {_written_before(args)}")
        return EXIT_TERMINATED
    except KeyboardInterrupt:
        _print_error(f"error: interrupted; {_written_before(args)}")
        return EXIT_INTERRUPTED
    except Exception as err:
        msg = one_line(err, 500)
        frame = _user_code_frame(err)
        if frame is not None:
            _print_error(
                f"error: your code raised {type(err).__name__}: {msg} (at {frame.filename}:"
                f"{frame.lineno}, in {frame.name}); fix it there, it is not an ofrl_drake error"
            )
            return EXIT_BAD_INPUT
        _print_error(f"internal error: {type(err).__name__}: {msg}")
        return EXIT_INTERNAL
    finally:
        warnings.showwarning = showwarning
        if sigterm is not None:
            signal.signal(signal.SIGTERM, sigterm)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
