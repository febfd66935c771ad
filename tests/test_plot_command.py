"""``ofrl-drake plot``: a run's figures redrawn from its folder, as ``run`` drew them."""

import json
import math
import re
import shutil

import numpy as np
import pytest
from matplotlib.image import imread
from pydrake.common.yaml import yaml_dump, yaml_load

from ofrl_drake.cli import FIGURES_MARKER, main
from tests.cli_helpers import assert_one_line, run_cli

from .conftest import PAPER_SCENARIO, ROOT

#: Scenarios whose runs draw every kind of figure: an equilibrium with units (the
#: cart-pole: plant coordinates, policy updates and health), and the scheduled observer
#: (its gain schedule) on the paper's toy.
SCENARIOS = {
    "cart_pole": (ROOT / "diagrams" / "cart_pole.yaml", {}),
    "scheduled": (
        PAPER_SCENARIO,
        {
            "xhat0": [-0.5, 0.5],
            "observer": {"schedule_period": 0.1, "schedule_half_width": [1.0, 1.0]},
        },
    ),
}


def _scenario(folder, source, edits, duration=0.5):
    data = yaml_load(data=source.read_text())
    data["simulation"]["duration"] = duration
    for key, value in edits.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) else value
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "scenario.yaml"
    path.write_text(yaml_dump(data))
    return path


@pytest.fixture(scope="module", params=sorted(SCENARIOS))
def run_folder(request, tmp_path_factory):
    """A run folder written by ``ofrl-drake run`` (kept as written: copy it to change it)."""
    source, edits = SCENARIOS[request.param]
    folder = tmp_path_factory.mktemp(request.param)
    scenario = _scenario(folder / "in", source, edits)
    out = folder / "run"
    code = main(["run", str(scenario), "--out", str(out), "--quiet", "--checkpoints", "2"])
    assert code == 0
    return out


@pytest.fixture
def copied(run_folder, tmp_path):
    """A copy of the run folder, to damage."""
    return shutil.copytree(run_folder, tmp_path / "run")


def _pngs(folder):
    return sorted(p.name for p in folder.glob("*.png"))


def _assert_same_pixels(drawn, reference):
    assert _pngs(drawn) == _pngs(reference)
    for name in _pngs(reference):
        a, b = imread(drawn / name), imread(reference / name)
        assert a.shape == b.shape, name
        np.testing.assert_array_equal(a, b, err_msg=name)


def test_plot_redraws_every_figure_run_drew_pixel_for_pixel(run_folder, tmp_path, capsys):
    out = tmp_path / "figures"
    assert main(["plot", str(run_folder), "--out", str(out)]) == 0
    line = capsys.readouterr().out.strip()
    assert re.fullmatch(rf"wrote {re.escape(str(out))}: \d+ figures \(png, page size\) of .*", line)
    _assert_same_pixels(out, run_folder / "figures")
    names = _pngs(out)
    assert {"learning_curve.png", "learning_health.png", "overview.png"} <= set(names)
    if "scheduled" in str(run_folder):
        assert "gain_schedule.png" in names
    else:
        assert "state_4.png" in names
    assert (out / FIGURES_MARKER).is_file()


def test_plot_replaces_the_runs_own_figures_by_default(copied, tmp_path):
    before = shutil.copytree(copied / "figures", tmp_path / "before")
    (copied / "figures" / "state_1.png").write_bytes(b"stale")
    assert main(["plot", str(copied)]) == 0
    _assert_same_pixels(copied / "figures", before)
    assert not list(copied.glob(".figures.*"))  # no temporary or backup folder left
    assert main(["plot", str(copied)]) == 0  # and again: a folder plot wrote


def test_plot_writes_pdf_and_svg_at_column_size(run_folder, tmp_path):
    out = tmp_path / "paper"
    args = ["plot", str(run_folder), "--out", str(out), "--format", "png", "pdf", "svg"]
    assert main([*args, "--size", "column"]) == 0
    stems = {p[: -len(".png")] for p in _pngs(run_folder / "figures")}
    for kind in ("png", "pdf", "svg"):
        assert {p.stem for p in out.glob(f"*.{kind}")} == stems
    assert (out / "overview.pdf").read_bytes().startswith(b"%PDF")
    assert (out / "overview.svg").read_text().lstrip().startswith(("<?xml", "<svg"))
    # 3.5 in wide at 200 dpi (a page figure is twice as wide)
    assert imread(out / "cost.png").shape[1] <= 3.6 * 200
    assert imread(run_folder / "figures" / "cost.png").shape[1] > 3.6 * 200


def _truncate(path):
    path.write_bytes(path.read_bytes()[:100])


def _other_samples(path):
    with np.load(path) as data:
        arrays = {k: data[k][:-1] for k in data.files}
    np.savez(path, **arrays)


def _rename_scenario(path):
    path.write_text(path.read_text().replace("name: ", "name: other_", 1))


def _bad_curve(path):
    data = json.loads(path.read_text())
    data["learning_curve"] = [{"t": "zero"}]
    path.write_text(json.dumps(data))


def _edit_summary(folder, edit):
    data = json.loads((folder / "summary.json").read_text())
    edit(data)
    (folder / "summary.json").write_text(json.dumps(data))


def _older(folder):
    """``folder`` as ``run`` wrote it before it saved the figure inputs in summary.json."""
    _edit_summary(folder, lambda data: data.pop("figure_inputs"))
    return folder


def _edit_npz(path, **changes):
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    arrays.update({key: change(arrays[key]) for key, change in changes.items()})
    np.savez(path, **arrays)


def _wider_box(data):
    box = data["figure_inputs"]["observer_box"]
    box["lower"], box["upper"] = [*box["lower"], -1.0], [*box["upper"], 1.0]


def _other_basis(folder):
    path = _older(folder) / "scenario.yaml"
    text = path.read_text()
    assert "basis_degrees: [2]" in text
    path.write_text(text.replace("basis_degrees: [2]", "basis_degrees: [3]"))


#: Damage done to a copy of a run folder, and the one error line ``plot`` prints.
DAMAGE = {
    "truncated trajectories": (
        lambda d: _truncate(d / "trajectories.npz"),
        r"^error: .*/trajectories\.npz: not a readable \.npz archive \(File is not a zip "
        r"file\); the file is damaged or was not written by SimulationResult\.save; write "
        r"the run again \(ofrl-drake run RUN_DIR/scenario\.yaml --out NEW_DIR\)\.$",
    ),
    "corrupt summary": (
        lambda d: (d / "summary.json").write_text("{"),
        r"^error: .*/summary\.json: not readable JSON \(Expecting property name",
    ),
    "an older folder without scenario.yaml": (
        lambda d: (_older(d) / "scenario.yaml").unlink(),
        r"^error: RUN_DIR: .*/scenario\.yaml: no such file, and .*/summary\.json has no "
        r"figure_inputs \(a run written before it was saved there\), so .* is not the --out "
        r"folder of ofrl-drake run",
    ),
    "an older folder's scenario of another basis": (
        _other_basis,
        r"^error: .*/scenario\.yaml: the critic basis of degrees \[3\] has \d+ terms, but W "
        r"in trajectories\.npz has \d+ columns; the files are of two runs, or one is damaged: "
        r"write the run again \(ofrl-drake run SCENARIO --out NEW_DIR\)\.$",
    ),
    "figure inputs of another box": (
        lambda d: _edit_summary(d, _wider_box),
        r"^error: .*/summary\.json: the observer box has (\d+) entries, but x in "
        r"trajectories\.npz has (?!\1)\d+ columns; the files are of two runs",
    ),
    "figure inputs of more inputs than u has": (
        lambda d: _edit_summary(d, lambda data: data["figure_inputs"].update(inputs=2)),
        r"^error: .*/summary\.json: the scenario has 2 inputs, but u in trajectories\.npz has "
        r"1 columns; the files are of two runs",
    ),
    "an accuracy that is text": (  # was an internal error (exit 1) while drawing
        lambda d: _edit_summary(d, lambda data: data["integrator"].update(accuracy="1e-4")),
        r"^error: .*/summary\.json: integrator = .* cannot be read back \(expected a number, "
        r"got str\); the file is damaged",
    ),
    "value eigenvalues of one dimension": (  # was an internal error (exit 1) while drawing
        lambda d: _edit_npz(d / "learning_health.npz", value_eigenvalues=lambda v: v[:, 0]),
        r"^error: .*/learning_health\.npz: value_eigenvalues has shape \(\d+,\); expected "
        r"\(\d+, \d\) \(from trajectories\.npz\); the file is damaged",
    ),
    "a learning condition of two columns": (
        lambda d: _edit_npz(
            d / "learning_health.npz", learning_condition=lambda c: np.stack([c, c], axis=1)
        ),
        r"^error: .*/learning_health\.npz: learning_condition has shape \(\d+, 2\); expected "
        r"\(\d+,\)",
    ),
    "another run's scenario": (
        lambda d: _rename_scenario(_older(d) / "scenario.yaml"),
        r"^error: .*/scenario\.yaml: the scenario 'other_\w+', but summary\.json holds a run "
        r"of '\w+'; the files are of two runs",
    ),
    "learning health of other samples": (
        lambda d: _other_samples(d / "learning_health.npz"),
        r"^error: .*/learning_health\.npz: its t is not the t of trajectories\.npz",
    ),
    "no learning health": (
        lambda d: (d / "learning_health.npz").unlink(),
        r"^error: .*/learning_health\.npz: no such file, though the run folder needs it "
        r"\(removed\?\); write the run again",
    ),
    "a checkpoint after the run": (  # was drawn, with a time axis to 1e9 s
        lambda d: _edit_summary(d, lambda data: data["learning_curve"][-1].update(t=1e9)),
        r"^error: .*/summary\.json: learning_curve = .* cannot be read back \(checkpoint \d+ "
        r"is at t = 1000000000\.0, outside the run's times \[0, [\d.]+\]\)",
    ),
    "a checkpoint at NaN": (
        lambda d: _edit_summary(d, lambda data: data["learning_curve"][0].update(t=math.nan)),
        r"cannot be read back \(checkpoint 0 is at t = nan, outside the run's times",
    ),
    "a basis no run can have": (  # said "has None terms"
        lambda d: _edit_summary(d, lambda data: data["figure_inputs"].update(basis_degrees=[1])),
        r"^error: .*/summary\.json: the critic basis of degrees \[1\] is not one a run could "
        r"have used \(PolynomialBasis: degree 1 is not allowed; .*\); the file was edited",
    ),
    "a curve without costs": (
        lambda d: _bad_curve(d / "summary.json"),
        r"^error: .*/summary\.json: learning_curve = \[\{'t': 'zero'\}\] cannot be read back "
        r"\(expected a number, got str\)",
    ),
}


@pytest.mark.parametrize("case", sorted(DAMAGE))
def test_a_damaged_run_folder_exits_2_in_one_line_and_leaves_the_figures(copied, capsys, case):
    damage, message = DAMAGE[case]
    damage(copied)
    before = {p.name: p.read_bytes() for p in (copied / "figures").iterdir()}
    assert main(["plot", str(copied)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(message, err[0]), err
    assert {p.name: p.read_bytes() for p in (copied / "figures").iterdir()} == before
    assert not list(copied.glob(".figures.*"))


def test_an_interrupt_after_the_figures_are_written_says_they_were(copied, tmp_path, capsys):
    """It said "no output written" beside the figures folder it had just put in place."""
    import builtins
    from unittest import mock

    import ofrl_drake.cli as cli

    def interrupted(*args, **kwargs):
        if args and str(args[0]).startswith("wrote "):
            raise KeyboardInterrupt
        builtins.print(*args, **kwargs)

    out = tmp_path / "figures"
    with mock.patch.object(cli, "print", interrupted, create=True):
        assert main(["plot", str(copied), "--out", str(out)]) == 130
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == [f"error: interrupted; {out} was written in full before it"], lines
    assert (out / "overview.png").is_file()


def test_a_folder_that_is_not_a_run_exits_2_in_one_line(tmp_path):
    proc = run_cli("plot", tmp_path / "missing", timeout=300)
    assert_one_line(
        proc,
        2,
        r"^error: RUN_DIR: .*missing is not a folder; name the --out folder of "
        r"ofrl-drake run\.$",
    )
    (tmp_path / "saved").mkdir()
    (tmp_path / "saved" / "scenario.yaml").write_text("name: x\n")
    proc = run_cli("plot", tmp_path / "saved", timeout=300)
    assert_one_line(proc, 2, r"trajectories\.npz: no such file, so .*saved is not a run folder")
    assert sorted(p.name for p in (tmp_path / "saved").iterdir()) == ["scenario.yaml"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["--format", "jpg"],
            r"^error: argument --format: unknown value 'jpg'; choose one of "
            r"png, pdf, svg; see ofrl-drake plot --help$",
        ),
        (
            ["--size", "a4"],
            r"^error: argument --size: unknown value 'a4'; choose one of page, "
            r"column; see ofrl-drake plot --help$",
        ),
    ],
)
def test_an_unknown_format_or_size_is_refused_while_parsing(tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) as exit_:
        main(["plot", str(tmp_path), *args])
    assert exit_.value.code == 2
    assert re.search(message, capsys.readouterr().err.strip())


def test_out_that_is_not_plots_to_replace_is_refused(copied, tmp_path, capsys):
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "photo.png").write_bytes(b"mine")
    for out, message in (
        (
            foreign,
            r"--out: .*mine is not empty and was not written by ofrl-drake plot \(no "
            r"\.ofrl_drake_figures\); choose a new folder or empty this one\.$",
        ),
        (
            copied,
            r"--out: .*run is the run folder or holds it, which the figures would "
            r"replace; name another folder \(default RUN_DIR/figures\)\.$",
        ),
        (tmp_path, r"--out: .* is the run folder or holds it"),
    ):
        assert main(["plot", str(copied), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and re.search(message, err[0]), err
    assert (foreign / "photo.png").read_bytes() == b"mine"
    assert (copied / "trajectories.npz").is_file()


def test_a_failure_while_drawing_leaves_the_figures_as_they_were(copied, capsys, monkeypatch):
    import ofrl_drake.plotting as plotting

    before = {p.name: p.read_bytes() for p in (copied / "figures").iterdir()}

    def broken(*args, **kwargs):
        raise RuntimeError("drawing failed")

    monkeypatch.setattr(plotting, "plot_cost", broken)
    assert main(["plot", str(copied)]) == 2  # raised here: "your code raised RuntimeError"
    assert "RuntimeError: drawing failed" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in (copied / "figures").iterdir()} == before
    assert not list(copied.glob(".figures.*"))


def test_a_run_folder_being_written_is_refused(copied, capsys):
    from ofrl_drake.atomic import output_lock

    with output_lock(copied):  # what run holds while it writes the folder
        assert main(["plot", str(copied)]) == 2
    err = capsys.readouterr().err.strip()
    assert re.fullmatch(
        r"error: RUN_DIR: another ofrl-drake command is writing .*run now; wait for it to "
        r"finish, or choose another path\.",
        err,
    ), err


def test_plot_needs_neither_the_scenario_nor_its_plant(copied, tmp_path):
    older = _older(shutil.copytree(copied, tmp_path / "older"))
    (copied / "scenario.yaml").unlink()  # run wrote what the figures need in summary.json
    assert main(["plot", str(copied), "--out", str(tmp_path / "new")]) == 0
    _assert_same_pixels(tmp_path / "new", copied / "figures")
    # An older folder reads them from its scenario.yaml, as data: its plant is never loaded.
    path = older / "scenario.yaml"
    lines = path.read_text().splitlines()
    assert sum(line.startswith("system:") for line in lines) == 1
    gone = "system: /nowhere/gone.py:make_plant"
    path.write_text("\n".join(gone if x.startswith("system:") else x for x in lines) + "\n")
    assert main(["plot", str(older), "--out", str(tmp_path / "old")]) == 0
    _assert_same_pixels(tmp_path / "old", copied / "figures")


def test_plot_refuses_the_figures_of_another_run(copied, tmp_path, capsys):
    other = tmp_path / "other"
    (other / "figures").mkdir(parents=True)
    (other / ".ofrl_drake_output").write_text("written by ofrl-drake run\n")
    (other / "figures" / FIGURES_MARKER).write_text("written by ofrl-drake plot\n")
    (other / "figures" / "state_1.png").write_bytes(b"its own")
    assert main(["plot", str(copied), "--out", str(other / "figures")]) == 2
    _assert_one_error_line(
        capsys,
        r"error: --out: .*other/figures is inside .*other, the folder of another run, whose "
        r"files are its own; name a folder outside it \(default RUN_DIR/figures\)\.",
    )
    assert (other / "figures" / "state_1.png").read_bytes() == b"its own"


def test_plots_of_one_run_share_it_but_a_run_into_it_is_refused(copied, tmp_path, capsys):
    from ofrl_drake.atomic import output_lock

    with output_lock(copied, shared=True):  # what another plot of the run holds
        assert main(["plot", str(copied), "--out", str(tmp_path / "second")]) == 0
        capsys.readouterr()
        assert main(["run", str(copied / "scenario.yaml"), "--out", str(copied)]) == 2
    _assert_one_error_line(
        capsys,
        r"error: --out: another ofrl-drake command is writing or reading .*run now; wait for "
        r"it to finish, or choose another path\.",
    )


def _assert_one_error_line(capsys, pattern):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.fullmatch(pattern, err[0]), err


def test_repeated_format_options_add_up(copied, tmp_path, capsys):
    out = tmp_path / "both"
    assert main(["plot", str(copied), "--out", str(out), "--format", "pdf", "--format", "svg"]) == 0
    assert "(pdf, svg, page size)" in capsys.readouterr().out
    assert {p.suffix for p in out.iterdir() if not p.name.startswith(".")} == {".pdf", ".svg"}
