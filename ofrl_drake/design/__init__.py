"""Observer gain design: solve an LMI for ``P, L (, H, K)`` and certify it in numpy.

One module per concept:

* :mod:`~ofrl_drake.design.driver`: :func:`design_observer`, the entry point;
* :mod:`~ofrl_drake.design.formulations`: the LMI formulations (``"polytopic"``,
  a sound decay certificate; ``"paper"``, the paper's (lmi2)) by name;
* :mod:`~ofrl_drake.design.sdp`: the SDP as data and what a backend is;
  :mod:`~ofrl_drake.design.backend_drake`, :mod:`~ofrl_drake.design.backend_cvxpy`
  the two backends, :mod:`~ofrl_drake.design.backends` them by name;
* :mod:`~ofrl_drake.design.pipeline`: from checked inputs to a design whose
  numbers certify in numpy;
* :mod:`~ofrl_drake.design.result`: :class:`ObserverDesign` and its JSON;
* :mod:`~ofrl_drake.design.rate`: :func:`max_decay_rate`;
* :mod:`~ofrl_drake.design.errors`: the exceptions.
"""

from ofrl_drake.design.backends import BACKENDS, SOLVERS
from ofrl_drake.design.driver import design_observer
from ofrl_drake.design.errors import DesignError, ObserverDesignInaccurate, ObserverDesignInfeasible
from ofrl_drake.design.formulations import FORMULATIONS
from ofrl_drake.design.rate import DecayRateBracket, max_decay_rate
from ofrl_drake.design.result import ObserverDesign
from ofrl_drake.design.sdp import OBJECTIVES

__all__ = [
    "BACKENDS",
    "FORMULATIONS",
    "OBJECTIVES",
    "SOLVERS",
    "DecayRateBracket",
    "DesignError",
    "ObserverDesign",
    "ObserverDesignInaccurate",
    "ObserverDesignInfeasible",
    "design_observer",
    "max_decay_rate",
]
