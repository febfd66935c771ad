"""How far the model is from the truth it controls, on the observer's box.

The observer certificate, the critic and the controller all use the model.
When the simulated plant (``truth:``) differs, the certificate says nothing
about the difference; :func:`model_mismatch` measures it where the certificate
claims to hold, so ``summary.json`` can say how large it is.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.points import uniform_points

if TYPE_CHECKING:  # annotations only
    from pydrake.multibody.plant import MultibodyPlant

__all__ = ["ModelMismatch", "model_mismatch"]

#: What ``summary.json`` says of a certificate when the truth is not the model.
NOTE = (
    "the observer certificate, the critic and the controller use the model; the certificate "
    "does not cover the difference between the model and the truth"
)


@dataclass(frozen=True)
class ModelMismatch:
    """``max |f_true - f_model|`` and ``max |g_true - g_model|`` over sampled states.

    Attributes
    ----------
    samples : int
        States drawn uniformly in the box (plus the origin).
    box : tuple of ndarray
        ``(lower, upper)``, in the model's coordinates.
    max_f_error : ndarray, shape (n,)
        Per state component.
    max_g_error : ndarray, shape (n, m)
        Per entry.
    equilibrium_residual : ndarray, shape (n,)
        ``f_true(0)``: nonzero when the model's equilibrium is not the truth's.
    """

    samples: int
    box: tuple[np.ndarray, np.ndarray]
    max_f_error: np.ndarray
    max_g_error: np.ndarray
    equilibrium_residual: np.ndarray

    def to_dict(self) -> dict[str, Any]:
        """For ``summary.json`` → ``model_error``."""
        return {
            "samples": self.samples,
            "box": {"lower": self.box[0].tolist(), "upper": self.box[1].tolist()},
            "max_f_error": self.max_f_error.tolist(),
            "max_g_error": self.max_g_error.tolist(),
            "equilibrium_residual": self.equilibrium_residual.tolist(),
            "note": NOTE,
        }


def _multibody_dynamics(
    truth: ControlAffineSystem,
    plant: MultibodyPlant,
    body_mass_scale: Mapping[str, float],
    X: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """``f`` and ``g`` of a multibody truth at the columns of ``X``, masses scaled.

    The truth's own ``plant`` (``truth.multibody_plant``; ``EvalTimeDerivatives``
    at ``u*`` and at each unit input), in the shifted coordinates of ``truth``.
    """
    context = plant.CreateDefaultContext()
    for body, scale in body_mass_scale.items():
        rigid = plant.GetBodyByName(body)
        rigid.SetMass(context, rigid.default_mass() * float(scale))
    n, m = truth.n, truth.m
    x_eq, u_eq = truth.equilibrium
    port = plant.get_actuation_input_port()
    f = np.empty_like(X)
    g = np.empty((n, m, X.shape[1]))
    for i in range(X.shape[1]):  # a report, not a derivative: one plant evaluation per state
        plant.SetPositionsAndVelocities(context, X[:, i] + x_eq)
        port.FixValue(context, u_eq)
        f[:, i] = plant.EvalTimeDerivatives(context).CopyToVector()
        for k in range(m):
            port.FixValue(context, u_eq + np.eye(m)[k])
            g[:, k, i] = plant.EvalTimeDerivatives(context).CopyToVector() - f[:, i]
    return f, g


def model_mismatch(
    model: ControlAffineSystem,
    truth: ControlAffineSystem,
    box: tuple[Any, Any],
    *,
    body_mass_scale: Mapping[str, float] | None = None,
    samples: int = 200,
    seed: int = 0,
) -> ModelMismatch:
    """The model's error against the truth at ``samples`` states drawn in ``box``.

    Parameters
    ----------
    model, truth : ControlAffineSystem
        In the same coordinates (the scenario's equilibrium).
    box : (lower, upper)
        Where to sample: the observer's box, where the certificate claims to hold.
    body_mass_scale : mapping, optional
        Mass factors of a multibody truth, evaluated on its own plant.
    samples : int
        Uniform samples (the origin is added).
    seed : int

    Returns
    -------
    ModelMismatch
    """
    lower, upper = (np.asarray(b, dtype=float) for b in box)
    drawn = uniform_points(lower, upper, samples, seed)
    X = np.concatenate([np.zeros((model.n, 1)), drawn], axis=1)
    f_model, g_model = model.f_batch(X), model.g_batch(X)
    plant = truth.multibody_plant
    if body_mass_scale and plant is not None:
        f_true, g_true = _multibody_dynamics(truth, plant, body_mass_scale, X)
    else:
        f_true, g_true = truth.f_batch(X), truth.g_batch(X)
    return ModelMismatch(
        samples=samples,
        box=(lower, upper),
        max_f_error=np.max(np.abs(f_true - f_model), axis=1),
        max_g_error=np.max(np.abs(g_true - g_model), axis=2),
        equilibrium_residual=np.asarray(f_true[:, 0], dtype=float),
    )
