"""Which plant a scenario runs: the one place where ``scenario.system`` is resolved.

``system:`` in a scenario is either

* the name of a registered example (:mod:`ofrl_drake.examples`), or
* an import path ``"module.path:callable"``: a callable that takes no
  arguments and returns a :class:`~ofrl_drake.model.ControlAffineSystem`.
  The module is looked up first in the scenario file's folder, then on
  ``sys.path``. :func:`locate_system_entry` (called by
  :func:`~ofrl_drake.scenario.load_scenario`) rewrites a module found in the
  scenario's folder to the absolute file form ``"/abs/path/module.py:callable"``,
  so the scenario can be shipped to Dask workers that start in any directory.

A scenario may instead name a Drake plant under ``plant:`` (a multibody model
file or URL, or a Drake ``System`` by import path, with ``C``), built by
:meth:`~ofrl_drake.model.ControlAffineSystem.from_multibody` and
:meth:`~ofrl_drake.model.ControlAffineSystem.from_drake`. With an
``equilibrium:`` the system is then :meth:`shifted
<ofrl_drake.model.ControlAffineSystem.shifted>` so that the origin is that
point.

Every failure (bad entry, missing module or callable, an import error or any
exception raised inside the user's module, a wrong return type, a bad
equilibrium) raises :class:`~ofrl_drake.errors.ScenarioError` with a one-line
message that names the entry.

Built systems are kept per process (keyed by the scenario's plant entries), so
validating, designing and wiring one scenario builds its plant once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import importlib.util
import os
import re
import socket
import sys
from collections.abc import Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

from ofrl_drake.atomic import FileVersion, file_version
from ofrl_drake.errors import ModelError, ScenarioError, status_line
from ofrl_drake.model import ControlAffineSystem

__all__ = [
    "check_dynamics",
    "dynamics_fingerprints",
    "is_import_path",
    "load_callable",
    "locate_model_file",
    "locate_system_entry",
    "multibody_body_names",
    "resolve_system",
    "resolve_truth",
    "system_from_entry",
]

_DOTTED = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")


def is_import_path(entry: str) -> bool:
    """True if ``entry`` is meant as ``"module.path:callable"`` (it holds a colon)."""
    return ":" in entry


def _split(entry: str, key: str) -> tuple[str, str]:
    """``"module.path:callable"`` or ``"/file.py:callable"`` -> (module, attribute)."""
    module, sep, attr = entry.rpartition(":")
    is_file = module.endswith(".py")
    if not sep or not module or not _DOTTED.match(attr) or not (is_file or _DOTTED.match(module)):
        raise ScenarioError(
            f"{key}: {entry!r} is not an import path; write 'module.path:callable' (a module "
            "beside the scenario file or on sys.path, and a function of no arguments), "
            "e.g. 'my_plant:make_plant'."
        )
    return module, attr


def _module_file(module: str, folder: Path) -> Path | None:
    """``folder/a/b.py`` or ``folder/a/b/__init__.py`` for module ``a.b``, if it exists."""
    base = folder.joinpath(*module.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate.resolve()
    return None


def locate_system_entry(entry: str, folder: str | Path | None, *, key: str = "system") -> str:
    """``entry`` with a module found in ``folder`` rewritten to its absolute file.

    Registered names and modules not in ``folder`` are returned unchanged
    (those are imported from ``sys.path``); a relative file form
    ``"plants/cart.py:make"`` is made absolute against ``folder``.

    Raises
    ------
    ScenarioError
        If ``entry`` holds a colon but is not a well-formed import path.
    """
    if not is_import_path(entry):
        return entry
    module, attr = _split(entry, key)
    if folder is None:
        return entry
    folder = Path(folder)
    if module.endswith(".py"):
        path = Path(module)
        return f"{(path if path.is_absolute() else folder / path).resolve()}:{attr}"
    found = _module_file(module, folder)
    return entry if found is None else f"{found}:{attr}"


#: The version (:func:`~ofrl_drake.atomic.file_version`) of each user module file as last run.
_LOADED: dict[str, FileVersion] = {}


def _load_file(path: Path, entry: str, key: str) -> ModuleType:
    """Import the file ``path`` under a private name, again whenever the file changed."""
    if not path.is_file():
        raise ScenarioError(f"{key}: {entry!r}: no such module file {path}.")
    digest = hashlib.sha256(str(path).encode()).hexdigest()[:12]
    stem = re.sub(r"\W", "_", path.stem)
    name = f"_ofrl_drake_user_{digest}_{stem}"
    version = file_version(path)
    if name in sys.modules and _LOADED.get(name) == version:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    # Sibling modules of the file import as they would from a script in its folder.
    root = str(path.parent)
    sys.path.insert(0, root)
    try:
        # Compiled from the source, not through the loader, whose bytecode cache
        # takes a file rewritten within the same second at the same size for the old one.
        code = compile(path.read_bytes(), str(path), "exec", dont_inherit=True)
        exec(code, module.__dict__)
    except KeyboardInterrupt:
        del sys.modules[name]
        raise
    except BaseException as err:  # anything the user's module raises, SystemExit included
        del sys.modules[name]
        raise ScenarioError(
            f"{key}: {entry!r}: importing {path} failed: {status_line(err)}"
        ) from None
    finally:
        if root in sys.path:
            sys.path.remove(root)
    _LOADED[name] = version
    return module


def _import(module: str, entry: str, key: str) -> ModuleType:
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        if err.name is not None and (module == err.name or module.startswith(err.name + ".")):
            raise ScenarioError(
                f"{key}: {entry!r}: no module {module!r} beside the scenario file or on "
                "sys.path; put the module in the scenario's folder or install it."
            ) from None
        raise ScenarioError(
            f"{key}: {entry!r}: importing {module} failed: {status_line(err)}"
        ) from None
    except KeyboardInterrupt:
        raise
    except BaseException as err:
        raise ScenarioError(
            f"{key}: {entry!r}: importing {module} failed: {status_line(err)}"
        ) from None


def load_callable(entry: str, *, key: str = "system") -> Any:
    """The object named by ``entry`` (``"module.path:name"`` or ``"/file.py:name"``).

    Raises
    ------
    ScenarioError
        If the entry is malformed, the module cannot be found or fails to
        import, or it has no attribute of that name.
    """
    module_name, attr = _split(entry, key)
    if module_name.endswith(".py"):
        module = _load_file(Path(module_name), entry, key)
    else:
        module = _import(module_name, entry, key)
    try:
        return getattr(module, attr)
    except AttributeError:
        raise ScenarioError(
            f"{key}: {entry!r}: module {module_name} has no attribute {attr!r}; "
            "name a function defined there."
        ) from None


def _call_entry(entry: str, key: str, kind: type, not_callable: str, wrong_type: str) -> Any:
    """Load ``entry``, call it with no arguments and check the result is a ``kind``.

    ``not_callable`` and ``wrong_type`` finish the one-line errors (after the
    type name) that name the entry and the fix.
    """
    factory = load_callable(entry, key=key)
    if not callable(factory):
        raise ScenarioError(
            f"{key}: {entry!r} is an object of type {type(factory).__name__}{not_callable}"
        )
    try:
        result = factory()
    except KeyboardInterrupt:
        raise
    except BaseException as err:
        raise ScenarioError(f"{key}: {entry!r} raised {status_line(err)}") from None
    if not isinstance(result, kind):
        raise ScenarioError(
            f"{key}: {entry!r} returned an object of type {type(result).__name__}{wrong_type}"
        )
    return result


def _call_factory(entry: str, key: str) -> ControlAffineSystem:
    return _call_entry(
        entry,
        key,
        ControlAffineSystem,
        ", not a callable; name a function of no arguments that returns a ControlAffineSystem.",
        "; it must return an ofrl_drake.ControlAffineSystem.",
    )


def system_from_entry(entry: str, *, key: str = "system") -> ControlAffineSystem:
    """The system named by ``entry``: a registered example or an import path."""
    if is_import_path(entry):
        return _call_factory(entry, key)
    from ofrl_drake.examples import make_system

    return make_system(entry)


def locate_model_file(model: str, folder: str | Path | None) -> str:
    """A relative model file made absolute against ``folder``; URLs unchanged."""
    if not model or "://" in model or folder is None or Path(model).is_absolute():
        return model
    return str((Path(folder) / model).resolve())


def _drake_system(plant: Any) -> ControlAffineSystem:
    from pydrake.systems.framework import System

    entry, key = plant.drake_system, "plant.drake_system"
    system = _call_entry(
        entry,
        key,
        System,
        "; name a Drake System class or a function of no arguments returning a System.",
        "; it must return a Drake System (pydrake.systems.framework.System).",
    )
    if plant.C is None:
        raise ScenarioError(
            f"plant.C: required with plant.drake_system; give the output matrix y = C x "
            f"as a list of rows of length {system.num_continuous_states()}."
        )
    try:
        return ControlAffineSystem.from_drake(system, plant.C, plant.input_port or 0)
    except ModelError as err:
        raise ScenarioError(f"{key}: {entry!r}: {err}") from None


def _multibody(plant: Any) -> ControlAffineSystem:
    try:
        return ControlAffineSystem.from_multibody(plant.multibody, plant.C)
    except ModelError as err:
        raise ScenarioError(f"plant.multibody: {err}") from None


def _base_system(scenario: Any) -> ControlAffineSystem:
    plant = getattr(scenario, "plant", None)
    if plant is None:
        if not scenario.system:
            raise ScenarioError(
                "system: missing; name the plant with system: (a registered example or "
                "'module.path:callable') or with plant: (multibody: or drake_system:)."
            )
        return system_from_entry(scenario.system)
    if scenario.system:
        raise ScenarioError(
            f"plant: the scenario names its plant twice (system: {scenario.system!r} and "
            "plant:); keep one of them."
        )
    if bool(plant.multibody) == bool(plant.drake_system):
        raise ScenarioError(
            "plant: give exactly one of plant.multibody (a model file or package:// URL) "
            "and plant.drake_system ('module.path:callable' of a Drake System)."
        )
    if plant.input_port and plant.multibody:
        raise ScenarioError(
            "plant.input_port: only for plant.drake_system; a multibody plant's input is "
            "its actuation."
        )
    return _multibody(plant) if plant.multibody else _drake_system(plant)


def _shift(
    system: ControlAffineSystem, equilibrium: Any, *, check: bool = True
) -> ControlAffineSystem:
    x, u = list(equilibrium.x), list(equilibrium.u)
    if len(x) != system.n:
        raise ScenarioError(
            f"equilibrium.x: expected {system.n} entries (the plant's state); got {len(x)}."
        )
    if u and len(u) != system.m:
        raise ScenarioError(
            f"equilibrium.u: expected {system.m} entries (the plant's inputs); got {len(u)}."
        )
    try:
        if not check:  # a truth runs in the model's coordinates, equilibrium or not
            return system.shifted(x, u or None, tol=float("inf"))
        return system.shifted(x, u or None)
    except ModelError as err:
        raise ScenarioError(f"equilibrium: {err}") from None


def _registered_factory(name: Any) -> Any:
    """The factory registered under ``name`` now (None for an import path or no name)."""
    if not isinstance(name, str) or not name or is_import_path(name):
        return None
    from ofrl_drake.examples import EXAMPLES

    return EXAMPLES.get(name)


def _source_files(scenario: Any) -> list[str]:
    """The local files ``scenario``'s system is built from: module files, a model file.

    Modules imported from ``sys.path`` (``"package.module:make"``) are not
    among them: Python imports those once per process.
    """
    plant = getattr(scenario, "plant", None)
    files = []
    for entry in (scenario.system, getattr(plant, "drake_system", "")):
        if isinstance(entry, str) and is_import_path(entry):
            module = entry.rpartition(":")[0]
            if module.endswith(".py"):
                files.append(module)
    model = getattr(plant, "multibody", "")
    if isinstance(model, str) and model and "://" not in model:
        files.append(model)
    return files


def _cache_key(scenario: Any) -> tuple[str, Any]:
    """The key of ``scenario``'s system in :data:`_BUILT`, and its registered factory.

    A name registered again (``register(name, new_factory)``) is a new key: the
    factory's identity is part of it, and the cache holds the factory, so the
    identity is not reused while the entry lives. So is an edited module or
    model file (its :func:`~ofrl_drake.atomic.file_version`), and a relative
    model file read from another working folder.
    """
    plant = getattr(scenario, "plant", None)
    eq = getattr(scenario, "equilibrium", None)
    factory = _registered_factory(scenario.system)
    key = repr(
        (
            scenario.system,
            id(factory),
            [file_version(f) for f in _source_files(scenario)],
            None if plant is None else dataclasses.astuple(plant),
            None if eq is None else dataclasses.astuple(eq),
        )
    )
    return key, factory


#: Systems built for a cache key: ``(factory, system)``.
_BUILT: dict[str, tuple[Any, ControlAffineSystem]] = {}


def _built(key: str) -> ControlAffineSystem | None:
    hit = _BUILT.get(key)
    return None if hit is None else hit[1]


def resolve_system(scenario: Any) -> ControlAffineSystem:
    """The :class:`ControlAffineSystem` that ``scenario`` runs.

    Every module that needs the scenario's plant (validation, observer design,
    diagram, optimal cost) calls this. With ``scenario.equilibrium`` it is the
    shifted system (a :class:`~ofrl_drake.model.ShiftedSystem`, whose
    ``equilibrium`` maps results back to the plant's coordinates).

    Raises
    ------
    ScenarioError
        Naming the entry, if the system cannot be built.
    """
    key, factory = _cache_key(scenario)
    system = _built(key)
    if system is None:
        system = _base_system(scenario)
        equilibrium = getattr(scenario, "equilibrium", None)
        if equilibrium is not None:
            system = _shift(system, equilibrium)
        _BUILT[key] = (factory, system)
    return system


def _check_truth_sizes(truth: ControlAffineSystem, model: ControlAffineSystem) -> None:
    """Refuse a truth whose numbers of states, inputs and outputs are not the model's.

    The truth is simulated in the model's place, in its coordinates (shifted by
    the scenario's ``equilibrium``), so ``(n, m, q)`` must agree.
    """
    got, want = (truth.n, truth.m, truth.q), (model.n, model.m, model.q)
    if got != want:
        raise ScenarioError(
            f"truth: the truth {truth.name!r} has (n, m, q) = {got} (states, inputs, "
            f"outputs), the model {model.name!r} {want}; they must agree, since the truth "
            "is simulated in the model's place and coordinates. Name a truth of the "
            "model's sizes (or leave truth.system and truth.plant out: the model's plant)."
        )


def multibody_body_names(system: ControlAffineSystem | None) -> list[str] | None:
    """The body names of a model built from a multibody plant; None for any other (or None)."""
    plant = None if system is None else system.multibody_plant
    if plant is None:
        return None
    from pydrake.multibody.tree import BodyIndex

    return [plant.get_body(BodyIndex(i)).name() for i in range(plant.num_bodies())]


def resolve_truth(scenario: Any) -> ControlAffineSystem | None:
    """The plant that ``scenario`` simulates when its ``truth`` is not the model; else None.

    ``truth.system`` or ``truth.plant`` is built as the scenario's own plant
    would be, shifted by the scenario's equilibrium without the equilibrium
    check (a wrong model need not share it); with neither, it is the model's
    own plant (for ``body_mass_scale``).

    Raises
    ------
    ScenarioError
        Naming ``truth`` and the entry, if the truth cannot be built, its
        numbers of states, inputs or outputs differ from the model's (naming
        both), or ``body_mass_scale`` names a body that does not exist or the
        truth is not a multibody plant.
    """
    truth = getattr(scenario, "truth", None)
    if truth is None:
        return None
    system: ControlAffineSystem | None
    model = resolve_system(scenario)
    if not truth.system and truth.plant is None:
        system = model
    else:
        proxy = dataclasses.make_dataclass("TruthProxy", ["system", "plant", "equilibrium"])(
            truth.system, truth.plant, getattr(scenario, "equilibrium", None)
        )
        key, factory = _cache_key(proxy)
        key = "truth:" + key
        system = _built(key)
        if system is None:
            try:
                system = _base_system(proxy)
            except ScenarioError as err:
                raise ScenarioError(f"truth.{err}") from None
            # Before the shift, whose own check would name equilibrium.x, not the truth.
            _check_truth_sizes(system, model)
            if proxy.equilibrium is not None:
                try:
                    system = _shift(system, proxy.equilibrium, check=False)
                except ScenarioError as err:
                    raise ScenarioError(f"truth.{err}") from None
            _BUILT[key] = (factory, system)
        else:  # built for a scenario whose model may have other sizes
            _check_truth_sizes(system, model)
    if truth.body_mass_scale:
        names = multibody_body_names(system)
        if names is None:
            raise ScenarioError(
                "truth.body_mass_scale: scales the bodies of a multibody plant; the truth "
                f"{system.name!r} is not one (use truth.plant.multibody)."
            )
        for body in truth.body_mass_scale:
            if body not in names:
                raise ScenarioError(
                    f"truth.body_mass_scale.{body}: no body of that name in {system.name!r}; "
                    f"its bodies are {names}."
                )
    return system


def dynamics_fingerprints(scenario: Any) -> dict[str, str | None]:
    """The :meth:`~ofrl_drake.model.ControlAffineSystem.fingerprint` of the model and truth.

    ``{"model": ..., "truth": ...}``, the truth None when the model is the
    truth. A scenario's text names its plant's code but does not hold it; a
    store of results (a sweep's plan) keeps these to tell that the code changed.

    Raises
    ------
    ScenarioError
        If the model or the truth cannot be built.
    """
    truth = resolve_truth(scenario)
    return {
        "model": resolve_system(scenario).fingerprint(),
        "truth": None if truth is None else truth.fingerprint(),
    }


def check_dynamics(scenario: Any, expected: Mapping[str, str | None] | None) -> None:
    """Refuse to run ``scenario`` here if its plant's code is not the one ``expected``.

    A sweep's tasks run where Dask puts them; a worker on another machine
    builds the plant from its own copy of the plant's module and model files.
    ``expected`` is :func:`dynamics_fingerprints` on the client (None: no
    check); a worker whose copy differs would run another plant under the
    same name, and its rows would be mixed with the others.

    Raises
    ------
    ScenarioError
        If the model's or the truth's fingerprint here differs from ``expected``.
    """
    if expected is None:
        return
    here = dynamics_fingerprints(scenario)
    for role in ("model", "truth"):
        if here.get(role) != expected.get(role):
            raise ScenarioError(
                f"the {role} dynamics on {socket.gethostname()} (pid {os.getpid()}) differ from "
                f"those the sweep was started with (fingerprint {here.get(role)} against "
                f"{expected.get(role)}): give every worker the same copy of the plant's module "
                "and model files as the client, and restart workers after an edit; then "
                "--resume --retry-failed runs these rows again."
            )
