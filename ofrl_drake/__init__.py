"""ofrl_drake: output-feedback, model-based RL control as Drake block diagrams.

The paper's method (../shared/paper) in blocks: a plant, a three-gain observer
with LMI-certified gains, a critic learned from extrapolated Bellman errors, a
least-squares gain Gamma and a saturated controller.

>>> import ofrl_drake as od                                     # doctest: +SKIP
>>> scenario = od.load_scenario("diagrams/two_state_paper.yaml")  # doctest: +SKIP
>>> result = od.simulate(scenario)                              # doctest: +SKIP
"""

from ofrl_drake.ablation import Variant, ablate
from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.diagram import ClosedLoop, build_closed_loop
from ofrl_drake.errors import ModelError, OfrlError, OutputError, ScenarioError, SwapError
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.scenario import Scenario, load_scenario
from ofrl_drake.simulation import SimulationResult, simulate

__version__ = "0.1.0"

__all__ = [
    "ClosedLoop",
    "ControlAffineSystem",
    "ModelError",
    "OfrlError",
    "OutputError",
    "PolynomialBasis",
    "Scenario",
    "ScenarioError",
    "SimulationResult",
    "SwapError",
    "Variant",
    "ablate",
    "build_closed_loop",
    "load_scenario",
    "simulate",
]
