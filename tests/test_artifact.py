"""The policy artifact: round trip, hash, validation of malformed files (kiloforge.artifact, kiloforge.policies)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from kiloforge.actors.mlp import MLPPolicy
from kiloforge.artifact import FORMAT_VERSION
from kiloforge.errors import PolicyError
from kiloforge.policies import load_policy, save_policy
from tests.fixtures import init_policy
from sim.config import preset

WORLD = preset("kilobot")


def small_policy(seed: int = 1, t_prev: int = 3, hidden=(8, 6), act: str = "elu") -> MLPPolicy:
    return init_policy(WORLD, t_prev, hidden, act, seed=seed, out_scale=0.3,
                       provenance={"trainer": "test", "seed": seed, "notes": "unit test"})


def write_raw(path: Path, arrays: dict[str, np.ndarray], meta: dict | None) -> Path:
    """Write an .npz with the given arrays and (optionally) a JSON meta blob."""
    payload = dict(arrays)
    if meta is not None:
        payload["meta"] = np.frombuffer(json.dumps(meta).encode("utf-8"), np.uint8)
    with open(path, "wb") as f:
        np.savez(f, **payload)
    return path


def parts(p: MLPPolicy) -> tuple[dict[str, np.ndarray], dict]:
    arrays = {}
    for k, (w, b) in enumerate(zip(p.weights, p.biases)):
        arrays[f"w{k}"], arrays[f"b{k}"] = np.array(w), np.array(b)
    return arrays, dict(p.meta(), policy_hash=p.hash)


def assert_policy_error(path: Path, *needles: str) -> str:
    with pytest.raises(PolicyError) as ei:
        load_policy(path)
    msg = str(ei.value)
    assert "\n" not in msg, f"message is not one line: {msg!r}"
    assert str(path) in msg, f"message does not name the file: {msg}"
    for n in needles:
        assert n in msg, f"{n!r} not in {msg!r}"
    return msg


def test_round_trip_equal_arrays_and_hash(tmp_path):
    """save_policy then load_policy gives identical arrays, activations, world, provenance and hash."""
    p = small_policy()
    path = save_policy(p, tmp_path / "p.npz")
    q = load_policy(path)
    assert q.hash == p.hash
    for a, b in zip(p.weights + p.biases, q.weights + q.biases):
        np.testing.assert_array_equal(a, b)
        assert b.dtype == np.float32
    assert q.activations == p.activations and q.t_prev == p.t_prev
    assert q.world == p.world and q.provenance == p.provenance


def test_same_policy_same_bytes(tmp_path):
    """Saving the same policy twice gives byte-identical files (no timestamps)."""
    p = small_policy()
    a = save_policy(p, tmp_path / "a.npz").read_bytes()
    b = save_policy(p, tmp_path / "b.npz").read_bytes()
    assert a == b


def test_hash_depends_on_weights_and_meta():
    """Changing one weight or the provenance changes the hash; equal contents give equal hashes."""
    p = small_policy()
    assert small_policy().hash == p.hash
    w = [np.array(x) for x in p.weights]
    w[1][0, 0] += 1e-3
    assert MLPPolicy(w, p.biases, p.activations, p.t_prev, p.world, p.provenance).hash != p.hash
    assert MLPPolicy(p.weights, p.biases, p.activations, p.t_prev, p.world, {"notes": "x"}).hash != p.hash


def test_act_is_float64_clipped_forward():
    """MLPPolicy.act equals a hand-written float64 forward, clipped to [0, 1]."""
    p = small_policy(act="tanh")
    rng = np.random.default_rng(0)
    x = rng.normal(size=(5, 7, p.in_dim))
    h = x
    for w, b in zip(p.weights[:-1], p.biases[:-1]):
        h = np.tanh(h @ w.astype(np.float64).T + b)
    u = np.clip(h @ p.weights[-1].astype(np.float64).T + p.biases[-1], 0, 1)
    got = p.act(x)
    assert got.dtype == np.float64 and got.shape == (5, 7, 2)
    np.testing.assert_allclose(got, u, rtol=0, atol=1e-12)


def test_meta_fields(tmp_path):
    """The stored meta carries format, version, kind, sizes, activations, t_prev, mapping, world, hash."""
    p = small_policy()
    with np.load(save_policy(p, tmp_path / "p.npz"), allow_pickle=False) as z:
        meta = json.loads(z["meta"].tobytes().decode("utf-8"))
    assert meta["format"] == "kiloforge-policy" and meta["format_version"] == FORMAT_VERSION
    assert meta["kind"] == "mlp" and meta["action_mapping"] == "clip01"
    assert meta["layer_sizes"] == [WORLD.history_dim(3), 8, 6, 2] and meta["t_prev"] == 3
    assert meta["world"] == WORLD.to_dict() and meta["policy_hash"] == p.hash


def test_missing_file(tmp_path):
    """A path that does not exist gives a PolicyError naming it."""
    assert_policy_error(tmp_path / "nope.npz", "does not exist")


def test_truncated_file(tmp_path):
    """A truncated .npz gives a PolicyError, not a zipfile traceback."""
    good = save_policy(small_policy(), tmp_path / "p.npz").read_bytes()
    for cut in (len(good) // 2, len(good) - 30, 100):
        bad = tmp_path / f"cut{cut}.npz"
        bad.write_bytes(good[:cut])
        assert_policy_error(bad)


def test_not_a_zip(tmp_path):
    """A text file is refused as not a .npz archive."""
    bad = tmp_path / "p.npz"
    bad.write_text("hello, I am not a policy\n")
    assert_policy_error(bad, "not a .npz")


def test_empty_file(tmp_path):
    """An empty file is refused."""
    bad = tmp_path / "p.npz"
    bad.write_bytes(b"")
    assert_policy_error(bad, "empty")


def test_missing_meta(tmp_path):
    """An .npz without the meta entry is refused."""
    arrays, _ = parts(small_policy())
    assert_policy_error(write_raw(tmp_path / "p.npz", arrays, None), "meta")


def test_pickled_object_array_refused(tmp_path):
    """An object array (which would need unpickling) never gets loaded."""
    arrays, meta = parts(small_policy())
    arrays["w0"] = np.array([object()], dtype=object)
    path = tmp_path / "p.npz"
    with open(path, "wb") as f:
        np.savez(f, **arrays, meta=np.frombuffer(json.dumps(meta).encode(), np.uint8))
    assert_policy_error(path)


def test_wrong_version(tmp_path):
    """A future format version is refused with the version in the message."""
    arrays, meta = parts(small_policy())
    meta["format_version"] = 99
    assert_policy_error(write_raw(tmp_path / "p.npz", arrays, meta), "version 99")


def test_wrong_format_and_kind(tmp_path):
    """Another format name or an unknown kind is refused."""
    arrays, meta = parts(small_policy())
    assert_policy_error(write_raw(tmp_path / "f.npz", arrays, dict(meta, format="other")), "format")
    assert_policy_error(write_raw(tmp_path / "k.npz", arrays, dict(meta, kind="transformer")), "kind")


def test_meta_not_json(tmp_path):
    """A meta blob that is not JSON is refused."""
    arrays, _ = parts(small_policy())
    path = tmp_path / "p.npz"
    with open(path, "wb") as f:
        np.savez(f, **arrays, meta=np.frombuffer(b"\xff\xfe{", np.uint8))
    assert_policy_error(path, "JSON")


def test_nan_weight(tmp_path):
    """A NaN weight is refused, naming the layer."""
    arrays, meta = parts(small_policy())
    arrays["w1"][2, 3] = np.nan
    assert_policy_error(write_raw(tmp_path / "p.npz", arrays, meta), "layer 1", "non-finite")


def test_bad_shapes(tmp_path):
    """Weight shapes that do not chain are refused."""
    arrays, meta = parts(small_policy())
    arrays["w1"] = arrays["w1"][:, :-1]  # takes 7 inputs, layer 0 produces 8
    meta["layer_sizes"] = [meta["layer_sizes"][0], 8, 6, 2]
    msg = assert_policy_error(write_raw(tmp_path / "p.npz", arrays, meta))
    assert "layer_sizes" in msg or "layer 1" in msg


def test_bias_shape(tmp_path):
    """A bias of the wrong length is refused."""
    arrays, meta = parts(small_policy())
    arrays["b0"] = arrays["b0"][:-1]
    assert_policy_error(write_raw(tmp_path / "p.npz", arrays, meta), "bias shape")


def test_missing_layer_array(tmp_path):
    """A declared layer whose arrays are missing is refused."""
    arrays, meta = parts(small_policy())
    del arrays["b2"]
    assert_policy_error(write_raw(tmp_path / "p.npz", arrays, meta), "b2")


def test_unknown_activation(tmp_path):
    """An activation outside numfmt.ACTIVATIONS is refused."""
    arrays, meta = parts(small_policy())
    meta["activations"] = ["elu", "gelu", "identity"]
    assert_policy_error(write_raw(tmp_path / "p.npz", arrays, meta), "unknown activation", "gelu")


def test_history_width_inconsistent_with_world(tmp_path):
    """An input width that is not t_prev x tuple_dim of the stored world is refused."""
    arrays, meta = parts(small_policy())
    meta["world"] = dict(meta["world"], n_rbf=5)  # tuple_dim 10 instead of 16
    assert_policy_error(write_raw(tmp_path / "p.npz", arrays, meta), "history width")
    arrays2, meta2 = parts(small_policy())
    meta2["t_prev"] = 4
    assert_policy_error(write_raw(tmp_path / "q.npz", arrays2, meta2), "history width")


def test_invalid_world(tmp_path):
    """An invalid or unknown world field becomes a PolicyError."""
    arrays, meta = parts(small_policy())
    assert_policy_error(write_raw(tmp_path / "a.npz", arrays, dict(meta, world=dict(meta["world"], comm_radius_mm=-1))),
                        "world")
    assert_policy_error(write_raw(tmp_path / "b.npz", arrays, dict(meta, world=dict(meta["world"], warp=1))),
                        "warp")


def test_modified_weights_fail_hash(tmp_path):
    """Changing a weight without updating policy_hash is detected."""
    arrays, meta = parts(small_policy())
    arrays["w0"][0, 0] += 0.5
    assert_policy_error(write_raw(tmp_path / "p.npz", arrays, meta), "modified")


def test_constructor_validates():
    """MLPPolicy() itself refuses a wrong output width and a non-dict provenance."""
    p = small_policy()
    w = list(p.weights)
    w[-1] = np.zeros((3, 6), np.float32)
    b = list(p.biases)
    b[-1] = np.zeros(3, np.float32)
    with pytest.raises(PolicyError, match="output width"):
        MLPPolicy(w, b, p.activations, p.t_prev, p.world)
    with pytest.raises(PolicyError, match="provenance"):
        MLPPolicy(p.weights, p.biases, p.activations, p.t_prev, p.world, provenance=[1])  # type: ignore[arg-type]


def test_save_is_atomic(tmp_path, monkeypatch):
    """A failing write leaves the previous file untouched and no temp files behind."""
    path = save_policy(small_policy(1), tmp_path / "p.npz")
    before = path.read_bytes()
    import kiloforge.io as atomic

    def boom(*a, **k):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(atomic.os, "replace", boom)
    with pytest.raises(PolicyError, match="No space"):
        save_policy(small_policy(2), path)
    assert path.read_bytes() == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["p.npz"]


def test_default_policy_loads():
    """The shipped default policy loads, is < 200 KB, and is a trained kilobot actor with its provenance."""
    from importlib import resources
    ref = resources.files("export").joinpath("data", "default_policy.npz")
    with resources.as_file(ref) as path:
        p = load_policy(path)
        assert path.stat().st_size < 200_000
    assert p.world.name == "kilobot" and "untrained" not in p.provenance["notes"]
    assert p.activations == ("elu", "elu", "identity") and p.hidden == [32, 32]
    prov = p.provenance
    assert prov["trainer"].startswith("kiloforge.learn") and prov["config"]["world"] == "kilobot"
    assert prov["config"]["t_prev"] == p.t_prev and list(prov["config"]["actor_hidden"]) == p.hidden
    assert isinstance(prov["seed"], int) and prov["wall_s"] > 0 and prov["date"]
    # trained: the output layer has left its near-zero initialisation U[-3e-3, 3e-3] (thesis §4.3.1)
    assert np.abs(np.asarray(p.weights[-1])).max() > 0.05
