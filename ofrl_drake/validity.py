"""Where the observer certificate holds: inside the box, with ``|u_k| <= lbar``.

The Jacobian bounds, and so the LMI certificate, are valid only while both x
and xhat stay in the box they were computed on and the input stays within its
bound. :func:`validity_report` checks the logged trajectories against that.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["ValidityReport", "validity_report"]


@dataclass(frozen=True)
class ValidityReport:
    """When and for how long the certificate's assumptions were violated.

    Attributes
    ----------
    first_exit_time : float or None
        First logged time at which x or xhat was outside the box or some
        ``|u_k| > lbar``; None if never.
    fraction_outside : float
        Fraction of the horizon (by log samples, time-weighted) spent outside.
    state_outside, estimate_outside, input_exceeded : bool
        Which condition was violated at least once.
    """

    first_exit_time: float | None
    fraction_outside: float
    state_outside: bool
    estimate_outside: bool
    input_exceeded: bool

    @property
    def valid(self) -> bool:
        """True if the certificate's assumptions held at every logged sample."""
        return self.first_exit_time is None

    def warning(self) -> str | None:
        """A one-line warning, or None if everything stayed valid."""
        if self.valid:
            return None
        what = [
            name
            for name, flag in (
                ("x", self.state_outside),
                ("xhat", self.estimate_outside),
                ("|u|", self.input_exceeded),
            )
            if flag
        ]
        return (
            f"warning: {', '.join(what)} left the certified region at t = "
            f"{self.first_exit_time:.3f} s ({100 * self.fraction_outside:.1f}% of the "
            "horizon outside); the observer guarantee holds only inside the box."
        )

    def to_dict(self) -> dict:
        return asdict(self)


def validity_report(
    t: np.ndarray,
    x: np.ndarray,
    xhat: np.ndarray,
    u: np.ndarray,
    box: tuple[np.ndarray, np.ndarray],
    input_bound: float,
    *,
    tol: float = 1e-9,
) -> ValidityReport:
    """Check logged trajectories (time first) against the certified region."""
    lower, upper = (np.asarray(b, dtype=float) for b in box)

    def outside(z: np.ndarray) -> np.ndarray:
        return np.any((z < lower - tol) | (z > upper + tol), axis=1)

    x_out = outside(x)
    xhat_out = outside(xhat)
    u_out = np.any(np.abs(u) > input_bound + tol, axis=1)
    bad = x_out | xhat_out | u_out
    if t.size > 1:
        dt = np.diff(t)
        weights = np.concatenate([dt, dt[-1:]]) if dt.size else np.ones_like(t)
        fraction = float(weights[bad].sum() / weights.sum())
    else:
        fraction = float(bad.mean()) if bad.size else 0.0
    first = float(t[np.argmax(bad)]) if bad.any() else None
    return ValidityReport(
        first_exit_time=first,
        fraction_outside=fraction,
        state_outside=bool(x_out.any()),
        estimate_outside=bool(xhat_out.any()),
        input_exceeded=bool(u_out.any()),
    )
