"""Issue 47's causes 3-8 and 11, each with generated variants: names that Matplotlib would read as mathtext or
cannot draw, file names that are not UTF-8 or too long, a full disk, a standard output that fails, run folders
that lie, and weights too large for the int8 format. Every one works, or ends in exactly one stderr line with
exit status 2 (141 for a reader that went away) and nothing half-written."""
from __future__ import annotations

import dataclasses
import os
import resource
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.bad_inputs import KILOBOT, assert_one_clean_line, crafted, parts, small_policy
from kiloforge.actors.gru import random_gru_policy
from kiloforge.cli import main as kf_main
from kiloforge.plotting import figure, png_bytes
from kiloforge.policies import save_policy

ROOT = Path(__file__).resolve().parents[1]
SIM = ["--episodes", "1", "--steps", "3", "--quiet"]
EVAL = ["--robots", "2", "--episodes", "1", "--steps", "3", "--quiet", "--no-baselines"]
EXPORT = ["--robots-calib", "2", "--calib-steps", "3", "--quiet", "--no-avr"]
VERIFY = ["--episodes", "1", "--steps", "3", "--robots", "2", "--robots-calib", "2", "--calib-steps", "3", "--quiet"]
#: names built from what Matplotlib parses ($, backslash commands, sub/superscripts) and a non-UTF-8 byte
HOSTILE = ["a$x$", "$\\frac{1}{$", "p$$q", "\\$\\alpha$_^", "w$\\sqrt{\udcff", "\udcffname", "$\u202e$"]


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    """The ``kiloforge`` command in-process (its whole entry machinery): (status, stdout, stderr)."""
    rc = kf_main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def refused(argv: list[str], capsys) -> str:
    rc, _, err = run(argv, capsys)
    assert rc == 2, err
    return assert_one_clean_line(err)


def env_for_subprocess(**extra: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT), **extra)
    env.pop("PYTHONUNBUFFERED", None)
    return env


# --- 3 and 4: names on plots -----------------------------------------------------------------------
@settings(max_examples=25, deadline=None, database=None, derandomize=True)
@given(text=st.text(st.sampled_from("$\\{}_^ab\udcff\u202e\x1b"), min_size=1, max_size=30))
def test_any_text_draws_on_a_figure(text):
    """Generated text of mathtext syntax, surrogates and control characters in a title, legend and tick labels
    draws without an error or a warning."""
    fig = figure(3, 2)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot([0, 1], [0, 1], label="x" + text)
    ax.set_xticks([0, 1], [text, text + "$"])
    ax.set_title(text)
    ax.legend()
    fig.suptitle(text + "$x")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert png_bytes(fig, dpi=40).startswith(b"\x89PNG")


@pytest.mark.parametrize("name", HOSTILE[:3])
def test_sim_and_evaluate_plot_hostile_names(tmp_path, capsys, name):
    """A policy file and its world named with mathtext or a non-UTF-8 byte: sim and learn evaluate write every
    plot and the GIF (exit 0)."""
    world = dataclasses.replace(KILOBOT, name=name.replace("\udcff", "x"))
    path = save_policy(small_policy(world=world), tmp_path / (os.fsdecode(os.fsencode(name)) + ".npz"))
    rc, out, err = run(["sim", "--policy", str(path), "--out", str(tmp_path / "s"), *SIM], capsys)
    assert rc == 0, err
    assert {"trajectories.png", "episode.gif", "coverage.png", "metrics.json"} <= {p.name for p in (tmp_path / "s").iterdir()}
    rc, out, err = run(["evaluate", "--policy", str(path), "--out", str(tmp_path / "e"), *EVAL], capsys)
    assert rc == 0, err
    assert (tmp_path / "e" / "evaluation.json").is_file() and list((tmp_path / "e").glob("episode_*_2.gif"))


def test_verify_plots_a_world_named_in_mathtext(tmp_path, capsys):
    """export verify --out draws a policy whose world name is mathtext."""
    path = save_policy(small_policy(world=dataclasses.replace(KILOBOT, name="k$\\frac{1}{0$")), tmp_path / "d$.npz")
    rc, _, err = run(["verify", "--policy", str(path), "--out", str(tmp_path / "v"), *VERIFY], capsys)
    assert rc in (0, 1), err
    assert {p.name for p in (tmp_path / "v").iterdir()} == {"coverage.png", "returns_box.png", "closed_loop.json"}


def test_non_utf8_output_name_prints_escaped_under_a_strict_stdout(tmp_path):
    """An export to a non-UTF-8 --out under a strict UTF-8 stdout writes its set and prints the name escaped."""
    out = os.fsdecode(bytes(tmp_path) + b"/k\xff\xfe.c")
    res = subprocess.run([sys.executable, "-m", "export", "--out", out, *EXPORT], capture_output=True,
                         env=env_for_subprocess(PYTHONIOENCODING="utf-8:strict"), timeout=300)
    assert res.returncode == 0, res.stderr.decode(errors="replace")
    assert b"wrote " + bytes(tmp_path) + b"/k\\udcff\\udcfe.c" in res.stdout and Path(out).is_file()


# --- 5: names too long -----------------------------------------------------------------------------
@pytest.mark.parametrize("length", [256, 300, -1])
@pytest.mark.parametrize("command", ["export", "verify", "rehash", "sim", "evaluate", "plot"])
def test_too_long_names_are_one_line_before_work(tmp_path, capsys, command, length):
    """An output (or input) name over the file system's limit (256, 300 bytes), or a file name that leaves no
    room for the temporary written beside it first (-1: 240 bytes): one line, exit 2, nothing written."""
    policy = save_policy(small_policy(), tmp_path / "p.npz")
    long = str(tmp_path / ("n" * (240 if length < 0 else length)))
    argv = {"export": ["export", "--policy", str(policy), "--out", long + ".c", *EXPORT],
            "verify": ["verify", "--policy", long + ".npz", *VERIFY] if length < 0 else
                      ["verify", "--policy", str(policy), "--out", long, *VERIFY],
            "rehash": ["rehash", str(policy), "--out", long + ".npz"],
            "sim": ["sim", "--policy", long + ".npz", "--out", str(tmp_path / "s"), *SIM] if length < 0 else
                   ["sim", "--out", long, *SIM],
            "evaluate": ["evaluate", "--policy", long + ".npz", *EVAL] if length < 0 else
                        ["evaluate", "--policy", str(policy), "--out", long, *EVAL],
            "plot": ["plot", str(tmp_path), "--out", long + ".png"]}[command]
    before = sorted(os.listdir(tmp_path))
    line = refused(argv, capsys)
    assert "bytes" in line or "too long" in line or "does not exist" in line or "neither" in line, line
    assert sorted(os.listdir(tmp_path)) == before


# --- 6: a full disk --------------------------------------------------------------------------------
@pytest.mark.parametrize("command", [["-m", "sim", *SIM], ["-m", "learn", "evaluate", "--policy", "P", *EVAL]])
@pytest.mark.parametrize("kib", [4, 15])
def test_a_full_disk_while_plotting_is_one_line(tmp_path, command, kib):
    """Files limited to a few KiB (RLIMIT_FSIZE: writes fail as on a full disk) while sim / evaluate write PNGs
    and the GIF: one line, exit 2, no output folder and no temporaries left."""
    policy = save_policy(small_policy(), tmp_path / "p.npz")
    argv = [str(policy) if a == "P" else a for a in command] + ["--out", str(tmp_path / "out")]

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (kib * 1024, kib * 1024))

    res = subprocess.run([sys.executable, *argv], capture_output=True, text=True, env=env_for_subprocess(),
                         preexec_fn=limit, timeout=300)
    assert res.returncode == 2, res.stderr
    assert "File too large" in assert_one_clean_line(res.stderr)
    assert sorted(os.listdir(tmp_path)) == ["p.npz"]


# --- 7: standard output that fails -----------------------------------------------------------------
STDOUT_COMMANDS = [["-m", "kiloforge", "--version"], ["-m", "export", "budget", "--hidden", "4", "--history", "2"],
                   ["-m", "export", *EXPORT, "--out", "OUT"], ["-m", "learn", "--version"]]


@pytest.mark.parametrize("argv", STDOUT_COMMANDS, ids=["version", "budget", "export", "learn-version"])
def test_standard_output_that_fails(tmp_path, argv):
    """stdout /dev/full: one line naming standard output, exit 2; a closed pipe: exit 141, nothing on stderr."""
    argv = [str(tmp_path / "k.c") if a == "OUT" else a for a in argv]
    with open("/dev/full", "w") as full:
        res = subprocess.run([sys.executable, *argv], stdout=full, stderr=subprocess.PIPE, text=True,
                             env=env_for_subprocess(), timeout=300)
    assert res.returncode == 2 and "standard output" in assert_one_clean_line(res.stderr), res.stderr
    r, w = os.pipe()
    os.close(r)  # the reader went away before the first byte
    res = subprocess.run([sys.executable, *argv], stdout=w, stderr=subprocess.PIPE, text=True,
                         env=env_for_subprocess(), timeout=300)
    os.close(w)
    assert res.returncode == 141 and res.stderr == "", res.stderr


@pytest.mark.parametrize("encoding", ["ascii", "latin-1"])
def test_names_the_terminal_cannot_encode(tmp_path, encoding):
    """A world name in other scripts under an ASCII / Latin-1 stdout: the export works, the name printed escaped."""
    path = save_policy(small_policy(world=dataclasses.replace(KILOBOT, name="kil\u00f6bot\u2713\u0663")),
                       tmp_path / "u.npz")
    res = subprocess.run([sys.executable, "-m", "export", "--policy", str(path), "--out", str(tmp_path / "k.c"),
                          *EXPORT], capture_output=True, env=env_for_subprocess(PYTHONIOENCODING=encoding), timeout=300)
    assert res.returncode == 0, res.stderr.decode(errors="replace")
    assert b"\\u2713\\u0663" in res.stdout and (tmp_path / "k.c").is_file()


# --- 8: run folders that lie -----------------------------------------------------------------------
GOOD_CSV = "env_steps,eval_return,eval_final_coverage\n1,2,0.5\n2,3,0.6\n"
RUN_FOLDERS = {
    "config a list": ("[1, 2]", GOOD_CSV),
    "config a number": ("3.5", GOOD_CSV),
    "config not JSON": ("{'a': 1}", GOOD_CSV),
    "n_robots a string": ('{"n_robots": "4"}', GOOD_CSV),
    "n_robots a float": ('{"n_robots": [4, 16.0]}', GOOD_CSV),
    "exp_name a list": ('{"exp_name": ["x"]}', GOOD_CSV),
    "t_prev negative": ('{"t_prev": -1}', GOOD_CSV),
    "missing column": ("{}", "env_steps,eval_return\n1,2\n"),
    "no header": ("{}", ""),
    "duplicate column": ("{}", "env_steps,eval_return,eval_final_coverage,eval_return\n1,2,3,4\n"),
    "extra field": ("{}", GOOD_CSV + "3,4,0.7,9\n"),
    "short row": ("{}", GOOD_CSV + "3,4\n"),
    "long field": ("{}", GOOD_CSV + "3,4," + "1" * 200_000 + "\n"),
    "long quoted field": ("{}", GOOD_CSV + '3,4,"' + "1\n" * 70_000 + '"\n'),
    "text for a number": ("{}", GOOD_CSV + "3,four,0.7\n"),
    "not UTF-8": ("{}", GOOD_CSV.encode() + b"3,\xff,1\n"),
}


@pytest.mark.parametrize("case", sorted(RUN_FOLDERS))
def test_run_folders_that_lie(tmp_path, capsys, case):
    """learn plot of a run folder whose config.json or metrics.csv is malformed: one line naming the file, exit 2,
    no plot written."""
    config, metrics = RUN_FOLDERS[case]
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.json").write_text(config)
    (run_dir / "metrics.csv").write_bytes(metrics if isinstance(metrics, bytes) else metrics.encode())
    line = refused(["plot", str(run_dir), "--out", str(tmp_path / "c.png")], capsys)
    assert "config.json" in line or "metrics.csv" in line, line
    assert not (tmp_path / "c.png").exists()


@pytest.mark.parametrize("which", ["config.json", "metrics.csv"])
@pytest.mark.parametrize("kind", ["fifo", "/dev/zero", "directory"])
def test_run_files_that_are_not_files(tmp_path, capsys, which, kind):
    """A FIFO (would hang), a link to /dev/zero (would exhaust memory) or a directory in a run folder: one line."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.json").write_text("{}")
    (run_dir / "metrics.csv").write_text(GOOD_CSV)
    (run_dir / which).unlink()
    if kind == "fifo":
        os.mkfifo(run_dir / which)
    elif kind == "directory":
        (run_dir / which).mkdir()
    else:
        os.symlink(kind, run_dir / which)
    line = refused(["plot", str(run_dir), "--out", str(tmp_path / "c.png")], capsys)
    assert which in line, line


def test_a_run_folder_with_odd_but_valid_contents_plots(tmp_path, capsys):
    """Extra columns, empty fields (NaN), an exp_name in mathtext and a title in mathtext: plotted, exit 0."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.json").write_text('{"exp_name": "$\\\\frac{a}{$", "n_robots": [4, 16], "t_prev": 2}')
    (run_dir / "metrics.csv").write_text("env_steps,eval_return,eval_final_coverage,bc_pass\n1,,0.5,\n2,nan,,1\n")
    rc, _, err = run(["plot", str(run_dir), "--out", str(tmp_path / "c.png"), "--title", "$x^$"], capsys)
    assert rc == 0 and err == "", err
    assert (tmp_path / "c.png").read_bytes().startswith(b"\x89PNG")


# --- 11: weights beyond the int8 format --------------------------------------------------------------
@pytest.mark.parametrize("seed", range(6))
def test_huge_weights_are_one_line_without_warnings(tmp_path, capsys, seed):
    """A weight or bias of an MLP or GRU scaled by 1e7..1e38 (re-hashed, so loading accepts it): export refuses
    in exactly one line and NumPy warns about nothing."""
    rng = np.random.default_rng(seed)
    pol = small_policy() if seed % 2 == 0 else random_gru_policy(KILOBOT, 4, seed=seed)
    arrays, meta = parts(pol)
    name = sorted(arrays)[rng.integers(len(arrays))]
    scale = float(10.0 ** rng.uniform(7, 38))
    arrays[name] = (arrays[name].astype(np.float64) * scale).clip(-3e38, 3e38).astype(np.float32)
    path = tmp_path / "huge.npz"
    path.write_bytes(crafted(arrays, meta))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        rc, _, err = run(["export", "--policy", str(path), "--out", str(tmp_path / "k.c"), *EXPORT], capsys)
    assert [str(w.message) for w in seen if issubclass(w.category, RuntimeWarning)] == []
    assert rc == 2, (name, scale, err)
    assert_one_clean_line(err)
    assert not (tmp_path / "k.c").exists()


# --- found by tests/soak/fuzz_all.py ------------------------------------------------------------------
@pytest.mark.parametrize("ahead", [1, 2, 50])
def test_onnx_opset_newer_than_onnx_knows_is_refused(tmp_path, capsys, ahead):
    """An ONNX model claiming an opset newer than the installed onnx defines (onnxruntime cannot load it): one line."""
    onnx = pytest.importorskip("onnx")
    from tests.onnx_models import tiny_model

    m = onnx.load(str(tiny_model(tmp_path / "b.onnx")))
    m.opset_import[0].version = onnx.defs.onnx_opset_version() + ahead
    (tmp_path / "m.onnx").write_bytes(m.SerializeToString())
    line = refused(["export", "--onnx", str(tmp_path / "m.onnx"), "--out", str(tmp_path / "k.c"), *EXPORT], capsys)
    assert "newer than" in line and not (tmp_path / "k.c").exists()
