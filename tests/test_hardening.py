"""Regression tests of issue 17's "what we saw" list: strict inputs, mandatory hashes, resource limits,
interrupted exports, escaped text (the ONNX Cast case is in test_onnx_ops.py, training in test_kill.py)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.bad_inputs import (assert_one_clean_line, crafted, huge_shape_member, many_members, nested_json, parts,
                        raw_meta_file, small_policy, zip_bomb)
from export.cli.main import main as export_main
from export.codegen.manifest import verify_manifest
from kiloforge import io as kio
from kiloforge.errors import InputError, PolicyError
from kiloforge.policies import load_policy, save_policy
from tests.signal_delivery import deliver
from sim.__main__ import main as sim_main
from sim.config import WorldConfig, preset

ROOT = Path(__file__).resolve().parents[1]
FAST = ["--robots-calib", "2", "--calib-steps", "4", "--quiet", "--no-avr"]
EXPORT_FILES = ("kilobot_policy.c", "kilobot_target.c", "kilobot_policy.c.manifest.json")


def export(argv, capsys) -> tuple[int, str, str]:
    rc = export_main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def export_error(argv, capsys, rc_expected: int = 2) -> str:
    rc, _, err = export(argv, capsys)
    assert rc == rc_expected, err
    return assert_one_clean_line(err)


def leftovers(d: Path) -> list[str]:
    """Hidden entries (temporaries, staging directories, backups) in d."""
    return sorted(p.name for p in d.iterdir() if p.name.startswith("."))


# --- 1. a policy without its hash ------------------------------------------------------------
@pytest.mark.parametrize("how", ["removed", "null"])
def test_policy_without_hash_is_refused_and_rehash_fixes_it(tmp_path, capsys, how):
    """A policy whose policy_hash is removed or null is refused (naming 'rehash'); `export rehash` re-hashes it."""
    arrays, meta = parts(small_policy())
    if how == "null":
        meta = dict(meta, policy_hash=None)
    path = tmp_path / "p.npz"
    path.write_bytes(crafted(arrays, meta, hashed=False))
    with pytest.raises(PolicyError, match="no policy_hash.*python -m export rehash"):
        load_policy(path)
    line = export_error(["--policy", str(path), "--out", str(tmp_path / "k.c")] + FAST, capsys)
    assert "rehash" in line and not (tmp_path / "k.c").exists()
    rc, out, err = export(["rehash", str(path), "--out", str(tmp_path / "fixed.npz")], capsys)
    assert rc == 0 and "had none" in out, err
    assert load_policy(tmp_path / "fixed.npz").hash == small_policy().hash
    rc, out, _ = export(["rehash", str(path)], capsys)  # in place, atomically
    assert rc == 0 and load_policy(path).hash == small_policy().hash and leftovers(tmp_path) == []


@pytest.mark.parametrize("value", [42, "", "abc", "0" * 63, "G" * 64, ["0" * 64]])
def test_malformed_hash_is_refused(tmp_path, value):
    """A policy_hash that is not 64 hex digits is refused (a string, not a number or list)."""
    arrays, meta = parts(small_policy())
    path = tmp_path / "p.npz"
    path.write_bytes(crafted(arrays, dict(meta, policy_hash=value), hashed=False))
    with pytest.raises(PolicyError, match="policy_hash must be 64 hex digits"):
        load_policy(path)


def test_rehash_keeps_every_other_check(tmp_path, capsys):
    """rehash refuses a file that is invalid for other reasons (a NaN weight), exit 2, nothing written."""
    arrays, meta = parts(small_policy())
    arrays["w0"][0, 0] = np.nan
    path = tmp_path / "p.npz"
    path.write_bytes(crafted(arrays, meta, hashed=False))
    line = export_error(["rehash", str(path), "--out", str(tmp_path / "o.npz")], capsys)
    assert "non-finite" in line and not (tmp_path / "o.npz").exists()


def test_unknown_meta_field_is_refused(tmp_path):
    """A meta field the kind does not write is refused by name, even with a matching hash."""
    arrays, meta = parts(small_policy())
    path = tmp_path / "p.npz"
    path.write_bytes(crafted(arrays, dict(meta, surprise=1)))
    with pytest.raises(PolicyError, match="'surprise'"):
        load_policy(path)


# --- 2. tracebacks: --seed -1, deep JSON, loose types ------------------------------------------
@pytest.mark.parametrize("args", [["--seed", "-1"], ["--seed", "1.5"], ["--seed", "99999999999999999999999"],
                                  ["--percentile", "nan"], ["--percentile", "inf"], ["--calib-steps", "0"],
                                  ["--robots-calib", "100000"], ["--calib-episodes", "-3"]])
def test_bad_export_numbers_are_one_line(tmp_path, capsys, args):
    """`python -m export --out p.c --seed -1` and other out-of-range numbers: exit 2, one line, nothing written."""
    line = export_error(["--out", str(tmp_path / "p.c")] + args, capsys)
    assert args[0] in line and list(tmp_path.iterdir()) == []


def test_seed_minus_one_as_a_program(tmp_path):
    """The reported command itself, as a program: exit 2 and one line on stderr (it was a traceback)."""
    r = subprocess.run([sys.executable, "-m", "export", "--out", "p.c", "--seed", "-1"], cwd=tmp_path,
                       env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--seed" in assert_one_clean_line(r.stderr)


def test_world_json_nested_100000_levels(tmp_path, capsys):
    """A world JSON nested 100,000 levels deep is one line ('nested'), not a RecursionError traceback."""
    from tests.onnx_models import tiny_model

    model = tiny_model(tmp_path / "m.onnx", metadata=False)
    deep = tmp_path / "w.json"
    deep.write_text('{"t_prev": 1, "world": ' + nested_json(100_000) + "}")
    line = export_error(["--onnx", str(model), "--world-json", str(deep), "--out", str(tmp_path / "k.c")] + FAST,
                        capsys)
    assert "nested 100001 levels" in line and "w.json" in line


def test_policy_meta_nested_deep(tmp_path):
    """A policy whose meta JSON is nested 100,000 levels deep is refused before parsing."""
    arrays, _ = parts(small_policy())
    path = tmp_path / "p.npz"
    path.write_bytes(raw_meta_file(arrays, ('{"a": ' + nested_json(100_000) + "}").encode()))
    with pytest.raises(PolicyError, match="nested 100001 levels deep"):
        load_policy(path)


LOOSE = [("n_rbf", 11.0, "11.0"), ("emitter_uid", 1.0, "1.0"), ("collisions", "true", '"true"'),
         ("tick_level", 1, "1"), ("arena_half_mm", float("inf"), "Infinity"), ("msg_loss", float("nan"), "NaN"),
         ("episode_steps", True, "true"), ("name", 7, "7")]


@pytest.mark.parametrize("field, value, literal", LOOSE)
def test_loose_world_types_refused_on_every_path(tmp_path, field, value, literal):
    """Float n_rbf, float emitter_uid, string booleans, Infinity, NaN...: refused by WorldConfig, from_dict,
    preset overrides, a policy's meta (with a valid hash), an ONNX model's metadata and a --world-json file."""
    from export.interop.onnx_import import load_onnx_policy
    from tests.onnx_models import tiny_model

    with pytest.raises(InputError, match=field):
        WorldConfig(**{field: value})
    with pytest.raises(InputError, match=field):
        WorldConfig.from_dict({field: value})
    if field != "name":
        with pytest.raises(InputError, match=field):
            preset("thesis", **{field: value})
    arrays, meta = parts(small_policy(world=preset("thesis")))
    text = json.dumps(dict(meta["world"], **{field: "@@"})).replace('"@@"', literal)
    meta_text = json.dumps(dict(meta, world="@W@", policy_hash="0" * 64)).replace('"@W@"', text)  # checked later
    path = tmp_path / "p.npz"
    path.write_bytes(raw_meta_file(arrays, meta_text.encode()))
    with pytest.raises(PolicyError, match=field if literal not in ("Infinity", "NaN") else literal):
        load_policy(path)
    world_text = json.dumps({field: "@@"}).replace('"@@"', literal)
    model = tiny_model(tmp_path / "m.onnx", metadata=False, world_meta=world_text)
    with pytest.raises(PolicyError, match=field if literal not in ("Infinity", "NaN") else literal):
        load_onnx_policy(model)
    wj = tmp_path / "w.json"
    wj.write_text('{"t_prev": 1, "world": ' + world_text + "}")
    with pytest.raises(PolicyError, match=field if literal not in ("Infinity", "NaN") else literal):
        load_onnx_policy(tiny_model(tmp_path / "n.onnx", metadata=False), wj)


def test_world_preset_name_must_be_a_string(tmp_path):
    """{"world": {"preset": 7}} is refused (it was str()-ed into an unknown preset name)."""
    from export.interop.onnx_import import load_onnx_policy
    from tests.onnx_models import tiny_model

    with pytest.raises(PolicyError, match="'preset' must be a preset name"):
        load_onnx_policy(tiny_model(tmp_path / "m.onnx", metadata=False), {"world": {"preset": 7}, "t_prev": 1})


# --- 3. resource limits ------------------------------------------------------------------------
@pytest.mark.parametrize("flag", ["--policy", "--onnx"])
def test_dev_zero_is_refused_without_reading(tmp_path, capsys, flag):
    """--policy /dev/zero (it read until memory ran out) and --onnx /dev/zero: refused as a device."""
    line = export_error([flag, "/dev/zero", "--out", str(tmp_path / "k.c")] + FAST, capsys)
    assert "/dev/zero" in line and "device" in line


def test_fifo_and_directory_are_refused(tmp_path, capsys):
    """A FIFO is refused without opening it (it would block); a run directory suggests its policy_best.npz."""
    fifo = tmp_path / "p.npz"
    os.mkfifo(fifo)
    assert "FIFO" in export_error(["--policy", str(fifo), "--out", str(tmp_path / "k.c")] + FAST, capsys)
    run = tmp_path / "run"
    run.mkdir()
    save_policy(small_policy(), run / "policy_best.npz")
    line = export_error(["--policy", str(run), "--out", str(tmp_path / "k.c")] + FAST, capsys)
    assert "is a directory" in line and "policy_best.npz" in line


def test_world_json_that_is_a_device(tmp_path, capsys):
    """--world-json /dev/zero is refused as a device, not read."""
    from tests.onnx_models import tiny_model

    model = tiny_model(tmp_path / "m.onnx", metadata=False)
    line = export_error(["--onnx", str(model), "--world-json", "/dev/zero", "--out", str(tmp_path / "k.c")] + FAST,
                        capsys)
    assert "device" in line


def test_zip_bomb_is_refused_before_decompression(tmp_path):
    """A member that inflates to 100 MiB (declared honestly, 100 KB on disk) is refused from the zip directory."""
    path = tmp_path / "bomb.npz"
    path.write_bytes(zip_bomb(100))
    assert path.stat().st_size < 1 << 20
    with pytest.raises(PolicyError, match="decompress to more than"):
        load_policy(path)


@pytest.mark.parametrize("declared", [1000, 2**32 - 1])
def test_zip_member_lying_about_its_size(tmp_path, declared):
    """A member whose headers claim another size than its 100 MiB stream: refused (declared size, or CRC after
    at most the declared bytes), never inflated whole."""
    path = tmp_path / "liar.npz"
    path.write_bytes(zip_bomb(100, declared=declared))
    with pytest.raises(PolicyError, match="corrupt|decompress to more than|truncated"):
        load_policy(path)


def test_zip_bomb_in_a_subprocess_with_little_memory(tmp_path):
    """Loading the bombs under a 1 GiB address-space limit ends in a one-line refusal, not a MemoryError."""
    (tmp_path / "a.npz").write_bytes(zip_bomb(100))
    (tmp_path / "b.npz").write_bytes(zip_bomb(100, declared=1000))
    code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30));"
            "from export.cli.main import main; sys.exit(main(['--policy', sys.argv[1], '--out', sys.argv[2]]))")
    for name in ("a.npz", "b.npz"):
        r = subprocess.run([sys.executable, "-c", code, str(tmp_path / name), str(tmp_path / "k.c")],
                           env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and name in assert_one_clean_line(r.stderr)


def test_archive_limits(tmp_path):
    """5,000 members, and a 1-KB member whose header claims 10**12 floats, are refused before allocation."""
    (tmp_path / "many.npz").write_bytes(many_members(5000))
    with pytest.raises(PolicyError, match="5,000 members"):
        load_policy(tmp_path / "many.npz")
    (tmp_path / "shape.npz").write_bytes(huge_shape_member())
    with pytest.raises(PolicyError, match="header says"):
        load_policy(tmp_path / "shape.npz")


# --- 5. interrupted exports ----------------------------------------------------------------------
def _two_exports(tmp_path, capsys):
    """Export once (the old set), return the argv of a second export that writes different files."""
    out = tmp_path / "kilobot_policy.c"
    rc, _, err = export(["--out", str(out), "--seed", "1"] + FAST, capsys)
    assert rc == 0, err
    old = {n: (tmp_path / n).read_bytes() for n in EXPORT_FILES}
    return old, ["--out", str(out), "--seed", "2", "--calib-steps", "6", "--target-uids", "0,7"] + FAST[2:]


def test_sigint_inside_the_final_renames_finishes_the_set(tmp_path, capsys, monkeypatch):
    """SIGINT between the renames: the new set is completed (manifest matching), exit 130, the message says so,
    no .bak or temporaries (it left a .bak and a mismatching manifest while printing 'nothing written')."""
    old, argv = _two_exports(tmp_path, capsys)
    real = os.replace
    calls = []

    def replace_then_sigint(src, dst):
        real(src, dst)
        if Path(dst).parent == tmp_path:
            calls.append(Path(dst).name)
            if len(calls) == 1:
                deliver(signal.SIGINT)
    monkeypatch.setattr(os, "replace", replace_then_sigint)
    rc, _, err = export(argv, capsys)
    monkeypatch.setattr(os, "replace", real)
    assert rc == 130 and calls == list(EXPORT_FILES)
    line = assert_one_clean_line(err)
    assert "interrupted after writing" in line and "nothing written" not in line
    assert verify_manifest(tmp_path / EXPORT_FILES[2]) == []
    assert (tmp_path / EXPORT_FILES[0]).read_bytes() != old[EXPORT_FILES[0]]
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("signum, rc_expected", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_before_the_commit_keeps_the_old_set(tmp_path, capsys, monkeypatch, signum, rc_expected):
    """SIGINT / SIGTERM while the new files are staged: the old set is unchanged, exit 130 / 143, 'nothing written'."""
    old, argv = _two_exports(tmp_path, capsys)
    import kiloforge.io

    real = kiloforge.io._sha256_file

    def hash_then_signal(path):
        deliver(signum)
        return real(path)
    monkeypatch.setattr(kiloforge.io, "_sha256_file", hash_then_signal)
    rc, _, err = export(argv, capsys)
    assert rc == rc_expected and "nothing written" in assert_one_clean_line(err)
    assert {n: (tmp_path / n).read_bytes() for n in EXPORT_FILES} == old
    assert verify_manifest(tmp_path / EXPORT_FILES[2]) == [] and leftovers(tmp_path) == []


def _dead_writer(tmp_path: Path, die_after_renames: int) -> None:
    """A process that publishes a new export set and is SIGKILLed after that many renames."""
    code = f"""
import os, signal, sys
from pathlib import Path
import kiloforge.io as kio
real, n = os.replace, [0]
def replace(src, dst):
    real(src, dst)
    if Path(dst).parent == Path(sys.argv[1]):
        n[0] += 1
        if n[0] == {die_after_renames}:
            os.kill(os.getpid(), signal.SIGKILL)
os.replace = replace
d = Path(sys.argv[1])
kio.write_files_atomic({{d / "kilobot_policy.c": "new c", d / "kilobot_target.c": "new t",
                        d / "kilobot_policy.c.manifest.json": "new m"}})
"""
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path)], env=dict(os.environ, PYTHONPATH=str(ROOT)),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == -signal.SIGKILL, r.stderr


@pytest.mark.parametrize("renames", [1, 2])
def test_sigkill_mid_publish_is_completed_by_the_next_writer(tmp_path, renames):
    """A writer killed between its renames leaves no manifest (the set is visibly incomplete); the next publish
    of the same set, or recover(), completes it from the journal: the new complete set, no temporaries."""
    kio.write_files_atomic({tmp_path / n: f"old {n}" for n in EXPORT_FILES})
    _dead_writer(tmp_path, renames)
    assert not (tmp_path / EXPORT_FILES[2]).exists() and leftovers(tmp_path) != []
    kio.recover(tmp_path)
    got = [(tmp_path / n).read_text() for n in EXPORT_FILES]
    assert got == ["new c", "new t", "new m"] and leftovers(tmp_path) == []


def test_uncommitted_staging_of_a_dead_writer_is_removed(tmp_path):
    """A staging directory without a journal (killed while writing) is removed; the old set stays."""
    kio.write_files_atomic({tmp_path / n: f"old {n}" for n in EXPORT_FILES})
    stage = tmp_path / ".kilobot_policy.c.manifest.json.kf999999-0123abcd.stage"  # pid 999999: not running
    stage.mkdir()
    (stage / "kilobot_policy.c").write_text("half")
    tmp = tmp_path / ".kilobot_target.c.kf999999-0123abcd.tmp"
    tmp.write_text("half")
    kio.write_files_atomic({tmp_path / n: f"newer {n}" for n in EXPORT_FILES})
    assert leftovers(tmp_path) == [] and (tmp_path / EXPORT_FILES[0]).read_text() == f"newer {EXPORT_FILES[0]}"


def test_live_writers_temporaries_are_kept(tmp_path):
    """recover() leaves the staging directory of a running process (this one) alone."""
    with kio.staged_files(tmp_path, ["a", "b"]) as stage:
        (stage / "a").write_text("a")
        (stage / "b").write_text("b")
        assert kio.recover(tmp_path) == [] and stage.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]


# --- 7. control characters from files ----------------------------------------------------------
ESC = "\x1b]0;owned\x07\x1b[2J\u202e"


def test_control_characters_in_metadata_are_escaped(tmp_path, capsys):
    """Provenance notes, a kind name and a file name with terminal escapes are printed escaped, never raw."""
    path = save_policy(small_policy(notes=f"trained {ESC} here"), tmp_path / "p.npz")
    rc, out, err = export(["--policy", str(path), "--out", str(tmp_path / "k.c")] + FAST, capsys)
    assert rc == 0, err
    assert "\x1b" not in out and "\\x1b]0;owned\\x07" in out and "\u202e" not in out
    arrays, meta = parts(small_policy())
    bad = tmp_path / "k.npz"
    bad.write_bytes(crafted(arrays, dict(meta, kind=f"mlp{ESC}")))
    line = export_error(["--policy", str(bad), "--out", str(tmp_path / "k2.c")] + FAST, capsys)
    assert "unknown kind" in line and "\\x1b" in line
    weird = tmp_path / f"a{ESC}.npz"
    line = export_error(["--policy", str(weird), "--out", str(tmp_path / "k2.c")] + FAST, capsys)
    assert "does not exist" in line


def test_control_characters_in_world_name_are_refused_and_escaped(tmp_path, capsys):
    """A world name with control characters is refused; the message shows it escaped (sim CLI too)."""
    arrays, meta = parts(small_policy())
    path = tmp_path / "p.npz"
    path.write_bytes(crafted(arrays, dict(meta, world=dict(meta["world"], name=f"kb{ESC}"))))
    with pytest.raises(PolicyError, match="control characters"):
        load_policy(path)
    assert sim_main(["--policy", str(path), "--out", str(tmp_path / "o"), "--episodes", "1", "--steps", "3"]) == 2
    assert "control characters" in assert_one_clean_line(capsys.readouterr().err)
    assert not (tmp_path / "o").exists()


# --- found by the fuzzer --------------------------------------------------------------------------
def test_calibration_longer_than_the_worlds_episode(tmp_path, capsys):
    """--calib-steps beyond the world's episode length (301 > 300) calibrates on longer episodes; it was a
    RuntimeError traceback from the simulator."""
    rc, _, err = export(["--out", str(tmp_path / "k.c"), "--robots-calib", "2", "--calib-steps", "301",
                         "--no-avr", "--quiet"], capsys)
    assert rc == 0, err
    assert json.loads((tmp_path / "k.c.manifest.json").read_text())["calibration"]["steps"] == 301


def test_staged_files_with_names_chosen_while_writing(tmp_path):
    """staged_files(record=R) publishes whatever the block wrote, R last; nothing on an error."""
    with kio.staged_files(tmp_path / "ev", record="evaluation.json", create=True) as stage:
        for n in ("coverage_4.png", "returns_4.png", "evaluation.json"):
            (stage / n).write_text(n)
    assert sorted(p.name for p in (tmp_path / "ev").iterdir()) == ["coverage_4.png", "evaluation.json",
                                                                   "returns_4.png"]
    with pytest.raises(RuntimeError):
        with kio.staged_files(tmp_path / "ev2", record="evaluation.json", create=True) as stage:
            (stage / "coverage_4.png").write_text("x")
            raise RuntimeError("evaluation failed")
    assert not (tmp_path / "ev2").exists() and leftovers(tmp_path) == []
    with pytest.raises(kio.OutputError, match="evaluation.json.*not produced"):
        with kio.staged_files(tmp_path / "ev3", record="evaluation.json", create=True) as stage:
            (stage / "a.png").write_text("x")
    assert not (tmp_path / "ev3").exists()


SIGNAL_AT_IMPORT = """
import os, runpy, signal, sys
sig, pkg, module = sys.argv[1:4]
class Hook:
    def find_spec(self, name, path=None, target=None):
        if name == module:
            os.kill(os.getpid(), getattr(signal, sig))
        return None
sys.meta_path.insert(0, Hook())
sys.argv = [pkg, *sys.argv[4:]]
runpy.run_module(pkg, run_name="__main__", alter_sys=True)
"""


@pytest.mark.parametrize("pkg, module, args", [
    ("export", "kiloforge.interrupts", ["--out", "p.c"]),  # before the entry point's own handler exists
    ("learn", "kiloforge.interrupts", ["train", "--out", "run"]),
    ("learn", "learn.train", ["train", "--out", "run"]),  # the trainer's modules loading
    ("learn", "learn.evaluate", ["evaluate", "--policy", "p.npz", "--out", "ev"]),  # a command's own imports
])
def test_sigint_while_a_command_loads_is_one_line(tmp_path, pkg, module, args):
    """A Ctrl-C while python -m export / learn loads its modules ends in one line and exit 130, nothing written."""
    res = subprocess.run([sys.executable, "-c", SIGNAL_AT_IMPORT, "SIGINT", pkg, module, *args], cwd=tmp_path,
                         capture_output=True,
                         text=True, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=300)
    assert res.returncode == 130, res.stderr
    assert "Traceback" not in res.stderr and "interrupted" in assert_one_clean_line(res.stderr)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("pkg, module, args", [
    ("sim", "kiloforge.interrupts", ["--out", "o"]),  # before the entry point's own handler exists
    ("sim", "sim.config", ["--out", "o"]),  # the world definitions (sim/__init__ defers them to first use)
    ("sim", "kiloforge.policies", ["--out", "o"]),  # the policy loader loading
    ("sim", "sim.baselines", ["--policy", "baseline", "--out", "o"]),  # the policy loading
    ("sim", "sim.rollout", ["--policy", "baseline", "--episodes", "1", "--out", "o"]),  # before the first step
    ("learn", "learn.evaluate", ["evaluate", "--policy", "p.npz", "--out", "ev"]),
    ("learn", "torch", ["train", "--out", "run"]),  # a trainer loading torch (evaluate does not need it)
    ("export", "export.cli.main", ["--out", "p.c"]),
])
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_signal_while_sim_evaluate_or_export_starts_is_one_line(tmp_path, pkg, module, args, sig):
    """A SIGINT / SIGTERM while python -m sim, learn evaluate or export loads its modules, world or policy, before the
    first step: exit 130 / 143 with one line and no traceback, nothing written."""
    res = subprocess.run([sys.executable, "-c", SIGNAL_AT_IMPORT, sig, pkg, module, *args], cwd=tmp_path,
                         capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=300)
    assert res.returncode == 128 + getattr(signal, sig), res.stderr
    assert "Traceback" not in res.stderr and "interrupted" in assert_one_clean_line(res.stderr)
    assert list(tmp_path.iterdir()) == []
