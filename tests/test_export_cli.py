"""The exporter command line: python -m export [budget] (export.cli, kiloforge.io)."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from export.cli.main import main
from tests.fixtures import init_policy
from kiloforge.errors import OutputError
from kiloforge.io import write_files_atomic
from kiloforge.policies import save_policy
from sim.config import preset

KB = preset("kilobot")
ROOT = Path(__file__).resolve().parents[1]
FAST = ["--robots-calib", "2", "3", "--calib-steps", "5", "--quiet"]


def run(argv, capsys) -> tuple[int, str, str]:
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def one_error_line(err: str) -> str:
    lines = [l for l in err.splitlines() if l.strip()]
    assert len(lines) == 1 and lines[0].startswith("python -m export") and ": error: " in lines[0], \
        f"expected one error line, got {err!r}"
    assert "Traceback" not in err
    return lines[0]


def test_budget_subcommand_fits(capsys):
    """budget --history 10 --hidden 32 32 fits: exit 0 and the table says FITS."""
    rc, out, err = run(["budget", "--history", "10", "--hidden", "32", "32"], capsys)
    assert rc == 0 and "FITS" in out and "weights int8" in out and err == ""


def test_budget_subcommand_does_not_fit(capsys):
    """budget --history 20 --hidden 64 32 does not fit: exit 1 and what would fit."""
    rc, out, _ = run(["budget", "--history", "20", "--hidden", "64", "32", "--world", "kilobot"], capsys)
    assert rc == 1 and "DOES NOT FIT" in out and "would fit: t_prev <= " in out


def test_budget_subcommand_gru(capsys):
    """budget --gru 32 fits (exit 0, gate tables listed); --gru 200 does not and names the largest GRU that fits."""
    rc, out, err = run(["budget", "--gru", "32"], capsys)
    assert rc == 0 and "FITS" in out and "GRU actor" in out and "gate tables" in out and err == ""
    rc, out, _ = run(["budget", "--gru", "200"], capsys)
    assert rc == 1 and "DOES NOT FIT" in out and "would fit: a GRU of <= " in out
    rc, _, err = run(["budget", "--gru", "8", "--history", "3"], capsys)
    assert rc == 2 and "--gru" in one_error_line(err)
    rc, _, err = run(["budget"], capsys)
    assert rc == 2 and "--history" in one_error_line(err)


def test_budget_subcommand_bad_args(capsys):
    """A non-numeric history or unknown preset is one error line and exit 2."""
    rc, _, err = run(["budget", "--history", "x"], capsys)
    assert rc == 2 and "--history" in one_error_line(err)
    rc, _, err = run(["budget", "--history", "3", "--world", "mars"], capsys)
    assert rc == 2 and "mars" in one_error_line(err)


def test_over_budget_policy_refused(tmp_path, capsys):
    """A policy too big for the Kilobot: exit 1, says what would fit, writes nothing."""
    p = init_policy(KB, 30, (96, 64), "elu", seed=1)
    path = save_policy(p, tmp_path / "big.npz")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    rc, out, err = run(["--policy", str(path), "--out", str(out_dir / "k.c")] + FAST, capsys)
    line = one_error_line(err)
    assert rc == 1 and "does not fit" in line and "would fit: t_prev <= " in line
    assert "DOES NOT FIT" in out
    assert list(out_dir.iterdir()) == []


@pytest.mark.parametrize("content", [b"", b"not a zip at all", b"PK\x03\x04truncated"])
def test_bad_policy_file(tmp_path, capsys, content):
    """An empty, non-zip or truncated policy: exit 2, one line naming the file, nothing written."""
    bad = tmp_path / "bad.npz"
    bad.write_bytes(content)
    out = tmp_path / "k.c"
    rc, _, err = run(["--policy", str(bad), "--out", str(out)] + FAST, capsys)
    assert rc == 2 and str(bad) in one_error_line(err)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["bad.npz"]


def test_nan_policy(tmp_path, capsys):
    """A policy with a NaN weight: exit 2 and one line."""
    p = init_policy(KB, 3, (8,), "elu", seed=1)
    path = save_policy(p, tmp_path / "p.npz")
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["w0"][0, 0] = np.nan
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    rc, _, err = run(["--policy", str(path), "--out", str(tmp_path / "k.c")] + FAST, capsys)
    assert rc == 2 and "non-finite" in one_error_line(err)


def test_missing_policy(tmp_path, capsys):
    """A policy path that does not exist: exit 2, one line."""
    rc, _, err = run(["--policy", str(tmp_path / "nope.npz"), "--out", str(tmp_path / "k.c")], capsys)
    assert rc == 2 and "does not exist" in one_error_line(err)


def test_missing_onnx(tmp_path, capsys):
    """--onnx with a missing file: exit 2, one line."""
    rc, _, err = run(["--onnx", str(tmp_path / "nope.onnx"), "--out", str(tmp_path / "k.c")], capsys)
    assert rc == 2 and "nope.onnx" in one_error_line(err)


@pytest.mark.parametrize("kind", ["missing_dir", "parent_is_file", "not_c", "is_dir"])
def test_unwritable_out_path(tmp_path, capsys, kind):
    """An output path that cannot be written: non-zero exit, one line, nothing written."""
    (tmp_path / "afile").write_text("x")
    (tmp_path / "adir.c").mkdir()
    out = {"missing_dir": tmp_path / "no" / "k.c", "parent_is_file": tmp_path / "afile" / "k.c",
           "not_c": tmp_path / "k.txt", "is_dir": tmp_path / "adir.c"}[kind]
    before = sorted(p.name for p in tmp_path.rglob("*"))
    rc, _, err = run(["--out", str(out)] + FAST, capsys)
    assert rc != 0
    one_error_line(err)
    assert sorted(p.name for p in tmp_path.rglob("*")) == before


def test_all_or_nothing_write(tmp_path, monkeypatch):
    """A failure while the set is staged leaves the old set; a rename failing after the commit leaves
    no record (an incomplete set, said so) and no temporaries."""
    a, b = tmp_path / "a.c", tmp_path / "b.json"
    write_files_atomic({a: "old a", b: "old b"})
    real_open = open

    def failing_open(path, *args, **kw):
        if Path(path).name == "b.json" and Path(path).parent != tmp_path:
            raise OSError(28, "No space left on device")
        return real_open(path, *args, **kw)
    monkeypatch.setattr("builtins.open", failing_open)
    with pytest.raises(OutputError, match="No space left"):
        write_files_atomic({a: "new a", b: "new b"})
    monkeypatch.setattr("builtins.open", real_open)
    assert a.read_text() == "old a" and b.read_text() == "old b"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.c", "b.json"]

    real = os.replace

    def flaky(src, dst):
        if Path(dst) == a:
            raise OSError(5, "I/O error")
        return real(src, dst)
    monkeypatch.setattr(os, "replace", flaky)
    with pytest.raises(OutputError, match="I/O error.*incomplete"):
        write_files_atomic({a: "new a", b: "new b"})
    monkeypatch.setattr(os, "replace", real)
    assert not b.exists() and a.read_text() == "old a"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.c"]


def test_bad_arguments(capsys):
    """An unknown option is one error line and exit 2, not an argparse exit."""
    rc, _, err = run(["--frobnicate"], capsys)
    assert rc == 2 and "frobnicate" in one_error_line(err)


def test_default_export_writes_c_target_and_manifest(tmp_path, capsys):
    """The shipped default policy exports: C, kilobot_target.c and a manifest with hash and format."""
    out = tmp_path / "kilobot_policy.c"
    loud = [a for a in FAST if a != "--quiet"]  # no bar off a terminal either way; --quiet also drops the hint
    rc, stdout, err = run(["--out", str(out), "--target-uids", "0,5"] + loud, capsys)
    assert rc == 0, err
    target = tmp_path / "kilobot_target.c"
    manifest = tmp_path / "kilobot_policy.c.manifest.json"
    assert out.exists() and target.exists() and manifest.exists()
    m = json.loads(manifest.read_text())
    from kiloforge import numfmt
    assert m["number_format"] == numfmt.FORMAT_NAME and m["rounding"] == numfmt.ROUNDING
    assert len(m["policy_hash"]) == 64 and m["policy_hash"][:16] in stdout
    assert m["budget"]["fits"] is True and m["options"]["emitter_uids"] == [0, 5]
    import hashlib
    assert m["files"]["kilobot_policy.c"]["sha256"] == hashlib.sha256(out.read_bytes()).hexdigest()
    assert "end to end" in stdout and "FITS" in stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, target.name, manifest.name])
    last = stdout.splitlines()[-2:]  # the next step: the same command with --kilolib, and the flashing guide
    assert last[0] == ("next: .hex images for KiloGUI: python -m export --out " + str(out) + " --target-uids 0,5 "
                       + " ".join(loud) + " --kilolib DIR (DIR: your built kilolib checkout)")
    assert "kilo_uid 0, 5 is the beacon" in last[1] and last[1].endswith("docs/flashing.md")


@pytest.mark.parametrize("layout", ["missing", "empty", "unbuilt"])
def test_bad_kilolib_refused_before_any_work(layout, tmp_path, capsys):
    """A --kilolib that is no built kilolib checkout is one line (exit 2) before the policy is even loaded."""
    kilolib = tmp_path / "kilolib"
    if layout != "missing":
        kilolib.mkdir()
    if layout == "unbuilt":
        (kilolib / "Makefile").write_text("all:\n")
        (kilolib / "kilolib.h").write_text("")
    out = tmp_path / "o" / "kp.c"
    out.parent.mkdir()
    rc, stdout, err = run(["--out", str(out), "--kilolib", str(kilolib), *FAST], capsys)
    assert rc == 2 and stdout == ""  # nothing printed: neither the policy line nor the calibration
    assert "--kilolib" in one_error_line(err) or "AVR toolchain" in err
    assert list(out.parent.iterdir()) == []


def test_next_steps_name_the_images_and_the_command():
    """After an export with --kilolib the hint names the .hex to flash; without, the kiloforge command to rerun; the
    beacon robot is named as the task calls it."""
    from export.cli.firmware import next_steps
    from kiloforge.cliparse import invoked_as

    lines = next_steps(["--out", "a b/kp.c", "--kilolib", "kl"], Path("a b/kp.c"), Path("a b/kilobot_target.c"), (0,),
                       Path("kl"))
    assert len(lines) == 2 and lines[0].startswith("next: flash a b/kp.hex onto every robot with KiloGUI")
    assert "a b/kilobot_target.hex" in lines[0] and "kilo_uid 0 " in lines[0] and "docs/flashing.md" in lines[1]
    with invoked_as("python -m export", "kiloforge export"):
        lines = next_steps(["--out", "a b/kp.c"], Path("a b/kp.c"), Path("a b/kilobot_target.c"), (3,), None)
    assert lines[0].startswith("next: .hex images for KiloGUI: kiloforge export --out 'a b/kp.c' --kilolib DIR ")
    lines = next_steps(["--out", "t.c"], Path("t.c"), Path("kilobot_target.c"), (0,), None, "the object's robot")
    assert "(the robot with kilo_uid 0 is the object's robot)" in lines[1]


def test_python_dash_m_entry_point(tmp_path):
    """`python -m export budget` runs as a program with the documented exit status."""
    r = subprocess.run([sys.executable, "-m", "export", "budget", "--history", "4", "--hidden", "8"],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "FITS" in r.stdout
    r = subprocess.run([sys.executable, "-m", "export", "--policy", str(tmp_path / "x.npz"),
                        "--out", str(tmp_path / "k.c")], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr


def test_export_pipeline_with_stub_renderer(tmp_path, capsys, monkeypatch):
    """With a stand-in renderer: calibrate, quantise, write C + target + manifest; --verify failing writes nothing."""
    import types
    seen = {}

    def render_firmware(qp, emitter_uids=(0,), generator_version=None, task=None):
        seen["qp"], seen["uids"], seen["ver"] = qp, emitter_uids, generator_version
        return {"kilobot_policy.c": f"/* policy {qp.policy_hash} */\n", "kilobot_target.c": "/* target */\n"}
    monkeypatch.setattr("export.cli.firmware.render_firmware", render_firmware)
    out = tmp_path / "robot.c"
    rc, stdout, err = run(["--out", str(out), "--target-uids", "7", "--no-avr"] + FAST, capsys)
    assert rc == 0, err
    assert "next:" not in stdout  # --quiet: no next-step hint
    qp = seen["qp"]
    assert seen["uids"] == (7,) and qp.world.name == "kilobot" and out.read_text().startswith(f"/* policy {qp.policy_hash}")
    m = json.loads((tmp_path / "robot.c.manifest.json").read_text())
    assert m["quantization"]["e_in"] == qp.e_in and m["calibration"]["n_samples"] == 5 * (2 + 3)
    assert m["layer_sizes"] == qp.layer_sizes and m["generator_version"] == seen["ver"]
    assert (tmp_path / "kilobot_target.c").read_text() == "/* target */\n"

    def verify_host(qp, files, task=None):
        return types.SimpleNamespace(ok=False, __str__=lambda self: "mismatch")
    monkeypatch.setattr("export.cli.firmware.verify_host", verify_host)
    out2 = tmp_path / "sub"
    out2.mkdir()
    rc, _, err = run(["--out", str(out2 / "k.c"), "--verify", "host", "--no-avr"] + FAST, capsys)
    assert rc == 1 and "host verification failed" in one_error_line(err)
    assert list(out2.iterdir()) == []


@pytest.mark.skipif(importlib.util.find_spec("onnx") is None, reason="needs onnx (kiloforge[onnx])")
def test_onnx_input_with_stub_renderer(tmp_path, capsys, monkeypatch):
    """--onnx reads an ONNX actor (via export.interop.onnx_import) and quantises the same weights."""
    from learn.onnx_export import export_onnx
    p = init_policy(KB, 3, (8,), "elu", seed=4, out_scale=0.3)
    export_onnx(p, tmp_path / "actor.onnx")
    seen = {}

    def render_firmware(qp, emitter_uids=(0,), generator_version=None, task=None):
        seen["qp"] = qp
        return {"kilobot_policy.c": "a", "kilobot_target.c": "b"}
    monkeypatch.setattr("export.cli.firmware.render_firmware", render_firmware)
    rc, _, err = run(["--onnx", str(tmp_path / "actor.onnx"), "--out", str(tmp_path / "k.c"), "--no-avr"] + FAST, capsys)
    assert rc == 0, err
    assert seen["qp"].layer_sizes == p.layer_sizes and seen["qp"].t_prev == 3


def test_thesis_world_policy_warns_before_any_output(tmp_path, capsys):
    """Exporting a policy of a world other than the Kilobot's warns on stderr, naming the world and the fix."""
    path = tmp_path / "thesis.npz"
    save_policy(init_policy(preset("thesis"), 2, (8,)), path)
    rc, _, err = run(["--policy", str(path), "--out", str(tmp_path / "kp.c")] + FAST, capsys)
    assert rc == 0, err
    assert "warning: this policy was trained in the 'thesis' world" in err and "--world kilobot" in err
    rc, _, err = run(["--out", str(tmp_path / "kd.c")] + FAST, capsys)
    assert rc == 0 and "warning" not in err
