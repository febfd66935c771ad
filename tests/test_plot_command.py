"""``ofrl-drake plot``: a run's figures redrawn from its folder, as ``run`` drew them."""

import json
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
    "no scenario.yaml": (
        lambda d: (d / "scenario.yaml").unlink(),
        r"^error: RUN_DIR: .*/scenario\.yaml: no such file, so .* is not the --out folder of "
        r"ofrl-drake run",
    ),
    "another run's scenario": (
        lambda d: _rename_scenario(d / "scenario.yaml"),
        r"^error: .*/scenario\.yaml: the scenario 'other_\w+', but summary\.json holds a run "
        r"of '\w+'; the files are of two runs",
    ),
    "learning health of other samples": (
        lambda d: _other_samples(d / "learning_health.npz"),
        r"^error: .*/learning_health\.npz: its t is not the t of trajectories\.npz",
    ),
    "no learning health": (
        lambda d: (d / "learning_health.npz").unlink(),
        r"^error: .*/learning_health\.npz: no such file, so .* is not a run folder",
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
