"""The ``random`` observation feature (issue 42): the firmware's xorshift32 seeded from kilo_uid and rand_hard(),
the simulator's float reference and the emulator's twin drawing the same values."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from export.codegen.render import POLICY_FILE, render_firmware
from export.contract import firmware as fwspec
from export.verify.emulator import INT_FEATURES, FirmwareEmulator
from export.verify.hostbuild import StreamSpec, build_host, compare, compiler, random_inputs, run_host
from kiloforge.policies import save_policy
from kiloforge.xorshift import rng_seed, top_byte, xorshift32
from sim.config import preset
from sim.env import SwarmEnv
from sim.tasks import get_task
from tests.fixtures import init_policy, synthetic_qpolicy

TASK = f"{Path(__file__).resolve().parent / 'random_task.py'}:RandomAggregation"
WORLD = get_task(TASK).world(preset("kilobot", neighbour_table_size=5, period_ticks=12))
needs_gcc = pytest.mark.skipif(compiler() is None, reason="no host C compiler (gcc) installed")


def _stream(uids, hard, n):
    """(n, R) signed top bytes of the words after each of n steps."""
    w, out = rng_seed(uids, hard), []
    for _ in range(n):
        w = xorshift32(w)
        out.append(top_byte(w))
    return np.stack(out)


def test_streams_differ_by_uid_and_repeat_by_seed():
    """Two robots with different kilo_uids draw different streams; the same uid and rand_hard byte the same one."""
    a = _stream(np.array([1, 2, 1]), np.array([7, 7, 7]), 50)
    assert not np.array_equal(a[:, 0], a[:, 1]) and np.array_equal(a[:, 0], a[:, 2])
    assert not np.array_equal(a[:, 0], _stream(np.array([1]), np.array([8]), 50)[:, 0])  # rand_hard mixes in
    assert a.min() < -100 and a.max() > 100


@needs_gcc
def test_random_block_equals_emulator_on_fuzzed_streams(tmp_path):
    """The host build of a wall,rbf,random layout equals the emulator byte for byte, random input included."""
    qp = synthetic_qpolicy(WORLD, 4, (8,), seed=7)
    exe = build_host(render_firmware(qp, generator_version="t")[POLICY_FILE], tmp_path, name="random")
    rng = np.random.default_rng(np.random.SeedSequence(43))
    inputs = random_inputs(rng, WORLD.period_ticks, (), StreamSpec(n_robots=32, n_steps=40, rate=0.9),
                           fwspec.DEFAULT_MSG_TYPE, WORLD.comm_radius_mm, WORLD.light_threshold)
    emu = FirmwareEmulator(qp, inputs.uids, inputs.calib)
    want = emu.run(inputs)
    got = run_host(exe, inputs, WORLD.period_ticks, WORLD.obs_dim, fill="random:3")
    np.testing.assert_array_equal(got.steps, want.steps, err_msg=compare(want, got))
    np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
    r = want.obs[..., WORLD.obs_index("random")].astype(np.int64)
    assert np.unique(r).size > 20 and not np.array_equal(r[0], r[1])


def test_float_reference_equals_firmware_value():
    """SwarmEnv's random input, quantised at e_in, equals the emulator's per robot per period (same uids, same seeds)."""
    env = SwarmEnv(WORLD, 2, 6, seed=5, task=TASK)
    obs, _ = env.reset()
    xs = [obs[..., WORLD.obs_index("random")]]
    for _ in range(30):
        obs, *_ = env.step(np.zeros((2, 6, 2), np.float32))
        xs.append(obs[..., WORLD.obs_index("random")])
    x = np.stack(xs, -1).astype(np.float64)  # (B, M, T)
    b = x * 128
    np.testing.assert_array_equal(b, np.round(b))  # b / 128 exactly
    qp = synthetic_qpolicy(WORLD, 4, (8,), seed=7)
    one = int(qp.one_q)
    for e in range(2):
        emu = FirmwareEmulator(qp, np.arange(1, 7), rand_hard=env.rand_hard[e])
        q = []
        for _ in range(x.shape[-1]):  # what the control step does: step the word, then the feature's twin
            emu.rand_word = xorshift32(emu.rand_word)
            q.append(INT_FEATURES["random"](emu, None)[:, 0])
        np.testing.assert_array_equal(np.stack(q, 1), (b[e].astype(np.int64) * one) >> 7)
    assert not np.array_equal(x[0], x[1])  # envs draw their own rand_hard bytes


@needs_gcc
def test_random_task_exports_bit_exact(tmp_path, capsys):
    """python -m export --task <wall,rbf,random task> --verify host passes bit-exact."""
    from export.cli.main import main

    p = dataclasses.replace(init_policy(WORLD, 2, (8,)), task=get_task(TASK).ref)
    path = save_policy(p, tmp_path / "rand.npz")
    out = tmp_path / "kilobot_policy.c"
    rc = main(["--task", TASK, "--policy", str(path), "--out", str(out), "--verify", "host",
               "--robots-calib", "4", "--calib-steps", "20", "--no-avr", "--quiet"])
    assert rc == 0 and "bit-exact" in capsys.readouterr().out
    assert "KF_OBS_RANDOM" in out.read_text()
