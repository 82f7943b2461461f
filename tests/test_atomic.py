"""Files written whole or not at all (hmdrt.files.atomic): exact modes, and never overwriting when asked not to."""

import os
import stat

import pytest

from hmdrt.errors import HmdrtError
from hmdrt.files.atomic import write_atomic


def test_a_file_gets_exactly_its_mode_and_is_not_overwritten_unless_asked(tmp_path):
    path = tmp_path / "deep" / "name.key_secret"
    write_atomic(path, b"first", mode=0o600, replace=False)
    assert path.read_bytes() == b"first" and stat.S_IMODE(path.stat().st_mode) == 0o600
    with pytest.raises(FileExistsError):
        write_atomic(path, b"second", mode=0o600, replace=False)
    assert path.read_bytes() == b"first"
    write_atomic(path, b"third", mode=0o644)
    assert path.read_bytes() == b"third" and stat.S_IMODE(path.stat().st_mode) == 0o644
    assert sorted(p.name for p in path.parent.iterdir()) == ["name.key_secret"]  # no temporary file left


def test_a_folder_that_cannot_be_written_is_an_error_naming_the_path(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_bytes(b"")
    with pytest.raises(HmdrtError, match=f"cannot write {blocker}/x"):
        write_atomic(blocker / "x", b"data")


def test_a_file_without_a_mode_gets_the_one_open_would_give_it(tmp_path):
    """0666 less the umask, as open() would make it: frames, plots and logs stay as readable as they were."""
    umask = os.umask(0o027)
    try:
        write_atomic(tmp_path / "report.json", b"{}")
    finally:
        os.umask(umask)
    assert stat.S_IMODE((tmp_path / "report.json").stat().st_mode) == 0o640


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600)])
def test_outputs_a_lab_shares_get_the_umasks_mode(tmp_path, umask, mode):
    """A render's PNG and stats JSON (written by rename, as reports and eval results are) are 0644 under umask 022,
    as the PNGs always were, and 0600 for a user who asked for private files with umask 077."""
    from hmdrt.cli import main

    previous = os.umask(umask)
    try:
        out, stats = tmp_path / "frame.png", tmp_path / "stats.json"
        args = "render --scene whitted --profile sim-cpu --method full --resolution 16x12".split()
        assert main([*args, "--out", str(out), "--stats", str(stats)]) == 0
    finally:
        os.umask(previous)
    assert {stat.S_IMODE(p.stat().st_mode) for p in (out, stats)} == {mode}
