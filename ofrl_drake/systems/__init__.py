"""Drake blocks of the closed loop; each is a thin wrapper over a math module."""

from ofrl_drake.systems.baselines import (
    ConstantController,
    FullStateObserver,
    LinearizedLuenbergerObserver,
    MovingBellmanExtrapolator,
    SaturatedLqrController,
)
from ofrl_drake.systems.bellman import BellmanExtrapolator
from ofrl_drake.systems.controller import SaturatedController
from ofrl_drake.systems.cost import RunningCost
from ofrl_drake.systems.critic import CriticWeights
from ofrl_drake.systems.drake_plant import DrakePlant
from ofrl_drake.systems.gamma import GammaGain
from ofrl_drake.systems.observer import ThreeGainObserver
from ofrl_drake.systems.plant import ControlAffinePlant
from ofrl_drake.systems.policy_gate import PolicyGate, PolicyPassThrough
from ofrl_drake.systems.scheduled_observer import ScheduledThreeGainObserver
from ofrl_drake.systems.symbolic import (
    SymbolicController,
    SymbolicObserver,
    SymbolicPlant,
    SymbolicRunningCost,
)

__all__ = [
    "BellmanExtrapolator",
    "ConstantController",
    "ControlAffinePlant",
    "CriticWeights",
    "DrakePlant",
    "FullStateObserver",
    "GammaGain",
    "LinearizedLuenbergerObserver",
    "MovingBellmanExtrapolator",
    "PolicyGate",
    "PolicyPassThrough",
    "RunningCost",
    "SaturatedController",
    "SaturatedLqrController",
    "ScheduledThreeGainObserver",
    "SymbolicController",
    "SymbolicObserver",
    "SymbolicPlant",
    "SymbolicRunningCost",
    "ThreeGainObserver",
]
