"""ONNX in and out: torch / artifact → ONNX → Kilobot policy, bit-exact firmware outputs, clear errors."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from kiloforge.errors import PolicyError  # noqa: E402
from export.interop.onnx_import import OnnxImportError, load_onnx_policy  # noqa: E402
from sim.config import OBS_NBR_SENSING, OBS_RBF, OBS_TARGET, OBS_WALL, preset  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
T_PREV = 3


def _rng(tag: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([4711, tag]))


def _histories(world, t_prev: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """Plausible flat histories (n, history_dim): actions in [0,1], 0/1 flags, target -1 or [0,1], RBF bins."""
    tup = np.zeros((n, t_prev, world.tuple_dim), np.float32)  # (n, T, tuple_dim)
    tup[..., :2] = rng.uniform(0, 1, (n, t_prev, 2))
    obs = tup[..., 2:]
    obs[..., OBS_WALL] = rng.integers(0, 2, (n, t_prev))
    heard = rng.random((n, t_prev)) < 0.5
    obs[..., OBS_TARGET] = np.where(heard, rng.uniform(0, 1, (n, t_prev)), -1.0)
    obs[..., OBS_NBR_SENSING] = rng.integers(0, 2, (n, t_prev))
    obs[..., OBS_RBF:] = rng.uniform(0, 1.2, (n, t_prev, world.n_rbf)) * (rng.random((n, t_prev, world.n_rbf)) < 0.3)
    return tup.reshape(n, -1)


def _torch_actor(world, t_prev: int, hidden=(32, 24), seed: int = 0):
    """A learn.networks.Actor whose outputs cover [0, 1] (the thesis init keeps them near 0)."""
    torch = pytest.importorskip("torch")
    from learn.networks import Actor

    torch.manual_seed(seed)
    actor = Actor(world.history_dim(t_prev), hidden)
    with torch.no_grad():
        actor.net[-1].weight.mul_(200.0)
        actor.net[-1].bias.fill_(0.5)
    return actor


def _policy_from_layers(layers, world, t_prev):
    from kiloforge.actors.mlp import MLPPolicy

    return MLPPolicy(weights=[w for w, _, _ in layers], biases=[b for _, b, _ in layers],
                     activations=[a for _, _, a in layers], t_prev=t_prev, world=world, provenance={"source": "test"})


def _quantise(policy, calib_inputs: np.ndarray):
    from export.quantize import quantize_policy
    from kiloforge.actors.mlp import calibration_from_inputs

    return quantize_policy(policy, calibration_from_inputs(policy, calib_inputs))


def _firmware_commands(policy, calib_inputs: np.ndarray, test_inputs: np.ndarray) -> np.ndarray:
    """Quantise with the given calibration inputs and run the integer actor: uint8 motor commands."""
    qp = _quantise(policy, calib_inputs)
    return qp.forward_int(qp.quantize_history(test_inputs))


def _emulate(qp, seed: int = 21, n_robots: int = 5, n_steps: int = 12):
    """Run the firmware emulator on a random message stream (same stream for every qp): FirmwareOutputs."""
    from export.contract import firmware as fwspec
    from export.verify.emulator import FirmwareEmulator, FirmwareInputs

    rng = _rng(seed)
    P = qp.world.period_ticks
    n_ticks = n_steps * P
    uids = np.arange(1, n_robots + 1)
    n_ev = 40 * n_steps
    ev = np.zeros(n_ev, fwspec.EVENT_DTYPE)
    ev["robot"] = rng.integers(0, n_robots, n_ev)
    ev["tick"] = rng.integers(0, n_ticks, n_ev)
    ev["uid"] = rng.choice(np.append(uids, qp.world.emitter_uid), n_ev)
    ev["role"] = (ev["uid"] == qp.world.emitter_uid).astype(np.uint8)
    ev["flag"] = rng.integers(0, 2, n_ev)
    ev["type"] = fwspec.DEFAULT_MSG_TYPE
    ev["version"] = fwspec.MSG_VERSION
    ev["dist"] = rng.integers(33, 120, n_ev)
    ev = ev[np.lexsort((ev["tick"], ev["robot"]))]
    calib = np.tile(np.asarray(fwspec.DEFAULT_CALIB, np.uint8), (n_robots, 1))
    probe = FirmwareInputs(uids=uids, calib=calib, light=np.zeros((n_robots, 1)), events=ev, n_ticks=n_ticks)
    light = rng.integers(100, 900, (n_robots, probe.n_steps(P)))  # one reading per control step
    inputs = FirmwareInputs(uids=uids, calib=calib, light=light, events=ev, n_ticks=n_ticks)
    return FirmwareEmulator(qp, uids, calib).run(inputs)


def _save(model, path: Path) -> Path:
    onnx.save(model, str(path))
    return path


def _mlp_model(nodes, inits, in_dim, out_dim=2, opset=17, meta=None, in_name="x", out_name="y"):
    g = helper.make_graph(nodes, "g", [helper.make_tensor_value_info(in_name, TensorProto.FLOAT, ["batch", in_dim])],
                          [helper.make_tensor_value_info(out_name, TensorProto.FLOAT, ["batch", out_dim])],
                          initializer=inits)
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", opset)], producer_name="otherframework",
                          ir_version=8)
    if meta:
        helper.set_model_props(m, meta)
    return m


def _ort(path: Path, x: np.ndarray) -> np.ndarray:
    ort = pytest.importorskip("onnxruntime")
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return sess.run(None, {sess.get_inputs()[0].name: x.astype(np.float32)})[0]


def _world_json(tmp_path: Path, obj, name="world.json") -> Path:
    p = tmp_path / name
    p.write_text(json.dumps(obj))
    return p


# --- out and back in ----------------------------------------------------------------------------
def test_torch_onnx_import_quantise_is_bit_exact_with_artifact_path(tmp_path):
    """torch → ONNX → load_onnx_policy → quantise → forward_int equals torch → artifact → quantise → forward_int."""
    from learn.onnx_export import export_onnx

    world = preset("thesis")
    actor = _torch_actor(world, T_PREV)
    export_onnx(actor, tmp_path / "actor.onnx", world, T_PREV)
    from_onnx = load_onnx_policy(tmp_path / "actor.onnx")
    from_torch = _policy_from_layers(actor.layers(), world, T_PREV)

    assert from_onnx.activations == from_torch.activations == ("elu", "elu", "identity")
    for a, b in zip(from_onnx.weights + from_onnx.biases, from_torch.weights + from_torch.biases):
        np.testing.assert_array_equal(a, b)  # float32 weights survive ONNX bit for bit
    calib = _histories(world, T_PREV, 2000, _rng(1))
    test = _histories(world, T_PREV, 1000, _rng(2))
    q_onnx = _firmware_commands(from_onnx, calib, test)
    q_torch = _firmware_commands(from_torch, calib, test)
    np.testing.assert_array_equal(q_onnx, q_torch)
    assert q_onnx.dtype == np.uint8 and q_onnx.shape == (1000, 2)
    assert len(np.unique(q_onnx)) > 20, "outputs should cover many motor commands, not a constant"


def test_onnx_and_torch_paths_give_the_same_firmware_in_the_emulator(tmp_path):
    """The emulated firmware (every tick's motors, LED, message bytes) is identical for the ONNX and the torch path."""
    from learn.onnx_export import export_onnx

    world = preset("kilobot")
    actor = _torch_actor(world, T_PREV, hidden=(24,), seed=2)
    export_onnx(actor, tmp_path / "actor.onnx", world, T_PREV)
    calib = _histories(world, T_PREV, 1500, _rng(5))
    qp_onnx = _quantise(load_onnx_policy(tmp_path / "actor.onnx"), calib)
    qp_torch = _quantise(_policy_from_layers(actor.layers(), world, T_PREV), calib)
    out_onnx, out_torch = _emulate(qp_onnx), _emulate(qp_torch)
    np.testing.assert_array_equal(out_onnx.ticks, out_torch.ticks)
    np.testing.assert_array_equal(out_onnx.steps, out_torch.steps)
    assert len(np.unique(out_onnx.commands)) > 5, "the run must exercise varying motor commands"


def test_onnxruntime_matches_torch_within_1e5(tmp_path):
    """onnxruntime on the exported actor agrees with torch (clipped to [0, 1]) within 1e-5."""
    torch = pytest.importorskip("torch")
    from learn.onnx_export import export_onnx

    world = preset("kilobot")
    actor = _torch_actor(world, 4, hidden=(48,), seed=3)
    model = export_onnx(actor, tmp_path / "a.onnx", world, 4)
    x = _histories(world, 4, 512, _rng(3))
    y_ort = _ort(tmp_path / "a.onnx", x)
    with torch.no_grad():
        y_torch = actor(torch.from_numpy(x)).clamp(0.0, 1.0).numpy()
    assert y_ort.shape == (512, 2)
    np.testing.assert_allclose(y_ort, y_torch, rtol=0, atol=1e-5)
    inner = (y_torch > 0.01) & (y_torch < 0.99)
    assert inner.mean() > 0.2, "the check must cover unsaturated outputs"
    meta = {p.key: p.value for p in model.metadata_props}
    assert meta["kiloforge.t_prev"] == "4" and json.loads(meta["kiloforge.world"])["name"] == "kilobot"
    assert model.opset_import[0].version == 17
    assert [i.name for i in model.graph.input] == ["history"] and [o.name for o in model.graph.output] == ["action"]


def test_sequential_with_all_activations_roundtrips(tmp_path):
    """An nn.Sequential with ReLU/Tanh/Sigmoid hidden layers exports and imports with the same layers."""
    torch = pytest.importorskip("torch")
    from torch import nn

    from learn.onnx_export import export_onnx

    world = preset("thesis")
    d = world.history_dim(2)
    torch.manual_seed(5)
    seq = nn.Sequential(nn.Linear(d, 16), nn.ReLU(), nn.Linear(16, 12), nn.Tanh(), nn.Linear(12, 8), nn.Sigmoid(),
                        nn.Linear(8, 2))
    export_onnx(seq, tmp_path / "s.onnx", world, 2, opset=13)
    pol = load_onnx_policy(tmp_path / "s.onnx")
    assert pol.activations == ("relu", "tanh", "sigmoid", "identity")
    x = _histories(world, 2, 256, _rng(4))
    with torch.no_grad():
        ref = seq(torch.from_numpy(x)).clamp(0, 1).double().numpy()
    np.testing.assert_allclose(pol.act(x), ref, atol=1e-6)
    np.testing.assert_allclose(_ort(tmp_path / "s.onnx", x), ref, atol=1e-5)


def test_export_from_artifact_cli_and_back(tmp_path):
    """`python -m learn.onnx_export --policy P --out actor.onnx` writes a model that imports to the same policy."""
    from kiloforge.policies import save_policy

    world = preset("kilobot")
    rng = _rng(6)
    d = world.history_dim(2)
    layers = [(rng.normal(0, 0.3, (10, d)).astype(np.float32), rng.normal(0, 0.1, 10).astype(np.float32), "tanh"),
              (rng.normal(0, 2.0, (2, 10)).astype(np.float32), np.full(2, 0.5, np.float32), "identity")]
    pol = _policy_from_layers(layers, world, 2)
    save_policy(pol, tmp_path / "p.npz")
    r = subprocess.run([sys.executable, "-m", "learn.onnx_export", "--policy", str(tmp_path / "p.npz"),
                        "--out", str(tmp_path / "actor.onnx")], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "onnxruntime vs policy max |diff|" in r.stdout
    back = load_onnx_policy(tmp_path / "actor.onnx")
    assert back.world == world and back.t_prev == 2 and back.activations == pol.activations
    for a, b in zip(back.weights + back.biases, pol.weights + pol.biases):
        np.testing.assert_array_equal(a, b)
    meta = {p.key: p.value for p in onnx.load(str(tmp_path / "actor.onnx")).metadata_props}
    assert meta["kiloforge.policy_hash"] == pol.hash


# --- models written by other frameworks --------------------------------------------------------
def test_handbuilt_matmul_add_relu_imports_with_world_json(tmp_path):
    """A MatMul+Add+Relu MLP (TF/JAX style, no metadata) imports with --world JSON and matches onnxruntime."""
    world = preset("kilobot")
    d = world.history_dim(3)
    rng = _rng(7)
    w1, b1 = rng.normal(0, 0.3, (d, 20)).astype(np.float32), rng.normal(0, 0.1, (20,)).astype(np.float32)
    w2, b2 = rng.normal(0, 1.5, (20, 2)).astype(np.float32), np.full((1, 2), 0.4, np.float32)
    nodes = [helper.make_node("MatMul", ["x", "w1"], ["h1"]), helper.make_node("Add", ["b1", "h1"], ["z1"]),
             helper.make_node("Relu", ["z1"], ["a1"]), helper.make_node("Identity", ["a1"], ["a1i"]),
             helper.make_node("MatMul", ["a1i", "w2"], ["h2"]), helper.make_node("Add", ["h2", "b2"], ["y"])]
    inits = [numpy_helper.from_array(v, n) for n, v in (("w1", w1), ("b1", b1), ("w2", w2), ("b2", b2))]
    path = _save(_mlp_model(nodes, inits, d), tmp_path / "tf.onnx")
    wj = _world_json(tmp_path, {"world": "kilobot", "t_prev": 3})
    pol = load_onnx_policy(path, wj)
    assert pol.activations == ("relu", "identity") and pol.layer_sizes == [d, 20, 2]
    assert pol.provenance["world_source"].startswith("json:")
    x = _histories(world, 3, 300, _rng(8))
    np.testing.assert_allclose(pol.act(x), np.clip(_ort(path, x), 0, 1), atol=1e-5)
    q = _firmware_commands(pol, x, x)  # the imported policy quantises
    assert q.shape == (300, 2)


def test_handbuilt_gemm_transb_tanh_and_noops_import(tmp_path):
    """Gemm(transB=1, alpha, beta) + Tanh, Flatten/Reshape/Dropout no-ops, Gemm(transB=0) + Clip(0, 1) import exactly."""
    world = preset("thesis")
    d = world.history_dim(2)
    rng = _rng(9)
    w1 = rng.normal(0, 0.4, (16, d)).astype(np.float32)  # (out, in): transB=1
    c1 = rng.normal(0, 0.1, (16,)).astype(np.float32)
    w2 = rng.normal(0, 1.0, (16, 2)).astype(np.float32)  # (in, out): transB=0
    c2 = np.full((2,), 0.5, np.float32)
    nodes = [helper.make_node("Flatten", ["x"], ["xf"], axis=1),
             helper.make_node("Gemm", ["xf", "w1", "c1"], ["z1"], transB=1, alpha=0.5, beta=2.0),
             helper.make_node("Tanh", ["z1"], ["a1"]),
             helper.make_node("Reshape", ["a1", "shape"], ["a1r"]),
             helper.make_node("Dropout", ["a1r"], ["a1d"]),
             helper.make_node("Gemm", ["a1d", "w2", "c2"], ["z2"]),
             helper.make_node("Clip", ["z2", "lo", "hi"], ["y"])]
    inits = [numpy_helper.from_array(v, n) for n, v in (
        ("w1", w1), ("c1", c1), ("w2", w2), ("c2", c2), ("shape", np.array([-1, 16], np.int64)),
        ("lo", np.array(0, np.float32)), ("hi", np.array(1, np.float32)))]
    path = _save(_mlp_model(nodes, inits, d, opset=13), tmp_path / "gemm.onnx")
    flat_json = dict(world.to_dict(), t_prev=2)  # WorldConfig fields at the top level
    pol = load_onnx_policy(path, _world_json(tmp_path, flat_json))
    assert pol.activations == ("tanh", "identity") and pol.world == world
    x = _histories(world, 2, 300, _rng(10))
    np.testing.assert_allclose(pol.act(x), _ort(path, x), atol=1e-5)


def test_torch_legacy_exporter_file_with_world_json_beside_it(tmp_path):
    """A file from torch.onnx.export (Stable-Baselines3 style) imports with its world JSON given."""
    torch = pytest.importorskip("torch")
    import warnings

    world = preset("thesis")
    actor = _torch_actor(world, 2, hidden=(16,), seed=11)
    x0 = torch.zeros(1, world.history_dim(2))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(actor.net, (x0,), str(tmp_path / "sb3.onnx"), dynamo=False, opset_version=17,
                              input_names=["obs"], output_names=["act"], dynamic_axes={"obs": {0: "n"}, "act": {0: "n"}})
    except Exception as e:  # pragma: no cover - depends on the torch build
        pytest.skip(f"torch.onnx.export (TorchScript) unavailable here: {type(e).__name__}")
    wj = _world_json(tmp_path, {"world": world.to_dict(), "t_prev": 2}, name="sb3.world.json")
    pol = load_onnx_policy(tmp_path / "sb3.onnx", world_json=wj)
    for a, b in zip(pol.weights, [w for w, _, _ in actor.layers()]):
        np.testing.assert_array_equal(a, b)
    assert pol.provenance["world_source"].endswith("sb3.world.json")


# --- errors ------------------------------------------------------------------------------------
def _good_model(world, t_prev=2, meta=True):
    d = world.history_dim(t_prev)
    rng = _rng(12)
    nodes = [helper.make_node("Gemm", ["x", "w1", "b1"], ["z1"], transB=1), helper.make_node("Elu", ["z1"], ["a1"]),
             helper.make_node("Gemm", ["a1", "w2", "b2"], ["y"], transB=1)]
    inits = [numpy_helper.from_array(rng.normal(0, 0.2, (8, d)).astype(np.float32), "w1"),
             numpy_helper.from_array(np.zeros(8, np.float32), "b1"),
             numpy_helper.from_array(rng.normal(0, 0.2, (2, 8)).astype(np.float32), "w2"),
             numpy_helper.from_array(np.zeros(2, np.float32), "b2")]
    m = {"kiloforge.world": world.to_json(), "kiloforge.t_prev": str(t_prev)} if meta else None
    return _mlp_model(nodes, inits, d, meta=m)


def _expect_error(path, match: str, world_json=None) -> str:
    with pytest.raises(OnnxImportError, match=match) as ei:
        load_onnx_policy(path, world_json)
    msg = str(ei.value)
    assert "\n" not in msg and str(Path(path).name) in msg
    assert isinstance(ei.value, PolicyError)
    return msg


def test_good_model_imports(tmp_path):
    """The base model that the error tests break imports cleanly (so each error test isolates one fault)."""
    pol = load_onnx_policy(_save(_good_model(preset("thesis")), tmp_path / "ok.onnx"))
    assert pol.activations == ("elu", "identity") and pol.t_prev == 2


def test_truncated_and_garbage_files_are_refused(tmp_path):
    """Truncated, empty and non-ONNX files give a one-line 'truncated or corrupt' style error."""
    data = _good_model(preset("thesis")).SerializeToString()
    for name, blob in (("trunc.onnx", data[: len(data) // 2]), ("garbage.onnx", b"\x00\xff" * 100 + b"hello"),
                       ("empty.onnx", b"")):
        p = tmp_path / name
        p.write_bytes(blob)
        _expect_error(p, "truncated|corrupt|empty|invalid|not a valid")
    _expect_error(tmp_path / "missing.onnx", "does not exist")


@pytest.mark.parametrize("op", ["Conv", "LSTM", "LeakyRelu", "Softmax"])
def test_unsupported_op_is_named(tmp_path, op):
    """An unsupported op (Conv, LSTM, LeakyRelu, Softmax) gives an error naming the node and the op."""
    m = _good_model(preset("thesis"))
    g = m.graph
    extra = {"Conv": [("cw", np.zeros((8, 8, 1), np.float32))],
             "LSTM": [("lw", np.zeros((1, 16, 8), np.float32)), ("lr", np.zeros((1, 16, 4), np.float32))]}.get(op, [])
    attrs = {"hidden_size": 4} if op == "LSTM" else {}
    g.node[1].CopyFrom(helper.make_node(op, ["z1"] + [n for n, _ in extra], ["a1"], name="bad_node", **attrs))
    g.initializer.extend([numpy_helper.from_array(v, n) for n, v in extra])
    p = tmp_path / f"{op}.onnx"
    p.write_bytes(m.SerializeToString())  # unchecked on purpose: the importer must judge it
    msg = _expect_error(p, f"node 'bad_node' \\({op}\\): op {op} is not supported")
    assert "docs/onnx.md" in msg


def test_wrong_input_width_for_world(tmp_path):
    """A model whose input width does not match world.history_dim(t_prev) is refused with both numbers."""
    world = preset("thesis")
    p = _save(_good_model(world, t_prev=2, meta=False), tmp_path / "w.onnx")
    msg = _expect_error(p, "input has 32 features", _world_json(tmp_path, {"world": "thesis", "t_prev": 3}))
    assert "48" in msg


def test_wrong_output_and_weight_dims(tmp_path):
    """Three outputs, or a weight whose shape does not fit its input, are refused."""
    world = preset("thesis")
    m = _good_model(world)
    m.graph.initializer[2].CopyFrom(numpy_helper.from_array(np.zeros((3, 8), np.float32), "w2"))
    m.graph.initializer[3].CopyFrom(numpy_helper.from_array(np.zeros(3, np.float32), "b2"))
    m.graph.output[0].CopyFrom(helper.make_tensor_value_info("y", TensorProto.FLOAT, ["batch", 3]))
    _expect_error(_save(m, tmp_path / "out3.onnx"), "outputs 3 values")
    m = _good_model(world)
    m.graph.initializer[2].CopyFrom(numpy_helper.from_array(np.zeros((2, 9), np.float32), "w2"))
    _expect_error(_save(m, tmp_path / "dims.onnx"), r"weight \(2, 9\) expects 9 inputs but its input has width 8")


def test_huge_initialiser_is_refused(tmp_path):
    """More than 1M parameters is refused with a message that the Kilobot cannot hold it."""
    world = preset("thesis")
    d = world.history_dim(2)
    nodes = [helper.make_node("MatMul", ["x", "w1"], ["h"]), helper.make_node("MatMul", ["h", "w2"], ["y"])]
    inits = [numpy_helper.from_array(np.zeros((d, 40000), np.float32), "w1"),
             numpy_helper.from_array(np.zeros((40000, 2), np.float32), "w2")]
    m = _mlp_model(nodes, inits, d, meta={"kiloforge.world": world.to_json(), "kiloforge.t_prev": "2"})
    _expect_error(_save(m, tmp_path / "huge.onnx"), "Kilobot.*cannot hold")


def test_missing_metadata_without_world_json(tmp_path):
    """A model without kiloforge metadata and no --world JSON says how to give the world."""
    _expect_error(_save(_good_model(preset("thesis"), meta=False), tmp_path / "nometa.onnx"), "--world-json")


def test_bad_world_json_and_disagreement(tmp_path):
    """A broken world JSON, a missing t_prev, and a --world that contradicts the metadata are clear errors."""
    world = preset("thesis")
    p = _save(_good_model(world, meta=False), tmp_path / "m.onnx")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(OnnxImportError, match="not valid JSON"):
        load_onnx_policy(p, bad)
    with pytest.raises(OnnxImportError, match="unknown field"):
        load_onnx_policy(p, _world_json(tmp_path, {"world": {"radius": 3}, "t_prev": 2}, "uf.json"))
    pm = _save(_good_model(world), tmp_path / "meta.onnx")
    other = dict(world.to_dict(), comm_radius_mm=50.0)
    with pytest.raises(OnnxImportError, match="comm_radius_mm"):
        load_onnx_policy(pm, _world_json(tmp_path, {"world": other, "t_prev": 2}, "other.json"))
    assert load_onnx_policy(pm, _world_json(tmp_path, {"world": "thesis", "t_prev": 2}, "same.json")).t_prev == 2
    with pytest.raises(OnnxImportError, match="unexpected key"):
        load_onnx_policy(p, _world_json(tmp_path, {"world": "thesis", "t_prev": 2, "tprev": 3}, "extra.json"))


def test_run_world_json_without_t_prev_is_accepted(tmp_path):
    """A run directory's own world.json (WorldConfig fields, no t_prev) imports, t_prev read off the input width."""
    world = preset("thesis")
    p = _save(_good_model(world, t_prev=3, meta=False), tmp_path / "m.onnx")
    run_world = tmp_path / "world.json"
    run_world.write_text(json.dumps(world.to_dict(), indent=2, sort_keys=True) + "\n")  # as learn.train writes it
    pol = load_onnx_policy(p, run_world)
    assert pol.t_prev == 3 and pol.world == world


def test_world_json_without_t_prev_and_odd_width_is_one_line(tmp_path):
    """Without t_prev, an input width that is no whole number of the world's tuples is an error asking for t_prev."""
    thesis, wide = preset("thesis"), preset("thesis", n_rbf=12)
    assert thesis.history_dim(2) % wide.tuple_dim != 0  # the premise of the test
    p = _save(_good_model(thesis, meta=False), tmp_path / "m.onnx")
    msg = _expect_error(p, "no 't_prev'", _world_json(tmp_path, {"world": {"preset": "thesis", "n_rbf": 12}}, "k.json"))
    assert "k.json" in msg and '"t_prev": N' in msg


def test_world_json_preset_with_overrides(tmp_path):
    """{"world": {"preset": "kilobot", field: value}, "t_prev": N} gives the preset with that field replaced."""
    world = preset("kilobot", comm_radius_mm=70.0)
    p = _save(_good_model(world, meta=False), tmp_path / "m.onnx")
    pol = load_onnx_policy(p, {"world": {"preset": "kilobot", "comm_radius_mm": 70.0}, "t_prev": 2})
    assert pol.world == world and pol.world.comm_radius_mm == 70.0


@pytest.mark.parametrize("case,match", [
    ("elu_alpha", "alpha=0.5"), ("final_tanh", "last layer ends in tanh"), ("narrow_clip", r"Clip\(0.1, 0.9\)"),
    ("two_inputs", "exactly one input"), ("branch", "not a single chain"), ("act_first", "before any dense"),
    ("external", "external data"), ("transA", "transA"),
])
def test_unrepresentable_graphs_are_refused(tmp_path, case, match):
    """Graphs the firmware cannot run exactly (ELU alpha, final Tanh, narrow Clip, branches, external data) are refused."""
    world = preset("thesis")
    m = _good_model(world)
    g = m.graph
    if case == "elu_alpha":
        g.node[1].CopyFrom(helper.make_node("Elu", ["z1"], ["a1"], alpha=0.5))
    elif case == "final_tanh":
        g.node[2].output[0] = "z2"
        g.node.append(helper.make_node("Tanh", ["z2"], ["y"]))
    elif case == "narrow_clip":
        g.node[2].output[0] = "z2"
        g.node.append(helper.make_node("Clip", ["z2", "lo", "hi"], ["y"]))
        g.initializer.extend([numpy_helper.from_array(np.array(0.1, np.float32), "lo"),
                              numpy_helper.from_array(np.array(0.9, np.float32), "hi")])
    elif case == "two_inputs":
        g.input.append(helper.make_tensor_value_info("x2", TensorProto.FLOAT, ["batch", 8]))
    elif case == "branch":
        g.node[2].input[0] = "a1b"
        g.node.insert(2, helper.make_node("Add", ["a1", "z1"], ["a1b"]))
    elif case == "act_first":
        g.node[0].input[0] = "xr"
        g.node.insert(0, helper.make_node("Relu", ["x"], ["xr"]))
    elif case == "external":
        t = g.initializer[0]
        t.ClearField("raw_data")
        t.ClearField("float_data")
        t.data_location = TensorProto.EXTERNAL
        t.external_data.add(key="location", value="weights.bin")
    elif case == "transA":
        g.node[0].attribute.append(helper.make_attribute("transA", 1))
    p = tmp_path / f"{case}.onnx"
    p.write_bytes(m.SerializeToString())
    _expect_error(p, match)


def test_wide_final_clip_and_relu_are_subsumed(tmp_path):
    """A final Clip(-1, 2) or Relu cannot change clip01's result, so they import as a linear output layer."""
    world = preset("thesis")
    m = _good_model(world)
    g = m.graph
    g.node[2].output[0] = "z2"
    g.node.extend([helper.make_node("Clip", ["z2", "lo", "hi"], ["c"]), helper.make_node("Relu", ["c"], ["y"])])
    g.initializer.extend([numpy_helper.from_array(np.array(-1, np.float32), "lo"),
                          numpy_helper.from_array(np.array(2, np.float32), "hi")])
    p = _save(m, tmp_path / "wide.onnx")
    pol = load_onnx_policy(p)
    assert pol.activations == ("elu", "identity")
    assert len(pol.provenance["onnx_output_ops_subsumed_by_clip01"]) == 2
    x = _histories(world, 2, 200, _rng(13))
    np.testing.assert_allclose(pol.act(x), np.clip(_ort(p, x), 0, 1), atol=1e-6)


# --- export-side errors and CLIs ----------------------------------------------------------------
def test_export_refuses_unrepresentable_modules(tmp_path):
    """Exporting a Tanh-output module, a wrong t_prev or a module whose forward() is not its layers fails clearly."""
    torch = pytest.importorskip("torch")
    from torch import nn

    from learn.onnx_export import OnnxExportError, export_onnx

    world = preset("thesis")
    d = world.history_dim(2)
    with pytest.raises(OnnxExportError, match="output layer's activation is tanh"):
        export_onnx(nn.Sequential(nn.Linear(d, 2), nn.Tanh()), tmp_path / "a.onnx", world, 2)
    with pytest.raises(OnnxExportError, match="takes 32 inputs"):
        export_onnx(nn.Sequential(nn.Linear(d, 2)), tmp_path / "a.onnx", world, 3)

    class Squashed(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = nn.Sequential(nn.Linear(d, 8), nn.ELU(), nn.Linear(8, 2))

        def forward(self, h):
            return torch.sigmoid(self.net(h))

    torch.manual_seed(0)
    with pytest.raises(OnnxExportError, match="forward\\(\\) differs"):
        export_onnx(Squashed(), tmp_path / "a.onnx", world, 2)
    assert not (tmp_path / "a.onnx").exists(), "nothing is written on error"


def test_cli_errors_are_one_line(tmp_path):
    """Both ONNX CLIs exit 2 with one 'error:' line and no traceback on a bad input file."""
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not an onnx file at all")
    for cmd in (["-m", "learn.onnx_export", "--policy", str(tmp_path / "nope.npz"), "--out", str(tmp_path / "o.onnx")],
                ["-m", "export.interop.onnx_import", str(bad), "--out", str(tmp_path / "p.npz")]):
        r = subprocess.run([sys.executable, *cmd], cwd=REPO, capture_output=True, text=True)
        assert r.returncode == 2, (cmd, r.stdout, r.stderr)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("python -m ") and ": error: " in lines[0], r.stderr
        assert "Traceback" not in r.stderr
    assert not (tmp_path / "o.onnx").exists() and not (tmp_path / "p.npz").exists()


def test_learn_cli_export_onnx_subcommand(tmp_path):
    """`python -m learn export-onnx --policy P --out actor.onnx` writes the policy's actor as ONNX."""
    from kiloforge.policies import save_policy

    world = preset("thesis")
    rng = _rng(14)
    layers = [(rng.normal(0, 0.3, (6, world.history_dim(1))).astype(np.float32), np.zeros(6, np.float32), "elu"),
              (rng.normal(0, 1.0, (2, 6)).astype(np.float32), np.zeros(2, np.float32), "identity")]
    save_policy(_policy_from_layers(layers, world, 1), tmp_path / "p.npz")
    r = subprocess.run([sys.executable, "-m", "learn", "export-onnx", "--policy", str(tmp_path / "p.npz"), "--out",
                        str(tmp_path / "a.onnx")], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert load_onnx_policy(tmp_path / "a.onnx").layer_sizes == [world.history_dim(1), 6, 2]


def test_onnx_import_cli_writes_policy_artifact(tmp_path):
    """`python -m export.interop.onnx_import M.onnx --world-json W --out P.npz` writes an artifact load_policy accepts."""
    from kiloforge.policies import load_policy

    world = preset("kilobot")
    p = _save(_good_model(world, meta=False), tmp_path / "m.onnx")
    wj = _world_json(tmp_path, {"world": "kilobot", "t_prev": 2})
    r = subprocess.run([sys.executable, "-m", "export.interop.onnx_import", str(p), "--world-json", str(wj), "--out",
                        str(tmp_path / "p.npz")], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    pol = load_policy(tmp_path / "p.npz")
    assert pol.world == world and pol.provenance["source"] == "onnx"


def test_export_cli_renders_c_from_onnx(tmp_path):
    """`python -m export --onnx actor.onnx [--world-json W] --out DIR/kilobot_policy.c` renders firmware from ONNX."""
    world = preset("kilobot")
    fast = ["--robots-calib", "4", "--calib-steps", "20", "--quiet"]
    with_meta = _save(_good_model(world), tmp_path / "actor.onnx")
    no_meta = _save(_good_model(world, meta=False), tmp_path / "plain.onnx")
    wj = _world_json(tmp_path, {"world": "kilobot", "t_prev": 2})
    for name, src in (("a", [str(with_meta)]), ("b", [str(no_meta), "--world-json", str(wj)])):
        out = tmp_path / name / "kilobot_policy.c"
        out.parent.mkdir()
        r = subprocess.run([sys.executable, "-m", "export", "--onnx", *src, "--out", str(out), *fast], cwd=REPO,
                           capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        assert out.exists() and "kilo" in out.read_text()
    (tmp_path / "c").mkdir()
    r = subprocess.run([sys.executable, "-m", "export", "--onnx", str(no_meta), "--out",
                        str(tmp_path / "c" / "kilobot_policy.c"), *fast], cwd=REPO, capture_output=True, text=True)
    assert r.returncode != 0 and "--world-json" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "c" / "kilobot_policy.c").exists()
