"""The control-affine plant model ``x' = f(x) + g(x) u``, ``y = C x``.

``f`` and ``g`` are written once, with numpy operations (``np.cos``,
``np.exp``, ``**``, ...), and are then usable on

* a single state ``x`` of shape ``(n,)`` (floats, Drake ``AutoDiffXd`` or
  ``symbolic.Expression``), and
* a batch of states ``X`` of shape ``(n, N)`` (one column per point), which is
  how the Bellman extrapolation evaluates them without a Python loop.

Write constants that must broadcast over a batch as ``0 * x[0]`` or
``np.zeros_like(x[0])`` rather than a bare ``0``.
"""

from __future__ import annotations

import hashlib
import json
import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike
from pydrake.symbolic import Expression, MakeVectorVariable

from ofrl_drake.checks import is_real_number
from ofrl_drake.drake_models import (
    AFFINITY_POINTS,
    DrakeDynamics,
    extract_drake_system,
    extract_multibody,
)
from ofrl_drake.errors import SMOOTH_FORMS, ModelError, OfrlError
from ofrl_drake.interval import as_expression

if TYPE_CHECKING:  # annotations only
    from pydrake.multibody.plant import MultibodyPlant

__all__ = ["ControlAffineSystem", "ShiftedSystem", "SymbolicDynamics", "require_system"]

#: Largest ``max |f(x*) + g(x*) u*|`` accepted by :meth:`ControlAffineSystem.shifted`.
EQUILIBRIUM_TOL = 1e-8

ArrayFunction = Callable[[np.ndarray], np.ndarray]


def _probe_point(n: int) -> np.ndarray:
    """A deterministic, generic point: nonzero, distinct entries."""
    return 0.1 + 0.05 * np.arange(n, dtype=float)


def _check_output_columns(label: str, C: Any, n: int) -> None:
    """A clear error when C does not have one column per state of a Drake model."""
    try:
        shape = np.shape(np.asarray(C, dtype=float))
    except (TypeError, ValueError):
        return  # ControlAffineSystem names the bad entries
    if len(shape) == 2 and shape[1] != n:
        raise ModelError(
            f"{label}: C has {shape[1]} columns but the system has n = {n} states; "
            f"give C one column per state (shape (q, {n}))."
        )


def _real_array(value: Any, expected: str, fix: str) -> np.ndarray:
    """``value`` as a new float array, else a :class:`ModelError` saying what was ``expected``.

    Ragged nesting, strings and complex numbers (numpy would drop the
    imaginary part with a warning) are refused.
    """
    try:
        if np.iscomplexobj(value):
            raise TypeError("complex")
        return np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ModelError(f"{expected}; got {value!r}. {fix}") from None


def _to_expressions(values: Any, shape: tuple[int, ...], what: str) -> np.ndarray:
    """``values`` as an object array of Drake ``Expression`` of shape ``shape``."""
    arr = np.asarray(values, dtype=object)
    if arr.shape != shape:
        raise ModelError(f"{what} returned shape {arr.shape} on symbolic input; expected {shape}.")
    out = np.empty(shape, dtype=object)
    for idx, v in np.ndenumerate(arr):
        out[idx] = as_expression(v)
    return out


@dataclass(frozen=True)
class SymbolicDynamics:
    """``f`` and ``g`` of a model as ``pydrake.symbolic`` expressions.

    Attributes
    ----------
    x : ndarray of Variable, shape (n,)
        The state variables.
    f : ndarray of Expression, shape (n,)
        The drift at ``x``.
    g : ndarray of Expression, shape (n, m)
        The input matrix at ``x``.
    """

    x: np.ndarray
    f: np.ndarray
    g: np.ndarray

    def substitute(self, point: Any) -> tuple[np.ndarray, np.ndarray]:
        """``(f, g)`` at ``point``, an array of expressions of shape ``(n,)``."""
        subst = {v: e for v, e in zip(self.x, point, strict=True)}
        f = np.array([e.Substitute(subst) for e in self.f], dtype=object)
        g = np.array([[e.Substitute(subst) for e in row] for row in self.g], dtype=object)
        return f, g


class ControlAffineSystem:
    """A control-affine system ``x' = f(x) + g(x) u`` with output ``y = C x``.

    Parameters
    ----------
    f : callable
        Drift, ``f(x) -> (n,)``; also ``f(X) -> (n, N)`` for ``X`` of shape
        ``(n, N)``.
    g : callable
        Input matrix, ``g(x) -> (n, m)``; also ``g(X) -> (n, m, N)``.
    C : array_like, shape (q, n)
        Output matrix.
    name : str, optional
        A label used in diagrams and reports.
    source : object, optional
        Where ``f`` and ``g`` came from, kept for blocks that can use it (the
        Drake ``System`` of :meth:`from_drake`, the model of
        :meth:`from_multibody`); None for hand-written plants.
    state_units, input_units : sequence of str, optional
        The unit of each state and input, e.g. ``("m", "rad", "m/s", "rad/s")``
        and ``("N",)``; figures label their axes with them. ``""`` for a
        dimensionless entry; None (the default) when the units are not known.
        :func:`~ofrl_drake.drake_models.from_multibody` fills them from the
        joints and actuators.

    Attributes
    ----------
    n, m, q : int
        State, input and output dimensions, found once at construction by
        calling ``f`` and ``g`` on a probe point.
    vectorized : bool
        True if ``f`` and ``g`` accept a batch ``(n, N)`` of states. If not, the
        batch methods fall back to a (slower) loop and a warning is issued; a
        block that would run that loop at every evaluation refuses such a
        model with :meth:`require_vectorized`.

    Raises
    ------
    ModelError
        If ``C`` is not a finite 2-D array of real numbers (ragged rows,
        strings and complex entries are refused), or ``f``/``g`` return values
        of the wrong shape or non-finite values at the probe point.

    Examples
    --------
    >>> import numpy as np
    >>> sys = ControlAffineSystem(
    ...     f=lambda x: np.array([x[1], -x[0]]),
    ...     g=lambda x: np.array([[0 * x[0]], [1 + 0 * x[0]]]),
    ...     C=[[1.0, 0.0]],
    ... )
    >>> (sys.n, sys.m, sys.q)
    (2, 1, 1)
    """

    def __init__(
        self,
        f: ArrayFunction,
        g: ArrayFunction,
        C: ArrayLike,
        *,
        name: str = "control_affine_system",
        source: Any = None,
        state_units: Sequence[str] | None = None,
        input_units: Sequence[str] | None = None,
    ) -> None:
        self.f = f
        self.g = g
        self.C = C
        self.name = name
        self.source = source
        self.state_units = state_units
        self.input_units = input_units

        C_arr = _real_array(
            C,
            "C must be a 2-D array of real numbers, shape (q, n)",
            "Pass C as a list of rows of equal length, e.g. [[0.0, 1.0]].",
        )
        if C_arr.ndim != 2 or C_arr.shape[0] < 1 or C_arr.shape[1] < 1:
            raise ModelError(
                f"C must be a 2-D array of shape (q, n); got shape {C_arr.shape}. "
                "Pass C as a list of rows, e.g. [[0.0, 1.0]]."
            )
        if not np.all(np.isfinite(C_arr)):
            raise ModelError(f"C must be finite; got {C_arr.tolist()}.")
        self._C = C_arr
        self.q, self.n = C_arr.shape

        x = _probe_point(self.n)
        fx = self._call("f", f, x)
        if fx.shape != (self.n,):
            raise ModelError(
                f"f(x) must return shape (n,) = ({self.n},) to match C with "
                f"n = {self.n} columns; got shape {fx.shape}. Check f or C."
            )
        gx = self._call("g", g, x)
        if gx.ndim != 2 or gx.shape[0] != self.n or gx.shape[1] < 1:
            raise ModelError(
                f"g(x) must return shape (n, m) = ({self.n}, m) to match C with "
                f"n = {self.n} columns; got shape {gx.shape}. Return a 2-D array, "
                "e.g. np.array([[0 * x[0]], [1 + 0 * x[0]]]) for m = 1."
            )
        self.m = gx.shape[1]
        for what, units, size in (("state", state_units, self.n), ("input", input_units, self.m)):
            if units is not None and (
                isinstance(units, str)
                or len(units) != size
                or not all(isinstance(u, str) for u in units)
            ):
                raise ModelError(
                    f"{what}_units must give one string per {what} ({size} in all); got {units!r}. "
                    'Use "" for a dimensionless entry, or leave it None.'
                )
        self.vectorized = self._check_batch()
        self._fingerprint: str | None = None  # computed by fingerprint() when asked

    # ------------------------------------------------------------------ checks
    def _call(self, name: str, fn: ArrayFunction, x: np.ndarray) -> np.ndarray:
        try:
            raw = fn(x)
        except Exception as err:
            raise ModelError(
                f"{name}(x) failed at the probe point x = {x.tolist()}: {err}"
            ) from err
        if raw is None:
            raise ModelError(
                f"{name}(x) returned None at the probe point x = {x.tolist()}; it must return "
                f"an array (a missing return statement in {name}?)."
            )
        if np.iscomplexobj(raw):
            raise ModelError(
                f"{name}(x) returned complex values {np.asarray(raw).tolist()} at the probe "
                f"point x = {x.tolist()}; {name} must be real."
            )
        try:
            value = np.asarray(raw, dtype=float)
        except (TypeError, ValueError) as err:
            raise ModelError(
                f"{name}(x) returned {raw!r} at the probe point x = {x.tolist()}, which is "
                f"not an array of numbers ({err})."
            ) from err
        if not np.all(np.isfinite(value)):
            raise ModelError(
                f"{name}(x) returned non-finite values {value.tolist()} at the "
                f"probe point x = {x.tolist()}; {name} must be finite."
            )
        return value

    def _check_batch(self) -> bool:
        X = np.stack([_probe_point(self.n), -2.0 * _probe_point(self.n)], axis=1)
        try:  # a probe: numpy's warnings at these made-up states say nothing to the user
            with np.errstate(all="ignore"):
                fX = np.asarray(self.f(X), dtype=float)
                gX = np.asarray(self.g(X), dtype=float)
                ok = fX.shape == (self.n, 2) and gX.shape == (self.n, self.m, 2)
                ok = ok and np.allclose(fX[:, 0], self._call("f", self.f, X[:, 0]))
                ok = ok and np.allclose(gX[..., 1], self._call("g", self.g, X[:, 1]))
        except Exception:
            ok = False
        if not ok:
            warnings.warn(
                f"{self.name}: f and g do not accept a batch of states of shape "
                "(n, N); falling back to a Python loop over points. Write "
                "constants as 0 * x[0] so they broadcast.",
                stacklevel=3,
            )
        return ok

    def require_vectorized(self, owner: str) -> None:
        """Refuse the model for ``owner`` unless ``f`` and ``g`` accept batches.

        For a block that calls :meth:`f_batch` and :meth:`g_batch` at every
        evaluation (points that move with the estimate): with a model that is
        not :attr:`vectorized` each call would loop over the points in
        Python, a run that crawls where the construction only warned.

        Parameters
        ----------
        owner : str
            Who needs the batches, named in the message
            (``"MovingBellmanExtrapolator"``).

        Raises
        ------
        ModelError
            If :attr:`vectorized` is False; the message names the model and
            how to write ``f`` and ``g`` so that they broadcast.
        """
        if not self.vectorized:
            raise ModelError(
                f"{owner}: the model {self.name!r} evaluates f and g at every step over a "
                "batch of points, but its f and g do not accept a batch of states of shape "
                "(n, N) (vectorized = False), so each evaluation would loop over the points "
                "in Python. Write constants as 0 * x[0] or np.zeros_like(x[0]) so they "
                "broadcast, and index states as x[i] (not float(x[i]) or math.* functions)."
            )

    # ------------------------------------------------------------ coordinates
    @property
    def is_shifted(self) -> bool:
        """Whether the model is seen from an equilibrium (a :class:`ShiftedSystem`).

        Then its states and inputs are offsets from :attr:`equilibrium`, and
        results are mapped back to the plant's own coordinates; False here.
        """
        return False

    @property
    def equilibrium(self) -> tuple[np.ndarray, np.ndarray]:
        """``(x*, u*)``: where the origin of the model's coordinates sits, as read-only arrays.

        The state ``x*`` (shape ``(n,)``) and input ``u*`` (shape ``(m,)``)
        that ``z = 0`` and ``v = 0`` stand for: zeros for a model in the
        plant's own coordinates, a :class:`ShiftedSystem`'s equilibrium (in
        the coordinates of its ``base``) otherwise.
        """
        return _frozen(np.zeros(self.n)), _frozen(np.zeros(self.m))

    @property
    def multibody_plant(self) -> MultibodyPlant | None:
        """The ``MultibodyPlant`` the model was built from, else None.

        Asked of :attr:`source` (its ``multibody_plant``): the plant of a
        model from :meth:`from_multibody` (shifted or not), None for a
        hand-written model or one from :meth:`from_drake`.
        """
        return getattr(self.source, "multibody_plant", None)

    # --------------------------------------------------------------- evaluate
    @property
    def output_matrix(self) -> np.ndarray:
        """``C`` as a float array of shape ``(q, n)``."""
        return self._C

    def fingerprint(self) -> str:
        """A hash of the dynamics: ``C``, and ``f`` and ``g`` at three fixed small states.

        Two systems with the same fingerprint agree there to 12 significant
        digits; a plant whose code was edited (a mass, a sign) almost surely
        has a new one. Caches of results keyed by a scenario, whose text names
        the plant but does not hold its code, add it to their key (the ``J*``
        cache of :mod:`ofrl_drake.optimal`, a resumed ``ablate``). A state where
        ``f`` or ``g`` raises or is not finite is hashed as such.

        Returns
        -------
        str
            24 hexadecimal digits.
        """
        if self._fingerprint is None:
            p = _probe_point(self.n)
            parts: list[Any] = [self._C.tolist()]
            for x in (p, -p, 0.5 * p[::-1]):
                for fn in (self.f, self.g):
                    try:
                        with np.errstate(all="ignore"):
                            value = np.asarray(fn(x), dtype=float).ravel()
                        parts.append([f"{v:.12e}" for v in value])
                    except Exception as err:  # a state outside the model's domain
                        parts.append(type(err).__name__)
            text = json.dumps(parts)
            self._fingerprint = hashlib.sha256(text.encode()).hexdigest()[:24]
        return self._fingerprint

    def f_batch(self, X: np.ndarray) -> np.ndarray:
        """Drift at each column of ``X`` (shape ``(n, N)``): shape ``(n, N)``."""
        if self.vectorized:
            return np.asarray(self.f(X), dtype=float).reshape(self.n, X.shape[1])
        return np.stack([np.asarray(self.f(x), float) for x in X.T], axis=-1)

    def g_batch(self, X: np.ndarray) -> np.ndarray:
        """Input matrix at each column of ``X``: shape ``(n, m, N)``."""
        if self.vectorized:
            return np.asarray(self.g(X), dtype=float).reshape(self.n, self.m, X.shape[1])
        return np.stack([np.asarray(self.g(x), float) for x in X.T], axis=-1)

    def dynamics(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``f(x) + g(x) u`` for one state (any scalar type).

        Raises
        ------
        ModelError
            If ``u`` is not a vector of the model's ``m`` inputs.
        """
        if np.shape(u) != (self.m,):
            raise ModelError(
                f"{self.name}: dynamics(x, u) needs u of shape (m,) = ({self.m},); "
                f"got shape {np.shape(u)}."
            )
        return self.f(x) + self.g(x) @ u

    def output(self, x: np.ndarray) -> np.ndarray:
        """``C x``."""
        return self._C @ x

    def symbolic(self) -> SymbolicDynamics:
        """``f`` and ``g`` traced once on ``pydrake.symbolic`` states.

        Drake can then differentiate them (the Jacobian bounds) and evaluate
        them in C++ (the ``SymbolicVectorSystem`` blocks of
        :mod:`ofrl_drake.systems.symbolic`).

        Raises
        ------
        ModelError
            If ``f`` or ``g`` cannot be called on ``pydrake.symbolic.Expression``
            states, for example because they call scipy or branch on the state.
        """
        n, m = self.n, self.m
        x = MakeVectorVariable(n, "x")
        xe = np.array([Expression(v) for v in x], dtype=object)
        try:
            # numpy's object loops flag "invalid value" on Drake expressions; harmless.
            with np.errstate(invalid="ignore"):
                f = _to_expressions(self.f(xe), (n,), "f")
                g = _to_expressions(self.g(xe), (n, m), "g")
        except ModelError:
            raise
        except Exception as err:
            if "__bool__" in str(err) and "Formula" in str(err):
                # A comparison of the state used as a truth value: np.maximum, np.minimum,
                # np.sign, np.clip, np.where or an if. Drake's own text is about dict keys.
                raise ModelError(
                    f"{self.name}: f or g branches on the state (a comparison such as "
                    "np.maximum, np.minimum, np.sign, np.clip, np.where or an if on x), which "
                    "Drake's symbolic Jacobians and the certified bounds cannot follow; f and "
                    f"g must be continuously differentiable on the box. {SMOOTH_FORMS}."
                ) from err
            raise ModelError(
                f"{self.name}: f and g must accept pydrake.symbolic.Expression states "
                f"({type(err).__name__}: {err}); write them with numpy functions "
                "(np.cos, np.exp, **) and no branches."
            ) from err
        return SymbolicDynamics(x, f, g)  # type: ignore[arg-type]  # pydrake array stub

    def multibody_structure(self) -> Any:
        """The ``M(q)``, ``tau(q, v)``, ``B`` structure of a multibody model, else None.

        A :class:`~ofrl_drake.multibody_bounds.MultibodyStructure` for models
        built by :meth:`from_multibody` (shifted along with the model), which
        certified Jacobian bounds use instead of ``f`` and ``g``.
        """
        return getattr(self.source, "structure", None)

    # ------------------------------------------------------------ from Drake
    @classmethod
    def from_drake(
        cls,
        system: Any,
        C: Any,
        input_port: int | str = 0,
        *,
        name: str | None = None,
        check_points: int = AFFINITY_POINTS,
        seed: int = 0,
    ) -> ControlAffineSystem:
        """A model of a Drake ``System``, extracted with symbolic scalars.

        ``f`` and ``g`` come from
        :func:`ofrl_drake.drake_models.extract_drake_system` (see there for
        the affinity checks: ``d xdot / d u`` must not depend on ``u``,
        symbolically after expansion or else at ``check_points`` random
        ``(x, u)`` to a relative ``drake_models.AFFINITY_RTOL``); they are
        ``pydrake.symbolic`` expressions and ``source`` keeps the system.

        Parameters
        ----------
        system : pydrake.systems.framework.System
            One continuous state vector, a vector input, symbolic support.
        C : array_like, shape (q, n)
            Output matrix, ``y = C x``.
        input_port : int or str
            The input port that is ``u``, by index or name.
        name : str, optional
            Defaults to the system's name or class name.
        check_points : int
            Random points of the numerical checks.
        seed : int
            Their seed.

        Raises
        ------
        ModelError
            As :func:`~ofrl_drake.drake_models.extract_drake_system`, or if ``C``
            does not have ``n`` columns.

        Examples
        --------
        >>> from pydrake.examples import PendulumPlant
        >>> ControlAffineSystem.from_drake(PendulumPlant(), C=[[1.0, 0.0]]).n
        2
        """
        dynamics = extract_drake_system(
            system, input_port, name=name, check_points=check_points, seed=seed
        )
        return _from_dynamics(dynamics, C)

    @classmethod
    def from_multibody(
        cls,
        model: Any,
        C: Any = None,
        *,
        name: str | None = None,
        check_points: int = AFFINITY_POINTS,
        seed: int = 0,
    ) -> ControlAffineSystem:
        """A model of a multibody plant: state ``[q; v]``, input the actuation.

        ``f`` and ``g`` come from :func:`ofrl_drake.drake_models.extract_multibody`
        (see there); ``model`` is a file path, a ``package://`` URL or a
        finalized continuous ``MultibodyPlant``, and ``C`` defaults to
        measuring the positions.

        Raises
        ------
        ModelError
            As :func:`~ofrl_drake.drake_models.extract_multibody`, or if ``C``
            does not have ``n`` columns.
        """
        dynamics = extract_multibody(model, name=name, check_points=check_points, seed=seed)
        return _from_dynamics(dynamics, dynamics.default_C if C is None else C)

    # ------------------------------------------------------ operating points
    def shifted(
        self, x_eq: Any, u_eq: Any | None = None, *, tol: float = EQUILIBRIUM_TOL
    ) -> ShiftedSystem:
        """The system in coordinates whose origin is the equilibrium ``(x*, u*)``.

        ``z = x - x*`` and ``v = u - u*``:

            z' = f~(z) + g~(z) v,  f~(z) = f(z + x*) + g(z + x*) u*,
            g~(z) = g(z + x*),     y~ = C z = y - C x*.

        Parameters
        ----------
        x_eq : array_like, shape (n,)
            The equilibrium state ``x*``.
        u_eq : array_like, shape (m,), optional
            The equilibrium input ``u*`` (zeros if omitted).
        tol : float
            Largest accepted ``max_i |f(x*) + g(x*) u*|_i``, absolute, in the
            units of ``x'`` (default :data:`EQUILIBRIUM_TOL`).

        Returns
        -------
        ShiftedSystem
            A :class:`ControlAffineSystem` (same ``C``) that keeps ``x_eq`` and
            ``u_eq`` as given, the unshifted ``base``, the ``residual`` and,
            as float arrays, the ``equilibrium`` ``(x*, u*)``.

        Raises
        ------
        ModelError
            If ``x_eq`` or ``u_eq`` is not real, has the wrong length or is not
            finite, ``tol`` is not a finite number >= 0, or ``(x*, u*)`` is not
            an equilibrium to within ``tol``.

        Examples
        --------
        >>> import numpy as np
        >>> pendulum = ControlAffineSystem(
        ...     f=lambda x: np.array([x[1], -np.sin(x[0])]),
        ...     g=lambda x: np.array([[0 * x[0]], [1 + 0 * x[0]]]),
        ...     C=[[1.0, 0.0]],
        ... )
        >>> up = pendulum.shifted([np.pi, 0.0])
        >>> bool(np.allclose(up.f(np.zeros(2)), 0.0))
        True
        """
        return ShiftedSystem(self, x_eq, u_eq, tol=tol)

    def __repr__(self) -> str:
        return f"ControlAffineSystem(name={self.name!r}, n={self.n}, m={self.m}, q={self.q})"


def require_system(
    value: Any, what: str, error: type[OfrlError] = ModelError
) -> ControlAffineSystem:
    """``value`` if it is a :class:`ControlAffineSystem`, else ``error`` naming ``what``.

    For functions that take a model: a name such as ``"two_state"`` or None
    would otherwise fail on its first attribute (``'str' object has no
    attribute 'n'``).

    Raises
    ------
    OfrlError
        ``error`` (default :class:`ModelError`), if ``value`` is not a model.
    """
    if isinstance(value, ControlAffineSystem):
        return value
    shown = repr(value) if isinstance(value, str | int | float) or value is None else ""
    got = f"{type(value).__name__} {shown}".rstrip()
    hint = (
        f"; for the registered example, pass ofrl_drake.examples.make_system({value!r})"
        if isinstance(value, str)
        else ""
    )
    raise error(
        f"{what} must be a ControlAffineSystem; got {got}{hint}. Build a model with "
        "ControlAffineSystem(f, g, C), ControlAffineSystem.from_drake(system, C) or "
        "ofrl_drake.examples.make_system(name)."
    )


def _from_dynamics(dynamics: DrakeDynamics, C: Any) -> ControlAffineSystem:
    """The :class:`ControlAffineSystem` of extracted Drake dynamics, measured by ``C``."""
    _check_output_columns(dynamics.name, C, dynamics.n)
    return ControlAffineSystem(
        dynamics.f,
        dynamics.g,
        C,
        name=dynamics.name,
        source=dynamics.source,
        state_units=dynamics.state_units,
        input_units=dynamics.input_units,
    )


def _frozen(arr: np.ndarray) -> np.ndarray:
    """``arr``, made read-only."""
    arr.setflags(write=False)
    return arr


def _as_vector(value: Any, size: int, what: str, fix: str) -> np.ndarray:
    arr = _real_array(value, f"{what} must be a list of {size} numbers", fix)
    if arr.shape != (size,):
        raise ModelError(
            f"{what} must have length {size}; got shape {arr.shape} ({value!r}). {fix}"
        )
    if not np.all(np.isfinite(arr)):
        raise ModelError(f"{what} must be finite; got {arr.tolist()}. {fix}")
    return _frozen(arr)


class ShiftedSystem(ControlAffineSystem):
    """A :class:`ControlAffineSystem` seen from an equilibrium ``(x*, u*)``.

    Built by :meth:`ControlAffineSystem.shifted`; see there for the formulas.
    ``f`` and ``g`` call the base system's ``f`` and ``g``, so they accept the
    same scalar types (floats, batches ``(n, N)``, ``AutoDiffXd``, symbolic
    expressions), and certified Jacobian bounds of the shifted system are
    bounds of the base Jacobians over the shifted box.

    Parameters
    ----------
    base : ControlAffineSystem
        The system in original coordinates.
    x_eq : array_like, shape (n,)
        ``x*``.
    u_eq : array_like, shape (m,), optional
        ``u*`` (zeros if omitted).
    tol : float
        Largest accepted ``max |f(x*) + g(x*) u*|``.

    Attributes
    ----------
    base, tol
        As given.
    x_eq, u_eq
        As given (``u_eq`` None when omitted); :attr:`equilibrium` is the
        pair as read-only float arrays, ``u*`` zeros when omitted.
    residual : ndarray, shape (n,)
        ``f(x*) + g(x*) u*`` at construction (within ``tol`` of zero), read-only.

    Raises
    ------
    ModelError
        See :meth:`ControlAffineSystem.shifted`.
    """

    def __init__(
        self,
        base: ControlAffineSystem,
        x_eq: Any,
        u_eq: Any | None = None,
        *,
        tol: float = EQUILIBRIUM_TOL,
    ) -> None:
        self.base = base
        self.x_eq = x_eq
        self.u_eq = u_eq
        self.tol = tol
        fix = "Give the equilibrium in the system's original coordinates."
        self._x_eq = _as_vector(x_eq, base.n, "equilibrium x", fix)
        u = np.zeros(base.m) if u_eq is None else u_eq
        self._u_eq = _as_vector(u, base.m, "equilibrium u", fix)
        if not (is_real_number(tol) and not math.isnan(tol) and tol >= 0):
            raise ModelError(
                f"{base.name}: shifted: tol must be a number >= 0 (the largest accepted "
                f"|f(x*) + g(x*) u*|, default {EQUILIBRIUM_TOL:g}; inf checks nothing); "
                f"got {tol!r}."
            )
        residual = np.asarray(base.f(self._x_eq), dtype=float) + np.asarray(
            base.g(self._x_eq), dtype=float
        ) @ np.asarray(self._u_eq)
        self._residual = _frozen(residual)
        worst = int(np.argmax(np.abs(residual)))
        if not abs(residual[worst]) <= tol:
            raise ModelError(
                f"{base.name}: (x*, u*) = ({self._x_eq.tolist()}, {self._u_eq.tolist()}) is "
                f"not an equilibrium: f(x*) + g(x*) u* = {residual.tolist()}, whose row "
                f"{worst} is {residual[worst]:.3g} (tolerance {tol:g}); choose x* and u* "
                "with f(x*) + g(x*) u* = 0, e.g. solve for u* given x*."
            )
        self._zero_input = not np.any(self._u_eq)
        super().__init__(
            self._shifted_f,
            self._shifted_g,
            base.C,
            name=base.name,
            source=base.source,
            state_units=base.state_units,
            input_units=base.input_units,
        )

    @property
    def residual(self) -> np.ndarray:
        """``f(x*) + g(x*) u*`` at construction, shape ``(n,)`` (read-only)."""
        return self._residual

    @property
    def is_shifted(self) -> bool:
        """True: states and inputs are offsets from :attr:`equilibrium`."""
        return True

    @property
    def equilibrium(self) -> tuple[np.ndarray, np.ndarray]:
        """``(x*, u*)`` as read-only float arrays (``u*`` zeros when omitted)."""
        return self._x_eq, self._u_eq

    def _column(self, vector: np.ndarray, z: np.ndarray) -> np.ndarray:
        return vector.reshape((-1,) + (1,) * (np.ndim(z) - 1))

    def _shifted_f(self, z: Any) -> Any:
        z = np.asarray(z)
        x = z + self._column(self._x_eq, z)
        fx = np.asarray(self.base.f(x))
        if self._zero_input:
            return fx
        gx = np.asarray(self.base.g(x))
        u = self._u_eq.reshape((1, -1) + (1,) * (gx.ndim - 2))
        return fx + (gx * u).sum(axis=1)

    def _shifted_g(self, z: Any) -> Any:
        z = np.asarray(z)
        return self.base.g(z + self._column(self._x_eq, z))

    def multibody_structure(self) -> Any:
        """The base model's multibody structure seen from ``(x*, u*)``, or None."""
        structure = self.base.multibody_structure()
        return None if structure is None else structure.shifted(self._x_eq, self._u_eq)

    def to_original_state(self, z: np.ndarray) -> np.ndarray:
        """``x = z + x*`` for ``z`` of shape ``(n,)`` or ``(..., n)`` (time first)."""
        return np.asarray(z, dtype=float) + self._x_eq

    def to_original_input(self, v: np.ndarray) -> np.ndarray:
        """``u = v + u*`` for ``v`` of shape ``(m,)`` or ``(..., m)`` (time first)."""
        return np.asarray(v, dtype=float) + self._u_eq

    def __repr__(self) -> str:
        return (
            f"ShiftedSystem(name={self.name!r}, n={self.n}, m={self.m}, q={self.q}, "
            f"x_eq={self._x_eq.tolist()}, u_eq={self._u_eq.tolist()})"
        )
