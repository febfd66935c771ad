"""The validity monitor on synthetic logs: fixed box, box schedule, no box."""

import json

import numpy as np
import pytest

from ofrl_drake.errors import ModelError
from ofrl_drake.validity import BoxSchedule, ValidityReport, validity_report

BOX = (np.array([-1.0, -1.0]), np.array([1.0, 1.0]))
T = np.array([0.0, 1.0, 2.0, 3.0, 4.0])  # five samples, equal weights 1/5


def _inside(T_=T):
    return np.zeros((T_.size, 2))


def test_fixed_box_flags_state_estimate_and_input_at_their_samples():
    x, xhat, u = _inside(), _inside(), np.zeros((T.size, 1))
    x[3] = [1.5, 0.0]  # x leaves at t = 3
    xhat[2] = [0.0, -1.2]  # xhat leaves at t = 2
    u[4] = [2.5]  # |u| > 2 at t = 4
    r = validity_report(T, x, xhat, u, BOX, 2.0)
    assert r.box_check == "fixed" and r.box_checked and r.note is None
    assert r.first_exit_time == pytest.approx(2.0, abs=1e-12)
    assert r.fraction_outside == pytest.approx(3 / 5, abs=1e-12)
    assert r.state_outside is True and r.estimate_outside is True and r.input_exceeded is True
    assert not r.valid
    assert r.warning().startswith("warning: x, xhat, |u| left the certified region at t = 2.000 s")


def test_fraction_outside_weights_each_sample_by_its_time_step():
    # Uneven samples: each weighs the step after it, the last one the step before
    # it: 0.5, 1.5, 0.25, 1.75, 1.75 (5.75 in all). Outside at t = 0.5 (x) and at
    # t = 4 (|u|): (1.5 + 1.75) / 5.75 = 13 / 23, where the share of samples is 2 / 5.
    t = np.array([0.0, 0.5, 2.0, 2.25, 4.0])
    x, xhat, u = _inside(t), _inside(t), np.zeros((t.size, 1))
    x[1] = [0.0, 1.5]
    u[4] = [-2.5]
    r = validity_report(t, x, xhat, u, BOX, 2.0)
    assert r.first_exit_time == 0.5
    assert r.fraction_outside == pytest.approx(13 / 23, rel=1e-12)


def test_fixed_box_inside_is_valid_and_has_no_warning():
    r = validity_report(T, _inside(), _inside(), np.full((T.size, 1), 2.0), BOX, 2.0)
    assert r.valid and r.warning() is None
    assert r.fraction_outside == 0.0
    assert r.state_outside is False and r.estimate_outside is False and not r.input_exceeded


def test_without_a_box_only_the_input_is_checked_and_the_report_says_why():
    far = np.full((T.size, 2), 100.0)  # would be outside any sensible box
    u = np.zeros((T.size, 1))
    reason = "no observer design (observer block X): box checks not applicable"
    r = validity_report(T, far, far, u, None, 2.0, note=reason)
    assert r.valid and r.warning() is None
    assert r.box_check == "not_applicable" and not r.box_checked
    assert r.state_outside is None and r.estimate_outside is None
    assert r.note == reason
    d = json.loads(json.dumps(r.to_dict()))
    assert d["box_checked"] is False and d["box_check"] == "not_applicable"
    assert d["state_outside"] is None and d["note"] == reason and d["valid"] is True

    u[1:3] = [[-2.5], [2.5]]
    r = validity_report(T, far, far, u, None, 2.0, note=reason)
    assert not r.valid and r.input_exceeded
    assert r.first_exit_time == pytest.approx(1.0, abs=1e-12)
    assert r.fraction_outside == pytest.approx(2 / 5, abs=1e-12)
    assert r.state_outside is None and r.estimate_outside is None
    assert r.warning() == (
        "warning: |u| exceeded the input bound at t = 1.000 s (40.0% of the horizon in "
        f"violation); x and xhat were not checked against a box: {reason}."
    )


def test_without_a_box_and_without_a_reason_a_generic_one_is_stored():
    r = validity_report(T, _inside(), _inside(), np.zeros((T.size, 1)), None, 2.0)
    assert r.note == "no certified box given: box checks not applicable"


def test_box_schedule_switches_after_each_time_and_keeps_the_old_box_at_it():
    s = BoxSchedule(
        times=[0.0, 2.0, 3.0],
        lower=[[-1.0, -1.0], [10.0, 10.0], [20.0, 20.0]],
        upper=[[1.0, 1.0], [11.0, 11.0], [21.0, 21.0]],
    )
    lower, upper = s.at(np.array([0.0, 1.9, 2.0, 2.0 + 1e-12, 2.5, 3.0, 3.5]))
    np.testing.assert_array_equal(lower[:, 0], [-1.0, -1.0, -1.0, -1.0, 10.0, 10.0, 20.0])
    np.testing.assert_array_equal(upper[:, 1], [1.0, 1.0, 1.0, 1.0, 11.0, 11.0, 21.0])


def test_validity_against_a_box_schedule_uses_the_box_in_force():
    schedule = BoxSchedule(
        times=[0.0, 1.5], lower=[[-1.0, -1.0], [4.0, -1.0]], upper=[[1.0, 1.0], [6.0, 1.0]]
    )
    x = np.array([[0.0, 0.0], [0.5, 0.0], [5.0, 0.0], [5.5, 0.0], [5.0, 0.0]])
    u = np.zeros((T.size, 1))
    # x leaves the first box after it was replaced: valid against the schedule ...
    r = validity_report(T, x, x, u, schedule, 2.0, note="moving")
    assert r.valid and r.box_check == "scheduled" and r.note == "moving"
    assert r.state_outside is False and r.estimate_outside is False
    # ... but not against the first box held fixed.
    fixed = validity_report(T, x, x, u, BOX, 2.0)
    assert not fixed.valid and fixed.first_exit_time == pytest.approx(2.0, abs=1e-12)
    # An estimate that stays in the first box leaves the box in force at t = 2.
    xhat = np.zeros((T.size, 2))
    r = validity_report(T, x, xhat, u, schedule, 2.0)
    assert r.state_outside is False and r.estimate_outside is True
    assert r.first_exit_time == pytest.approx(2.0, abs=1e-12)
    assert r.fraction_outside == pytest.approx(3 / 5, abs=1e-12)
    assert "inside the box of the design in force" in r.warning()


def test_box_schedule_rejects_mismatched_shapes_and_unsorted_times():
    with pytest.raises(ModelError, match=r"BoxSchedule: times \(K,\), lower and upper \(K, n\)"):
        BoxSchedule(times=[0.0, 1.0], lower=[[0.0, 0.0]], upper=[[1.0, 1.0]])
    with pytest.raises(ModelError, match=r"BoxSchedule: times must be nondecreasing"):
        BoxSchedule(times=[1.0, 0.0], lower=[[0.0], [0.0]], upper=[[1.0], [1.0]])


def test_report_defaults_keep_the_old_constructor_working():
    r = ValidityReport(
        first_exit_time=None,
        fraction_outside=0.0,
        state_outside=False,
        estimate_outside=False,
        input_exceeded=False,
    )
    assert r.box_check == "fixed" and r.box_checked and r.note is None and r.valid
    # The injection points were not checked: nobody gave the gains.
    assert r.injection_check == "no_gains" and r.box_excursions is None
    assert r.injection_h_outside is None and r.injection_k_outside is None
    assert hash(r) == hash(r)  # still hashable


def test_box_schedule_from_samples_checks_each_sample_against_its_logged_box():
    t = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    boxes = np.array([[0, 1], [0, 1], [2, 3], [2, 3], [4, 5]], float)  # n = 1: [lower, upper]
    s = BoxSchedule.from_samples(t, boxes)
    np.testing.assert_array_equal(s.times, [0.0, 0.1, 0.3])
    lower, upper = s.at(t)
    np.testing.assert_array_equal(np.hstack([lower, upper]), boxes)
    with pytest.raises(ModelError, match=r"boxes must have shape \(T, 2 n\) for T sample times"):
        BoxSchedule.from_samples(t, boxes[:, :1])


# --- the injection points xhat + H ytil, xhat + K ytil (ytil = C (x - xhat)) ---

C1 = np.array([[1.0, 0.0]])  # y = x_1: n = 2, q = 1
ZERO = np.zeros((2, 1))


def _flagged_logs():
    """The logs of the first test: x leaves at t = 3, xhat at t = 2, |u| at t = 4."""
    x, xhat, u = _inside(), _inside(), np.zeros((T.size, 1))
    x[3] = [1.5, 0.0]
    xhat[2] = [0.0, -1.2]
    u[4] = [2.5]
    return x, xhat, u


def test_paper_design_k_injection_point_leaves_the_box_at_t0(paper_design, paper_result):
    d, r = paper_design, paper_result
    np.testing.assert_allclose(d.K.ravel(), [-2.7868, 0.0], atol=1e-3)
    np.testing.assert_allclose(d.C, [[0.0, 1.0]])
    box = (np.asarray(d.box.lower, float), np.asarray(d.box.upper, float))
    np.testing.assert_allclose(box, [[-2.0, -2.0], [2.0, 2.0]])
    old = validity_report(r.t, r.x, r.xhat, r.u, box, d.input_bound)
    assert old.first_exit_time == pytest.approx(0.02, abs=1e-9)  # xhat only, one sample later
    assert old.injection_check == "no_gains" and old.injection_k_outside is None

    rep = validity_report(r.t, r.x, r.xhat, r.u, box, d.input_bound, C=d.C, H=d.H, K=d.K)
    # t = 0: x = (-1, 1), xhat = (2, 1.5), ytil = -0.5, xhat + K ytil = (2 + 0.5 * 2.7868, 1.5).
    np.testing.assert_allclose(r.x[0], [-1.0, 1.0])
    np.testing.assert_allclose(r.xhat[0], [2.0, 1.5])
    assert rep.injection_check == "checked" and rep.injection_k_outside is True
    k = rep.box_excursions["xhat + K ytil"]
    assert k["outside"] is True and k["first_exit_time"] == 0.0 and k["worst_time"] == 0.0
    np.testing.assert_allclose(k["worst_point"], [3.3934, 1.5], atol=1e-3)
    assert k["worst_excursion"] == pytest.approx(1.3934, abs=1e-3)
    assert rep.first_exit_time == 0.0 and not rep.valid
    assert rep.fraction_outside > old.fraction_outside
    assert rep.state_outside is False and rep.estimate_outside is True
    assert rep.warning().startswith(
        "warning: xhat, xhat + H ytil, xhat + K ytil left the certified region at t = 0.000 s"
    )
    d_json = json.loads(json.dumps(rep.to_dict()))
    assert d_json["injection_k_outside"] is True and d_json["injection_check"] == "checked"
    assert d_json["box_excursions"]["xhat + K ytil"]["first_exit_time"] == 0.0


def test_zero_gains_leave_the_report_unchanged():
    x, xhat, u = _flagged_logs()
    before = validity_report(T, x, xhat, u, BOX, 2.0)
    for H, K in ((ZERO, ZERO), (np.zeros((T.size, 2, 1)), np.zeros((T.size, 2, 1)))):
        r = validity_report(T, x, xhat, u, BOX, 2.0, C=C1, H=H, K=K)
        assert r.injection_check == "zero_gains"
        assert r.injection_h_outside is None and r.injection_k_outside is None
        assert set(r.box_excursions) == {"x", "xhat"}
        assert r.box_excursions == before.box_excursions
        for name in (
            "first_exit_time",
            "fraction_outside",
            "state_outside",
            "estimate_outside",
            "input_exceeded",
            "box_check",
            "note",
        ):
            assert getattr(r, name) == getattr(before, name), name
        assert r.warning() == before.warning()
    assert before.box_excursions["x"] == {
        "outside": True,
        "first_exit_time": 3.0,
        "worst_excursion": pytest.approx(0.5, abs=1e-12),
        "worst_time": 3.0,
        "worst_point": [1.5, 0.0],
    }
    assert before.box_excursions["xhat"]["first_exit_time"] == 2.0


def test_zero_gains_on_the_paper_run_keep_its_report(paper_design, paper_result):
    d, r = paper_design, paper_result
    box = (np.asarray(d.box.lower, float), np.asarray(d.box.upper, float))
    before = validity_report(r.t, r.x, r.xhat, r.u, box, d.input_bound)
    zero = np.zeros_like(d.H)
    after = validity_report(r.t, r.x, r.xhat, r.u, box, d.input_bound, C=d.C, H=zero, K=zero)
    assert after.injection_check == "zero_gains"
    assert {**after.to_dict(), "injection_check": "no_gains"} == before.to_dict()


def test_h_only_injection_point_is_checked_and_k_is_not():
    x, xhat, u = _inside(), _inside(), np.zeros((T.size, 1))
    xhat[1] = [0.5, 0.0]  # ytil = -0.5: xhat + H ytil = (0.5, -1.0), on the boundary
    xhat[3] = [-0.8, 0.2]  # ytil = 0.8: xhat + H ytil = (-0.8, 1.8), 0.8 outside
    xhat[4] = [0.3, 0.5]  # ytil = -0.3: (0.3, -0.1), inside
    H = np.array([[0.0], [2.0]])
    assert validity_report(T, x, xhat, u, BOX, 2.0).valid  # x and xhat alone stay inside
    r = validity_report(T, x, xhat, u, BOX, 2.0, C=C1, H=H, K=ZERO)
    assert r.injection_check == "checked"
    assert r.injection_h_outside is True and r.injection_k_outside is None
    assert r.state_outside is False and r.estimate_outside is False
    assert set(r.box_excursions) == {"x", "xhat", "xhat + H ytil"}
    h = r.box_excursions["xhat + H ytil"]
    assert h["first_exit_time"] == 3.0 and h["worst_time"] == 3.0
    assert h["worst_excursion"] == pytest.approx(0.8, abs=1e-12)
    np.testing.assert_allclose(h["worst_point"], [-0.8, 1.8], atol=1e-12)
    assert r.first_exit_time == 3.0 and r.fraction_outside == pytest.approx(1 / 5, abs=1e-12)
    assert r.warning().startswith(
        "warning: xhat + H ytil left the certified region at t = 3.000 s (20.0% of the horizon"
    )
    assert r.box_excursions["x"]["worst_time"] is None  # never left: no worst sample


def test_per_sample_gains_and_a_box_schedule_use_what_is_in_force():
    schedule = BoxSchedule(
        times=[0.0, 1.5], lower=[[-1.0, -1.0], [-1.0, -5.0]], upper=[[1.0, 1.0], [1.0, 5.0]]
    )
    x, u = _inside(), np.zeros((T.size, 1))
    xhat = np.tile([-0.5, 0.0], (T.size, 1))  # ytil = 0.5 at every sample
    K = np.zeros((T.size, 2, 1))
    K[1] = [[0.0], [4.0]]  # t = 1: (-0.5, 2.0), outside the first box
    K[3] = [[0.0], [8.0]]  # t = 3: (-0.5, 4.0), inside the second box
    r = validity_report(T, x, xhat, u, schedule, 2.0, C=C1, H=np.zeros((T.size, 2, 1)), K=K)
    assert r.injection_k_outside is True and r.injection_h_outside is None
    k = r.box_excursions["xhat + K ytil"]
    assert k["first_exit_time"] == 1.0 and k["worst_excursion"] == pytest.approx(1.0, abs=1e-12)
    assert r.fraction_outside == pytest.approx(1 / 5, abs=1e-12)
    # Held fixed, the first box also misses the point at t = 3.
    fixed = validity_report(T, x, xhat, u, BOX, 2.0, C=C1, H=ZERO, K=K)
    assert fixed.box_excursions["xhat + K ytil"]["worst_time"] == 3.0
    assert fixed.fraction_outside == pytest.approx(2 / 5, abs=1e-12)


def test_without_a_box_the_injection_points_are_not_applicable():
    far = np.full((T.size, 2), 100.0)
    r = validity_report(T, far, far - 1.0, np.zeros((T.size, 1)), None, 2.0, C=C1, H=ZERO, K=C1.T)
    assert r.valid and r.injection_check == "not_applicable"
    assert r.injection_h_outside is None and r.injection_k_outside is None
    assert r.box_excursions is None


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"H": ZERO, "K": ZERO}, r"C, H and K go together .*; C missing"),
        ({"C": C1, "H": ZERO}, r"C, H and K go together .*; K missing\. Pass"),
        ({"K": ZERO}, r"; C and H missing"),
        (
            {"C": [[1.0, 0.0, 0.0]], "H": ZERO, "K": ZERO},
            r"C must have shape \(q, n\) with n = 2 .*; got \(1, 3\)",
        ),
        (
            {"C": C1, "H": np.zeros((2, 2)), "K": ZERO},
            r"H must have shape \(n, q\) = \(2, 1\), or \(5, 2, 1\) .*; got \(2, 2\)",
        ),
        ({"C": C1, "H": ZERO, "K": [[np.nan], [0.0]]}, r"K must be finite; got \[\[nan\], \[0"),
        ({"C": "y = x1", "H": ZERO, "K": ZERO}, r"C must be numeric; got 'y = x1'"),
    ],
)
def test_bad_injection_arguments_raise_model_error_naming_them(kwargs, match):
    x, xhat, u = _flagged_logs()
    with pytest.raises(ModelError, match=r"validity_report: .*" + match):
        validity_report(T, x, xhat, u, BOX, 2.0, **kwargs)


def test_injection_points_need_x_and_xhat_of_one_shape():
    with pytest.raises(
        ModelError,
        match=r"x and xhat must both have shape \(T, n\).*\(5, 2\) and \(5, 3\)",
    ):
        validity_report(
            T, _inside(), np.zeros((5, 3)), np.zeros((5, 1)), BOX, 2.0, C=C1, H=ZERO, K=ZERO
        )


def test_a_validity_report_reads_back_what_to_dict_wrote():
    report = ValidityReport(
        first_exit_time=0.5,
        fraction_outside=0.1,
        state_outside=True,
        estimate_outside=None,
        input_exceeded=False,
        box_check="scheduled",
        note="a note",
        box_excursions={"x": {"outside": True}},
    )
    assert ValidityReport.from_dict(json.loads(json.dumps(report.to_dict()))) == report
    with pytest.raises(ValueError, match=r"no entries \['state_box'\] in a validity report"):
        ValidityReport.from_dict({**report.to_dict(), "state_box": "nope"})
    with pytest.raises(ValueError, match=r"box_check: 'round' is not one of \['fixed'"):
        ValidityReport.from_dict({**report.to_dict(), "box_check": "round"})
    with pytest.raises(TypeError, match=r"input_exceeded: expected true or false, got 'no'"):
        ValidityReport.from_dict({**report.to_dict(), "input_exceeded": "no"})
    with pytest.raises(TypeError, match=r"expected a number, got str"):
        ValidityReport.from_dict({**report.to_dict(), "fraction_outside": "0.1"})


def test_nan_states_and_inputs_count_as_outside():
    # Before: comparisons with NaN are False, so a run that turned NaN was "valid", inside
    # the box and within the input bound; an estimate [inf, nan] was outside by 0.0.
    t = np.array([0.0, 0.1, 0.2])
    x = np.array([[0.0, 0.0], [1.0, 0.5], [np.nan, np.nan]])
    xhat = np.array([[0.1, 0.0], [0.9, 0.4], [np.inf, np.nan]])
    u = np.array([[0.0], [0.5], [np.nan]])
    box = (np.array([-2.0, -2.0]), np.array([2.0, 2.0]))
    report = validity_report(t, x, xhat, u, box, 1.0)
    assert not report.valid
    assert report.state_outside and report.estimate_outside and report.input_exceeded
    for key in ("x", "xhat"):
        excursion = report.box_excursions[key]
        assert excursion["first_exit_time"] == 0.2 and excursion["worst_excursion"] == np.inf
    finite = validity_report(t[:2], x[:2], xhat[:2], u[:2], box, 1.0)
    assert finite.valid and not finite.state_outside and not finite.input_exceeded
