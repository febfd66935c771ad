"""Where one derivative evaluation of the diagram goes, block by block.

:func:`evaluation_profile` times, in interleaved batches:

* the whole diagram as an integrator evaluates it (set the continuous state,
  which invalidates every cached value, then ``CalcTimeDerivatives``), and
  setting the state alone;
* each block of the loop alone, in its own context with its inputs fixed at
  the values they have in the diagram: for a block with state, setting its
  state and computing its derivatives; for a block without, writing a new
  value into one of its fixed inputs and evaluating its output, both chosen
  by signal name (:func:`timed_signals`). The block's *work* is that minus
  the same invalidation alone;
* one whole ``simulate()``, whose ``AdvanceTo`` time over its derivative
  evaluations, minus the diagram's evaluation, is what the integrator, the
  logging and the run guard cost per evaluation.

The blocks' work does not add up to the diagram's evaluation exactly: inside
the diagram the inputs come through Drake's cache rather than fixed values.
Each number is given from the fastest of the interleaved batches (what the
code costs; on a loaded machine a burst of load can land on one block's
batch) and as the median of the batches.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from benchmarks.timing import interleaved
from ofrl_drake.scenario import Scenario

__all__ = ["evaluation_profile", "timed_signals"]


def timed_signals(slot: str, block: Any) -> tuple[str, str]:
    """``(input, output)``: the ports, by signal name, that time a block without state.

    The output is the slot's own signal, the first that :data:`SIGNALS` has
    the slot provide (the bellman block's ``critic_sum``, the policy's
    ``policy_weights``); the input the first signal of :data:`SIGNALS` that
    the block reads (``weights`` for both). So the ports timed do not depend
    on the order in which a block declares them.
    """
    from ofrl_drake.diagram import SIGNALS

    output = next(signal for signal, provider in SIGNALS.items() if provider == slot)
    read = [signal for signal in SIGNALS if block.HasInputPort(signal)]
    if not read:
        raise ValueError(
            f"{slot}: the block {type(block).__name__} reads no signal of the loop, so "
            "no input can invalidate its output; it cannot be timed alone."
        )
    return read[0], output


def _block_batches(
    slot: str, block: Any, root: Any, calls: int
) -> tuple[Callable[[], None], Callable[[], None]]:
    """``(work, invalidation)``: two batches of ``calls`` on the ``slot`` block alone."""
    context = block.CreateDefaultContext()
    mine = block.GetMyContextFromRoot(root)
    ports = [block.get_input_port(i) for i in range(block.num_input_ports())]
    values = {port.get_name(): port.Eval(mine) for port in ports}
    fixed = {port.get_name(): port.FixValue(context, values[port.get_name()]) for port in ports}
    if context.num_continuous_states():
        derivatives = block.AllocateTimeDerivatives()
        x0 = context.get_continuous_state_vector().CopyToVector()
        states = (x0, x0 + 1e-9)

        def work() -> None:
            for k in range(calls):
                context.SetContinuousState(states[k & 1])
                block.CalcTimeDerivatives(context, derivatives)

        def invalidation() -> None:
            for k in range(calls):
                context.SetContinuousState(states[k & 1])

        return work, invalidation
    # A new value of the fixed input, written in place (a new FixValue would
    # allocate each time): asking for the mutable data invalidates what
    # depends on it.
    signal_in, signal_out = timed_signals(slot, block)
    written = fixed[signal_in]
    output = block.GetOutputPort(signal_out)
    inputs = (values[signal_in], values[signal_in] + 1e-9)

    def work() -> None:
        for k in range(calls):
            written.GetMutableData().get_mutable_value().SetFromVector(inputs[k & 1])
            output.Eval(context)

    def invalidation() -> None:
        for k in range(calls):
            written.GetMutableData().get_mutable_value().SetFromVector(inputs[k & 1])

    return work, invalidation


def evaluation_profile(scenario: Scenario, calls: int, batches: int) -> dict[str, Any]:
    """Microseconds per evaluation: the diagram, each block alone, and the rest of a step.

    Parameters
    ----------
    scenario : Scenario
    calls : int
        Evaluations per batch.
    batches : int
        Interleaved batches; medians over them are reported.
    """
    from ofrl_drake.diagram import build_closed_loop
    from ofrl_drake.simulation import simulate
    from ofrl_drake.variants import design_for

    design = design_for(scenario)
    loop = build_closed_loop(scenario, design=design)
    diagram = loop.diagram
    root = diagram.CreateDefaultContext()
    derivatives = diagram.AllocateTimeDerivatives()
    x0 = root.get_continuous_state_vector().CopyToVector()
    x1 = x0.copy()
    x1[0] += 1e-3
    states = (x0, x1)
    diagram.CalcTimeDerivatives(root, derivatives)

    def whole() -> None:
        for k in range(calls):
            root.SetContinuousState(states[k & 1])
            diagram.CalcTimeDerivatives(root, derivatives)

    def set_state() -> None:
        for k in range(calls):
            root.SetContinuousState(states[k & 1])

    fns = {"diagram": whole, "set_state": set_state}
    for slot, block in loop.blocks.items():
        work, invalidation = _block_batches(slot, block, root, calls)
        fns[f"{slot}:work"] = work
        fns[f"{slot}:invalidation"] = invalidation
    timings, _ = interleaved(fns, batches)
    fastest = {key: 1e6 * t.min / calls for key, t in timings.items()}
    median = {key: 1e6 * t.median / calls for key, t in timings.items()}
    blocks = []
    for slot, block in loop.blocks.items():
        work, invalidation = f"{slot}:work", f"{slot}:invalidation"
        blocks.append(
            {
                "slot": slot,
                "block": type(block).__name__,
                "num_states": int(block.CreateDefaultContext().num_continuous_states()),
                "work_us": fastest[work] - fastest[invalidation],
                "work_median_us": median[work] - median[invalidation],
                "total_us": fastest[work],
                "invalidation_us": fastest[invalidation],
            }
        )
    result = simulate(scenario, loop=loop, progress=False)
    evals = int(result.integrator["num_derivative_evaluations"])
    per_evaluation = 1e6 * result.wall_time / evals
    return {
        "diagram_us": fastest["diagram"],
        "diagram_median_us": median["diagram"],
        "set_state_us": fastest["set_state"],
        "blocks": blocks,
        "blocks_work_us": float(np.sum([b["work_us"] for b in blocks])),
        "advance_us_per_evaluation": per_evaluation,
        "outside_evaluation_us": per_evaluation - median["diagram"],
        "num_derivative_evaluations": evals,
        "num_states": int(x0.size),
        "calls": calls,
        "batches": batches,
    }
