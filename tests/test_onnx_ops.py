"""ONNX import, op by op: every supported op and attribute combination computes what onnxruntime
computes on random inputs (a differential test each); what the importer does not support is refused by name."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from export.interop.onnx_import import OnnxImportError, load_onnx_policy  # noqa: E402
from kiloforge.actors.mlp import MLPPolicy  # noqa: E402
from sim.config import preset  # noqa: E402

WORLD = preset("thesis")
D = WORLD.history_dim(1)  #: input width with t_prev = 1
H = 12  #: hidden units
WORLD_JSON = {"world": "thesis", "t_prev": 1}
TOL = 1e-4  #: float32 (onnxruntime) vs float64 (the import's reference) on outputs of magnitude up to ~50


def _rng(tag: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([917, tag]))


def _model(nodes, inits, opset=17, out="y", in_type=TensorProto.FLOAT):
    g = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", in_type, ["n", D])],
                          [helper.make_tensor_value_info(out, in_type, ["n", 2])],
                          initializer=[numpy_helper.from_array(np.asarray(v), k) for k, v in inits.items()])
    return helper.make_model(g, opset_imports=[helper.make_opsetid("", opset)], ir_version=8)


def _run_both(tmp_path: Path, model, tag: int):
    """(imported policy, inputs, onnxruntime's outputs) on 256 random inputs (both signs, several scales)."""
    path = tmp_path / "m.onnx"
    onnx.save(model, str(path))
    pol = load_onnx_policy(path, WORLD_JSON)
    rng = _rng(tag)
    x = (rng.normal(0, 1, (256, D)) * rng.choice([0.1, 1.0, 4.0], (256, 1))).astype(np.float32)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    y = sess.run(None, {"x": x})[0]
    return pol, x, y


def _check(tmp_path, model, tag, *, linear_out=True):
    """The imported policy's clipped action equals onnxruntime's output clipped to [0, 1]; when the graph
    ends in its last dense layer, the unclipped outputs agree too."""
    pol, x, y = _run_both(tmp_path, model, tag)
    np.testing.assert_allclose(pol.act(x), np.clip(y, 0, 1), rtol=1e-5, atol=TOL)
    if linear_out:
        np.testing.assert_allclose(pol.layer_outputs(x)[-1][0], y, rtol=1e-5, atol=TOL)
    return pol, x, y


def _refused(tmp_path, model, match):
    path = tmp_path / "m.onnx"
    onnx.save(model, str(path))
    with pytest.raises(OnnxImportError, match=match) as ei:
        load_onnx_policy(path, WORLD_JSON)
    assert "\n" not in str(ei.value)


def _weights(tag: int):
    rng = _rng(1000 + tag)
    return (rng.normal(0, 0.5, (H, D)).astype(np.float32), rng.normal(0, 0.3, (H,)).astype(np.float32),
            rng.normal(0, 0.8, (2, H)).astype(np.float32), rng.normal(0, 0.3, (2,)).astype(np.float32))


def _two_layers(first: list, first_out: str, act: list, inits: dict, tag: int, opset=17, tail=()):
    """``first`` (nodes producing ``first_out`` from x) -> ``act`` nodes (a1 from first_out) -> Gemm -> tail."""
    _, _, w2, b2 = _weights(tag)
    inits = dict(inits, w2=w2, b2=b2)
    last = "z2" if tail else "y"
    nodes = first + act + [helper.make_node("Gemm", ["a1", "w2", "b2"], [last], transB=1)] + list(tail)
    return _model(nodes, inits, opset)


# --- dense layers --------------------------------------------------------------------------------
@pytest.mark.parametrize("trans_b", [0, 1])
@pytest.mark.parametrize("alpha, beta", [(1.0, 1.0), (0.5, 1.0), (-2.0, 0.25), (1.5, 0.0)])
@pytest.mark.parametrize("c_shape", [None, "vector", "row", "scalar"])
def test_gemm(tmp_path, trans_b, alpha, beta, c_shape):
    """Gemm with transB 0/1, any alpha and beta, and C absent, (n,), (1, n) or (1,), as onnxruntime computes it."""
    w1, b1, _, _ = _weights(1)
    inits = {"w1": w1 if trans_b else w1.T.copy()}
    ins = ["x", "w1"]
    if c_shape is not None:
        inits["c1"] = {"vector": b1, "row": b1[None, :], "scalar": b1[:1]}[c_shape]
        ins.append("c1")
    gemm = helper.make_node("Gemm", ins, ["z1"], transB=trans_b, alpha=alpha, beta=beta)
    _check(tmp_path, _two_layers([gemm], "z1", [helper.make_node("Relu", ["z1"], ["a1"])], inits, 1), 2)


def test_gemm_trans_a_is_refused(tmp_path):
    """Gemm(transA=1) is refused by name (the data must be [N, D])."""
    w1, b1, _, _ = _weights(1)
    gemm = helper.make_node("Gemm", ["x", "w1", "b1"], ["z1"], transA=1)
    g = _two_layers([gemm], "z1", [helper.make_node("Relu", ["z1"], ["a1"])], {"w1": np.zeros((D, H), np.float32),
                                                                                "b1": b1}, 1)
    _refused(tmp_path, g, "transA=1")


@pytest.mark.parametrize("bias", ["add", "add_commuted", "add_row", "add_scalar", "sub", "none"])
def test_matmul_with_bias(tmp_path, bias):
    """MatMul of a constant weight, then Add (either order, (n,), (1, n) or scalar bias) or Sub, as onnxruntime."""
    w1, b1, _, _ = _weights(3)
    nodes = [helper.make_node("MatMul", ["x", "w1"], ["m1"])]
    inits = {"w1": w1.T.copy()}
    if bias == "none":
        out = "m1"
    else:
        inits["b1"] = {"add_row": b1[None, :], "add_scalar": np.float32(0.3)}.get(bias, b1)
        op = "Sub" if bias == "sub" else "Add"
        ins = ["b1", "m1"] if bias == "add_commuted" else ["m1", "b1"]
        nodes.append(helper.make_node(op, ins, ["z1"]))
        out = "z1"
    _check(tmp_path, _two_layers(nodes, out, [helper.make_node("Tanh", [out], ["a1"])], inits, 3), 4)


def test_constant_minus_data_is_refused(tmp_path):
    """Sub(b, x) (not x - b) is refused."""
    w1, b1, _, _ = _weights(3)
    nodes = [helper.make_node("MatMul", ["x", "w1"], ["m1"]), helper.make_node("Sub", ["b1", "m1"], ["z1"])]
    _refused(tmp_path, _two_layers(nodes, "z1", [helper.make_node("Tanh", ["z1"], ["a1"])],
                                   {"w1": w1.T.copy(), "b1": b1}, 3), "first input of Sub")


# --- activations ---------------------------------------------------------------------------------
def _gemm1(tag=5):
    w1, b1, _, _ = _weights(tag)
    return [helper.make_node("Gemm", ["x", "w1", "b1"], ["z1"], transB=1)], {"w1": w1, "b1": b1}


@pytest.mark.parametrize("op, attrs", [("Relu", {}), ("Elu", {}), ("Elu", {"alpha": 1.0}), ("Tanh", {}),
                                       ("Sigmoid", {})])
def test_hidden_activation(tmp_path, op, attrs):
    """Relu, Elu (alpha 1), Tanh and Sigmoid between two dense layers, as onnxruntime."""
    first, inits = _gemm1()
    _check(tmp_path, _two_layers(first, "z1", [helper.make_node(op, ["z1"], ["a1"], **attrs)], inits, 5), 6)


@pytest.mark.parametrize("opset", [10, 13])
def test_clip_zero_inf_is_relu(tmp_path, opset):
    """Clip(0, inf) as a hidden activation (attributes before opset 11, inputs after) is a ReLU."""
    first, inits = _gemm1()
    if opset < 11:
        clip = helper.make_node("Clip", ["z1"], ["a1"], min=0.0)
    else:
        clip = helper.make_node("Clip", ["z1", "lo"], ["a1"])
        inits = dict(inits, lo=np.float32(0.0))
    pol, _, _ = _check(tmp_path, _two_layers(first, "z1", [clip], inits, 5, opset=opset), 7)
    assert pol.activations[0] == "relu"


@pytest.mark.parametrize("op, attrs, match", [
    ("Elu", {"alpha": 0.5}, "alpha=0.5"), ("LeakyRelu", {}, "op LeakyRelu is not supported"),
    ("Softplus", {}, "op Softplus is not supported"), ("HardSigmoid", {}, "op HardSigmoid is not supported"),
    ("Selu", {}, "op Selu is not supported")])
def test_unsupported_activation_semantics_are_refused(tmp_path, op, attrs, match):
    """An activation the firmware cannot compute (or an Elu alpha other than 1) is refused by name."""
    first, inits = _gemm1()
    _refused(tmp_path, _two_layers(first, "z1", [helper.make_node(op, ["z1"], ["a1"], **attrs)], inits, 5), match)


def test_hidden_clip_is_refused(tmp_path):
    """A Clip other than Clip(0, inf) between layers is refused (only after the last layer)."""
    first, inits = _gemm1()
    clip = helper.make_node("Clip", ["z1", "lo", "hi"], ["a1"])
    _refused(tmp_path, _two_layers(first, "z1", [clip], dict(inits, lo=np.float32(-1), hi=np.float32(1)), 5),
             "only supported after the last layer")


# --- after the last layer ------------------------------------------------------------------------
@pytest.mark.parametrize("tail", ["clip01", "clip_wide", "relu", "relu_clip", "identity"])
def test_output_tail(tmp_path, tail):
    """Ops after the last layer that cannot change the clipped action (Clip(lo<=0, hi>=1), Relu, Identity)."""
    first, inits = _gemm1(8)
    nodes = {"clip01": [helper.make_node("Clip", ["z2", "c0", "c1"], ["y"])],
             "clip_wide": [helper.make_node("Clip", ["z2", "cm", "c2"], ["y"])],
             "relu": [helper.make_node("Relu", ["z2"], ["y"])],
             "relu_clip": [helper.make_node("Relu", ["z2"], ["r"]), helper.make_node("Clip", ["r", "c0", "c1"], ["y"])],
             "identity": [helper.make_node("Identity", ["z2"], ["y"])]}[tail]
    inits = dict(inits, c0=np.float32(0), c1=np.float32(1), cm=np.float32(-1), c2=np.float32(2))
    _check(tmp_path, _two_layers(first, "z1", [helper.make_node("Elu", ["z1"], ["a1"])], inits, 8, tail=nodes), 9,
           linear_out=tail == "identity")


@pytest.mark.parametrize("tail, match", [("clip_narrow", r"Clip\(0.2, 1\) is not supported"),
                                         ("sigmoid", "ends in sigmoid"), ("tanh", "ends in tanh")])
def test_output_tail_that_changes_the_action_is_refused(tmp_path, tail, match):
    """A narrower Clip or a squashing function after the last layer is refused."""
    first, inits = _gemm1(8)
    nodes = {"clip_narrow": [helper.make_node("Clip", ["z2", "lo", "c1"], ["y"])],
             "sigmoid": [helper.make_node("Sigmoid", ["z2"], ["y"])],
             "tanh": [helper.make_node("Tanh", ["z2"], ["y"])]}[tail]
    inits = dict(inits, lo=np.float32(0.2), c1=np.float32(1))
    _refused(tmp_path, _two_layers(first, "z1", [helper.make_node("Elu", ["z1"], ["a1"])], inits, 8, tail=nodes), match)


# --- no-ops --------------------------------------------------------------------------------------
@pytest.mark.parametrize("noop", ["identity", "flatten1", "flatten_neg1", "reshape_minus1", "reshape_zero",
                                  "dropout", "dropout_eval"])
def test_noops_in_the_data_path(tmp_path, noop):
    """Identity, Flatten(axis 1 / -1), Reshape to [-1, D] / [0, D], Dropout (inference) change nothing."""
    first, inits = _gemm1(10)
    op = {"identity": helper.make_node("Identity", ["a0"], ["a1"]),
          "flatten1": helper.make_node("Flatten", ["a0"], ["a1"], axis=1),
          "flatten_neg1": helper.make_node("Flatten", ["a0"], ["a1"], axis=-1),
          "reshape_minus1": helper.make_node("Reshape", ["a0", "s"], ["a1"]),
          "reshape_zero": helper.make_node("Reshape", ["a0", "s0"], ["a1"]),
          "dropout": helper.make_node("Dropout", ["a0", "ratio"], ["a1"]),
          "dropout_eval": helper.make_node("Dropout", ["a0", "ratio", "mode"], ["a1"])}[noop]
    inits = dict(inits, s=np.array([-1, H], np.int64), s0=np.array([0, H], np.int64), ratio=np.float32(0.3),
                 mode=np.array(False))
    nodes = first + [helper.make_node("Relu", ["z1"], ["a0"])]
    _check(tmp_path, _two_layers(nodes, "a0", [op], inits, 10), 11)


@pytest.mark.parametrize("noop, match", [("flatten0", r"Flatten\(axis=0\)"), ("reshape_allowzero", "allowzero"),
                                         ("reshape_other", "changes the"), ("dropout_train", "training mode")])
def test_layout_changes_are_refused(tmp_path, noop, match):
    """Flatten(axis=0), Reshape with allowzero or to another layout, Dropout in training mode are refused."""
    first, inits = _gemm1(10)
    op = {"flatten0": helper.make_node("Flatten", ["a0"], ["a1"], axis=0),
          "reshape_allowzero": helper.make_node("Reshape", ["a0", "s"], ["a1"], allowzero=1),
          "reshape_other": helper.make_node("Reshape", ["a0", "s2"], ["a1"]),
          "dropout_train": helper.make_node("Dropout", ["a0", "ratio", "mode"], ["a1"])}[noop]
    inits = dict(inits, s=np.array([-1, H], np.int64), s2=np.array([-1, H // 2], np.int64), ratio=np.float32(0.3),
                 mode=np.array(True))
    nodes = first + [helper.make_node("Relu", ["z1"], ["a0"])]
    _refused(tmp_path, _two_layers(nodes, "a0", [op], inits, 10), match)


# --- constant folding ----------------------------------------------------------------------------
@pytest.mark.parametrize("chain", [
    ["FLOAT16", "FLOAT"],  # rounds the weights to half precision: must not be a no-op
    ["INT32", "FLOAT"],  # truncates toward zero
    ["INT8", "FLOAT"],
    ["BOOL", "FLOAT"],
    ["DOUBLE", "FLOAT"],
    ["FLOAT"],
])
def test_cast_of_a_constant_weight(tmp_path, chain):
    """Cast chains on a constant weight are folded with ONNX's semantics (rounding, truncation, != 0), as onnxruntime."""
    rng = _rng(20)
    w1 = (rng.normal(0, 1.0, (H, D)) * 3.3).astype(np.float32)  # values with fractions, |w| < 127
    _, b1, _, _ = _weights(20)
    nodes, src = [], "w1"
    for i, t in enumerate(chain):
        nodes.append(helper.make_node("Cast", [src], [f"wc{i}"], to=getattr(TensorProto, t)))
        src = f"wc{i}"
    nodes.append(helper.make_node("Gemm", ["x", src, "b1"], ["z1"], transB=1))
    pol, x, y = _check(tmp_path, _two_layers(nodes, "z1", [helper.make_node("Relu", ["z1"], ["a1"])],
                                             {"w1": w1, "b1": b1}, 20), 21)
    if chain[0] in ("FLOAT16", "INT32", "INT8", "BOOL"):  # folding the cast as a no-op would fail the check above
        ignored = MLPPolicy([w1, *pol.weights[1:]], pol.biases, pol.activations, pol.t_prev, pol.world)
        assert np.abs(ignored.layer_outputs(x)[-1][0] - y).max() > 100 * TOL


def test_integer_constant_cast_to_float(tmp_path):
    """An INT64 weight cast to FLOAT is exact."""
    w1 = _rng(22).integers(-3, 4, (H, D)).astype(np.int64)
    _, b1, _, _ = _weights(22)
    nodes = [helper.make_node("Cast", ["w1"], ["wf"], to=TensorProto.FLOAT),
             helper.make_node("Gemm", ["x", "wf", "b1"], ["z1"], transB=1)]
    _check(tmp_path, _two_layers(nodes, "z1", [helper.make_node("Tanh", ["z1"], ["a1"])], {"w1": w1, "b1": b1}, 22), 23)


@pytest.mark.parametrize("fold", ["transpose", "reshape", "identity", "constant_node"])
def test_other_constant_folds(tmp_path, fold):
    """Transpose, Reshape and Identity of a constant weight and a Constant node fold to what onnxruntime uses."""
    w1, b1, _, _ = _weights(24)
    inits = {"b1": b1}
    if fold == "transpose":
        inits["wt"] = w1.T.copy()
        pre = [helper.make_node("Transpose", ["wt"], ["w"], perm=[1, 0])]
    elif fold == "reshape":
        inits["wflat"], inits["shape"] = w1.reshape(-1), np.array([H, D], np.int64)
        pre = [helper.make_node("Reshape", ["wflat", "shape"], ["w"])]
    elif fold == "identity":
        inits["w0"] = w1
        pre = [helper.make_node("Identity", ["w0"], ["w"])]
    else:
        pre = [helper.make_node("Constant", [], ["w"], value=numpy_helper.from_array(w1))]
    nodes = pre + [helper.make_node("Gemm", ["x", "w", "b1"], ["z1"], transB=1)]
    _check(tmp_path, _two_layers(nodes, "z1", [helper.make_node("Sigmoid", ["z1"], ["a1"])], inits, 24), 25)


@pytest.mark.parametrize("to, match", [("BFLOAT16", "Cast to BFLOAT16 is not supported"),
                                       ("STRING", "Cast to STRING is not supported")])
def test_unsupported_cast_is_refused_by_name(tmp_path, to, match):
    """A Cast of a constant to a type the importer does not model is refused, naming the type."""
    w1, b1, _, _ = _weights(26)
    nodes = [helper.make_node("Cast", ["w1"], ["wc"], to=getattr(TensorProto, to)),
             helper.make_node("Cast", ["wc"], ["wf"], to=TensorProto.FLOAT),
             helper.make_node("Gemm", ["x", "wf", "b1"], ["z1"], transB=1)]
    _refused(tmp_path, _two_layers(nodes, "z1", [helper.make_node("Relu", ["z1"], ["a1"])], {"w1": w1, "b1": b1}, 26),
             match)


def test_cast_out_of_range_is_refused(tmp_path):
    """Casting a weight of 300.5 to INT8 (undefined in ONNX) is refused, not wrapped."""
    w1, b1, _, _ = _weights(27)
    w1[0, 0] = 300.5
    nodes = [helper.make_node("Cast", ["w1"], ["wc"], to=TensorProto.INT8),
             helper.make_node("Cast", ["wc"], ["wf"], to=TensorProto.FLOAT),
             helper.make_node("Gemm", ["x", "wf", "b1"], ["z1"], transB=1)]
    _refused(tmp_path, _two_layers(nodes, "z1", [helper.make_node("Relu", ["z1"], ["a1"])], {"w1": w1, "b1": b1}, 27),
             "outside its range")


def test_cast_in_the_data_path_is_refused(tmp_path):
    """A Cast of the data (not of a constant) is refused by name."""
    first, inits = _gemm1(28)
    cast = helper.make_node("Cast", ["z1"], ["a1"], to=TensorProto.FLOAT)
    _refused(tmp_path, _two_layers(first, "z1", [cast], inits, 28), "op Cast is not supported")


def test_half_precision_weight_on_float_data_is_refused(tmp_path):
    """A FLOAT16 weight multiplied with FLOAT data (a model no runtime accepts) is refused by type inference."""
    w1, b1, _, _ = _weights(29)
    nodes = [helper.make_node("Cast", ["w1"], ["wh"], to=TensorProto.FLOAT16),
             helper.make_node("Gemm", ["x", "wh", "b1"], ["z1"], transB=1)]
    _refused(tmp_path, _two_layers(nodes, "z1", [helper.make_node("Relu", ["z1"], ["a1"])], {"w1": w1, "b1": b1}, 29),
             "invalid ONNX model")
