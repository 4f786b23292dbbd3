"""Output files follow the user's umask (not mkstemp's private 0600)."""

import os
import stat

from comreg_core.io._files import atomic_output


def _mode_written(tmp_path, umask: int) -> int:
    old = os.umask(umask)
    try:
        with atomic_output(tmp_path / f"out_{umask:o}.json") as tmp:
            tmp.write_text("{}\n", encoding="utf-8")
    finally:
        os.umask(old)
    return stat.S_IMODE((tmp_path / f"out_{umask:o}.json").stat().st_mode)


def test_atomic_output_files_are_0644_under_umask_022(tmp_path):
    assert _mode_written(tmp_path, 0o022) == 0o644


def test_atomic_output_files_follow_a_private_umask(tmp_path):
    assert _mode_written(tmp_path, 0o077) == 0o600
