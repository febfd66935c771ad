"""Where the observer certificate holds: inside the box, with ``|u_k| <= lbar``.

The Jacobian bounds, and so the LMI certificate, are valid only while both x
and xhat stay in the box they were computed on and the input stays within its
bound. :func:`validity_report` checks the logged trajectories against that.

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

from dataclasses import asdict, dataclass

import numpy as np

from ofrl_drake.errors import ModelError

__all__ = ["BOX_CHECKS", "BoxSchedule", "ValidityReport", "validity_report"]

#: Values of :attr:`ValidityReport.box_check`.
BOX_CHECKS = ("fixed", "scheduled", "not_applicable")


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
        First logged time at which a checked condition was violated (x or
        xhat outside the box in force, or some ``|u_k| > lbar``); None if never.
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
    """

    first_exit_time: float | None
    fraction_outside: float
    state_outside: bool | None
    estimate_outside: bool | None
    input_exceeded: bool
    box_check: str = "fixed"
    note: str | None = None

    @property
    def valid(self) -> bool:
        """True if no *checked* condition was violated at any logged sample.

        With ``box_check == "not_applicable"`` only the input bound was
        checked; see :attr:`box_checked`.
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

    Returns
    -------
    ValidityReport
    """
    t = np.asarray(t, dtype=float)
    u_out = np.any(np.abs(np.asarray(u, dtype=float)) > input_bound + tol, axis=1)
    if box is None:
        check = "not_applicable"
        note = note or "no certified box given: box checks not applicable"
        x_out = xhat_out = None
        bad = u_out
    else:
        if isinstance(box, BoxSchedule):
            check = "scheduled"
            lower, upper = box.at(t, tol=tol)
        else:
            check = "fixed"
            lower, upper = (np.asarray(b, dtype=float) for b in box)

        def outside(z: np.ndarray) -> np.ndarray:
            return np.any((z < lower - tol) | (z > upper + tol), axis=1)

        x_out = outside(np.asarray(x, dtype=float))
        xhat_out = outside(np.asarray(xhat, dtype=float))
        bad = x_out | xhat_out | u_out
    if t.size > 1:
        dt = np.diff(t)
        weights = np.concatenate([dt, dt[-1:]])
        fraction = float(weights[bad].sum() / weights.sum())
    else:
        fraction = float(bad.mean()) if bad.size else 0.0
    first = float(t[np.argmax(bad)]) if bad.any() else None
    return ValidityReport(
        first_exit_time=first,
        fraction_outside=fraction,
        state_outside=None if x_out is None else bool(x_out.any()),
        estimate_outside=None if xhat_out is None else bool(xhat_out.any()),
        input_exceeded=bool(u_out.any()),
        box_check=check,
        note=note,
    )
