"""The private build cache (export.verify.buildcache, issue 47 item 1): a planted or altered program is
never run, a cache directory that is not private is refused (KILOFORGE_CACHE) or replaced (default)."""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.avr_tools import require_avr
from tests.bad_inputs import assert_one_clean_line
from export.verify import avr, buildcache, tools
from export.verify.buildcache import CACHE_ENV, CacheError, cached_program

ROOT = Path(__file__).resolve().parents[1]
AS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0
OTHER_UID = 65534  #: nobody


def _script(marker: Path, word: str) -> str:
    return f"#!/bin/sh\necho {word} >> '{marker}'\n"


def _builder(marker: Path):
    """A build step writing a shell program that appends 'built' to ``marker`` when run."""
    def build(out: Path) -> None:
        out.write_text(_script(marker, "built"))
    return build


def _plant(path: Path, marker: Path, *, mode: int = 0o700, sidecar: bool = True) -> None:
    """A foreign program at ``path`` that appends 'planted' to ``marker``; with ``sidecar`` its own
    matching sha256 beside it (an attacker who can write the directory can write that too)."""
    path.unlink(missing_ok=True)
    path.write_text(_script(marker, "planted"))
    os.chmod(path, mode)
    side = path.with_name(path.name + buildcache.SIDECAR_SUFFIX)
    side.unlink(missing_ok=True)
    if sidecar:
        side.write_text(hashlib.sha256(path.read_bytes()).hexdigest() + "\n")
        os.chmod(side, 0o600)


def _run_and_read(program: Path, marker: Path) -> str:
    subprocess.run([str(program)], check=True, timeout=30)
    return marker.read_text()


@pytest.fixture
def cache(tmp_path, monkeypatch) -> Path:
    d = tmp_path / "cache"
    monkeypatch.setenv(CACHE_ENV, str(d))
    return d


def test_cache_is_created_private_and_program_recorded(cache, tmp_path):
    """A new cache directory is 0700 and ours; the built program is 0700 with its sha256 in the sidecar."""
    marker = tmp_path / "m"
    prog = cached_program("kf_test", "k1", _builder(marker))
    assert prog.parent == cache.absolute()
    assert oct(cache.stat().st_mode & 0o777) == "0o700" and cache.stat().st_uid == os.geteuid()
    assert oct(prog.stat().st_mode & 0o777) == "0o700"
    side = prog.with_name(prog.name + ".sha256").read_text().strip()
    assert side == hashlib.sha256(prog.read_bytes()).hexdigest()
    assert buildcache.verified(prog)
    assert _run_and_read(prog, marker) == "built\n"


def _link_to_planted(prog: Path, marker: Path) -> None:
    elsewhere = prog.parent.parent / "evil"
    _plant(elsewhere, marker)
    prog.unlink()
    prog.symlink_to(elsewhere)


def _dir_at(prog: Path, marker: Path) -> None:
    prog.unlink()
    prog.mkdir()
    (prog / "x").write_text("x")


TAMPER = {
    "changed bytes, old sidecar": lambda p, m: (p.write_text(_script(m, "planted")), os.chmod(p, 0o700)),
    "changed bytes, no sidecar": lambda p, m: _plant(p, m, sidecar=False),
    "group-writable, matching sidecar": lambda p, m: _plant(p, m, mode=0o770),
    "world-writable, matching sidecar": lambda p, m: _plant(p, m, mode=0o777),
    "other-writable, matching sidecar": lambda p, m: _plant(p, m, mode=0o702),
    "not executable": lambda p, m: _plant(p, m, mode=0o600),
    "a symbolic link": _link_to_planted,
    "a directory": _dir_at,
    "sidecar is a link": lambda p, m: (p.with_name(p.name + ".sha256").unlink(),
                                       p.with_name(p.name + ".sha256").symlink_to(p)),
}


@pytest.mark.parametrize("how", sorted(TAMPER))
def test_tampered_program_is_rebuilt_not_run(cache, tmp_path, how):
    """A cached program that was replaced, linked, made writable or non-executable is rebuilt; the planted one never runs."""
    marker = tmp_path / "m"
    prog = cached_program("kf_test", "k1", _builder(marker))
    good = prog.read_bytes()
    TAMPER[how](prog, marker)
    again = cached_program("kf_test", "k1", _builder(marker))
    assert again == prog and not again.is_symlink() and again.read_bytes() == good
    assert _run_and_read(again, marker) == "built\n"  # 'planted' never written


@pytest.mark.skipif(not AS_ROOT, reason="needs root to give a file to another uid")
def test_program_of_another_owner_is_rebuilt(cache, tmp_path):
    """A program (with a matching sidecar) owned by another uid is rebuilt, not run."""
    marker = tmp_path / "m"
    prog = cached_program("kf_test", "k1", _builder(marker))
    _plant(prog, marker)
    os.chown(prog, OTHER_UID, OTHER_UID)
    again = cached_program("kf_test", "k1", _builder(marker))
    assert again.stat().st_uid == os.geteuid()
    assert _run_and_read(again, marker) == "built\n"


def _as_file(d: Path) -> None:
    d.write_text("not a directory")


def _as_link(d: Path) -> None:
    target = d.parent / "real"
    target.mkdir(mode=0o700)
    d.symlink_to(target)


def _with_mode(mode: int):
    def make(d: Path) -> None:
        d.mkdir()
        os.chmod(d, mode)
    return make


def _other_owner(d: Path) -> None:
    d.mkdir(mode=0o700)
    os.chown(d, OTHER_UID, OTHER_UID)


BAD_DIRS = {"a file": _as_file, "a symbolic link": _as_link, "mode 777": _with_mode(0o777),
            "mode 770": _with_mode(0o770), "mode 703": _with_mode(0o703), "mode 1777": _with_mode(0o1777)}
if AS_ROOT:
    BAD_DIRS["another owner"] = _other_owner


@pytest.mark.parametrize("how", sorted(BAD_DIRS))
def test_explicit_cache_not_private_is_refused(tmp_path, monkeypatch, how):
    """KILOFORGE_CACHE naming a file, a link, a group/other-writable or foreign directory: one-line CacheError, nothing run."""
    d = tmp_path / "cache"
    BAD_DIRS[how](d)
    monkeypatch.setenv(CACHE_ENV, str(d))
    marker = tmp_path / "m"
    with pytest.raises(CacheError) as e:
        cached_program("kf_test", "k1", _builder(marker))
    msg = str(e.value)
    assert "\n" not in msg and CACHE_ENV in msg and str(d) in msg
    assert not marker.exists()


@pytest.mark.parametrize("how", sorted(BAD_DIRS))
def test_default_cache_not_private_is_left_alone(tmp_path, monkeypatch, how):
    """The default location taken by something not private: a fresh private directory serves, the planted program is untouched and not run."""
    monkeypatch.delenv(CACHE_ENV, raising=False)
    monkeypatch.setattr(buildcache.tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(buildcache, "_FRESH", [])
    d = buildcache.default_location()
    BAD_DIRS[how](d)
    marker = tmp_path / "m"
    if d.is_dir() and not d.is_symlink():
        mode = d.stat().st_mode & 0o7777
        os.chmod(d, 0o700)  # to plant; the bad mode is restored at once
        _plant(d / "kf_test-k1", marker)
        os.chmod(d, mode)
    before = sorted(p.name for p in d.iterdir()) if d.is_dir() else None
    prog = cached_program("kf_test", "k1", _builder(marker))
    assert prog.parent != d and buildcache.not_private(prog.parent) is None
    assert _run_and_read(prog, marker) == "built\n"
    if before is not None:
        assert sorted(p.name for p in d.iterdir()) == before


def test_own_readable_cache_is_tightened(tmp_path, monkeypatch):
    """An own cache directory that only others can read (0755, as older versions made it) is tightened to 0700 and used."""
    d = tmp_path / "cache"
    d.mkdir()
    os.chmod(d, 0o755)
    monkeypatch.setenv(CACHE_ENV, str(d))
    prog = cached_program("kf_test", "k1", _builder(tmp_path / "m"))
    assert prog.parent == d and d.stat().st_mode & 0o777 == 0o700


def test_real_runner_planted_is_not_run(cache, tmp_path):
    """The real simavr runner: a planted program under its cache name is replaced by a fresh build before anything runs it."""
    require_avr(simulate=True)
    marker = tmp_path / "m"
    cache.mkdir(mode=0o700)
    planted = cache / f"{avr.RUNNER_NAME}-{avr.runner_key(tools.host_cc())}"
    _plant(planted, marker, mode=0o722)  # matching sidecar, but others may write it: rebuilt
    exe = avr.runner()
    assert exe == planted and buildcache.verified(exe)
    res = subprocess.run([str(exe)], capture_output=True, timeout=30)  # the real runner: usage, no marker
    assert not marker.exists(), res
    assert b"planted" not in exe.read_bytes()


def test_export_cli_default_cache_planted(tmp_path):
    """A plain export (exact AVR budget) with another user's-style 0777 default cache holding a planted runner: exit 0, the plant never runs."""
    require_avr(simulate=True)
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    d = tmpdir / f"kiloforge-{os.geteuid()}"
    d.mkdir()
    marker = tmp_path / "m"
    _plant(d / f"{avr.RUNNER_NAME}-{avr.runner_key(tools.host_cc())}", marker)
    os.chmod(d, 0o777)
    env = {k: v for k, v in os.environ.items() if k != CACHE_ENV}
    env.update(TMPDIR=str(tmpdir), PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-m", "export", "--out", str(tmp_path / "k.c"), "--robots-calib", "2",
                          "--calib-steps", "4", "--quiet"], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr
    assert not marker.exists()
    assert "stack_source simavr" in res.stdout or "simavr" in res.stdout
    assert sorted(p.name for p in d.iterdir()) == [f"{avr.RUNNER_NAME}-{avr.runner_key(tools.host_cc())}",
                                                    f"{avr.RUNNER_NAME}-{avr.runner_key(tools.host_cc())}.sha256"]


@pytest.mark.parametrize("how", ["a file", "mode 777"])
def test_export_cli_explicit_cache_refused(tmp_path, how):
    """A plain export with KILOFORGE_CACHE not private: exit 2, one line naming KILOFORGE_CACHE, no output files."""
    require_avr(simulate=True)
    d = tmp_path / "cache"
    BAD_DIRS[how](d)
    env = dict(os.environ, PYTHONPATH=str(ROOT), **{CACHE_ENV: str(d)})
    res = subprocess.run([sys.executable, "-m", "export", "--out", str(tmp_path / "k.c"), "--robots-calib", "2",
                          "--calib-steps", "4", "--quiet"], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 2, res.stderr
    assert CACHE_ENV in assert_one_clean_line(res.stderr)
    assert not (tmp_path / "k.c").exists()


def test_default_cache_in_an_unwritable_temp_dir_is_one_line(tmp_path, monkeypatch):
    """A temp directory where nothing can be created (default location and the fresh fallback both fail): one-line CacheError."""
    monkeypatch.delenv(CACHE_ENV, raising=False)
    monkeypatch.setattr(buildcache.tempfile, "tempdir", str(tmp_path / "missing" / "tmp"))
    monkeypatch.setattr(buildcache, "_FRESH", [])
    with pytest.raises(CacheError, match=CACHE_ENV) as e:
        cached_program("kf_test", "k1", _builder(tmp_path / "m"))
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("mode,ok", [(0o777, False), (0o775, False), (0o1777, True), (0o755, True)])
def test_default_cache_needs_a_sticky_or_private_temp_dir(tmp_path, monkeypatch, mode, ok):
    """A temp directory others may write without the sticky bit is refused (they could swap the cache); sticky or private is used."""
    shared = tmp_path / "shared"
    shared.mkdir()
    os.chmod(shared, mode)
    monkeypatch.delenv(CACHE_ENV, raising=False)
    monkeypatch.setattr(buildcache.tempfile, "tempdir", str(shared))
    monkeypatch.setattr(buildcache, "_FRESH", [])
    if ok:
        assert cached_program("kf_test", "k1", _builder(tmp_path / "m")).parent == shared / f"kiloforge-{os.geteuid()}"
    else:
        with pytest.raises(CacheError, match="not sticky"):
            cached_program("kf_test", "k1", _builder(tmp_path / "m"))


def _tiny_firmware() -> str:
    from export.codegen.render import POLICY_FILE, render_firmware
    from kiloforge.actors.searcher import quantize_searcher, searcher_policy
    from sim.config import preset
    return render_firmware(quantize_searcher(searcher_policy(preset("kilobot"))), generator_version="t")[POLICY_FILE]


def test_host_build_in_a_shared_directory_is_refused(tmp_path):
    """build_host into a directory others may write (0777) refuses in one line instead of reusing what is there."""
    from export.verify.hostbuild import build_host, compiler
    if compiler() is None:
        pytest.skip("no host C compiler")
    shared = tmp_path / "shared"
    shared.mkdir()
    os.chmod(shared, 0o777)
    with pytest.raises(CacheError, match="build directory"):
        build_host(_tiny_firmware(), shared)


def test_host_build_planted_is_rebuilt(tmp_path):
    """A host build replaced in its (private) build directory is rebuilt before build_host returns it."""
    from export.verify.hostbuild import build_host, compiler
    if compiler() is None:
        pytest.skip("no host C compiler")
    src = _tiny_firmware()
    exe = build_host(src, tmp_path / "b")
    good = exe.read_bytes()
    marker = tmp_path / "m"
    exe.write_text(_script(marker, "planted"))  # new bytes under the old sidecar
    again = build_host(src, tmp_path / "b")
    assert again == exe and again.read_bytes() == good and not marker.exists()
