"""``ofrl-drake verify-observer`` and the verification shown next to every design."""

import json

import pytest

from tests.cli_helpers import run_cli

from .conftest import PAPER_SCENARIO, ROOT

SOUND_SCENARIO = ROOT / "diagrams" / "two_state_sound.yaml"


def test_paper_design_is_falsified_exit_4_with_the_counterexample_in_one_line(tmp_path):
    out = tmp_path / "report.json"
    proc = run_cli("verify-observer", PAPER_SCENARIO, "--samples", 3000, "--seed", 1, "--out", out)
    assert proc.returncode == 4, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("two_state_paper: claims alpha = 2 (r <= -4); falsified: r = +")
    assert "at x = (" in lines[0] and "u = (" in lines[0]
    data = json.loads(out.read_text())
    report = data["verification"]
    assert report["falsified"] is True and report["worst_rate"] > 70.0
    assert report["samples"] == 3000 and report["seed"] == 1
    assert data["observer_design"]["formulation"] == "paper"


def test_sound_design_is_not_falsified_exit_0(tmp_path):
    proc = run_cli("verify-observer", SOUND_SCENARIO, "--samples", 3000)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("two_state_sound: decay-certified and not falsified")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--samples", "0"], "error: samples must be an integer >= 1; got 0."),
        (["--seed", "-3"], "error: seed must be an integer >= 0; got -3."),
    ],
)
def test_bad_arguments_exit_2_with_one_line(args, message):
    proc = run_cli("verify-observer", PAPER_SCENARIO, *args)
    assert proc.returncode == 2
    assert proc.stderr.strip() == message
    assert proc.stdout == ""


def test_missing_scenario_exits_2(tmp_path):
    proc = run_cli("verify-observer", tmp_path / "nope.yaml")
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "no such scenario file" in proc.stderr


def test_design_observer_shows_and_writes_its_verification(tmp_path):
    out = tmp_path / "design.json"
    proc = run_cli("design-observer", SOUND_SCENARIO, "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert "observer: decay-certified and not falsified" in proc.stdout
    verification = json.loads(out.read_text())["verification"]
    assert verification["falsified"] is False
    assert verification["samples"] == 10_000 and verification["refined"] is True


def test_a_design_on_sampled_bounds_is_not_called_a_proof(tmp_path):
    # Before: "observer: decay-certified and not falsified", as for certified bounds,
    # although sampled bounds are an inner estimate (bounds_are_guaranteed false).
    sampled = tmp_path / "sampled.yaml"
    text = SOUND_SCENARIO.read_text()
    assert text.count("jacobian_method: certified") == 1
    sampled.write_text(text.replace("jacobian_method: certified", "jacobian_method: sampled"))
    proc = run_cli("design-observer", sampled, "--out", tmp_path / "design.json")
    assert proc.returncode == 0, proc.stderr
    assert (
        "observer: decay-certified on sampled Jacobian bounds (not a proof) and not falsified"
        in proc.stdout
    ), proc.stdout
    proc = run_cli("verify-observer", sampled, "--samples", 2000)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(
        "two_state_sound: decay-certified on sampled Jacobian bounds (not a proof)"
    ), proc.stdout


def test_reports_with_an_infinite_rate_are_written_as_strict_json(tmp_path, monkeypatch):
    # Before: verify-observer --out (and design-observer, run's observer_design.json)
    # wrote the tokens Infinity and NaN, which strict JSON parsers refuse.
    import dataclasses

    import numpy as np

    from ofrl_drake import verification
    from ofrl_drake.cli import main

    real = verification.verify_observer

    def undefined_somewhere(design, system, **kwargs):  # as for f undefined in the box
        report = real(design, system, **kwargs)
        return dataclasses.replace(
            report, worst_rate=np.inf, worst_small_error_rate=np.inf, direction=[np.nan] * 2
        )

    monkeypatch.setattr(verification, "verify_observer", undefined_somewhere)

    def refuse(token):
        raise AssertionError(f"the report holds {token}")

    out = tmp_path / "report.json"
    assert (
        main(["verify-observer", str(SOUND_SCENARIO), "--samples", "200", "--out", str(out)]) == 4
    )
    data = json.loads(out.read_text(), parse_constant=refuse)
    assert data["verification"]["worst_rate"] is None and data["verification"]["falsified"]
    design = tmp_path / "design.json"
    assert main(["design-observer", str(SOUND_SCENARIO), "--out", str(design)]) == 0
    json.loads(design.read_text(), parse_constant=refuse)


def test_an_interrupt_after_the_design_is_written_says_it_was_written(tmp_path, capsys):
    """A Ctrl-C while the verdict was printed said "no output written" beside the new file."""
    from unittest import mock

    from ofrl_drake.cli import main

    out = tmp_path / "d.json"
    with mock.patch(
        "ofrl_drake.verification.VerificationReport.verdict", side_effect=KeyboardInterrupt
    ):
        assert main(["design-observer", str(SOUND_SCENARIO), "--out", str(out)]) == 130
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == [f"error: interrupted; {out} was written in full before it"], lines
    assert json.loads(out.read_text())["alpha"] == 0.9


def test_the_console_ignores_sigint_once_the_command_has_returned():
    """The exit code stands while Python shuts down (a Ctrl-C there printed a traceback)."""
    import signal
    from unittest import mock

    from ofrl_drake.__main__ import console

    before = signal.getsignal(signal.SIGINT)
    try:
        with mock.patch("ofrl_drake.cli.main", return_value=4):
            assert console() == 4
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)
