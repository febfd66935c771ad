"""The observer design's entry point: :func:`design_observer`.

It checks its arguments, builds the SDP of the chosen formulation
(:mod:`ofrl_drake.design.formulations`), solves it with the chosen backend
(:mod:`ofrl_drake.design.backends`) and returns the numbers as an
:class:`~ofrl_drake.design.result.ObserverDesign` only if they certify in numpy
(:mod:`ofrl_drake.design.pipeline`).
"""

from __future__ import annotations

from typing import Any

from ofrl_drake.design.formulations import _zero_injection
from ofrl_drake.design.pipeline import _box_and_bounds, _check_request, _finish, _problem
from ofrl_drake.design.result import ObserverDesign
from ofrl_drake.design.sdp import DEFAULT_MARGIN
from ofrl_drake.jacobian_bounds import JacobianBounds
from ofrl_drake.model import ControlAffineSystem

__all__ = ["design_observer"]


def design_observer(
    system: ControlAffineSystem,
    box: Any,
    input_bound: float,
    alpha: float,
    *,
    bounds: JacobianBounds | None = None,
    jacobian_method: str = "certified",
    solver: str = "clarabel",
    margin: float = DEFAULT_MARGIN,
    objective: str = "min_gain",
    max_gain: float | None = None,
    backend: str = "drake",
    sector: str = "sign_correct",
    formulation: str = "polytopic",
    injection_gains: bool = True,
    time_limit: float | None = None,
) -> ObserverDesign:
    """Design certified observer gains by solving an LMI.

    The formulations are described in :mod:`ofrl_drake.design.formulations`,
    the semidefinite program and its objectives in :mod:`ofrl_drake.design.sdp`.

    Parameters
    ----------
    system : ControlAffineSystem
        The plant.
    box : Box or (lower, upper)
        Compact set where the Jacobian bounds hold; ``x`` and ``x-hat`` must
        stay in it for the certificate to apply.
    input_bound : float
        ``lambda_bar``; one common set of gains is certified at all 3**m
        vertices, hence for every ``|u_k| <= input_bound``.
    alpha : float
        Decay rate: ``dV_e/dt <= -2 alpha V_e``, ``V_e = e^T P e`` (for
        ``"paper"``, only in the sense of (lmi2); see
        :mod:`ofrl_drake.design.formulations`).
    bounds : JacobianBounds, optional
        Precomputed bounds on a box containing ``box``; default: computed with
        ``jacobian_method``.
    jacobian_method : {"certified", "sampled"}
        How to compute ``bounds`` when they are not given. ``"certified"``
        (default) gives guaranteed interval enclosures, so a decay certificate
        is a proof; ``"sampled"`` is an inner estimate, faster but not a
        guarantee (see :attr:`ObserverDesign.bounds_are_guaranteed`).
    solver : {"clarabel", "scs", "csdp", "mosek"}
        SDP solver (the cvxpy backend accepts "clarabel" and "scs").
    margin : float
        Strict margin: ``LMI <= -margin I`` at every vertex (and corner).
    objective : {"min_gain", "min_condition", "feasibility"}
        See :mod:`ofrl_drake.design.sdp`; "min_gain" minimizes ``||R||_2`` (plus
        ``||[H K]||_F`` when ``H, K`` are free).
    max_gain : float, optional
        Enforce ``||L||_2 <= max_gain`` (through ``||R||_2 <= max_gain``).
    backend : {"drake", "cvxpy"}
        Modelling layer.
    sector : {"sign_correct", "paper"}
        Input sector of the ``"paper"`` formulation; "paper" reproduces the
        paper's literal (aug_jac_g), valid only for ``u >= 0``.
    formulation : {"polytopic", "paper"}
        ``"polytopic"``: the sound decay certificate with ``H = K = 0``.
        ``"paper"``: the paper's (lmi2).
    injection_gains : bool
        ``"paper"`` only: False pins ``H = K = 0`` (a linear Luenberger observer
        checked against (lmi2)). The polytopic formulation always has ``H = K =
        0`` and ignores it.
    time_limit : float, optional
        Wall-clock seconds for the whole design: bounds computed here stop
        their refinement at it (with sound bounds), and the solver gets what
        they leave as its own time limit (Clarabel ``time_limit``, SCS
        ``time_limit_secs``, MOSEK ``MSK_DPAR_OPTIMIZER_MAX_TIME``; CSDP has
        none and is refused with one). Default: no limit.

    Returns
    -------
    ObserverDesign
        Certified: :attr:`ObserverDesign.is_certified` is True (and, for
        ``"polytopic"``, so is :attr:`ObserverDesign.is_decay_certified`).

    Raises
    ------
    ObserverDesignInfeasible
        If the solver reports infeasibility or the numbers do not certify.
    WallTimeExceeded
        If the design ran out of ``time_limit``: the bounds left nothing of it,
        or the solve ran out of what they left.
    DesignError
        For an unknown solver, backend, objective, sector or formulation, or a
        bad ``alpha``, ``input_bound``, ``margin``, ``time_limit`` or
        ``max_gain`` (all checked before any Jacobian bounds are computed); a
        solver that is not usable here (MOSEK without licence), bounds that do
        not match, too many corners for the polytopic formulation, or a
        ``time_limit`` with CSDP.

    Examples
    --------
    >>> from ofrl_drake.examples import make_system
    >>> d = design_observer(make_system("two_state"), ([-2, -2], [2, 2]), 3.0, 0.5)
    >>> d.is_certified, d.is_decay_certified, d.condition_number < 1e3
    (True, True, True)
    >>> p = design_observer(make_system("two_state"), ([-2, -2], [2, 2]), 3.0, 2.0,
    ...                     formulation="paper")
    >>> p.is_certified, p.is_decay_certified
    (True, False)
    """
    # All of it before the bounds, which can take seconds.
    alpha, input_bound, margin, time_limit, max_gain = _check_request(
        solver,
        backend,
        formulation,
        sector,
        alpha,
        input_bound,
        margin,
        time_limit,
        max_gain,
        objective,
    )
    box, bounds, time_limit = _box_and_bounds(system, box, bounds, jacobian_method, time_limit)
    pinned = None if injection_gains else _zero_injection(system.n, system.q)
    problem = _problem(
        system.output_matrix,
        bounds,
        input_bound,
        alpha,
        margin,
        objective,
        max_gain,
        sector,
        formulation,
        HK=pinned,
    )
    return _finish(
        ObserverDesign,
        problem,
        bounds,
        box,
        input_bound,
        solver,
        backend,
        sector,
        max_gain,
        time_limit,
    )
