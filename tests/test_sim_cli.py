"""Tests of the ``python -m sim`` command line."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from sim.__main__ import main

ROOT = Path(__file__).resolve().parents[1]
OUTPUTS = ["coverage.png", "episode.gif", "metrics.json", "trajectories.png"]
TINY = ["--robots", "2", "--episodes", "2", "--steps", "12", "--quiet"]


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def test_cli_writes_plots_gif_and_metrics(tmp_path, capsys):
    """A tiny baseline run exits 0 and writes valid PNGs, a multi-frame GIF and metrics.json."""
    out = tmp_path / "run"
    assert main(["--world", "thesis", "--seed", "3", "--policy", "baseline", "--out", str(out)] + TINY) == 0
    assert sorted(p.name for p in out.iterdir()) == OUTPUTS  # no temp files left behind
    m = json.loads((out / "metrics.json").read_text())
    assert m["robots"] == 2 and m["seed"] == 3 and m["world"]["episode_steps"] == 12
    assert m["policy"]["kind"] == "baseline" and "stop_dist" in m["policy"]["params"]
    s = m["metrics"]["summary"]
    assert set(s) >= {"final_coverage", "time_to_find", "return", "found_rate", "mean_coverage"}
    assert 0.0 <= s["final_coverage"]["mean"] <= 1.0 and s["final_coverage"]["n"] == 2
    assert 1 <= s["time_to_find"]["mean"] <= 12
    with Image.open(out / "episode.gif") as im:
        assert im.n_frames > 1
    for f in ("trajectories.png", "coverage.png"):
        with Image.open(out / f) as im:
            assert im.format == "PNG"
    printed = capsys.readouterr().out
    assert "final cov" in printed and "baseline" in printed


def test_cli_same_seed_same_metrics(tmp_path):
    """Two runs with the same seed write identical metrics; the random policy runs too."""
    a, b = tmp_path / "a", tmp_path / "b"
    for out in (a, b):
        assert main(["--policy", "random", "--seed", "9", "--out", str(out), "--n-envs", "1"] + TINY) == 0
    ma = json.loads((a / "metrics.json").read_text())["metrics"]
    mb = json.loads((b / "metrics.json").read_text())["metrics"]
    assert ma == mb


@pytest.mark.parametrize("args, needle", [
    (["--world", "moon"], "unknown world 'moon'"),
    (["--robots", "0"], "--robots"),
    (["--robots", "two"], "--robots"),
    (["--episodes", "0"], "--episodes"),
    (["--steps", "-1"], "--steps"),
    (["--policy", "no/such/policy.npz"], "no/such/policy.npz"),
    (["--bogus"], "unrecognized option --bogus"),
    (["--world", "kilobot", "--robots", "400"], "400 robots"),
])
def test_cli_bad_input_one_line_exit_2(tmp_path, capsys, args, needle):
    """Bad arguments exit with 2 and one line on stderr naming the problem; nothing is created."""
    out = tmp_path / "out"
    assert main(["--out", str(out)] + TINY + args) == 2
    assert needle in _one_line_error(capsys)
    assert not out.exists()


def test_cli_missing_out_is_a_one_line_error(capsys):
    """Leaving out --out is a usage error: exit 2, one line."""
    assert main(TINY) == 2
    assert "--out" in _one_line_error(capsys)


def test_cli_unwritable_out_exit_2(tmp_path, capsys):
    """An --out below a regular file cannot be created: exit 2, one line, nothing written."""
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    assert main(["--out", str(blocker / "sub")] + TINY) == 2
    assert "cannot create" in _one_line_error(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt"]


def test_cli_runs_a_policy_artifact_in_its_own_world(tmp_path, capsys):
    """An artifact runs through its kind's float actor in its own world; a different --world gives a note."""
    from kiloforge.actors.mlp import MLPPolicy
    from kiloforge.policies import save_policy
    from sim.config import preset

    world = preset("thesis", episode_steps=50)
    rng = np.random.default_rng(0)
    t_prev = 2
    d = world.history_dim(t_prev)
    pol = MLPPolicy(weights=[rng.normal(0, 0.1, (8, d)).astype(np.float32), np.zeros((2, 8), np.float32)],
                    biases=[np.zeros(8, np.float32), np.full(2, 0.6, np.float32)],
                    activations=["elu", "identity"], t_prev=t_prev, world=world)
    path = tmp_path / "p.npz"
    save_policy(pol, path)
    out = tmp_path / "o"
    assert main(["--policy", str(path), "--world", "kilobot", "--out", str(out), "--robots", "2",
                 "--episodes", "1", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "differs from --world 'kilobot'" in err
    m = json.loads((out / "metrics.json").read_text())
    assert m["policy"]["kind"] == "artifact" and m["policy"]["actor"] == "mlp"
    assert m["policy"]["architecture"].startswith(f"t_prev {t_prev},")
    assert m["world"]["name"] == "thesis" and m["world"]["episode_steps"] == 50


def test_cli_corrupt_artifact_exit_2(tmp_path, capsys):
    """A file that is not a policy artifact is a one-line error with exit 2."""
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file")
    assert main(["--policy", str(bad), "--out", str(tmp_path / "o")] + TINY) == 2
    assert "bad.npz" in _one_line_error(capsys)
    assert not (tmp_path / "o").exists()


def test_python_dash_m_sim_subprocess(tmp_path):
    """`python -m sim` works as a module (exit 0) and reports a bad preset without a traceback (exit 2)."""
    out = tmp_path / "r"
    ok = subprocess.run([sys.executable, "-m", "sim", "--out", str(out)] + TINY, cwd=ROOT,
                        capture_output=True, text=True, timeout=300)
    assert ok.returncode == 0, ok.stderr
    assert (out / "metrics.json").is_file()
    bad = subprocess.run([sys.executable, "-m", "sim", "--world", "nope", "--out", str(out)], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2
    assert bad.stderr.strip().count("\n") == 0 and "Traceback" not in bad.stderr


SUITE = ["--suite", "robustness", "--robots", "2", "3", "--episodes", "2", "--steps", "10", "--quiet"]


@pytest.mark.parametrize("policy", ["baseline", str(ROOT / "export" / "data" / "default_policy.npz")])
def test_cli_robustness_suite(tmp_path, capsys, policy):
    """--suite robustness runs a baseline or an .npz policy in every variant at each robot count and
    writes robustness.json and robustness.md (nothing else)."""
    out = tmp_path / "rob"
    assert main(["--policy", policy, "--out", str(out)] + SUITE) == 0
    assert sorted(p.name for p in out.iterdir()) == ["robustness.json", "robustness.md"]
    rep = json.loads((out / "robustness.json").read_text())
    cov = rep["final_coverage"]
    assert "nominal" in cov and "graded motors" in cov and set(cov["nominal"]) == {"2", "3"}
    nominal = cov["nominal"]["2"]
    assert nominal["fraction_of_nominal"] == (1.0 if nominal["mean"] > 0 else None) and rep["robots"] == [2, 3]
    assert rep["world"]["name"] == "kilobot" and set(rep["variants"]) == set(cov)
    assert "msg period 15" in capsys.readouterr().out


@pytest.mark.parametrize("args, needle", [
    (["--robots", "2", "3"], "one count"),
    (SUITE + ["--world", "thesis"], "tick-level"),
    (SUITE + ["--robots", "400"], "400 robots"),
])
def test_cli_suite_bad_input_exit_2(tmp_path, capsys, args, needle):
    """Several robot counts without --suite, a suite in the thesis world, too many discs: exit 2, one line."""
    out = tmp_path / "out"
    assert main(["--out", str(out), "--quiet"] + args) == 2
    assert needle in _one_line_error(capsys)
    assert not out.exists()
