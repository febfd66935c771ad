"""One contract for observer blocks: ``observer_certificate()``, asked by ``simulate()``."""

import dataclasses

import numpy as np
import pytest

from ofrl_drake import ModelError, build_closed_loop, simulate
from ofrl_drake.examples import make_system
from ofrl_drake.jacobian_bounds import Box
from ofrl_drake.observer import ObserverGains
from ofrl_drake.observer_certificate import ObserverCertificate, certificate_of
from ofrl_drake.systems import ThreeGainObserver
from ofrl_drake.systems.baselines import FullStateObserver


def _short(scenario, **variant):
    return dataclasses.replace(
        scenario,
        simulation=dataclasses.replace(scenario.simulation, duration=0.3),
        variant=dataclasses.replace(scenario.variant, **variant),
    )


@pytest.mark.parametrize(
    ("variant", "kind", "has_design", "has_box"),
    [
        ("three_gain", "design", True, True),
        ("linear_luenberger", "design", True, True),
        ("drake_luenberger", "local", True, False),
        ("true_state", "none", False, False),
    ],
)
def test_every_shipped_observer_answers_the_contract(
    paper_scenario, variant, kind, has_design, has_box
):
    loop = build_closed_loop(_short(paper_scenario, observer=variant))
    cert = loop.observer.observer_certificate()
    assert cert == certificate_of(loop.observer)
    assert cert.kind == kind
    assert (cert.design is not None) == has_design
    assert (cert.box is not None) == has_box
    if has_box:
        assert cert.box == loop.design.box
        assert cert.design == loop.design.to_dict()
    else:
        assert cert.note.endswith("only |u_k| <= lambda_bar was checked")


def test_scheduled_observer_is_of_kind_scheduled(paper_scenario, paper_design):
    s = dataclasses.replace(
        paper_scenario, observer=dataclasses.replace(paper_scenario.observer, schedule_period=1.0)
    )
    cert = certificate_of(build_closed_loop(s, design=paper_design).observer)
    assert cert.kind == "scheduled" and cert.box is None
    assert cert.design == paper_design.to_dict()


class _BoxedTrueState(FullStateObserver):
    """Not a shipped class: simulate() must take its box from the contract alone."""

    def __init__(self, box):
        super().__init__(2)
        self.box = box

    def observer_certificate(self):
        return ObserverCertificate("design", design={"kind": "made_up"}, box=self.box)


def test_simulate_asks_the_contract_not_the_class(paper_scenario):
    # x stays in [-2, 2]^2 but leaves the made-up box [-0.5, 0.5]^2 at once.
    box = Box([-0.5, -0.5], [0.5, 0.5])
    r = simulate(_short(paper_scenario), observer=_BoxedTrueState(box), progress=False)
    assert r.design == {"kind": "made_up"}
    v = r.validity
    assert v.box_check == "fixed" and v.state_outside is True and not v.valid
    wide = simulate(
        _short(paper_scenario), observer=_BoxedTrueState(Box([-9, -9], [9, 9])), progress=False
    )
    assert wide.validity.box_check == "fixed" and wide.validity.valid


def test_a_block_without_the_method_certifies_nothing():
    class Plain:
        pass

    cert = certificate_of(Plain())
    assert cert.kind == "none" and cert.design is None and cert.box is None
    assert cert.note.startswith("no observer design (observer block Plain)")


def test_a_wrong_answer_raises():
    class Wrong:
        def observer_certificate(self):
            return {"box": None}

    with pytest.raises(ModelError, match=r"Wrong.observer_certificate\(\) must return"):
        certificate_of(Wrong())


def test_certificate_kinds_and_boxes_are_checked():
    with pytest.raises(ModelError, match=r"certificate kind must be one of"):
        ObserverCertificate("proof")
    with pytest.raises(ModelError, match=r"kind 'design' needs a box"):
        ObserverCertificate("design")
    with pytest.raises(ModelError, match=r"kind 'local' has no fixed box"):
        ObserverCertificate("local", box=Box([-1.0], [1.0]))


def test_three_gain_observer_refuses_a_design_it_does_not_run(paper_design):
    system = make_system("two_state")
    gains = ObserverGains.from_design(system, paper_design)
    other = dataclasses.replace(gains, L=gains.L + 1.0)
    with pytest.raises(ModelError, match=r"gains.L differs from design.L"):
        ThreeGainObserver(system, other, design=paper_design)
    bare = ThreeGainObserver(system, gains)
    assert bare.observer_certificate().kind == "none"
    np.testing.assert_array_equal(bare.gains.L, paper_design.L)
