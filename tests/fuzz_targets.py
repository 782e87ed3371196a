"""Fuzzing targets shared by tests/test_fuzz.py (a CI-sized slice) and tests/soak/fuzz_all.py (the full run).

Each target turns one generated input into an :data:`OUTCOMES` verdict. The property every input must
have: it works (``accepted``) or is refused with one printable line naming what is wrong
(``rejected``, exit 2, or 1 for budget / verification failures); never a traceback, never a partial
output, never an accepted corrupt file:

* **policy files** (:func:`check_policy_file`): valid files of every actor kind mutated at the byte
  level, in their JSON metadata (any field, any JSON value or literal such as ``NaN``, re-hashed or
  not) and in their arrays (shapes, dtypes, values, names, zip layout). An accepted file must be the
  original policy when it was not re-hashed, and must round-trip and step finitely in any case;
* **world JSON** (:func:`check_world_json`): mutated world documents and random JSON text through
  ``--world-json``. An accepted world holds exactly the values given (no silent coercion);
* **ONNX graphs** (:func:`check_onnx`): mutated models (bytes, ops, attributes, initializers,
  metadata, opsets). An accepted model must compute what onnxruntime computes;
* **command lines** (:func:`check_cli`): random argv for ``python -m export`` (every sub-command),
  ``python -m sim`` and ``python -m learn``, called in-process. Exit 0 leaves the complete new set
  (its manifest verified) and no temporaries; any other exit leaves the output directory as it was.
"""
from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import json
import os
import re
import shutil
import traceback
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from hypothesis import HealthCheck, Phase, settings
from hypothesis import strategies as st

from tests.bad_inputs import crafted, nested_json, small_policy
from kiloforge.artifact import META, canonical_json, npz_bytes, policy_hash
from kiloforge.errors import PolicyError
from kiloforge.validate import read_npz
from sim.compat import world_from_file
from sim.config import WorldConfig, preset

OUTCOMES = ("accepted", "rejected", "traceback", "hang", "partial_output", "accepted_corrupt", "bad_message")
FAILURES = ("traceback", "hang", "partial_output", "accepted_corrupt", "bad_message")
TOL = 1e-4  #: float32 runtime vs the float64 reference


@dataclass
class Tally:
    """Counts of outcomes per target, and the first few failures with their details."""

    counts: dict[str, dict[str, int]] = field(default_factory=dict)
    failures: list[str] = field(default_factory=list)

    def add(self, target: str, outcome: str, detail: str = "") -> None:
        c = self.counts.setdefault(target, {o: 0 for o in OUTCOMES})
        c[outcome] += 1
        if outcome in FAILURES and len(self.failures) < 50:
            cut = detail if len(detail) <= 2400 else f"{detail[:600]} ... {detail[-1800:]}"
            self.failures.append(f"{target}: {outcome}: {cut}")


def fuzz_settings(n: int) -> settings:
    """Generation only (no shrinking, no database): exactly the inputs asked for, reproducibly seeded."""
    return settings(max_examples=n, deadline=None, database=None, derandomize=True, phases=[Phase.generate],
                    suppress_health_check=list(HealthCheck))


def _clean_message(msg: str, must_name: str | None = None) -> bool:
    return bool(msg) and "\n" not in msg and msg.isprintable() and "Traceback" not in msg and \
        (must_name is None or must_name in msg)


# --- inputs shared by the targets ----------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def base_policies() -> dict[str, Any]:
    """One small valid policy of every actor kind."""
    from kiloforge.actors.gru import random_gru_policy
    from kiloforge.actors.lstm import random_lstm_policy

    kb = preset("kilobot")
    return {"mlp": small_policy(), "gru": random_gru_policy(kb, 4, seed=2), "lstm": random_lstm_policy(kb, 3, seed=4)}


JSON_LITERALS = ["NaN", "Infinity", "-Infinity", "1e999", "-1e999", "1" * 5000, "-0", "0.0", "1e-400", "true",
                 "false", "null", '"1"', '"true"', "[]", "{}", '"\\u001b[2J"', '"\\ud800"', "11.0", "2.5",
                 "18446744073709551616", "-1", "65536", nested_json(200), '{"a": 1, "a": 2}']

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=12),
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c, max_size=4), max_leaves=8)


def _paths(obj: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path of a JSON document (for picking the field to mutate)."""
    out = [prefix] if prefix else []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out += _paths(v, prefix + (i,))
    return out


def _set(obj: Any, path: tuple, value: Any, delete: bool = False) -> None:
    for k in path[:-1]:
        obj = obj[k]
    if delete:
        del obj[path[-1]]
    else:
        obj[path[-1]] = value


def _near(v: Any) -> list:
    """Values of another type that look like ``v`` (11 -> 11.0, True -> 1, "x" -> 1, 2.5 -> "2.5")."""
    if isinstance(v, bool):
        return [0, 1, "true", "false", None]
    if isinstance(v, int):
        return [float(v) if abs(v) < 2**53 else 1.0, True, str(v), -1, 2**64]
    if isinstance(v, float):
        return [True, str(v), int(v), -v, 1e308]
    if isinstance(v, str):
        return [1, None, "", "x" * 300, "\x1b[2J"]
    return [None, 0, "x"]


@st.composite
def json_document(draw, base: dict) -> str:
    """``base`` with a few fields replaced, deleted or added (any JSON value), then as text with a literal
    (NaN, Infinity, huge, a string boolean, deep nesting, a duplicate key...) perhaps spliced in."""
    doc = json.loads(json.dumps(base))
    for _ in range(draw(st.integers(1, 3))):
        paths = _paths(doc)
        op = draw(st.sampled_from(["set", "set", "delete", "add", "near"]))
        if op == "add" or not paths:
            target = doc
            if paths and draw(st.booleans()):
                p = draw(st.sampled_from(paths))
                holder = doc
                for k in p:
                    holder = holder[k]
                target = holder if isinstance(holder, dict) else doc
            target[draw(st.text(max_size=10))] = draw(json_values)
            continue
        p = draw(st.sampled_from(paths))
        if op == "delete":
            _set(doc, p, None, delete=True)
        elif op == "near":  # the field's value with another type that looks alike
            holder = doc
            for k in p:
                holder = holder[k]
            _set(doc, p, draw(st.sampled_from(_near(holder))))
        else:
            _set(doc, p, draw(json_values))
    text = json.dumps(doc)
    if draw(st.integers(0, 3)) == 0:
        numbers = [m.span() for m in re.finditer(r"(?<![\w.\"])-?\d+(\.\d+)?([eE][-+]?\d+)?(?![\w\"])", text)]
        if numbers:
            a, b = draw(st.sampled_from(numbers))
            text = text[:a] + draw(st.sampled_from(JSON_LITERALS)) + text[b:]
    if draw(st.integers(0, 9)) == 0:
        text = draw(st.sampled_from(['{"deep": ' + nested_json(draw(st.integers(60, 200_000))) + ", ",
                                     "\ufeff", " ", "[", '{"x": 1, '])) + text[1:]
    return text


byte_edits = st.lists(st.tuples(st.sampled_from(["flip", "set", "truncate", "insert", "delete", "dup"]),
                                st.floats(0, 1, exclude_max=True), st.integers(0, 255), st.integers(1, 64)),
                      min_size=1, max_size=6)


def apply_byte_edits(data: bytes, edits) -> bytes:
    b = bytearray(data)
    for op, where, value, n in edits:
        if not b:
            break
        i = int(where * len(b))
        if op == "flip":
            b[i] ^= 1 << (value % 8)
        elif op == "set":
            b[i] = value
        elif op == "truncate":
            del b[i:]
        elif op == "insert":
            b[i:i] = bytes([value]) * n
        elif op == "delete":
            del b[i:i + n]
        else:
            b[i:i] = b[i:i + n]
    return bytes(b)


# --- policy files --------------------------------------------------------------------------------
def policy_semantics_ok(policy: Any, path: Path, original: Any | None) -> str:
    """Why an accepted policy file is corrupt ('' when it is not)."""
    if original is not None and policy.hash != original.hash:
        return f"accepted a file whose contents changed without a new hash ({policy.hash[:12]} != {original.hash[:12]})"
    arrays = read_npz(path.read_bytes(), lambda m: PolicyError(m))
    meta = json.loads(arrays.pop(META).tobytes())
    stored = meta.pop("policy_hash")
    if canonical_json(meta) != canonical_json(policy.meta()):
        mine = policy.meta()
        diff = sorted(k for k in set(meta) | set(mine) if canonical_json(meta.get(k)) != canonical_json(mine.get(k)))
        return f"the file's meta differs from the policy's in {diff}: {[(meta.get(k), mine.get(k)) for k in diff]}"
    mine = policy.arrays()
    if set(arrays) != set(mine):
        return f"arrays {sorted(arrays)} vs the policy's {sorted(mine)}"
    for k, a in mine.items():
        if not np.array_equal(np.asarray(arrays[k], np.float32), a):
            return f"array {k} differs from the file's"
    if stored != policy_hash(mine, policy.meta()):
        return "stored hash does not cover the contents"
    state = policy.initial_state(3)
    u, _ = policy.step(np.zeros((3, policy.world.tuple_dim), np.float32), state)
    if not (np.all(np.isfinite(u)) and np.all((u >= 0) & (u <= 1))):
        return "the accepted policy computes non-finite or out-of-range actions"
    return ""


def check_policy_file(data: bytes, workdir: Path, original: Any | None) -> tuple[str, str]:
    """Load ``data`` as a policy file: (outcome, detail). ``original``: the policy it must still be if
    accepted (None when the mutation was re-hashed, i.e. may be a legitimately different policy)."""
    from kiloforge.policies import load_policy

    path = workdir / "fuzzed.npz"
    path.write_bytes(data)
    try:
        policy = load_policy(path)
    except PolicyError as e:
        return ("rejected", "") if _clean_message(str(e), "fuzzed.npz") else ("bad_message", repr(str(e)))
    except BaseException:
        return "traceback", traceback.format_exc()
    try:
        why = policy_semantics_ok(policy, path, original)
    except BaseException:
        return "traceback", traceback.format_exc()
    return ("accepted_corrupt", why) if why else ("accepted", "")


@st.composite
def policy_byte_mutation(draw) -> tuple[bytes, Any]:
    """A valid policy file of any kind with random byte edits (the original policy is what it must stay)."""
    kind = draw(st.sampled_from(sorted(base_policies())))
    pol = base_policies()[kind]
    return apply_byte_edits(pol.to_npz_bytes(), draw(byte_edits)), pol


@st.composite
def policy_meta_mutation(draw) -> tuple[bytes, Any]:
    """A valid file whose meta JSON is mutated; hashed correctly, stale, missing, or nonsense."""
    kind = draw(st.sampled_from(sorted(base_policies())))
    pol = base_policies()[kind]
    arrays = dict(pol.arrays())
    text = draw(json_document(pol.meta()))
    how = draw(st.sampled_from(["rehash", "rehash", "stale", "none", "junk"]))
    try:
        meta = json.loads(text)
        if not isinstance(meta, dict):
            raise ValueError
    except (ValueError, RecursionError):
        meta = None
    if how == "rehash" and meta is not None:
        try:
            return crafted(arrays, meta), None
        except (TypeError, ValueError):  # not hashable as canonical JSON: write it as text below
            pass
    if meta is not None and how in ("stale", "junk"):
        meta["policy_hash"] = pol.hash if how == "stale" else draw(json_values)
        try:
            text = json.dumps(meta, allow_nan=True)
        except (TypeError, ValueError):
            pass
    members = dict(arrays, **{META: np.frombuffer(text.encode("utf-8", "surrogatepass"), np.uint8)})
    return npz_bytes(members), pol if how != "rehash" else None


_DTYPES = ["<f8", "<f2", ">f4", "<i4", "|u1", "|b1", "<c8", "<f16"]


@st.composite
def policy_array_mutation(draw) -> tuple[bytes, Any]:
    """A valid file with an array reshaped, retyped, renamed, dropped, added, poisoned or pickled; the
    zip perhaps deflated, prefixed or given a duplicate member; re-hashed or not."""
    kind = draw(st.sampled_from(sorted(base_policies())))
    pol = base_policies()[kind]
    arrays = {k: np.array(v) for k, v in pol.arrays().items()}
    name = draw(st.sampled_from(sorted(arrays)))
    a = arrays[name]
    op = draw(st.sampled_from(["transpose", "add_axis", "flatten", "drop_row", "dtype", "nan", "inf", "huge",
                               "drop", "extra", "rename", "empty", "fortran", "object"]))
    pickled = None
    if op == "transpose" and a.ndim == 2:
        arrays[name] = a.T.copy()
    elif op == "add_axis":
        arrays[name] = a[None]
    elif op == "flatten":
        arrays[name] = a.reshape(-1)
    elif op == "drop_row" and a.shape[0] > 1:
        arrays[name] = a[1:]
    elif op == "dtype":
        dt = draw(st.sampled_from(_DTYPES))
        try:
            arrays[name] = a.astype(dt)
        except TypeError:
            pass
    elif op in ("nan", "inf", "huge"):
        b = a.astype(np.float64).copy()
        b.flat[draw(st.integers(0, b.size - 1))] = {"nan": np.nan, "inf": -np.inf, "huge": 1e39}[op]
        arrays[name] = b
    elif op == "drop":
        del arrays[name]
    elif op == "extra":
        arrays[draw(st.sampled_from(["w9", "b9", "extra", "w_in2"]))] = np.zeros(draw(st.integers(0, 5)), np.float32)
    elif op == "rename":
        arrays[draw(st.sampled_from(["W0", "w_0", name + "x", "meta2"]))] = arrays.pop(name)
    elif op == "empty":
        arrays[name] = np.zeros((0,) + a.shape[1:], np.float32)
    elif op == "fortran":
        arrays[name] = np.asfortranarray(a)
    elif op == "object":
        pickled = name
    rehash = draw(st.booleans())
    meta = pol.meta()
    try:
        hashed = {k: np.asarray(v, np.float32) for k, v in arrays.items()}
        full = dict(meta, policy_hash=policy_hash(hashed, meta) if rehash else pol.hash)
    except (TypeError, ValueError):
        full = dict(meta, policy_hash=pol.hash)
    members: dict[str, bytes] = {}
    for k, v in arrays.items():
        buf = io.BytesIO()
        if k == pickled:
            np.lib.format.write_array(buf, np.array([{"k": 1}, None], dtype=object), allow_pickle=True)
        else:
            np.lib.format.write_array(buf, v, allow_pickle=False)
        members[f"{k}.npy"] = buf.getvalue()
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.frombuffer(json.dumps(full).encode(), np.uint8), allow_pickle=False)
    members["meta.npy"] = buf.getvalue()
    layout = draw(st.sampled_from(["stored", "deflated", "prefix", "duplicate", "comment", "dir_entry"]))
    out = io.BytesIO()
    if layout == "prefix":
        out.write(b"#!junk\n" * 3)
    with warnings.catch_warnings(), zipfile.ZipFile(
            out, "a" if layout == "prefix" else "w",
            compression=zipfile.ZIP_DEFLATED if layout == "deflated" else zipfile.ZIP_STORED) as zf:
        warnings.simplefilter("ignore")  # the duplicate member is the point
        for k, v in members.items():
            zf.writestr(k, v)
        if layout == "duplicate":
            zf.writestr("meta.npy", members["meta.npy"])
        elif layout == "comment":
            zf.comment = b"PK\x05\x06" + bytes(30)
        elif layout == "dir_entry":
            zf.writestr("sub/", b"")
    accepted_must_be = pol if not rehash else None
    return out.getvalue(), accepted_must_be


# --- world JSON (--world-json) ---------------------------------------------------------------------
def _world_bases() -> list[dict]:
    kb = preset("kilobot").to_dict()
    return [{"world": "kilobot", "t_prev": 1}, {"world": dict(preset("thesis").to_dict()), "t_prev": 1},
            {"world": {"preset": "kilobot", "comm_radius_mm": 70.0}, "t_prev": 1},
            dict(preset("thesis").to_dict(), t_prev=1), {"world": dict(kb, name="kb2"), "t_prev": 1}]


@st.composite
def world_json_text(draw) -> str:
    """A world JSON document (mutated from the accepted forms) or arbitrary JSON-ish text."""
    if draw(st.integers(0, 7)) == 0:
        return draw(st.one_of(st.text(alphabet='{}[]":,0123456789.eE-+ truefalsnNIy\\', max_size=60),
                              json_values.map(json.dumps)))
    return draw(json_document(draw(st.sampled_from(_world_bases()))))


def world_exactly_as_given(world: WorldConfig, t_prev: int, doc: Any, in_dim: int) -> str:
    """'' if the world holds exactly the values the document gave (no coercion), else why not; a document
    without ``t_prev`` must get the one the model's input width ``in_dim`` implies."""
    if isinstance(doc, dict) and "world" in doc:
        given, t_given = doc["world"], doc.get("t_prev")
    else:
        given, t_given = {k: v for k, v in doc.items() if k != "t_prev"}, doc.get("t_prev")
    if "t_prev" not in doc:
        if world.history_dim(t_prev) != in_dim:
            return f"no t_prev given, and {t_prev} does not match the model's input width {in_dim}"
    elif type(t_given) is not int or t_given != t_prev:
        return f"t_prev {t_given!r} became {t_prev}"
    if isinstance(given, str):
        given = {"preset": given}
    base = preset(given["preset"]) if "preset" in given else WorldConfig()
    given = world_from_file(given, "the given world")  # world JSON keys -> WorldConfig attributes (sim.compat)
    for k, v in given.items():
        if k == "preset":
            continue
        got = getattr(world, k)
        if got != v or type(got) is not type(v):
            return f"{k}: {v!r} became {got!r}"
    for k in WorldConfig.__dataclass_fields__:
        if k not in given and getattr(world, k) != getattr(base, k):
            return f"{k} changed without being given"
    return ""


def check_world_json(text: str, workdir: Path, model: Path) -> tuple[str, str]:
    """``--world-json`` with this text for a model without metadata: (outcome, detail)."""
    from export.interop.onnx_import import load_onnx_policy

    path = workdir / "fuzzed.world.json"
    path.write_bytes(text.encode("utf-8", "surrogatepass"))
    try:
        pol = load_onnx_policy(model, world_json=path)
    except PolicyError as e:
        return ("rejected", "") if _clean_message(str(e)) else ("bad_message", repr(str(e)))
    except BaseException:
        return "traceback", traceback.format_exc()
    try:
        why = world_exactly_as_given(pol.world, pol.t_prev, json.loads(text), pol.layer_sizes[0])
    except BaseException:
        return "traceback", traceback.format_exc()
    return ("accepted_corrupt", why) if why else ("accepted", "")


# --- ONNX graphs -------------------------------------------------------------------------------------
ONNX_OPS = ["Gemm", "MatMul", "Add", "Sub", "Relu", "Elu", "Tanh", "Sigmoid", "Clip", "Identity", "Flatten",
            "Reshape", "Cast", "Dropout", "LeakyRelu", "Softmax", "Mul", "Div", "Transpose", "Abs", "Neg", "Exp",
            "Constant", "Conv", "Max", "HardSigmoid", "Selu", "Pow", "Sqrt"]
ATTRS = ["alpha", "beta", "transA", "transB", "axis", "to", "min", "max", "perm", "allowzero", "ratio", "bogus"]


@st.composite
def onnx_mutation(draw) -> bytes:
    """The tiny ONNX actor with random structural or byte-level damage."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    m = onnx.load_from_string(_base_onnx_bytes())
    g = m.graph
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["op", "attr", "attr", "inputs", "insert", "delete", "init_dtype", "init_shape",
                                   "init_value", "dims_lie", "input_type", "meta", "opset", "bytes"]))
        nodes = list(g.node)
        if op == "op" and nodes:
            nodes[draw(st.integers(0, len(nodes) - 1))].op_type = draw(st.sampled_from(ONNX_OPS))
        elif op == "attr" and nodes:
            n = nodes[draw(st.integers(0, len(nodes) - 1))]
            name = draw(st.sampled_from(ATTRS))
            value = draw(st.one_of(st.integers(-3, 20), st.floats(-5, 5, allow_nan=False),
                                   st.lists(st.integers(-2, 3), min_size=1, max_size=3)))
            kept = [a for a in n.attribute if a.name != name]
            del n.attribute[:]
            n.attribute.extend(kept + [helper.make_attribute(name, value)])
        elif op == "inputs" and nodes:
            n = nodes[draw(st.integers(0, len(nodes) - 1))]
            names = ["x", "z1", "a1", "y", "w1", "b1", "w2", "b2", "", "nope"]
            if n.input:
                n.input[draw(st.integers(0, len(n.input) - 1))] = draw(st.sampled_from(names))
        elif op == "insert":
            i = draw(st.integers(0, len(nodes)))
            src = "x" if i == 0 else nodes[i - 1].output[0]
            new = helper.make_node(draw(st.sampled_from(ONNX_OPS)), [src], [f"ins{i}"])
            if i < len(nodes):
                nxt = nodes[i]
                nxt.input[0] = f"ins{i}"
                g.node.insert(i, new)
            else:
                new.output[0] = "y"
                nodes[-1].output[0] = src = "pre_y"
                new.input[0] = src
                g.node.append(new)
        elif op == "delete" and len(nodes) > 1:
            del g.node[draw(st.integers(0, len(nodes) - 1))]
        elif op in ("init_dtype", "init_shape", "init_value", "dims_lie") and g.initializer:
            k = draw(st.integers(0, len(g.initializer) - 1))
            t = g.initializer[k]
            try:
                a = numpy_helper.to_array(t).copy()
            except ValueError:  # its dims were already made to lie
                continue
            if op == "init_dtype":
                a = a.astype(draw(st.sampled_from([np.float16, np.float64, np.int64, np.int32, np.bool_, np.uint8])))
            elif op == "init_shape":
                a = draw(st.sampled_from([a.reshape(-1), a[None], a.T.copy(), a[..., :1].copy()]))
            elif op == "init_value":
                a = a.astype(np.float32)
                a.flat[draw(st.integers(0, a.size - 1))] = draw(st.sampled_from([np.nan, np.inf, 1e30, -np.inf]))
            if op == "dims_lie":
                t.dims[0] = draw(st.sampled_from([0, 1, 10**6, 2**40]))
            else:
                g.initializer[k].CopyFrom(numpy_helper.from_array(a, t.name))
        elif op == "input_type":
            tt = g.input[0].type.tensor_type
            tt.elem_type = draw(st.sampled_from([TensorProto.FLOAT16, TensorProto.DOUBLE, TensorProto.INT64,
                                                 TensorProto.STRING, TensorProto.FLOAT]))
        elif op == "meta":
            key = draw(st.sampled_from(["kiloforge.world", "kiloforge.t_prev"]))
            props = {p.key: p.value for p in m.metadata_props}
            props[key] = draw(st.one_of(st.sampled_from(["0", "-1", "1.0", "x", "999999", " 1", "true", "",
                                                         '{"n_rbf": 11.0}', '{"collisions": "true"}',
                                                         '{"emitter_uid": 1.5}', nested_json(100_000), "NaN"]),
                                        st.text(max_size=10)))
            del m.metadata_props[:]
            for kk, vv in props.items():
                m.metadata_props.add(key=kk, value=vv)
        elif op == "opset":
            m.opset_import[0].version = draw(st.integers(1, 30))
    data = m.SerializeToString()
    if draw(st.integers(0, 5)) == 0:
        data = apply_byte_edits(data, draw(byte_edits))
    return data


@functools.lru_cache(maxsize=1)
def _base_onnx_bytes() -> bytes:
    import tempfile

    from tests.onnx_models import tiny_model

    with tempfile.TemporaryDirectory() as d:
        return tiny_model(Path(d) / "base.onnx").read_bytes()


def check_onnx(data: bytes, workdir: Path) -> tuple[str, str]:
    """Import ``data`` as an ONNX model: (outcome, detail). An accepted model must run in onnxruntime and
    give the same (clipped) actions as the imported policy."""
    from export.interop.onnx_import import load_onnx_policy

    path = workdir / "fuzzed.onnx"
    path.write_bytes(data)
    try:
        pol = load_onnx_policy(path)
    except PolicyError as e:
        return ("rejected", "") if _clean_message(str(e)) else ("bad_message", repr(str(e)))
    except BaseException:
        return "traceback", traceback.format_exc()
    import onnxruntime as ort

    x = np.random.default_rng(7).normal(0, 1, (64, pol.in_dim)).astype(np.float32)
    try:
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        y = sess.run(None, {sess.get_inputs()[0].name: x})[0]
    except Exception as e:
        return "accepted_corrupt", f"imported, but onnxruntime cannot run it: {str(e)[:300]}"
    try:
        if y.shape != (64, 2) or not np.allclose(pol.act(x), np.clip(np.asarray(y, np.float64), 0, 1),
                                                  rtol=1e-5, atol=TOL):
            return "accepted_corrupt", "imported function differs from onnxruntime's"
    except BaseException:
        return "traceback", traceback.format_exc()
    return "accepted", ""


# --- command lines -----------------------------------------------------------------------------------
class Fixtures:
    """Files the command-line fuzzer refers to (built once per work directory)."""

    def __init__(self, root: Path) -> None:
        from kiloforge.policies import save_policy
        from tests.onnx_models import tiny_model

        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self.policy = save_policy(small_policy(), root / "good.npz")
        self.gru = save_policy(base_policies()["gru"], root / "gru.npz")
        self.unhashed = root / "unhashed.npz"
        self.unhashed.write_bytes(crafted(*_arrays_meta(small_policy()), hashed=False))
        self.corrupt = root / "corrupt.npz"
        self.corrupt.write_bytes(self.policy.read_bytes()[:-40])
        self.onnx = tiny_model(root / "tiny.onnx")
        self.onnx_bare = tiny_model(root / "bare.onnx", metadata=False)
        self.world_json = root / "w.json"
        self.world_json.write_text('{"world": "thesis", "t_prev": 1}')
        self.deep_json = root / "deep.json"
        self.deep_json.write_text('{"t_prev": 1, "world": ' + nested_json(100_000) + "}")
        self.dir = root / "adir"
        self.dir.mkdir(exist_ok=True)
        self.fifo = root / "fifo"
        if not self.fifo.exists():
            os.mkfifo(self.fifo)

    def paths(self) -> list[str]:
        r = self.root
        return [str(p) for p in (self.policy, self.gru, self.unhashed, self.corrupt, self.onnx, self.onnx_bare,
                                 self.world_json, self.deep_json, self.dir, self.fifo)] + \
            ["/dev/zero", "/dev/null", str(r / "missing.npz"), "", "-", "\x1b[2J.npz", "a" * 300]


def _arrays_meta(pol):
    return dict(pol.arrays()), pol.meta()


INTS = ["-1", "0", "1", "2", "3", "1024", "1025", "9223372036854775808", "1.5", "nan", "x", "", " 2", "+3", "0x10",
        "\u0663", "1e3", "-0", "99999999999999999999999999999999"]
FLOATS = ["nan", "inf", "-inf", "1e999", "0", "100", "50", "-5", "abc", "1e-320", "0.97", "1.5", "2"]
JUNK = ["--frobnicate", "-", "--", "\x1b[2J", "\u202e", "--out=", "-h", "--help", "--version", "=", "--seed=-1"]


def _export_flags(fx: Fixtures, out: str) -> dict[str, list[str]]:
    P = fx.paths()
    return {"--out": [out, out, str(fx.dir), out[:-2] + ".txt", str(fx.root / "missing" / "k.c"),
                      str(Path(out).with_name("kilobot_target.c")), "", "/dev/null"],
            "--policy": P, "--onnx": P, "--world-json": P, "--robots-calib": INTS[:6] + INTS[6:], "--calib-episodes":
            INTS, "--calib-steps": INTS, "--seed": INTS, "--percentile": FLOATS,
            "--target-uids": ["0", "0,5", "-1", "70000", "a,b", ",,", "1" * 30, "3,", "65535"],
            "--kilolib": [str(fx.root / "nokilolib"), str(fx.dir)], "--verify": ["bogus", "", "HOST"],
            "--no-avr": [], "--quiet": []}


#: values that would make a valid run slow are never drawn (cheap sizes, or invalid ones)
CHEAP_EXPORT = ["--no-avr", "--quiet", "--robots-calib", "2", "--calib-steps", "3"]
CHEAP_SIM = ["--episodes", "1", "--steps", "3", "--quiet"]
CHEAP_VERIFY = ["--episodes", "2", "--steps", "3", "--robots", "2", "--robots-calib", "2", "--calib-steps", "3",
                "--quiet"]


@st.composite
def export_argv(draw, fx: Fixtures, out: str) -> list[str]:
    """Random argv for ``python -m export`` (the default command or a sub-command)."""
    sub = draw(st.sampled_from(["", "", "", "budget", "verify", "rehash"]))
    if sub == "budget":
        flags = {"--history": INTS, "--hidden": INTS, "--gru": INTS, "--lstm": INTS, "--world": ["kilobot", "mars",
                                                                                                  "", "thesis"],
                 "--activation": ["elu", "relu", "x"]}
        head = ["budget"]
    elif sub == "verify":
        flags = {"--policy": fx.paths(), "--robots": ["2", "0", "x", "2000"], "--episodes":
                 ["1", "2", "0", "-4", "x"], "--steps": ["2", "0", "x"], "--seed": INTS, "--goal": FLOATS,
                 "--percentile": FLOATS, "--out": [str(Path(out).parent / "vout"), str(fx.policy), out],
                 "--calib-seed": INTS}
        head = ["verify"] + CHEAP_VERIFY
    elif sub == "rehash":  # never in place: the fixtures stay as they are
        return ["rehash", draw(st.sampled_from(fx.paths())),
                *draw(st.sampled_from([["--out", str(Path(out).parent / "re.npz")], ["--out", str(fx.dir)],
                                       ["--out", str(Path(out).parent / "re.npz"), "--bogus"]]))]
    else:
        flags = _export_flags(fx, out)
        head = list(CHEAP_EXPORT) + ["--out", out]
    argv = list(head)
    for _ in range(draw(st.integers(0, 5))):
        if draw(st.integers(0, 9)) == 0:
            argv.append(draw(st.sampled_from(JUNK)))
            continue
        flag = draw(st.sampled_from(sorted(flags)))
        values = flags[flag]
        argv.append(flag)
        if values:
            for _ in range(draw(st.integers(1, 2)) if flag in ("--robots-calib", "--hidden", "--robots") else 1):
                argv.append(draw(st.sampled_from(values)))
    return argv


@st.composite
def sim_argv(draw, fx: Fixtures, out: str) -> list[str]:
    """Random argv for ``python -m sim``."""
    flags = {"--world": ["thesis", "kilobot", "moon", ""], "--robots": INTS, "--seed": INTS,
             "--policy": ["random", "baseline"] + fx.paths(),
             "--out": [out, str(Path(out).parent / "other"), "/dev/null", str(fx.policy)],
             "--episodes": ["1", "0", "-1", "x", "100001"], "--steps": ["2", "0", "x", "1000001"],
             "--n-envs": ["1", "0", "x"], "--quiet": [], "--suite": ["robustness", "bogus", ""]}
    argv = list(CHEAP_SIM) + ["--out", out]
    for _ in range(draw(st.integers(0, 4))):
        if draw(st.integers(0, 9)) == 0:
            argv.append(draw(st.sampled_from(JUNK)))
            continue
        flag = draw(st.sampled_from(sorted(flags)))
        argv.append(flag)
        if flags[flag]:
            argv.append(draw(st.sampled_from(flags[flag])))
    return argv


def snapshot(d: Path) -> dict[str, str]:
    """Every entry under d (recursively) with a hash of its contents ('dir' / 'other' for the rest)."""
    out = {}
    for p in sorted(d.rglob("*")) if d.exists() else []:
        rel = str(p.relative_to(d))
        if p.is_symlink() or (not p.is_file() and not p.is_dir()):
            out[rel] = "other"
        elif p.is_dir():
            out[rel] = "dir"
        else:
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def run_cli(main: Callable[[list[str]], int], argv: list[str]) -> tuple[int | None, str, str]:
    """Call ``main(argv)`` in-process with stdout / stderr captured: (exit status or None, stderr, traceback)."""
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            rc = main(argv)
        except SystemExit as e:  # argparse --help / --version paths of parsers that exit
            rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
        except BaseException:
            return None, err.getvalue(), traceback.format_exc()
    return rc, err.getvalue(), ""


def check_cli(which: str, argv: list[str], out_dir: Path, fx: Fixtures) -> tuple[str, str]:
    """Run one command line: (outcome, detail). See the module doc for the property."""
    from export.cli.main import main as export_main
    from export.codegen.manifest import verify_manifest
    from sim.__main__ import main as sim_main

    main = {"export": export_main, "sim": sim_main}[which]
    before = snapshot(out_dir)
    fixtures_before = snapshot(fx.root)
    rc, err, tb = run_cli(main, argv)
    if tb:
        return "traceback", f"{argv!r}\n{tb}"
    if snapshot(fx.root) != fixtures_before:
        return "partial_output", f"changed the input files: {argv!r}"
    after = snapshot(out_dir)
    detail = f"{argv!r} -> {rc}: {err[-400:]!r}"
    hidden = [k for k in after if any(part.startswith(".") for part in Path(k).parts)]
    if hidden:
        return "partial_output", f"temporaries left: {hidden} {detail}"
    if rc not in (0, 1, 2):
        return "traceback", f"exit status {rc}: {detail}"
    lines = [l for l in err.splitlines() if l.strip()]
    if rc != 0:
        budget_verdict = rc == 1 and argv[:1] == ["budget"] and not lines  # "does not fit": the table on stdout
        if not budget_verdict and (len(lines) != 1 or not _clean_message(lines[0])):
            return "bad_message", detail
        if after != before:
            return "partial_output", f"changed {sorted(set(after.items()) ^ set(before.items()))[:6]} {detail}"
        return "rejected", ""
    if any("Traceback" in l for l in lines) or not all(l.isprintable() for l in lines):
        return "bad_message", detail
    if "-h" in argv or "--help" in argv:  # help printed, nothing else done
        return ("accepted", "") if after == before else ("partial_output", f"--help wrote files {detail}")
    for m in [k for k in after if k.endswith(".manifest.json")]:
        problems = verify_manifest(out_dir / m)
        if problems:
            return "partial_output", f"{problems} {detail}"
    if which == "sim":
        from kiloforge.sim_cli import OUTPUT_FILES, SUITE_FILES

        suite = [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--suite"]
        names = SUITE_FILES if suite and suite[-1] == "robustness" else OUTPUT_FILES
        out_rel = [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--out"][-1]
        rel = Path(out_rel).relative_to(out_dir) if Path(out_rel).is_relative_to(out_dir) else None
        if rel is None or any(str(rel / n) not in after for n in names):
            return "partial_output", f"the outputs are not all in {out_rel} {detail}"
    return "accepted", ""


def reset_dir(d: Path) -> None:
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)


def cli_case(which: str, data: Any, fx: Fixtures, out_dir: Path) -> tuple[str, str]:
    """One command-line case: a fresh output directory (for export, a quarter of the time holding an old
    complete set that a failed run must leave alone), random argv, the check."""
    from export.cli.main import main as export_main

    reset_dir(out_dir)
    if which == "export":
        if data.draw(st.integers(0, 3)) == 0:
            run_cli(export_main, ["--out", str(out_dir / "kilobot_policy.c")] + CHEAP_EXPORT)
        argv = data.draw(export_argv(fx, str(out_dir / "kilobot_policy.c")))
    else:
        argv = data.draw(sim_argv(fx, str(out_dir / "s")))
    return check_cli(which, argv, out_dir, fx)
