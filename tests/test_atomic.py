"""ofrl_drake.atomic: whole files or none, umask permissions, clear errors on bad paths."""

import os
import stat

import pytest

from ofrl_drake.atomic import atomic_file, atomic_write_text, output_lock
from ofrl_drake.errors import OutputError


def _mode(path):
    return stat.S_IMODE(os.stat(path).st_mode)


def test_written_files_follow_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        atomic_write_text(tmp_path / "a" / "b.txt", "hello\n")
    finally:
        os.umask(old)
    assert (tmp_path / "a" / "b.txt").read_text() == "hello\n"
    assert _mode(tmp_path / "a" / "b.txt") == 0o640  # 0666 & ~027, not mkstemp's 0600


def test_a_failure_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "x.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError, match="half-way"), atomic_file(target, "wb") as fh:
        fh.write(b"new, partial")
        raise RuntimeError("half-way")
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["x.bin"]


def test_bad_paths_raise_output_error_naming_them(tmp_path):
    (tmp_path / "afile").write_text("x")
    with pytest.raises(OutputError, match=r"--out: .*afile is a file, so .*sub/c.json cannot be"):
        atomic_write_text(tmp_path / "afile" / "sub" / "c.json", "{}")
    with pytest.raises(OutputError, match=r"--out: .* is a folder; name a file inside it"):
        atomic_write_text(tmp_path, "{}")


def test_one_output_has_one_lock_whatever_its_spelling(tmp_path):
    # Keyed on the absolute path, "sweep" and "alias/sweep" (a link) or "absent/../sweep"
    # were two locks, and two sweeps wrote into one folder.
    (tmp_path / "sweep").mkdir()
    (tmp_path / "alias").symlink_to(tmp_path, target_is_directory=True)
    with output_lock(tmp_path / "sweep"):
        for spelling in (tmp_path / "alias" / "sweep", tmp_path / "absent" / ".." / "sweep"):
            with pytest.raises(OutputError, match=r"another ofrl-drake command is writing .*sweep"):
                with output_lock(spelling):
                    pass


def test_readers_share_a_lock_that_a_writer_cannot_take(tmp_path):
    # plot reads a run folder under a shared lock: two plots of one run, but no run into it.
    with output_lock(tmp_path / "run", shared=True), output_lock(tmp_path / "run", shared=True):
        with pytest.raises(
            OutputError, match=r"another ofrl-drake command is writing or reading .*run now"
        ):
            with output_lock(tmp_path / "run"):
                pass
    with output_lock(tmp_path / "run"):
        with pytest.raises(OutputError, match=r"another ofrl-drake command is writing .*run now"):
            with output_lock(tmp_path / "run", shared=True):
                pass
    with output_lock(tmp_path / "run"):  # released
        pass
