"""Policy iteration on the points, without the loop: does the basis hold the value?

The table of docs/learning.md, "A basis of higher degree". For the cart-pole
with its shipped quadratic basis and with the quartic monomials added
(``critic.basis_degrees: [2, 4]``), from multiples of the LQR value of the
linearization, this runs the iteration the loop's policy gate performs, with
each policy evaluation solved exactly
(:meth:`ofrl_drake.bellman.Extrapolator.policy_evaluation`, the rest point of
the critic law between two updates) instead of integrated:

* 9 decisions (the loop's at T/10, ..., 9 T/10), each putting the evaluation
  of the policy in force in force if :func:`ofrl_drake.learning.check_policy`
  accepts it (``P > 0``, Hurwitz, no larger local cost);
* the same without the local-cost condition (``P > 0`` and Hurwitz only);
* every policy evaluated alone over ``J*`` (critic frozen, true state fed
  back, from x0 over T), as in the loop's table.

The loop's own gains (``nu`` and the metric of ``rho``) are the ones it
derives for each basis. Run from the repository root::

    python -m benchmarks.learning_basis --out /tmp/learning_basis.md
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np

from benchmarks.learning_table import table_command
from ofrl_drake import build_closed_loop, load_scenario
from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.bellman import Extrapolator
from ofrl_drake.learning import check_policy, second_moment, value_matrix, value_weights
from ofrl_drake.learning_curve import PolicyEvaluator, lqr_weights
from ofrl_drake.optimal import optimal_control

ROOT = Path(__file__).resolve().parents[1]
STARTS = (0.7, 1.0, 1.5, 3.0, 10.0, 30.0)
DECISIONS = 9


def _loop(scenario, degrees):
    """The scenario's loop with ``degrees`` and ``W0`` at the LQR value in that basis."""
    n = len(scenario.x0)
    shipped = value_matrix(PolynomialBasis(n, scenario.critic.basis_degrees), scenario.critic.W0)
    critic = dataclasses.replace(
        scenario.critic,
        basis_degrees=list(degrees),
        W0=value_weights(PolynomialBasis(n, degrees), shipped).tolist(),
    )
    probe = build_closed_loop(dataclasses.replace(scenario, critic=critic))
    W_lqr = lqr_weights(probe)
    critic = dataclasses.replace(critic, W0=W_lqr.tolist())
    return build_closed_loop(dataclasses.replace(scenario, critic=critic)), W_lqr


def iterate(loop, W0: np.ndarray, *, local_cost: bool = True, at_points: bool = True) -> dict:
    """The gate's ``DECISIONS`` decisions from ``W0``, each evaluation exact.

    ``local_cost=False`` drops the local-cost condition (``P > 0`` and Hurwitz
    suffice), ``at_points=False`` the condition ``V(x_i) > 0`` (the test as it
    was before that condition, which reads only the quadratic part).
    """
    parts = loop.parts
    extrapolator = Extrapolator(
        parts.features,
        parts.r,
        parts.scenario.input_bound,
        parts.critic.gains.nu,
        parts.critic.metric,
    )
    A, B = parts.critic.linearization
    moment = second_moment(parts.features.points)

    def check(W, at_points=True):
        points = parts.features.points if at_points else None
        return check_policy(A, B, parts.Q, parts.r, parts.basis, W, moment, points=points)

    W_pi, current, accepted, last = W0, check(W0, at_points), 0, None
    for _ in range(DECISIONS):
        candidate = extrapolator.policy_evaluation(W_pi)
        last = check(candidate)  # the whole test, reported
        verdict = last if at_points else check(candidate, at_points=False)
        if verdict.improves_on(current) if local_cost else verdict.admissible:
            W_pi, current, accepted = candidate, verdict, accepted + 1
    return {
        "W": W_pi,
        "accepted": accepted,
        "last_min_eig": last.value_min_eigenvalue,
        "last_min_value": last.value_min_at_points,
    }


def _ratio(run, J_star: float) -> str:
    """``J / J*`` to four places, or the run's status when the plant left the abort box."""
    return f"{run.cost / J_star:.4f}" if np.isfinite(run.cost) else run.status.split(":")[0]


def measure(name: str = "cart_pole") -> list[dict]:
    scenario = load_scenario(ROOT / "diagrams" / f"{name}.yaml")
    solved = optimal_control(scenario)
    J_star = solved.cost if solved.converged else float("nan")
    rows = []
    for degrees in ((2,), (2, 4)):
        loop, W_lqr = _loop(scenario, degrees)
        evaluate = PolicyEvaluator(loop)
        for start in STARTS:
            W0 = start * W_lqr
            tested = iterate(loop, W0)
            quadratic_only = iterate(loop, W0, at_points=False)
            untested = iterate(loop, W0, local_cost=False)
            rows.append(
                {
                    "degrees": list(degrees),
                    "L": loop.parts.basis.size,
                    "start": start,
                    "initial": _ratio(evaluate(W0), J_star),
                    "learned": _ratio(evaluate(tested["W"]), J_star),
                    "accepted": tested["accepted"],
                    "last_min_eig": tested["last_min_eig"],
                    "last_min_value": tested["last_min_value"],
                    "learned_quadratic_only": _ratio(evaluate(quadratic_only["W"]), J_star),
                    "accepted_quadratic_only": quadratic_only["accepted"],
                    "learned_no_local": _ratio(evaluate(untested["W"]), J_star),
                    "accepted_no_local": untested["accepted"],
                }
            )
            print(rows[-1], file=sys.stderr, flush=True)
    return rows


def table(rows: list[dict]) -> str:
    head = (
        "| basis (L) | start | initial policy | learned | accepted | last candidate: "
        "min eig P, min V(x_i) | without V(x_i) > 0: learned, accepted "
        "| without the local cost: learned, accepted |\n"
        "| --- | --: | --: | --: | --: | --: | --: | --: |\n"
    )
    lines = [
        f"| {r['degrees']} ({r['L']}) | {r['start']:g} x LQR | {r['initial']} | "
        f"{r['learned']} | {r['accepted']} | {r['last_min_eig']:.3g}, "
        f"{r['last_min_value']:.3g} | {r['learned_quadratic_only']}, "
        f"{r['accepted_quadratic_only']} | {r['learned_no_local']}, {r['accepted_no_local']} |"
        for r in rows
    ]
    return head + "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    return table_command(argv, __doc__.splitlines()[0], lambda: table(measure()))


if __name__ == "__main__":
    sys.exit(main())
