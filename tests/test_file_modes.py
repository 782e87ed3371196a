"""Files written atomically get the permissions of any new file (0o666 less the umask), not the temp file's 0o600."""
from __future__ import annotations

import os
import stat
from contextlib import contextmanager

import numpy as np
import pytest

from kiloforge.io import atomic_path, new_file_mode, write_atomic, write_files_atomic


@contextmanager
def umask(mask: int):
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize("mask", (0o022, 0o002, 0o077))
def test_export_writes_follow_the_umask(tmp_path, mask):
    """write_files_atomic / write_atomic / atomic_path give 0o666 & ~umask, like a plain open()."""
    with umask(mask):
        assert new_file_mode() == 0o666 & ~mask
        write_files_atomic({tmp_path / "a.c": "int x;\n", tmp_path / "b.json": b"{}"})
        write_atomic(tmp_path / "a.c", "int y;\n")  # replacing an existing file
        with atomic_path(tmp_path / "plot.png") as tmp:
            tmp.write_bytes(b"png")
        with atomic_path(tmp_path / "prog", executable=True) as tmp:
            tmp.write_bytes(b"exe")
        (tmp_path / "plain.txt").write_text("x")
        assert os.umask(mask) == mask  # reading the mode left the umask as it was
    for name in ("a.c", "b.json", "plain.txt", "plot.png"):
        assert mode(tmp_path / name) == 0o666 & ~mask, name
    assert mode(tmp_path / "prog") == 0o777 & ~mask


@pytest.mark.parametrize("mask", (0o022, 0o077))
def test_run_files_follow_the_umask(tmp_path, mask):
    """A trainer's checkpoint and its JSON/CSV files are as readable as its plots."""
    pytest.importorskip("torch")
    from learn.checkpoint import load_file, save_file

    with umask(mask):
        save_file({"w": np.arange(3)}, tmp_path / "checkpoint.pt")
        write_atomic(tmp_path / "config.json", "{}\n")
    assert mode(tmp_path / "checkpoint.pt") == 0o666 & ~mask
    assert mode(tmp_path / "config.json") == 0o666 & ~mask
    np.testing.assert_array_equal(load_file(tmp_path / "checkpoint.pt")["w"], np.arange(3))
    assert (tmp_path / "config.json").read_text() == "{}\n"
