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


def test_box_schedule_from_samples_checks_each_sample_against_its_logged_box():
    t = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    boxes = np.array([[0, 1], [0, 1], [2, 3], [2, 3], [4, 5]], float)  # n = 1: [lower, upper]
    s = BoxSchedule.from_samples(t, boxes)
    np.testing.assert_array_equal(s.times, [0.0, 0.1, 0.3])
    lower, upper = s.at(t)
    np.testing.assert_array_equal(np.hstack([lower, upper]), boxes)
    with pytest.raises(ModelError, match=r"boxes must have shape \(T, 2 n\) for T sample times"):
        BoxSchedule.from_samples(t, boxes[:, :1])
