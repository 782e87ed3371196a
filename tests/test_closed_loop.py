"""Firmware in the loop: determinism, pairing with sim.rollout, exact equality when lossless, CLI."""
from __future__ import annotations

import json

import numpy as np
import pytest

from kiloforge.actors.mlp import MLPPolicy
from kiloforge.policies import save_policy
from export.cli.main import main
from export.verify.closed_loop import (ROBOT_BUDGET, Comparison, batch_env_seeds, default_n_envs, run_firmware,
                                run_float, spread_ticks)
from export.quantize import quantize_policy
from kiloforge.actors.mlp import calibration_from_inputs
from tests.fixtures import synthetic_qpolicy
from sim.config import OBS_NBR_SENSING, OBS_RBF, OBS_TARGET, OBS_WALL, preset
from sim.events import HeardEvents, summarise

KILOBOT = preset("kilobot", arena_half_mm=140.0, episode_steps=40)
THESIS = preset("thesis", episode_steps=40)


def flag_policy(world, t_prev: int, out: dict[str, tuple[float, float]]) -> MLPPolicy:
    """A policy whose float and int8 forwards agree exactly (see the test using it).

    Hidden ReLU units read only exactly representable inputs of the newest tuple: h_wall = wall,
    h_nbr = neighbour-sensing flag, h_lost = relu(-target) (1 when the target was not heard, 0 when
    heard). The output (in u units) is ``base + wall * h_wall + nbr * h_nbr + lost * h_lost - lost``,
    so a robot that hears the target gets ``base + ... - lost`` (chosen <= 0: it stops).
    """
    D = world.tuple_dim
    newest = (t_prev - 1) * D + 2  # first observation entry of the newest tuple
    W0 = np.zeros((3, t_prev * D))
    W0[0, newest + OBS_WALL] = 1.0
    W0[1, newest + OBS_NBR_SENSING] = 1.0
    W0[2, newest + OBS_TARGET] = -1.0
    W1 = np.array([out["wall"], out["nbr"], out["lost"]], np.float64).T  # (2, 3)
    b1 = np.array(out["base"], np.float64) - np.array(out["lost"], np.float64)
    return MLPPolicy(weights=[W0, W1], biases=[np.zeros(3), b1], activations=["relu", "identity"],
                  t_prev=t_prev, world=world, provenance={"notes": "lossless test policy"})


# kilobot: commands that land on q / 255 (multiples of 4, so the int8 weights are exact) and drive
# the real motor schedule; thesis: outputs that saturate to exactly 0 or 1 (thesis motion takes u as is)
LOSSLESS = {
    "kilobot": (KILOBOT, {"base": (200 / 255, 180 / 255), "wall": (0.0, -180 / 255), "nbr": (-100 / 255, 20 / 255),
                          "lost": (256 / 255, 256 / 255)}),
    "thesis": (THESIS, {"base": (2.0, 2.0), "wall": (0.0, -4.0), "nbr": (-4.0, 0.0), "lost": (4.0, 4.0)}),
}


def lossless_pair(name: str):
    world, out = LOSSLESS[name]
    p = flag_policy(world, 3, out)
    x = np.zeros((4, p.in_dim))
    x[:, (3 - 1) * world.tuple_dim + 2 + np.array([OBS_WALL, OBS_NBR_SENSING])] = 1.0
    x[:, (3 - 1) * world.tuple_dim + 2 + OBS_TARGET] = [-1.0, 0.0, 0.5, 1.0]
    qp = quantize_policy(p, calibration_from_inputs(p, x), e_in=6)
    return p, qp


@pytest.mark.parametrize("name, M", [("kilobot", 6), ("kilobot", 24), ("thesis", 6), ("thesis", 64)])
def test_lossless_policy_gives_identical_trajectories(name, M):
    """With a constructed policy the int8 forward computes exactly, the firmware-driven sim equals the float run."""
    p, qp = lossless_pair(name)
    f = run_float(p, M, 4, seed=3, record=True)
    q = run_firmware(qp, M, 4, seed=3, record=True)
    np.testing.assert_array_equal(q.commands, np.floor(f.commands.astype(np.float64) * 255 + 0.5).astype(np.uint8))
    np.testing.assert_array_equal(q.positions, f.positions)
    np.testing.assert_array_equal(q.headings, f.headings)
    np.testing.assert_array_equal(q.rewards, f.rewards)
    np.testing.assert_array_equal(q.success, f.success)
    # the case is not trivial: robots moved, several distinct commands, some robots found the target
    assert np.abs(np.diff(f.positions, axis=1)).max() > 1.0
    assert len({tuple(c) for c in q.commands.reshape(-1, 2).tolist()}) >= 3
    assert q.success.max() > 0


def test_lossless_needs_exact_plumbing():
    """The identity above is not automatic: the same policy reading the (inexact) RBF bins makes the runs differ."""
    p, _ = lossless_pair("kilobot")
    D = KILOBOT.tuple_dim
    W0 = np.array(p.weights[0], np.float64)
    W0[2, 2 * D + 2 + OBS_RBF:] = 0.3  # the 'lost' unit now also reads the newest RBF histogram
    p2 = MLPPolicy(weights=[W0, p.weights[1]], biases=list(p.biases), activations=list(p.activations),
                t_prev=p.t_prev, world=p.world)
    x = np.zeros((1, p2.in_dim))
    x[0, 2 * D + 2:] = 1.0
    qp2 = quantize_policy(p2, calibration_from_inputs(p2, x), e_in=6)
    f = run_float(p2, 8, 4, seed=1, record=True)
    q = run_firmware(qp2, 8, 4, seed=1, record=True)
    assert not np.array_equal(q.positions, f.positions)


def test_thesis_messages_must_be_spread():
    """Delivered all at tick 0, the thesis radio overflows the firmware's rx queue in a crowd (64 robots)."""
    p, qp = lossless_pair("thesis")
    f = run_float(p, 64, 4, seed=3, record=True)
    q = run_firmware(qp, 64, 4, seed=3, record=True, spread=False)
    assert not np.array_equal(q.positions, f.positions)


def test_firmware_runs_are_deterministic_per_seed():
    """Same seed, same closed-loop run, whatever ran before; another seed gives other episodes."""
    qp = synthetic_qpolicy(KILOBOT, 2, (8,), ("elu",), seed=4)
    a = run_firmware(qp, 5, 3, seed=11, steps=15, record=True)
    run_firmware(qp, 7, 2, seed=99, steps=5)
    b = run_firmware(qp, 5, 3, seed=11, steps=15, record=True)
    c = run_firmware(qp, 5, 3, seed=12, steps=15, record=True)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.commands, b.commands)
    np.testing.assert_array_equal(a.rewards, b.rewards)
    assert not np.array_equal(a.positions, c.positions)


def test_float_run_equals_sim_rollout():
    """The float side is exactly sim.rollout.rollout with HistoryActor (the seeds are derived the same way)."""
    from sim.env import SwarmEnv
    from sim.rollout import HistoryActor, rollout

    p, _ = lossless_pair("thesis")
    r = rollout(SwarmEnv(THESIS, 3, 6), HistoryActor(p.act, p.t_prev, THESIS), episodes=5, seed=7)
    f = run_float(p, 6, 5, seed=7, n_envs=3)
    np.testing.assert_array_equal(f.rewards, r.rewards)
    np.testing.assert_array_equal(f.success, r.success)
    assert batch_env_seeds(7, 2) == batch_env_seeds(7, 5)[:2]


def test_batches_split_evenly():
    """Default envs per batch respect the robot budget and waste at most one env per batch."""
    for E, M in [(200, 16), (200, 32), (200, 64), (7, 4096), (1, 3)]:
        B = default_n_envs(E, M)
        assert 1 <= B <= E and (B * M <= ROBOT_BUDGET or B == 1)
        n = -(-E // B)
        assert n * B - E < n


def test_spread_ticks_keeps_the_receive_rules():
    """Spreading thesis messages over the period keeps each receiver's table and never exceeds ceil(n/P) per tick."""
    rng = np.random.default_rng(np.random.SeedSequence(5))
    n, M, P = 400, 40, 31
    env = np.zeros(n, np.int32)
    rx = np.sort(rng.integers(0, 3, n)).astype(np.int32)
    snd = rng.permutation(np.arange(-1, M - 1).repeat(10))[:n].astype(np.int32)
    ev = HeardEvents(env, rx, snd, np.zeros(n, np.int16), rng.uniform(0, 40, n),
                     (snd < 0).astype(np.uint8), rng.integers(0, 2, n).astype(np.uint8))
    sp = spread_ticks(ev, M, P)
    cfg = preset("thesis", neighbour_table_size=8)
    a, b = summarise(ev, cfg, 1, M), summarise(sp, cfg, 1, M)
    for field in ("table_rx", "table_sender", "table_dist_mm", "table_flag", "target_dist_mm"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    per_tick = np.unique(sp.rx.astype(np.int64) * P + sp.tick, return_counts=True)[1]
    assert per_tick.max() <= -(-np.bincount(rx).max() // P)


def test_comparison_statistics():
    """The comparison pairs the same episodes: int8 vs itself is a zero difference and ratio 1, PASS."""
    qp = synthetic_qpolicy(THESIS, 2, (8,), ("relu",), seed=1)
    a = run_firmware(qp, 8, 6, seed=2, steps=30)
    b = run_firmware(qp, 8, 6, seed=2, steps=30)
    c = Comparison(8, a, b)
    assert c.stats["return"]["diff"].mean == 0.0 and c.stats["final_coverage"]["diff"].ci95 == 0.0
    if a.metrics().final_coverage.mean() > 0:
        assert c.ratio == 1.0 and c.ratio_ci == (1.0, 1.0)
    assert c.passed and "PASS" in c.table()


def test_cli_verify_smoke(tmp_path, capsys):
    """verify prints both columns, the ratio and a verdict, and writes plots + JSON."""
    p, _ = lossless_pair("kilobot")
    path = tmp_path / "p.npz"
    save_policy(p, path)
    out = tmp_path / "cl"
    rc = main(["verify", "--policy", str(path), "--robots", "4", "6", "--episodes", "3",
               "--steps", "12", "--robots-calib", "4", "--out", str(out), "--quiet"])
    text = capsys.readouterr().out
    assert rc in (0, 1)
    assert "float actor" in text and "int8 firmware" in text and "int8/float" in text
    assert ("PASS" in text) == (rc == 0)
    doc = json.loads((out / "closed_loop.json").read_text())
    assert [c["n_robots"] for c in doc["comparisons"]] == [4, 6]
    assert doc["comparisons"][0]["episodes"] == 3 and len(doc["comparisons"][0]["success_curve"]["int8"]["mean"]) == 12
    for name in ("coverage.png", "returns_box.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("argv, needle", [
    (["verify", "--robot", "4"], "--robot"),
    (["verify", "--policy", "/nonexistent/p.npz"], "does not exist"),
    (["verify", "--episodes", "0"], "--episodes: must be in [1, "),
    (["verify", "--robots", "5000", "--episodes", "1"], "robots"),
])
def test_cli_verify_errors(argv, needle, capsys):
    """Bad input: one line on stderr, exit 2, no traceback."""
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("python -m export verify: error: ") and err.count("\n") == 1 and needle in err


def test_cli_verify_refuses_unusable_out_before_running(tmp_path, capsys):
    """--out naming a file (or a path under one) fails at once with one line, exit 2, nothing written."""
    f = tmp_path / "afile"
    f.write_text("x")
    for out in (f, f / "sub"):
        rc = main(["verify", "--out", str(out), "--quiet"])
        err = capsys.readouterr().err
        assert rc == 2 and err.startswith("python -m export verify: error: ") and err.count("\n") == 1
    assert f.read_text() == "x" and sorted(p.name for p in tmp_path.iterdir()) == ["afile"]
