"""Calibration and quantisation of an MLP policy into the int8 format (export.quantize, kiloforge.actors.mlp)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from export.quantize import calibrate, error_report, quantize_policy
from tests.fixtures import init_policy
from kiloforge import numfmt
from kiloforge.actors.mlp import MLPPolicy, calibration_from_inputs
from kiloforge.errors import KiloforgeError, QuantizeError
from sim.config import preset
from sim.motion import action_to_u8

TINY_WORLD = preset("thesis", n_rbf=1)  # obs_dim 4, tuple_dim 6


def rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(seed))


def random_inputs(p: MLPPolicy, n: int, seed: int = 0, scale: float = 1.0) -> np.ndarray:
    return rng(seed).uniform(-scale, scale, size=(n, p.in_dim))


def test_exponents_follow_calibration_ranges():
    """e_in, e_out and e_act are the largest power-of-two exponents covering the calibrated ranges."""
    p = init_policy(TINY_WORLD, 2, (5,), "tanh", seed=3, out_scale=0.3)
    for scale, want_e_in in ((0.5, 6), (1.0, 6), (3.0, 5), (20.0, 2)):  # capped at DEFAULT_INPUT_EXP
        calib = calibration_from_inputs(p, random_inputs(p, 400, scale=scale))
        qp = quantize_policy(p, calib)
        assert qp.e_in == want_e_in == min(numfmt.DEFAULT_INPUT_EXP, numfmt.choose_exp(np.abs(calib.inputs).max()))
        l0 = qp.layers[0]
        assert l0.e_out == numfmt.choose_exp(np.abs(calib.pre[0]).max())
        assert l0.e_act == numfmt.choose_exp(np.abs(calib.post[0]).max())
        np.testing.assert_array_equal(l0.table, numfmt.act_table("tanh", l0.e_out, l0.e_act))
        assert qp.layers[1].e_in == l0.e_act


def test_percentile_and_headroom_change_exponents():
    """A headroom of 4 lowers the input exponent by 2; a low percentile raises a layer's exponent."""
    p = init_policy(TINY_WORLD, 2, (5,), "relu", seed=3, out_scale=0.3)
    x = random_inputs(p, 500, scale=3.0)
    x[0, 0] = 30.0  # one outlier
    calib = calibration_from_inputs(p, x)
    base = quantize_policy(p, calib)
    assert quantize_policy(p, calib, headroom=4.0).e_in == base.e_in - 2
    assert quantize_policy(p, calib, percentile=99.0).e_in > base.e_in
    with pytest.raises(QuantizeError):
        quantize_policy(p, calib, percentile=0.0)


def test_per_row_weight_exponents_use_int8_range():
    """Every non-zero weight row uses at least half the int8 range (per-row power-of-two scales)."""
    p = init_policy(preset("kilobot"), 3, (16, 8), "elu", seed=5, out_scale=0.3)
    w = [np.array(a) for a in p.weights]
    w[0][3] *= 40.0  # a row much larger than the others
    w[0][4] *= 1e-3  # and one much smaller
    p = dataclasses.replace(p, weights=w)
    qp = quantize_policy(p, calibration_from_inputs(p, random_inputs(p, 300)))
    for layer in qp.layers:
        row_max = np.abs(layer.w.astype(np.int64)).max(axis=1)
        assert np.all(row_max[row_max > 0] >= 64), row_max
        assert np.all(row_max <= 127)
        assert np.all((layer.shift >= 0) & (layer.shift <= numfmt.MAX_SHIFT))
    assert len(set(qp.layers[0].shift.tolist())) > 1  # the scaled rows got their own exponents


def test_lossless_case_matches_float_actor():
    """Weights and inputs on the grid: hidden layers are exact and q equals the rounded float command."""
    world = TINY_WORLD
    r = rng(7)
    n_in = world.history_dim(1)  # 6
    w0 = r.choice([-1.0, 0.0, 0.0, 1.0], size=(4, n_in))
    w0[np.arange(4), np.arange(4)] = 1.0  # every row non-zero
    b0 = r.integers(-8, 9, size=4) / 64.0
    c = r.integers(-3, 4, size=(2, 4))
    w1 = (c / 255.0).astype(np.float32)  # 255 * w1 is an integer
    b1 = (r.integers(60, 200, size=2) / 255.0).astype(np.float32)
    p = MLPPolicy([w0.astype(np.float32), w1], [b0.astype(np.float32), b1], ["relu", "identity"], 1, world)
    x = r.integers(-20, 21, size=(3000, n_in)) / 64.0  # on the e_in = 6 grid, |x| < 1/3
    calib = calibration_from_inputs(p, x)
    qp = quantize_policy(p, calib)
    assert qp.e_in == 6
    x_q = qp.quantize_history(x)
    np.testing.assert_array_equal(x_q.astype(np.int64), np.round(x * 64).astype(np.int64))
    hidden = qp.forward_layers(x_q)[0]
    np.testing.assert_array_equal(numfmt.dequantize(hidden, qp.layers[0].e_act), calib.post[0])
    q = qp.forward_int(x_q)
    assert q.dtype == np.uint8 and q.shape == (3000, 2)
    u = p.act(x)
    assert np.all(np.abs(q.astype(np.float64) - 255.0 * u) <= 0.5 + 1e-6)
    tie = np.abs(np.abs(255.0 * u - np.floor(255.0 * u)) - 0.5) < 1e-4
    np.testing.assert_array_equal(q[~tie], action_to_u8(u)[~tie])
    assert (~tie).sum() > 1000


def test_error_report_small_for_random_mlp():
    """A random ELU MLP on realistic inputs: end-to-end |du| is small but not zero."""
    p = init_policy(preset("kilobot"), 10, (32, 32), "elu", seed=11, out_scale=0.3)
    x = np.clip(rng(2).normal(0.3, 0.4, size=(2000, p.in_dim)), -1, 1.5)
    calib = calibration_from_inputs(p, x)
    qp = quantize_policy(p, calib)
    rep = error_report(p, qp, calib)
    assert 0.0 < rep.du_mean < 0.01
    assert rep.du_max < 0.05
    assert rep.same_command > 0.3
    assert len(rep.layers) == 3 and all(r.max_abs < 0.1 for r in rep.layers)
    text = rep.table()
    assert "end to end" in text and f"{rep.du_max:.5f}" in text
    u_int = qp.act_float(calib.inputs)
    np.testing.assert_allclose(np.abs(u_int - p.act(calib.inputs)).max(), rep.du_max)


def test_overflow_refused():
    """A bias too large for any int32 accumulator scale raises QuantizeError naming the layer and row."""
    p = init_policy(TINY_WORLD, 2, (4,), "relu", seed=1, out_scale=0.3)
    b = [np.array(a) for a in p.biases]
    b[1][1] = 1e9  # output bias: 255e9 at exponent >= 0 cannot fit int32
    p = dataclasses.replace(p, biases=b)
    with pytest.raises(QuantizeError, match=r"layer 1 row 1: the int32 accumulator could overflow") as ei:
        quantize_policy(p, calibration_from_inputs(p, random_inputs(p, 50)))
    assert isinstance(ei.value, KiloforgeError) and "\n" not in str(ei.value)


def test_overflow_avoided_by_lowering_row_exponent():
    """A large but representable bias lowers only its row's weight exponent; the proof bound holds."""
    p = init_policy(TINY_WORLD, 2, (4,), "relu", seed=1, out_scale=0.3)
    b = [np.array(a) for a in p.biases]
    w = [np.array(a) for a in p.weights]
    w[0][2] *= 1e-4  # tiny weights: the row's exponent would be large ...
    b[0][2] = 3.0  # ... and the bias at that exponent would not fit int32
    p = dataclasses.replace(p, biases=b, weights=w)
    qp = quantize_policy(p, calibration_from_inputs(p, random_inputs(p, 100)))
    l0 = qp.layers[0]
    s = l0.shift.astype(np.int64)
    x = rng(3).integers(-128, 128, size=(2000, l0.w.shape[1]))  # the bound holds for actual inputs too
    acc = x @ l0.w.astype(np.int64).T + l0.b.astype(np.int64) + numfmt.half_up_constant(s)
    bound = numfmt.acc_bound(l0.w, l0.b, s)
    assert np.all(np.abs(acc) <= bound) and np.all(bound < 2 ** 31) and qp.acc_max[0] == int(bound.max())
    assert bound[2] > 2 ** 29  # the large-bias row sits near the limit: its exponent was lowered
    assert qp.acc24_safe == tuple(bool(np.all(numfmt.acc_bound(l.w, l.b, l.shift) < 2 ** 23)) for l in qp.layers)


def test_sigmoid_output_refused():
    """An output activation the uint8 clamp cannot realise is refused with a one-line error."""
    p = init_policy(TINY_WORLD, 1, (4,), "elu", seed=1)
    p = dataclasses.replace(p, activations=("elu", "sigmoid"))
    with pytest.raises(QuantizeError, match="output activation 'sigmoid'"):
        quantize_policy(p, calibration_from_inputs(p, random_inputs(p, 10)))


def test_tables_and_fields():
    """The sensing tables come from numfmt with the policy's world and e_in; fields are consistent."""
    w = preset("kilobot")
    p = init_policy(w, 4, (8,), "elu", seed=2, out_scale=0.3)
    qp = quantize_policy(p, calibration_from_inputs(p, random_inputs(p, 100)))
    np.testing.assert_array_equal(qp.rbf_table, numfmt.rbf_table(w.rbf_centres_mm, w.rbf_sigma_mm, w.rbf_norm,
                                                                 w.comm_radius_mm, qp.e_in))
    np.testing.assert_array_equal(qp.target_table, numfmt.target_table(w.comm_radius_mm, qp.e_in))
    np.testing.assert_array_equal(qp.action_table, numfmt.action_table(qp.e_in))
    assert qp.policy_hash == p.hash and qp.t_prev == 4 and qp.world == w
    assert qp.layer_sizes == p.layer_sizes and qp.one_q == 1 << qp.e_in
    out = qp.layers[-1]
    assert (out.lo, out.hi, out.e_out, out.activation) == (0, 255, 0, "identity")
    assert qp.summary()["layers"][0]["n_in"] == p.in_dim


def test_forward_int_matches_numfmt_layers():
    """forward_int is the chain of numfmt.QuantLayer.forward on int8 inputs (batch shape kept)."""
    p = init_policy(preset("kilobot"), 2, (6, 5), "tanh", seed=4, out_scale=0.3)
    qp = quantize_policy(p, calibration_from_inputs(p, random_inputs(p, 100)))
    x_q = rng(9).integers(-128, 128, size=(3, 4, p.in_dim)).astype(np.int8)
    y = x_q.astype(np.int64)
    for layer in qp.layers:
        y = layer.forward(y)
    got = qp.forward_int(x_q)
    assert got.shape == (3, 4, 2) and got.dtype == np.uint8
    np.testing.assert_array_equal(got, y.astype(np.uint8))


def test_calibrate_records_rollouts_deterministically():
    """calibrate() records steps x robots rows per episode, every layer's values, same seed same data."""
    w = preset("kilobot")
    p = init_policy(w, 3, (8,), "elu", seed=2, out_scale=0.3)
    a = calibrate(p, episodes=1, n_robots=(2, 3), seed=5, steps=4)
    b = calibrate(p, episodes=1, n_robots=(2, 3), seed=5, steps=4)
    assert a.inputs.shape == (4 * (2 + 3), p.in_dim)
    assert [x.shape for x in a.pre] == [(20, 8), (20, 2)]
    np.testing.assert_array_equal(a.inputs, b.inputs)
    np.testing.assert_allclose(a.post[-1], p.act(a.inputs))
    # history layout: the newest tuple's observation part is a valid observation (target in [-1, 1])
    newest = a.inputs[:, -w.tuple_dim:]
    assert np.all(np.abs(newest[:, 2 + 1]) <= 1.0)
    assert a.info["n_robots"] == [2, 3] and a.info["steps"] == 4


def test_large_weights_lower_hidden_exponent():
    """A hidden row with weights too large for the calibrated output exponent coarsens e_out so shifts stay >= 0."""
    p = init_policy(TINY_WORLD, 2, (4,), "relu", seed=1, out_scale=0.3)
    w = [np.array(a) for a in p.weights]
    w[0][1, 0] = 200.0  # input 0 is always 0 in calibration, so the range does not see this weight
    p = dataclasses.replace(p, weights=w)
    x = random_inputs(p, 200, scale=0.5)
    x[:, 0] = 0.0
    calib = calibration_from_inputs(p, x)
    qp = quantize_policy(p, calib)
    l0 = qp.layers[0]
    assert numfmt.choose_exp(np.abs(calib.pre[0]).max()) > l0.e_out  # lowered from the calibrated choice
    assert int(l0.shift[1]) == 0 and int(l0.shift.min()) == 0  # row 1 (the large one) sets the new e_out
    assert qp.layers[1].e_in == l0.e_act == l0.e_out


def test_output_weights_too_large_refused():
    """Output weights that would need a negative shift are refused with a one-line message."""
    p = init_policy(TINY_WORLD, 1, (4,), "relu", seed=1, out_scale=0.3)
    w = [np.array(a) for a in p.weights]
    w[1][0, 0] = 1e4  # 255e4 at exponent -9 or less; a hidden exponent >= 0 cannot reach shift >= 0
    p = dataclasses.replace(p, weights=w)
    with pytest.raises(QuantizeError, match="layer 1 row 0: weights up to"):
        quantize_policy(p, calibration_from_inputs(p, random_inputs(p, 50)))
