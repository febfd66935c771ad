"""ofrl_drake: output-feedback, model-based RL control as Drake block diagrams.

The method of Output Feedback Adaptive Optimal Control of Affine Nonlinear
Systems with a Linear Measurement Model (see the README, Citation) in
blocks: a plant, a three-gain observer with LMI-certified gains, a critic
learned from extrapolated Bellman errors, a least-squares gain Gamma and a
saturated controller.

The names below are imported on first use, so ``import ofrl_drake`` (and the
``ofrl-drake`` command's start, ``--version``, ``--help``) does not load Drake.

>>> import ofrl_drake as od                                     # doctest: +SKIP
>>> scenario = od.load_scenario("diagrams/two_state_paper.yaml")  # doctest: +SKIP
>>> result = od.simulate(scenario)                              # doctest: +SKIP
"""

# Only modules the interpreter has already loaded are imported here, so that
# the ``ofrl-drake`` command can handle a SIGINT from its first instant.
import importlib

# ``__version__`` is read on first use (``__getattr__``) from the installed
# distribution's metadata, whose one source is ``version`` in pyproject.toml.

#: Public name -> the module that defines it.
_EXPORTS = {
    "Variant": "ofrl_drake.ablation_grid",
    "ablate": "ofrl_drake.ablation",
    "PolynomialBasis": "ofrl_drake.basis",
    "AblationError": "ofrl_drake.ablation_grid",
    "ClosedLoop": "ofrl_drake.diagram",
    "build_closed_loop": "ofrl_drake.diagram",
    "DesignError": "ofrl_drake.design.errors",
    "ObserverDesignInfeasible": "ofrl_drake.design.errors",
    "ModelError": "ofrl_drake.errors",
    "OfrlError": "ofrl_drake.errors",
    "OutputError": "ofrl_drake.errors",
    "RunFolderError": "ofrl_drake.errors",
    "ScenarioError": "ofrl_drake.errors",
    "SwapError": "ofrl_drake.errors",
    "WallTimeExceeded": "ofrl_drake.errors",
    "ControlAffineSystem": "ofrl_drake.model",
    "MonteCarloError": "ofrl_drake.monte_carlo",
    "montecarlo": "ofrl_drake.monte_carlo",
    "Scenario": "ofrl_drake.scenario",
    "load_scenario": "ofrl_drake.scenario",
    "SimulationResult": "ofrl_drake.simulation",
    "simulate": "ofrl_drake.simulation",
}

__all__ = [
    "AblationError",
    "ClosedLoop",
    "ControlAffineSystem",
    "DesignError",
    "ModelError",
    "MonteCarloError",
    "ObserverDesignInfeasible",
    "OfrlError",
    "OutputError",
    "PolynomialBasis",
    "RunFolderError",
    "Scenario",
    "ScenarioError",
    "SimulationResult",
    "SwapError",
    "Variant",
    "WallTimeExceeded",
    "ablate",
    "build_closed_loop",
    "load_scenario",
    "montecarlo",
    "simulate",
]


def __getattr__(name: str) -> object:
    """Import a public name, or a submodule (``ofrl_drake.systems``), on first use."""
    if name == "__version__":  # the version provenance records: ``not installed`` if so
        from ofrl_drake.provenance import versions

        globals()[name] = versions()["ofrl_drake"]
        return globals()[name]
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    try:
        return importlib.import_module(f"{__name__}.{name}")
    except ModuleNotFoundError as err:
        if err.name != f"{__name__}.{name}":
            raise
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])
