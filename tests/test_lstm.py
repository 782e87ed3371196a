"""The LSTM actor kind without a compiler: artifact, float cell, int8 cell and its overflow argument, quantiser,
emulator, budget."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from export.cli.main import main
from export.codegen import budget as bud
from export.codegen.render import POLICY_FILE, render_firmware
from export.quantize import calibrate, error_report, quantize_policy
from export.verify.emulator import FirmwareEmulator
from export.verify.hostbuild import StreamSpec, random_inputs
from kiloforge import numfmt
from kiloforge.actors.base import HiddenArch
from kiloforge.actors.lstm import (CELL_EXP, CELL_MAX, LSTM, LSTMPolicy, QuantizedLSTM, QuantLSTMCell,
                                   lstm_error_report, quantize_lstm, random_lstm_policy)
from kiloforge.actors.recurrent import ARRAYS, calibration_from_sequences
from kiloforge.errors import PolicyError
from kiloforge.policies import load_policy, save_policy
from sim.config import preset
from tests.fixtures import random_sequences

WORLD = preset("kilobot")


def small_qlstm(hidden: int = 8, seed: int = 1, scale: float = 2.0, world=WORLD) -> tuple[LSTMPolicy, QuantizedLSTM]:
    p = random_lstm_policy(world, hidden, seed=seed, scale=scale)
    return p, quantize_lstm(p, calibration_from_sequences(p, random_sequences(world, 16, 40, seed)))


# --- artifact -----------------------------------------------------------------------------
def test_round_trip_same_bytes_and_hash(tmp_path):
    """save_policy / load_policy round-trip an LSTMPolicy: equal arrays, world, hash; same policy, same bytes."""
    p = random_lstm_policy(WORLD, 12, seed=3)
    a = save_policy(p, tmp_path / "a.npz")
    q = load_policy(a)
    assert isinstance(q, LSTMPolicy) and q.hash == p.hash and q.world == p.world and q.provenance == p.provenance
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(q, name), getattr(p, name))
    assert save_policy(p, tmp_path / "b.npz").read_bytes() == a.read_bytes()
    assert q.meta()["kind"] == "lstm" and q.meta()["gate_order"] == "ifgo"


@pytest.mark.parametrize("change, needle", [
    (lambda a, m: a.pop("w_hh"), "lacks array(s) w_hh"),
    (lambda a, m: a.__setitem__("w_hh", a["w_hh"][:-1]), "w_hh must be (4H, H)"),
    (lambda a, m: m.__setitem__("gate_order", "ifog"), "gate order"),
    (lambda a, m: m.__setitem__("hidden", 7), "meta says hidden 7"),
])
def test_malformed_files_give_one_line_errors(tmp_path, change, needle):
    """Each corrupted LSTM file raises PolicyError with one line naming the file and the problem."""
    good = save_policy(random_lstm_policy(WORLD, 6, seed=2), tmp_path / "good.npz")
    with np.load(good, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("meta").tobytes())
    change(arrays, meta)
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    bad = tmp_path / "bad.npz"
    with open(bad, "wb") as f:
        np.savez(f, **arrays)
    with pytest.raises(PolicyError) as ei:
        load_policy(bad)
    msg = str(ei.value)
    assert "\n" not in msg and str(bad) in msg and needle in msg, msg


# --- float cell -----------------------------------------------------------------------------
def test_float_step_matches_the_lstm_equations():
    """LSTMPolicy.step is PyTorch's LSTM cell (i, f, g, o) written out by hand; u is clip01 of the output."""
    p = random_lstm_policy(WORLD, 5, seed=7, scale=3.0)
    rng = np.random.default_rng(0)
    x, h, c = rng.normal(size=(4, p.in_dim)), rng.uniform(-1, 1, (4, 5)), rng.normal(0, 2, (4, 5))
    sig = lambda v: 1 / (1 + np.exp(-v))  # noqa: E731
    W_i, W_f, W_g, W_o = np.split(p.w_ih.astype(np.float64), 4)
    U_i, U_f, U_g, U_o = np.split(p.w_hh.astype(np.float64), 4)
    b = p.b_ih.astype(np.float64) + p.b_hh
    b_i, b_f, b_g, b_o = np.split(b, 4)
    i, f = sig(x @ W_i.T + h @ U_i.T + b_i), sig(x @ W_f.T + h @ U_f.T + b_f)
    g, o = np.tanh(x @ W_g.T + h @ U_g.T + b_g), sig(x @ W_o.T + h @ U_o.T + b_o)
    c2 = f * c + i * g
    h2 = o * np.tanh(c2)
    u, s = p.step(x, np.concatenate([h, c], 1))
    np.testing.assert_allclose(s, np.concatenate([h2, c2], 1), atol=1e-12)
    np.testing.assert_allclose(u, np.clip(h2 @ p.w_out.T + p.b_out, 0, 1), atol=1e-12)


def test_torch_lstm_actor_and_its_artifact_agree():
    """learn.recurrent.LSTMActor's artifact steps to the same clipped actions and states as the torch actor."""
    torch = pytest.importorskip("torch")
    from learn.recurrent import LSTMActor

    torch.manual_seed(0)
    actor = LSTMActor(WORLD.tuple_dim, 7)
    with torch.no_grad():
        actor.out.weight.mul_(300.0)  # outputs spread over [0, 1] and beyond
    p = actor.policy(WORLD, {"notes": "test"})
    xs = random_sequences(WORLD, 3, 12, 5)
    s_t, s_np = actor.initial_state(3), p.initial_state(3)
    with torch.no_grad():
        states = actor.states(torch.from_numpy(xs), s_t)
        a_win, s_end = actor(torch.from_numpy(xs), s_t)
        for t in range(xs.shape[1]):
            a, s_t = actor.step(torch.from_numpy(xs[:, t]), s_t)
            u, s_np = p.step(xs[:, t], s_np)
            np.testing.assert_allclose(u, np.clip(a.double().numpy(), 0, 1), atol=2e-5)
            np.testing.assert_allclose(s_np, s_t.double().numpy(), atol=2e-5)
            np.testing.assert_allclose(states[:, t].numpy(), s_t.numpy(), atol=1e-6)
        np.testing.assert_allclose(a_win[:, -1].numpy(), a.numpy(), atol=1e-6)
        np.testing.assert_allclose(s_end.numpy(), s_t.numpy(), atol=1e-6)


# --- the int8 cell ------------------------------------------------------------------------------
def _cell_reference(cell: QuantLSTMCell, x: list[int], h: list[int], c: list[int]) -> tuple[list[int], list[int]]:
    """The module doc's LSTM semantics with Python integers, one unit at a time."""
    def rr(a, s):
        return (a + (1 << (s - 1))) >> s if s else a  # Python >> floors: half-up rounding

    def dense(layer, v):
        return [min(max(rr(int(layer.b[j]) + sum(int(w) * int(a) for w, a in zip(layer.w[j], v)),
                           int(layer.shift[j])), -128), 127) for j in range(layer.w.shape[0])]

    xh = x + h
    a = {k: dense(getattr(cell, k), xh) for k in "ifgo"}
    h2, c2 = [], []
    for j in range(len(h)):
        i, f = int(cell.i_table[a["i"][j] + 128]), int(cell.f_table[a["f"][j] + 128])
        g, o = int(cell.g_table[a["g"][j] + 128]), int(cell.o_table[a["o"][j] + 128])
        cj = min(max(rr(f * c[j], 8) + i * g, -CELL_MAX), CELL_MAX)
        p = min(max(rr(cj, CELL_EXP - cell.e_c), -128), 127)
        t = int(cell.c_table[p + 128])
        h2.append(min(max(rr(o * t, 8), -128), 127))
        c2.append(cj)
    return h2, c2


def test_int_cell_equals_a_scalar_reference():
    """QuantLSTMCell.gates equals a unit-by-unit Python-integer implementation on extreme and random inputs."""
    _, qp = small_qlstm(hidden=6, scale=4.0)
    rng = np.random.default_rng(1)
    n = 40
    xs = np.concatenate([rng.integers(-128, 128, (n, qp.in_dim)), np.full((2, qp.in_dim), -128)])
    hs = np.concatenate([rng.integers(-128, 128, (n, 6)), np.full((2, 6), 127)])
    cs = np.concatenate([rng.integers(-CELL_MAX, CELL_MAX + 1, (n, 6)), np.array([[CELL_MAX] * 6, [-CELL_MAX] * 6])])
    g = qp.cell.gates(xs, hs, cs)
    for k in range(len(xs)):
        want_h, want_c = _cell_reference(qp.cell, xs[k].tolist(), hs[k].tolist(), cs[k].tolist())
        assert g["h"][k].tolist() == want_h and g["c"][k].tolist() == want_c, k


def test_cell_state_bound_holds_for_every_gate_value():
    """The overflow argument: from |c| <= CELL_MAX, every f, i, g gives |rshift_round(f c, 8) + i g| <= CELL_MAX
    and |f c| < 2^31, so the cell state's saturation never acts; the bound is tight within i g's range."""
    f = np.arange(256, dtype=np.int64)[:, None]  # (256, 1) uint8 forget gate
    ig = np.arange(-128, 128, dtype=np.int64)[None, :] * 255  # (1, 256) i g with i = 255 (the largest |i g|)
    for c in (CELL_MAX, -CELL_MAX, CELL_MAX - 1, 1 << 22, -(1 << 22), 0):
        assert np.all(np.abs(f * c) < numfmt.ACC32_LIMIT)
        c2 = numfmt.rshift_round(f * c, numfmt.GATE_EXP) + ig
        assert np.abs(c2).max() <= CELL_MAX, c
    assert np.abs(numfmt.rshift_round(255 * CELL_MAX, 8) + 255 * 127) > CELL_MAX - 400  # not a loose bound


def test_saturated_gates_never_saturate_the_state():
    """A cell whose gates all read the extremes (f = 255/256, i = 255/256, g = +-1) for 600 steps keeps
    |c| within CELL_MAX without clamping and h within int8 without clamping (it passes 85% of the bound by then)."""
    _, qp = small_qlstm(hidden=4)
    c = qp.cell
    full = np.full(256, 255, np.uint8)
    for g_val in (127, -128):
        cell = replace(c, i_table=full, f_table=full, o_table=full, g_table=np.full(256, g_val, np.int8))
        x, h, cs = np.zeros((1, qp.in_dim), np.int64), np.zeros((1, 4), np.int64), np.zeros((1, 4), np.int64)
        peak = 0
        for _ in range(600):
            v = cell.gates(x, h, cs)
            raw = numfmt.rshift_round(v["f"] * cs, numfmt.GATE_EXP) + v["i"] * v["g"]
            np.testing.assert_array_equal(raw, v["c"])  # the clamp did nothing
            h, cs = v["h"], v["c"]
            peak = max(peak, int(np.abs(cs).max()))
        assert 0.85 * CELL_MAX < peak <= CELL_MAX and np.abs(h).max() <= 127
        assert np.all(np.sign(cs) == np.sign(g_val))


# --- quantiser ----------------------------------------------------------------------------
def test_quantized_lstm_tracks_the_float_policy():
    """On calibration data the int8 LSTM's commands stay within a few LSB of the float ones, free-running too."""
    p, qp = small_qlstm(hidden=16, scale=1.5)
    cal = calibration_from_sequences(p, random_sequences(WORLD, 12, 60, 9))
    rep = lstm_error_report(p, qp, cal)
    assert rep.step_err["u"][0] < 0.03 and rep.step_err["h'"][1] < 0.01, rep.table()
    assert rep.du_mean < 0.01 and rep.drift["c"][0] < 0.2, rep.table()
    assert "free-running" in rep.table() and rep.to_dict()["kind"] == "lstm"
    cc = qp.cell
    assert min(cc.i.e_out, cc.f.e_out, cc.o.e_out) >= numfmt.SIGMOID_SAT_EXP and cc.g.e_out >= numfmt.TANH_SAT_EXP
    assert numfmt.TANH_SAT_EXP <= cc.e_c <= CELL_EXP and len(qp.layers) == 5


def test_calibrate_quantize_report_and_budget_dispatch():
    """export.quantize's calibrate / quantize_policy / error_report and the budget take an LSTM policy."""
    p = random_lstm_policy(WORLD, 8, seed=5)
    cal = calibrate(p, episodes=1, n_robots=(3,), seed=2, steps=12)
    assert cal.seqs.shape == (3, 12, WORLD.tuple_dim) and cal.states.shape == (3, 12, 16)
    np.testing.assert_array_equal(cal.seqs[:, 0, :2], 0)  # a_0 = 0 (Algorithm 5)
    qp = quantize_policy(p, cal)
    assert isinstance(qp, QuantizedLSTM) and error_report(p, qp, cal).n_samples == 36
    assert bud.for_policy(p).kind is LSTM and bud.for_quantized(qp).layer_sizes == (16, 8, 2)


# --- emulator -----------------------------------------------------------------------------
def test_emulator_carries_the_state():
    """The emulator's commands are step_int chained over its own observations with x = [ACT[q_prev], obs]."""
    w = preset("kilobot", period_ticks=5)
    _, qp = small_qlstm(hidden=8, world=w)
    rng = np.random.default_rng(np.random.SeedSequence(4))
    inputs = random_inputs(rng, w.period_ticks, (0,), StreamSpec(n_robots=12, n_steps=30, emitter_p=0.0))
    out = FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs)
    obs = out.obs.astype(np.int64)
    s, q_prev = qp.initial_state(12), np.zeros((12, 2), np.int64)
    for t in range(obs.shape[1]):
        q, s = qp.step_int(np.concatenate([qp.action_table.astype(np.int64)[q_prev], obs[:, t]], 1), s)
        np.testing.assert_array_equal(out.commands[:, t], q)
        q_prev = q.astype(np.int64)
    assert np.unique(out.commands).size > 20 and np.abs(s[:, 8:]).max() > 1 << CELL_EXP - 3


# --- budget and render ------------------------------------------------------------------------
def test_lstm_budget_items_and_suggestion():
    """The LSTM budget counts five layers, five tables, h + c + x; too big names the largest LSTM that fits."""
    H, D = 32, WORLD.tuple_dim
    b = bud.estimate(LSTM, WORLD, HiddenArch(H))
    items = {i.name: i.bytes for i in b.items}
    assert items["weights int8"] == 4 * H * (D + H) + 2 * H and items["biases int32"] == 4 * (4 * H + 2)
    assert items["gate tables"] == 5 * 256 and items["hidden + cell state + input"] == H + 4 * H + D
    assert b.ok and "LSTM actor" in b.table()
    big = bud.estimate(LSTM, WORLD, HiddenArch(120))
    best = bud.largest(LSTM, WORLD, LSTM.resizes(WORLD, HiddenArch(120))[0])
    assert not big.ok and 32 <= best < 120 and big.suggest() == [f"an LSTM of <= {best} hidden units"]
    assert bud.estimate(LSTM, WORLD, HiddenArch(best)).ok and not bud.estimate(LSTM, WORLD, HiddenArch(best + 1)).ok


def test_budget_cli_lstm(capsys):
    """python -m export budget --lstm 32 fits (exit 0); --lstm 120 does not (exit 1) and names what fits."""
    assert main(["budget", "--lstm", "32"]) == 0
    out = capsys.readouterr().out
    assert "LSTM actor" in out and "FITS" in out
    assert main(["budget", "--lstm", "120"]) == 1
    assert "would fit: an LSTM of <= " in capsys.readouterr().out
    assert main(["budget", "--lstm", "8", "--gru", "8"]) == 2
    assert "one actor" in capsys.readouterr().err


def test_render_keeps_h_and_c_in_sram():
    """The LSTM program holds x, h and the int32 cell state, names its exponents and five layers."""
    _, qp = small_qlstm(hidden=16)
    a = render_firmware(qp, generator_version="t")[POLICY_FILE]
    assert a == render_firmware(qp, generator_version="t")[POLICY_FILE]
    assert "int8_t h[KF_HIDDEN];" in a and "int32_t c[KF_HIDDEN];" in a and "s->hist" not in a
    assert f"#define KF_C_SHIFT {qp.cell.c_shift}u" in a and "kf_lstm_cell(" in a and "kf_lstm_hidden(" in a
    assert "LSTM: input 16" in a and f"e_c {qp.cell.e_c}" in a
    for name in ("KF_LI", "KF_LF", "KF_LG", "KF_LO", "KF_LOUT", "KF_GATE_I", "KF_GATE_F", "KF_TANH_G", "KF_GATE_O",
                 "KF_TANH_C"):
        assert name in a, name


def test_export_cli_writes_an_lstm_program(tmp_path, capsys):
    """`python -m export --policy lstm.npz` calibrates, quantises, checks the budget and writes C + manifest."""
    p = random_lstm_policy(preset("kilobot"), 10, seed=6, scale=2.0)
    path = save_policy(p, tmp_path / "lstm.npz")
    out = tmp_path / "kilobot_policy.c"
    assert main(["--policy", str(path), "--out", str(out), "--robots-calib", "3", "--calib-steps", "20",
                 "--quiet", "--no-avr"]) == 0
    text = capsys.readouterr().out
    assert "LSTM quantisation error" in text and "LSTM actor" in text and "free-running" in text
    assert "#define KF_HIDDEN 10u" in out.read_text()
    man = json.loads(Path(str(out) + ".manifest.json").read_text())
    assert man["kind"] == "lstm" and man["quantization"]["kind"] == "lstm" and man["budget"]["kind"] == "lstm"
