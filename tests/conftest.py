"""Shared fixtures. Figures render off-screen."""

import os

os.environ["MPLBACKEND"] = "Agg"  # figures render off-screen, whatever the shell says

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAPER_SCENARIO = ROOT / "diagrams" / "two_state_paper.yaml"
MIMO_SCENARIO = ROOT / "diagrams" / "coupled_two_state.yaml"


def edited_two_state(f_scale=1.0, g_scale=1.0):
    """A factory of the paper's plant with f and g scaled: what an edit of its module gives.

    For ``ofrl_drake.examples.register``, to stand for a user's plant whose code changed.
    """
    from ofrl_drake.examples import two_state
    from ofrl_drake.model import ControlAffineSystem

    def make():
        base = two_state()
        return ControlAffineSystem(
            lambda x: f_scale * base.f(x), lambda x: g_scale * base.g(x), C=base.C
        )

    return make


@pytest.fixture(scope="session")
def paper_scenario():
    from ofrl_drake import load_scenario

    return load_scenario(PAPER_SCENARIO)


@pytest.fixture(scope="session")
def mimo_scenario():
    from ofrl_drake import load_scenario

    return load_scenario(MIMO_SCENARIO)


@pytest.fixture(scope="session")
def paper_design(paper_scenario):
    from ofrl_drake.variants import design_for

    return design_for(paper_scenario)


@pytest.fixture(scope="session")
def paper_result(paper_scenario, paper_design):
    from ofrl_drake import simulate

    return simulate(paper_scenario, design=paper_design, progress=False)
