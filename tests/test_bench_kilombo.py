"""tests/bench/bench_kilombo.py without Kilombo: it refuses in one line, and its pure helpers are right."""
from __future__ import annotations

import doctest
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from tests.bench import bench_kilombo

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "KILOMBO_DIR"}
    return subprocess.run([sys.executable, "-m", "tests.bench.bench_kilombo", *args], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=120)


def test_refuses_when_kilombo_not_given():
    """No --kilombo-dir and no KILOMBO_DIR: exit 2, one line on stderr naming the option, nothing on stdout."""
    r = _run()
    assert r.returncode == 2
    assert r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "--kilombo-dir" in lines[0]


def test_refuses_when_kilombo_not_found(tmp_path):
    """A directory without include/kilombo.h and lib/libheadless.a: exit 2, one line naming what is missing."""
    r = _run("--kilombo-dir", str(tmp_path))
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "kilombo.h" in lines[0] and "libheadless.a" in lines[0]


def test_helper_doctests():
    """The doctests of the bench's helpers (bot file mirroring, log parsing, coverage) pass."""
    result = doctest.testmod(bench_kilombo, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted >= 3 and result.failed == 0


def test_mirrored_start_keeps_distances_and_turns_the_same_way():
    """Bot file and log round trip: our positions come back unchanged, and a Kilombo left pivot
    (compass heading + d) is a left (counter-clockwise) pivot in our frame."""
    bk = bench_kilombo
    rng = np.random.default_rng(np.random.SeedSequence(3))
    target, pos, heading = rng.uniform(-200, 200, 2), rng.uniform(-200, 200, (4, 2)), rng.uniform(-3, 3, 4)
    states = bk.kilombo_bots(target, pos, heading)["bot_states"]
    fields = lambda s: [s["x_position"], s["y_position"], s["direction"]]  # noqa: E731
    line = "31 " + " ".join(f"{v:.6f}" for s in states for v in fields(s))
    xy = bk.log_positions(line + "\n" + line.replace("31 ", "62 ", 1), 5, 31, 1)
    np.testing.assert_allclose(xy[0, 0], target, atol=1e-5)
    np.testing.assert_allclose(xy[0, 1:], pos, atol=1e-5)
    d = states[1]["direction"] + 0.1  # Kilombo's left motor: direction += turn_rate * dt
    step = np.array([np.sin(d), -np.cos(d)])  # its forward unit vector (sin d, cos d), mirrored
    ours = np.array([np.cos(heading[0] + 0.1), np.sin(heading[0] + 0.1)])
    np.testing.assert_allclose(step, ours, atol=1e-12)


def test_phototaxis_bench_refuses_without_kilombo_and_its_doctests_pass():
    """tests/bench/bench_kilombo_phototaxis.py without Kilombo: exit 2, one line naming --kilombo-dir; its doctests pass."""
    from tests.bench import bench_kilombo_phototaxis

    env = {k: v for k, v in os.environ.items() if k != "KILOMBO_DIR"}
    r = subprocess.run([sys.executable, "-m", "tests.bench.bench_kilombo_phototaxis"], capture_output=True, text=True,
                       env=env, cwd=ROOT, timeout=120)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and r.stdout == "" and len(lines) == 1 and "--kilombo-dir" in lines[0], r.stderr
    result = doctest.testmod(bench_kilombo_phototaxis, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted >= 1 and result.failed == 0
