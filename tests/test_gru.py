"""The recurrent actor's export path without a compiler: artifact, int8 GRU cell, quantiser, emulator, budget."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from export.codegen import budget as bud
from export.quantize import calibrate, error_report, quantize_policy
from export.verify.emulator import FirmwareEmulator
from export.verify.hostbuild import StreamSpec, random_inputs
from kiloforge import numfmt
from kiloforge.actors.base import HiddenArch, StatefulActor
from kiloforge.actors.gru import (GRU, GRUPolicy, QuantGRUCell, QuantizedGRU, gru_error_report, quantize_gru,
                                  random_gru_policy)
from kiloforge.actors.recurrent import ARRAYS, calibration_from_sequences
from kiloforge.errors import PolicyError
from kiloforge.policies import load_policy, save_policy
from sim.config import preset
from tests.fixtures import random_sequences

WORLD = preset("kilobot")


def small_qgru(hidden: int = 8, seed: int = 1, scale: float = 2.0, world=WORLD) -> tuple[GRUPolicy, QuantizedGRU]:
    p = random_gru_policy(world, hidden, seed=seed, scale=scale)
    cal = calibration_from_sequences(p, random_sequences(world, 16, 40, seed))
    return p, quantize_gru(p, cal)


# --- artifact -----------------------------------------------------------------------------
def test_round_trip_same_bytes_and_hash(tmp_path):
    """save_policy / load_policy round-trip a GRUPolicy: equal arrays, world, hash; same policy, same bytes."""
    p = random_gru_policy(WORLD, 12, seed=3)
    a = save_policy(p, tmp_path / "a.npz")
    q = load_policy(a)
    assert isinstance(q, GRUPolicy) and q.hash == p.hash and q.world == p.world and q.provenance == p.provenance
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(q, name), getattr(p, name))
    assert save_policy(p, tmp_path / "b.npz").read_bytes() == a.read_bytes()
    assert random_gru_policy(WORLD, 12, seed=4).hash != p.hash


def _rewrite(path: Path, out: Path, change) -> Path:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("meta").tobytes())
    change(arrays, meta)
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    with open(out, "wb") as f:
        np.savez(f, **arrays)
    return out


@pytest.mark.parametrize("change, needle", [
    (lambda a, m: a.pop("w_hh"), "lacks array(s) w_hh"),
    (lambda a, m: a.__setitem__("w_ih", a["w_ih"][:, :-1]), "'w_ih' has shape"),
    (lambda a, m: a.__setitem__("b_out", np.array([np.nan, 0], np.float32)), "non-finite"),
    (lambda a, m: m.__setitem__("gate_order", "zrn"), "gate order"),
    (lambda a, m: m.__setitem__("hidden", 7), "meta says hidden 7"),
    (lambda a, m: a.__setitem__("extra", np.zeros(1)), "unexpected arrays"),
    (lambda a, m: a["w_out"].__setitem__((0, 0), 1.0), "policy_hash"),
])
def test_malformed_files_give_one_line_errors(tmp_path, change, needle):
    """Each corrupted GRU file raises PolicyError with one line naming the file and the problem."""
    good = save_policy(random_gru_policy(WORLD, 6, seed=2), tmp_path / "good.npz")
    bad = _rewrite(good, tmp_path / "bad.npz", lambda a, m: (a.__setitem__("w_out", a["w_out"].copy()), change(a, m)))
    with pytest.raises(PolicyError) as ei:
        load_policy(bad)
    msg = str(ei.value)
    assert "\n" not in msg and str(bad) in msg and needle in msg, msg


def test_float_step_matches_the_gru_equations():
    """GRUPolicy.step is PyTorch's GRU cell (r, z, n) written out by hand, and u is clip01 of the new state's output."""
    p = random_gru_policy(WORLD, 5, seed=7, scale=3.0)
    rng = np.random.default_rng(0)
    x, h = rng.normal(size=(4, p.in_dim)), rng.uniform(-1, 1, (4, 5))
    sig = lambda v: 1 / (1 + np.exp(-v))  # noqa: E731
    W_ir, W_iz, W_in = np.split(p.w_ih.astype(np.float64), 3)
    W_hr, W_hz, W_hn = np.split(p.w_hh.astype(np.float64), 3)
    b_ir, b_iz, b_in = np.split(p.b_ih.astype(np.float64), 3)
    b_hr, b_hz, b_hn = np.split(p.b_hh.astype(np.float64), 3)
    r = sig(x @ W_ir.T + b_ir + h @ W_hr.T + b_hr)
    z = sig(x @ W_iz.T + b_iz + h @ W_hz.T + b_hz)
    n = np.tanh(x @ W_in.T + b_in + r * (h @ W_hn.T + b_hn))
    h2 = (1 - z) * n + z * h
    u, got_h = p.step(x, h)
    np.testing.assert_allclose(got_h, h2, atol=1e-12)
    np.testing.assert_allclose(u, np.clip(h2 @ p.w_out.T + p.b_out, 0, 1), atol=1e-12)


# --- the int8 cell --------------------------------------------------------------------------
def _cell_reference(cell: QuantGRUCell, x: list[int], h: list[int]) -> list[int]:
    """The module doc's GRU semantics with Python integers, one unit at a time."""
    def dense(layer, v):
        out = []
        for j in range(layer.w.shape[0]):
            acc = int(layer.b[j]) + sum(int(w) * int(a) for w, a in zip(layer.w[j], v))
            s = int(layer.shift[j])
            q = (acc + (1 << (s - 1))) >> s if s else acc  # Python >> floors: half-up rounding
            out.append(min(max(q, -128), 127))
        return out

    def rr(a, s):
        return (a + (1 << (s - 1))) >> s if s else a

    a_r, a_z = dense(cell.r, x + h), dense(cell.z, x + h)
    nx, nh = dense(cell.nx, x), dense(cell.nh, h)
    out = []
    for j in range(len(h)):
        r, k = int(cell.r_table[a_r[j] + 128]), int(cell.k_table[a_z[j] + 128])
        p = min(max(nx[j] * 2 ** cell.nx_shift + rr(r * nh[j], cell.rn_shift), -128), 127)
        n = int(cell.n_table[p + 128])
        out.append(min(max(h[j] + rr(k * (n - h[j]), 8), -128), 127))
    return out


def test_int_cell_equals_a_scalar_reference():
    """QuantGRUCell.step equals a unit-by-unit Python-integer implementation on extreme and random inputs."""
    _, qp = small_qgru(hidden=6, scale=4.0)
    rng = np.random.default_rng(1)
    xs = np.concatenate([rng.integers(-128, 128, (40, qp.in_dim)), np.full((1, qp.in_dim), -128),
                         np.full((1, qp.in_dim), 127)])
    hs = np.concatenate([rng.integers(-128, 128, (40, 6)), np.full((1, 6), 127), np.full((1, 6), -128)])
    got = qp.cell.step(xs, hs)
    want = np.array([_cell_reference(qp.cell, x.tolist(), h.tolist()) for x, h in zip(xs, hs)])
    np.testing.assert_array_equal(got, want)


def test_state_update_stays_between_h_and_n():
    """h' lies between h and the candidate n for every state and candidate (the saturation never acts)."""
    _, qp = small_qgru(hidden=4)
    g = qp.cell.gates(np.zeros((1, qp.in_dim), np.int64), np.zeros((1, 4), np.int64))
    assert set(g) >= {"a_r", "a_z", "r", "k", "n", "h"}
    h, n = np.meshgrid(np.arange(-128, 128), np.arange(-128, 128), indexing="ij")
    for k in (0, 1, 77, 128, 254, 255):
        h2 = h + numfmt.rshift_round(k * (n - h), numfmt.GATE_EXP)
        assert np.all((h2 >= np.minimum(h, n)) & (h2 <= np.maximum(h, n)))
    np.testing.assert_array_equal(h + numfmt.rshift_round(0 * (n - h), 8), h)  # k = 0 keeps h bit for bit


def test_gate_tables():
    """σ and 1 - σ tables: uint8 at exponent 8, monotone, saturating to exactly 0 and 255 at the ends."""
    r, k = numfmt.gate_table(4), numfmt.gate_table(4, complement=True)
    assert r.dtype == k.dtype == np.uint8 and r.shape == (256,)
    assert np.all(np.diff(r.astype(int)) >= 0) and np.all(np.diff(k.astype(int)) <= 0)
    assert (r[0], r[255], k[0], k[255]) == (0, 255, 255, 0)
    assert r[128] == 128 and k[128] == 128


# --- quantiser ----------------------------------------------------------------------------
def test_quantized_gru_tracks_the_float_policy():
    """On calibration data the int8 GRU's commands stay within a few LSB of the float ones, free-running too."""
    p, qp = small_qgru(hidden=16, scale=1.5)
    cal = calibration_from_sequences(p, random_sequences(WORLD, 12, 60, 9))
    rep = gru_error_report(p, qp, cal)
    assert rep.step_err["u"][0] < 0.03 and rep.step_err["h'"][1] < 0.01, rep.table()
    assert rep.du_mean < 0.01 and rep.drift["h"][1] < 0.02, rep.table()
    assert "free-running" in rep.table() and rep.to_dict()["kind"] == "gru"
    c = qp.cell
    assert c.rn_shift == numfmt.GATE_EXP + c.nh.e_out - c.e_n and c.e_n == c.nx.e_out + c.nx_shift
    assert c.r.e_out >= numfmt.SIGMOID_SAT_EXP and c.e_n >= numfmt.TANH_SAT_EXP
    assert all(a < 2 ** 31 for a in qp.acc_max) and len(qp.layers) == 5


def test_hidden_columns_are_scaled_to_the_input_exponent():
    """The r gate's h columns are quantised from W_hr * 2^(e_in - 7): one accumulator exponent for [x, h]."""
    p, qp = small_qgru(hidden=4)
    D = qp.in_dim
    ew = qp.cell.r.shift.astype(np.int64) + qp.cell.r.e_out - qp.e_in  # per-row weight exponent
    W = np.concatenate([p.w_ih[:4], p.w_hh[:4] * 2.0 ** (qp.e_in - numfmt.HIDDEN_EXP)], 1)
    np.testing.assert_array_equal(qp.cell.r.w, numfmt.quantize(W * np.ldexp(1.0, ew)[:, None], 0))
    assert qp.cell.r.w.shape == (4, D + 4)


def test_calibrate_rolls_out_the_float_policy_and_dispatches():
    """export.quantize's calibrate / quantize_policy / error_report and the budget accept a GRU policy."""
    p = random_gru_policy(WORLD, 8, seed=5)
    cal = calibrate(p, episodes=1, n_robots=(3,), seed=2, steps=12)
    assert cal.seqs.shape == (3, 12, WORLD.tuple_dim) and cal.n == 36
    np.testing.assert_array_equal(cal.seqs[:, 0, :2], 0)  # a_0 = 0 (Algorithm 5)
    again = calibrate(p, episodes=1, n_robots=(3,), seed=2, steps=12)
    np.testing.assert_array_equal(again.seqs, cal.seqs)
    u = cal.values["u"].reshape(3, 12, 2)
    np.testing.assert_allclose(cal.seqs[:, 1:, :2], u[:, :-1], atol=1e-6)  # the next input holds this action
    qp = quantize_policy(p, cal)
    assert isinstance(qp, QuantizedGRU)
    assert error_report(p, qp, cal).n_samples == 36
    assert bud.for_policy(p).kind is GRU and bud.for_quantized(qp).layer_sizes == (16, 8, 2)


# --- emulator -----------------------------------------------------------------------------
def test_emulator_carries_the_hidden_state():
    """The emulator's commands are step_int chained over its own observations with x = [ACT[q_prev], obs]."""
    w = preset("kilobot", period_ticks=5)
    _, qp = small_qgru(hidden=8, world=w)
    rng = np.random.default_rng(np.random.SeedSequence(4))
    inputs = random_inputs(rng, w.period_ticks, (0,), StreamSpec(n_robots=12, n_steps=30, emitter_p=0.0))
    out = FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs)
    obs = out.obs.astype(np.int64)  # (R, S, obs_dim)
    h, q_prev = qp.initial_state(12), np.zeros((12, 2), np.int64)
    for t in range(obs.shape[1]):
        x = np.concatenate([qp.action_table.astype(np.int64)[q_prev], obs[:, t]], 1)
        q, h = qp.step_int(x, h)
        np.testing.assert_array_equal(out.commands[:, t], q)
        q_prev = q.astype(np.int64)
    assert np.unique(out.commands).size > 20


def test_swarm_policy_feeds_back_its_actions():
    """StatefulActor passes [previous action, obs] and restarts from zero state and zero action on reset."""
    seen = []

    def step(x, state):
        seen.append(x.copy())
        return np.full((x.shape[0], 2), 0.25 + state), state + 0.5

    pol = StatefulActor(step, lambda R: 0.0, WORLD)
    pol.reset(2, 3)
    obs = np.ones((2, 3, WORLD.obs_dim), np.float32)
    a1, a2 = pol.act(obs), pol.act(obs)
    np.testing.assert_array_equal(seen[0][:, :2], 0)
    np.testing.assert_array_equal(seen[1][:, :2], a1.reshape(6, 2))
    assert np.all(a2 == 0.75) and a1.shape == (2, 3, 2)
    pol.reset(2, 3)
    pol.act(obs)
    np.testing.assert_array_equal(seen[2][:, :2], 0)


# --- budget -------------------------------------------------------------------------------
def test_gru_budget_items_and_suggestion():
    """The GRU budget counts the five layers' weights, rows, gate tables and the hidden state; too big says what fits."""
    b = bud.estimate(GRU, WORLD, HiddenArch(32))
    items = {i.name: i.bytes for i in b.items}
    D, H = WORLD.tuple_dim, 32
    assert items["weights int8"] == 2 * H * (D + H) + H * D + H * H + 2 * H
    assert items["biases int32"] == 4 * (4 * H + 2) and items["gate tables"] == 768
    assert items["hidden state + input"] == H + D and b.ok and "GRU actor" in b.table()
    big = bud.estimate(GRU, WORLD, HiddenArch(120))
    best = bud.largest(GRU, WORLD, GRU.resizes(WORLD, HiddenArch(120))[0])
    assert not big.ok and 32 <= best < 120 and big.suggest() == [f"a GRU of <= {best} hidden units"]
    assert bud.estimate(GRU, WORLD, HiddenArch(best)).ok and not bud.estimate(GRU, WORLD, HiddenArch(best + 1)).ok
