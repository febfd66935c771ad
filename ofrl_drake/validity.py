"""Where the observer certificate holds: inside the box, with ``|u_k| <= lbar``.

The Jacobian bounds, and so the LMI certificate, are valid only while both x
and xhat stay in the box they were computed on and the input stays within its
bound. When the injection gains H or K are nonzero, the mean-value argument
behind the certificate evaluates f at ``xhat + H ytil`` and g at
``xhat + K ytil`` (``ytil = C (x - xhat)``), so those *injection points* must
stay in the box too (:mod:`ofrl_drake.lmi`). :func:`validity_report` checks
the logged trajectories against all of that; the injection points are
checked when it is given the observer's ``C``, ``H`` and ``K``.

Which box applies depends on the observer:

* ``"fixed"``: an observer running the gains of one design is certified on
  that design's box for the whole run.
* ``"scheduled"``: an observer re-designed along the run (the scheduled
  three-gain observer) is certified, between two re-designs, on the box of the
  design in force; a :class:`BoxSchedule` lists those boxes.
* ``"not_applicable"``: an observer without a design (full-state feedback,
  Drake's Luenberger observer on the linearization, a swapped block) has no
  certified box; only ``|u_k| <= lbar`` is checked, and the report says why.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ofrl_drake.checks import (
    finite_array,
    number_from_json,
    object_from_json,
    optional_number_from_json,
    string_from_json,
)
from ofrl_drake.errors import ModelError

__all__ = [
    "BOX_CHECKS",
    "INJECTION_CHECKS",
    "POINTS",
    "BoxSchedule",
    "ValidityReport",
    "injection_points",
    "validity_report",
]

#: Values of :attr:`ValidityReport.box_check`.
BOX_CHECKS = ("fixed", "scheduled", "not_applicable")

#: Values of :attr:`ValidityReport.injection_check`.
INJECTION_CHECKS = ("checked", "zero_gains", "no_gains", "not_applicable")

#: Names of the points checked against the box, the keys of
#: :attr:`ValidityReport.box_excursions`: the state, the estimate and the two
#: injection points (the last two only when their gain is nonzero).
POINTS = ("x", "xhat", "xhat + H ytil", "xhat + K ytil")


@dataclass(frozen=True)
class BoxSchedule:
    """Certified boxes in force one after another along a run.

    Box 0 is in force from the start; box ``k >= 1`` replaces box ``k - 1``
    for every sample later than ``times[k]`` (a sample at ``times[k]`` itself
    still belongs to box ``k - 1``: the old gains were in force up to then).

    Attributes
    ----------
    times : ndarray, shape (K,)
        When each box came into force, nondecreasing; ``times[0]`` is the start.
    lower, upper : ndarray, shape (K, n)
        The corners of each box.
    """

    times: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    def __post_init__(self) -> None:
        times = np.asarray(self.times, dtype=float).reshape(-1)
        lower = np.atleast_2d(np.asarray(self.lower, dtype=float))
        upper = np.atleast_2d(np.asarray(self.upper, dtype=float))
        if times.size == 0 or lower.shape != upper.shape or lower.shape[0] != times.size:
            raise ModelError(
                "BoxSchedule: times (K,), lower and upper (K, n) must describe the same K >= 1 "
                f"boxes; got shapes {times.shape}, {lower.shape}, {upper.shape}."
            )
        if np.any(np.diff(times) < 0):
            raise ModelError(f"BoxSchedule: times must be nondecreasing; got {times.tolist()}.")
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "lower", lower)
        object.__setattr__(self, "upper", upper)

    @classmethod
    def from_samples(cls, t: np.ndarray, boxes: np.ndarray) -> BoxSchedule:
        """The schedule of a logged box: ``boxes[k] = [lower, upper]`` at ``t[k]``.

        Each logged sample is checked against the box logged with it: a box
        that first appears at ``t[k]`` comes into force just after ``t[k-1]``.
        """
        t = np.asarray(t, dtype=float).reshape(-1)
        boxes = np.asarray(boxes, dtype=float)
        if t.size == 0 or boxes.ndim != 2 or boxes.shape[0] != t.size or boxes.shape[1] % 2:
            raise ModelError(
                "BoxSchedule.from_samples: boxes must have shape (T, 2 n) for T sample "
                f"times; got {boxes.shape} for {t.size} times."
            )
        n = boxes.shape[1] // 2
        change = np.flatnonzero(np.any(boxes[1:] != boxes[:-1], axis=1)) + 1
        keep = np.concatenate([[0], change])
        times = np.concatenate([[t[0]], t[change - 1]])
        return cls(times=times, lower=boxes[keep, :n], upper=boxes[keep, n:])

    def at(self, t: np.ndarray, *, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
        """Corners of the box in force at each time of ``t``, each of shape (T, n).

        A sample within ``tol`` (relative to ``1 + |time|``) of a switching
        time still belongs to the box before it.
        """
        t = np.asarray(t, dtype=float)
        switches = self.times[1:]
        index = np.searchsorted(switches + tol * (1.0 + np.abs(switches)), t, side="left")
        return self.lower[index], self.upper[index]


@dataclass(frozen=True)
class ValidityReport:
    """When and for how long the certificate's assumptions were violated.

    Attributes
    ----------
    first_exit_time : float or None
        First logged time at which a checked condition was violated (x, xhat
        or a checked injection point outside the box in force, or some
        ``|u_k| > lbar``); None if never.
    fraction_outside : float
        Fraction of the horizon (by log samples, time-weighted) with some
        checked condition violated.
    state_outside, estimate_outside : bool or None
        Whether x, resp. xhat, left the box in force at least once; None if
        the box was not checked (``box_check == "not_applicable"``).
    input_exceeded : bool
        Whether some ``|u_k| > lbar`` at least once; always checked.
    box_check : str
        Which box x and xhat were checked against, one of :data:`BOX_CHECKS`.
    note : str or None
        What was checked beyond the defaults, or why the box was not checked.
    injection_h_outside, injection_k_outside : bool or None
        Whether ``xhat + H ytil``, resp. ``xhat + K ytil`` (``ytil = C (x -
        xhat)``), left the box in force at least once; None if that point was
        not checked: no box, no gains given, or a zero gain (the point is then
        xhat itself).
    injection_check : str
        Whether the injection points were checked, one of
        :data:`INJECTION_CHECKS`: ``"checked"`` (H or K nonzero),
        ``"zero_gains"`` (H = K = 0: nothing beyond xhat to check),
        ``"no_gains"`` (C, H, K not given: the injection points were *not*
        checked), ``"not_applicable"`` (no certified box).
    box_excursions : dict or None
        Per checked point (keys from :data:`POINTS`; the injection points
        only when ``injection_check == "checked"`` and their gain is
        nonzero): ``outside`` (bool, with the slack ``tol``),
        ``first_exit_time`` (float or None), ``worst_excursion`` (the largest
        distance, max-norm, from the point to the box in force; 0 if it never
        left), ``worst_time`` and ``worst_point`` (when, and where, that
        distance was reached; None if it never left). None if the box was
        not checked.
    """

    first_exit_time: float | None
    fraction_outside: float
    state_outside: bool | None
    estimate_outside: bool | None
    input_exceeded: bool
    box_check: str = "fixed"
    note: str | None = None
    injection_h_outside: bool | None = None
    injection_k_outside: bool | None = None
    injection_check: str = "no_gains"
    box_excursions: dict[str, dict[str, Any]] | None = field(default=None, hash=False)

    @property
    def valid(self) -> bool:
        """True if no *checked* condition was violated at any logged sample.

        With ``box_check == "not_applicable"`` only the input bound was
        checked; see :attr:`box_checked`. The injection points ``xhat + H
        ytil``, ``xhat + K ytil`` count only if checked: with
        ``injection_check == "no_gains"`` (no C, H, K given) they were not, and
        True does not mean the certificate's hypotheses held for an observer
        with nonzero H or K.
        """
        return self.first_exit_time is None

    @property
    def box_checked(self) -> bool:
        """True if x and xhat were checked against a certified box."""
        return self.box_check != "not_applicable"

    def warning(self) -> str | None:
        """A one-line warning, or None if no checked condition was violated."""
        if self.valid:
            return None
        when = (
            f"at t = {self.first_exit_time:.3f} s ({100 * self.fraction_outside:.1f}% of the "
            "horizon"
        )
        if not self.box_checked:
            return (
                f"warning: |u| exceeded the input bound {when} in violation); x and xhat were "
                f"not checked against a box: {self.note}."
            )
        what = [
            name
            for name, flag in (
                ("x", self.state_outside),
                ("xhat", self.estimate_outside),
                ("xhat + H ytil", self.injection_h_outside),
                ("xhat + K ytil", self.injection_k_outside),
                ("|u|", self.input_exceeded),
            )
            if flag
        ]
        if self.box_check == "scheduled":
            return (
                f"warning: {', '.join(what)} left the certified region {when} outside); the "
                "observer guarantee holds only inside the box of the design in force."
            )
        return (
            f"warning: {', '.join(what)} left the certified region {when} outside); "
            "the observer guarantee holds only inside the box."
        )

    def to_dict(self) -> dict:
        """The report as a JSON-ready dict (the fields and ``valid``, ``box_checked``)."""
        out = asdict(self)
        out["valid"] = self.valid
        out["box_checked"] = self.box_checked
        return out

    @classmethod
    def from_dict(cls, data: Any) -> ValidityReport:
        """The report :meth:`to_dict` wrote (its derived ``valid``, ``box_checked`` dropped).

        Raises
        ------
        TypeError, ValueError, KeyError
            If ``data`` is not an object, lacks an entry without a default,
            holds an entry the report does not have, or one of the wrong
            type (``box_check``, ``injection_check`` not one of
            :data:`BOX_CHECKS`, :data:`INJECTION_CHECKS`); a reader of a
            file, such as :meth:`ofrl_drake.SimulationResult.load`, names the
            file.
        """
        data = dict(object_from_json(data))
        data.pop("valid", None)
        data.pop("box_checked", None)
        unknown = sorted(set(data) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"no entries {unknown} in a validity report")
        flags = ("state_outside", "estimate_outside", "injection_h_outside", "injection_k_outside")
        for key in ("input_exceeded", *flags):
            if key in data and not (
                isinstance(data[key], bool) or (key != "input_exceeded" and data[key] is None)
            ):
                raise TypeError(f"{key}: expected true or false, got {data[key]!r}")
        for key, choices in (("box_check", BOX_CHECKS), ("injection_check", INJECTION_CHECKS)):
            if key in data and data[key] not in choices:
                raise ValueError(f"{key}: {data[key]!r} is not one of {list(choices)}")
        if data.get("note") is not None:
            string_from_json(data["note"])
        if data.get("box_excursions") is not None:
            object_from_json(data["box_excursions"])
        return cls(
            **{
                **data,
                "first_exit_time": optional_number_from_json(data["first_exit_time"]),
                "fraction_outside": number_from_json(data["fraction_outside"]),
            }
        )


def injection_points(
    x: ArrayLike,
    xhat: ArrayLike,
    C: ArrayLike | None,
    H: ArrayLike | None,
    K: ArrayLike | None,
) -> dict[str, np.ndarray]:
    """``xhat + H ytil`` and ``xhat + K ytil`` at every sample, ``ytil = C (x - xhat)``.

    ``x`` and ``xhat`` are ``(T, n)``, one sample a row; the points too. Only
    the points whose gain is nonzero at some sample, keyed as in
    :data:`POINTS`; an empty dict when both gains are zero. ``H`` and ``K``
    are ``(n, q)``, or ``(T, n, q)`` with the gains in force at each sample
    (a re-designed observer's log). Raises :class:`ModelError` as
    :func:`validity_report` says.
    """
    if C is None or H is None or K is None:
        missing = [name for name, v in (("C", C), ("H", H), ("K", K)) if v is None]
        raise ModelError(
            "validity_report: C, H and K go together (the injection points xhat + H ytil and "
            f"xhat + K ytil need all three); {' and '.join(missing)} missing. Pass the "
            "observer's output matrix and both gains (zeros for a gain it does not have), "
            "or none of C, H, K."
        )
    xa, xh = np.asarray(x, dtype=float), np.asarray(xhat, dtype=float)
    if xa.ndim != 2 or xh.shape != xa.shape:
        raise ModelError(
            "validity_report: x and xhat must both have shape (T, n) to check the injection "
            f"points; got {xa.shape} and {xh.shape}."
        )
    T, n = xa.shape
    Cm = finite_array("validity_report: C", C)
    if Cm.ndim != 2 or Cm.shape[0] == 0 or Cm.shape[1] != n:
        raise ModelError(
            f"validity_report: C must have shape (q, n) with n = {n} (the columns of x) and "
            f"q >= 1; got {Cm.shape}."
        )
    q = Cm.shape[0]
    ytil = (xa - xh) @ Cm.T  # (T, q)
    points: dict[str, np.ndarray] = {}
    for name, gain in (("H", H), ("K", K)):
        G = finite_array(f"validity_report: {name}", gain)
        if G.shape not in ((n, q), (T, n, q)):
            raise ModelError(
                f"validity_report: {name} must have shape (n, q) = {(n, q)}, or {(T, n, q)} "
                f"with the gain in force at each of the T samples; got {G.shape}."
            )
        if not np.any(G):
            continue  # the point is xhat itself
        step = ytil @ G.T if G.ndim == 2 else np.einsum("tiq,tq->ti", G, ytil)
        points[f"xhat + {name} ytil"] = xh + step
    return points


def _excursion(
    t: np.ndarray, z: np.ndarray, lower: np.ndarray, upper: np.ndarray, tol: float
) -> tuple[np.ndarray, dict[str, Any]]:
    """Samples where ``z`` (T, n) is outside the box in force, and their summary.

    A NaN component is outside, at an infinite distance (a run that turned NaN
    left every box).
    """
    beyond = np.maximum(lower - z, z - upper)
    distance = np.max(np.where(np.isnan(beyond), np.inf, beyond), axis=1, initial=-np.inf)
    out = np.any(~((z >= lower - tol) & (z <= upper + tol)), axis=1)
    worst = int(np.argmax(distance)) if distance.size else 0
    left = bool(distance.size) and distance[worst] > 0
    summary = {
        "outside": bool(out.any()),
        "first_exit_time": float(t[np.argmax(out)]) if out.any() else None,
        "worst_excursion": float(distance[worst]) if left else 0.0,
        "worst_time": float(t[worst]) if left else None,
        "worst_point": z[worst].tolist() if left else None,
    }
    return out, summary


def validity_report(
    t: np.ndarray,
    x: np.ndarray,
    xhat: np.ndarray,
    u: np.ndarray,
    box: tuple[np.ndarray, np.ndarray] | BoxSchedule | None,
    input_bound: float,
    *,
    tol: float = 1e-9,
    note: str | None = None,
    C: ArrayLike | None = None,
    H: ArrayLike | None = None,
    K: ArrayLike | None = None,
) -> ValidityReport:
    """Check logged trajectories (time first) against the certified region.

    Parameters
    ----------
    t : ndarray, shape (T,)
    x, xhat : ndarray, shape (T, n)
    u : ndarray, shape (T, m)
    box : (lower, upper), BoxSchedule or None
        A fixed box, the boxes of a re-designed observer, or None when the
        observer has no certified box; then only the input bound is checked.
    input_bound : float
        lbar; ``|u_k| <= lbar`` is always checked.
    tol : float, optional
        Slack of every comparison.
    note : str, optional
        Stored in the report; with ``box=None`` it should say why no box
        applies (a generic reason is used if omitted).
    C : array_like, shape (q, n), optional
        The output matrix of the observer's model.
    H, K : array_like, shape (n, q) or (T, n, q), optional
        The observer's injection gains, fixed or in force at each sample (a
        re-designed observer). Given together with ``C`` (or none of the
        three), the injection points ``xhat + H ytil`` and ``xhat + K ytil``,
        ``ytil = C (x - xhat)``, are checked against the box too when their
        gain is nonzero; without them they are not checked
        (``injection_check == "no_gains"``).

    Returns
    -------
    ValidityReport

    Raises
    ------
    ModelError
        If only some of ``C``, ``H``, ``K`` are given, if they are not finite,
        or if their shapes do not fit ``x`` (``C`` (q, n), ``H`` and ``K``
        (n, q) or (T, n, q)); if x and xhat do not both have shape (T, n)
        when the gains are given.
    """
    t = np.asarray(t, dtype=float)
    given = not (C is None and H is None and K is None)
    injection = injection_points(x, xhat, C, H, K) if given else None
    u_out = np.any(~(np.abs(np.asarray(u, dtype=float)) <= input_bound + tol), axis=1)
    excursions: dict[str, dict[str, Any]] | None = None
    if box is None:
        check = "not_applicable"
        note = note or "no certified box given: box checks not applicable"
        x_out = xhat_out = None
        injection_check = "not_applicable"
        point_out: dict[str, np.ndarray] = {}
        bad = u_out
    else:
        if isinstance(box, BoxSchedule):
            check = "scheduled"
            lower, upper = box.at(t, tol=tol)
        else:
            check = "fixed"
            lower, upper = (np.asarray(b, dtype=float) for b in box)
        points = {"x": np.asarray(x, dtype=float), "xhat": np.asarray(xhat, dtype=float)}
        if injection is None:
            injection_check = "no_gains"
        else:
            injection_check = "checked" if injection else "zero_gains"
            points.update(injection)
        excursions, point_out = {}, {}
        for name, z in points.items():
            point_out[name], excursions[name] = _excursion(t, z, lower, upper, tol)
        x_out, xhat_out = point_out["x"], point_out["xhat"]
        bad = u_out
        for flags in point_out.values():
            bad = bad | flags
    if t.size > 1:
        dt = np.diff(t)
        weights = np.concatenate([dt, dt[-1:]])
        fraction = float(weights[bad].sum() / weights.sum())
    else:
        fraction = float(bad.mean()) if bad.size else 0.0
    first = float(t[np.argmax(bad)]) if bad.any() else None

    def flag(name: str) -> bool | None:
        return bool(point_out[name].any()) if name in point_out else None

    return ValidityReport(
        first_exit_time=first,
        fraction_outside=fraction,
        state_outside=None if x_out is None else bool(x_out.any()),
        estimate_outside=None if xhat_out is None else bool(xhat_out.any()),
        input_exceeded=bool(u_out.any()),
        box_check=check,
        note=note,
        injection_h_outside=flag("xhat + H ytil"),
        injection_k_outside=flag("xhat + K ytil"),
        injection_check=injection_check,
        box_excursions=excursions,
    )
