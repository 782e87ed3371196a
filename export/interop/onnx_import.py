"""ONNX in: any framework's MLP actor → a kiloforge :class:`~kiloforge.actors.mlp.MLPPolicy`.

Reads an ``.onnx`` file with the ``onnx`` package only (no onnxruntime, no torch) and walks its graph
as a single chain of dense layers. What is accepted (see ``docs/onnx.md``):

* **Dense layers**: ``Gemm`` (``transA = 0``, ``transB`` 0 or 1, any ``alpha`` / ``beta``, optional
  ``C``) or ``MatMul`` with a constant weight followed by ``Add`` / ``Sub`` of a constant bias.
  Two dense layers in a row become two layers, the first with an ``identity`` activation.
* **Hidden activations**: ``Relu``, ``Elu`` (``alpha = 1`` only), ``Tanh``, ``Sigmoid``, and ``Clip``
  with ``min = 0`` and no max (a ReLU).
* **Output**: the last layer must be linear; the Kilobot clips the two outputs to [0, 1] (``clip01``).
  Anything after the last dense layer that cannot change the clipped result is accepted: ``Clip``
  with ``min <= 0`` and ``max >= 1`` (``Clip(0, 1)`` is what ``learn.onnx_export`` writes) and
  ``Relu``. A narrower ``Clip`` or a final ``Tanh`` / ``Sigmoid`` is refused: the firmware's
  output layer cannot represent it.
* **No-ops**: ``Identity``, ``Dropout`` (inference), ``Flatten(axis=1)``, ``Reshape`` to ``[-1, D]`` /
  ``[0, D]`` of a constant shape. ``Constant`` nodes and constant-only ``Transpose`` / ``Cast`` /
  ``Identity`` / ``Reshape`` are folded.

The world (sensing constants) and ``t_prev`` come from the model's ``metadata_props``
(``kiloforge.world``, ``kiloforge.t_prev``; written by :mod:`learn.onnx_export`), or from a JSON
file: ``{"world": "kilobot", "t_prev": 20}`` (a preset), ``{"world": {"preset": "kilobot",
"comm_radius_mm": 70}, "t_prev": 20}`` (a preset with overrides), ``{"world": {...all WorldConfig
fields...}, "t_prev": 20}`` (missing fields take the ``thesis`` defaults), or the WorldConfig fields at
the top level next to ``t_prev``, given as ``world_json`` (CLI: ``--world-json``). No file beside the model is
ever opened (docs/hardening.md: a file the command was not given, such as a planted ``<model>.world.json`` in a
shared directory, never chooses the world).

Every user mistake raises :class:`OnnxImportError` (a :class:`~kiloforge.errors.PolicyError`) with a
one-line message that names the file, and the node and op where relevant.
"""
from __future__ import annotations

import hashlib
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from kiloforge.actors.mlp import MAX_T_PREV, MLPPolicy
from kiloforge.errors import InputError, PolicyError
from kiloforge.policies import save_policy
from kiloforge.validate import check_int, parse_decimal, parse_json, quote, read_json_file, read_regular_file, show
from sim.config import ACTION_DIM, WorldConfig, preset

# metadata_props keys (the same names are written by learn.onnx_export)
META_WORLD = "kiloforge.world"  #: JSON WorldConfig dict
META_T_PREV = "kiloforge.t_prev"  #: decimal integer
META_OBS_LAYOUT = "kiloforge.obs_layout"  #: JSON: per-tuple feature names and order (informative)
META_VERSION = "kiloforge.version"  #: kiloforge version that wrote the file (informative)
META_ACTION = "kiloforge.action"  #: "clip01" (informative)

MAX_PARAMS = 1_000_000  #: more float parameters than this cannot be a Kilobot policy (32 KB flash)
MAX_FILE_BYTES = 64 * 1024 * 1024  #: refuse to parse larger files (a Kilobot MLP is a few KB)
MAX_NODES = 10_000
MIN_OPSET = 7  #: older opsets give Gemm, Add and Dropout other semantics (and onnxruntime runs opset >= 7 only)
MAX_WORLD_JSON_BYTES = 1 << 20  #: a world JSON file or metadata entry (a full WorldConfig is under 1 KB)

_FLOAT_TYPES = {1: "float32", 10: "float16", 11: "float64", 16: "bfloat16"}  # TensorProto codes
_ACT_OPS = {"Relu": "relu", "Elu": "elu", "Tanh": "tanh", "Sigmoid": "sigmoid"}


class OnnxImportError(PolicyError):
    """An ONNX file cannot be turned into a Kilobot policy; the message is one line."""


def _need_onnx() -> Any:
    try:
        import onnx  # noqa: F401
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise OnnxImportError("reading ONNX files needs the 'onnx' package: pip install 'kiloforge[onnx]'") from e
    return onnx


# --- world metadata ----------------------------------------------------------------------------
def _world_from_obj(obj: Any, where: str, t_prev_text: bool = False,
                    t_prev_optional: bool = False) -> tuple[WorldConfig, int | None]:
    """``{"world": dict | preset name, "t_prev": int}`` or WorldConfig fields + ``t_prev``; with
    ``t_prev_optional`` (a JSON file) ``t_prev`` may be missing (None: the model's input width tells it),
    so that a run directory's own ``world.json`` (the WorldConfig fields alone) is accepted."""
    if not isinstance(obj, dict):
        raise OnnxImportError(f"{where}: expected a JSON object with 'world' and 't_prev', got {type(obj).__name__}")
    obj = dict(obj)
    if "t_prev" not in obj and not t_prev_optional:
        raise OnnxImportError(f"{where}: missing 't_prev' (the number of history tuples the actor reads)")
    t_prev = _parse_t_prev(obj.pop("t_prev"), where, t_prev_text) if "t_prev" in obj else None
    if "world" in obj:
        world_obj: Any = obj.pop("world")
        if obj:
            raise OnnxImportError(f"{where}: unexpected key(s) {', '.join(sorted(obj))} next to 'world' and 't_prev'")
    else:
        world_obj = obj  # WorldConfig fields at the top level
    if not world_obj:
        raise OnnxImportError(f"{where}: missing 'world' (a WorldConfig object or a preset name)")
    if isinstance(world_obj, str):
        world_obj = {"preset": world_obj}
    if isinstance(world_obj, dict) and "preset" in world_obj and not isinstance(world_obj["preset"], str):
        raise OnnxImportError(f"{where}: 'preset' must be a preset name, got {show(world_obj['preset'])}")
    if not isinstance(world_obj, dict):
        raise OnnxImportError(f"{where}: 'world' must be a preset name or an object, got {type(world_obj).__name__}")
    try:
        if "preset" in world_obj:  # {"preset": "kilobot", <field overrides>}
            rest = dict(world_obj)
            unknown = sorted(set(rest) - {"preset"} - set(WorldConfig.__dataclass_fields__))
            if unknown:
                raise ValueError(f"unknown world config field(s): {', '.join(unknown)}")
            return preset(rest.pop("preset"), **rest), t_prev
        return WorldConfig.from_dict(world_obj), t_prev
    except (TypeError, ValueError) as e:
        raise OnnxImportError(f"{where}: bad world config: {str(e).splitlines()[0]}") from None


def _parse_t_prev(v: Any, where: str, text: bool) -> int:
    """An integer in 1..MAX_T_PREV: decimal text in metadata_props (``text``), a JSON integer in a file."""
    if text:
        try:
            v = parse_decimal(v if isinstance(v, str) else "")
        except ValueError:
            raise OnnxImportError(f"{where}: t_prev must be a decimal integer (ASCII digits), got {quote(v)}") from None
    try:
        return check_int(v, f"{where}: t_prev", 1, MAX_T_PREV)
    except InputError as e:
        raise OnnxImportError(str(e)) from None


def _read_world_json(path: str | os.PathLike) -> tuple[WorldConfig, int | None]:
    try:
        obj = read_json_file(path, "world JSON", max_bytes=MAX_WORLD_JSON_BYTES)
    except InputError as e:
        raise OnnxImportError(str(e)) from None
    return _world_from_obj(obj, f"world JSON {quote(path)}", t_prev_optional=True)


def _world_from_metadata(meta: dict[str, str], where: str) -> tuple[WorldConfig, int | None] | None:
    if META_WORLD not in meta and META_T_PREV not in meta:
        return None
    for key in (META_WORLD, META_T_PREV):
        if key not in meta:
            raise OnnxImportError(f"{where}: metadata has no '{key}' (found {', '.join(sorted(meta))})")
    try:
        world_obj = parse_json(meta[META_WORLD], f"{where}: metadata '{META_WORLD}'", max_bytes=MAX_WORLD_JSON_BYTES)
    except InputError as e:
        raise OnnxImportError(str(e)) from None
    return _world_from_obj({"world": world_obj, "t_prev": meta[META_T_PREV]}, f"{where}: metadata", t_prev_text=True)


def _resolve_world(meta: dict[str, str], world_json: Any, model_path: Path) -> tuple[WorldConfig, int | None, str]:
    where = str(model_path)
    from_meta = _world_from_metadata(meta, where)
    if isinstance(world_json, dict):
        given, src = _world_from_obj(world_json, "world_json"), "world_json (dict)"
    elif world_json is not None:
        given, src = _read_world_json(world_json), f"json:{world_json}"
    else:
        given, src = None, ""
    if from_meta is not None and given is not None:
        (wm, tm), (wg, tg) = from_meta, given
        if (tg is not None and tm != tg) or wm.to_dict() != wg.to_dict():
            diff = [k for k, v in wm.to_dict().items() if wg.to_dict().get(k) != v]
            what = f"t_prev {tm} vs {tg}" if tg is not None and tm != tg else f"world fields differ: {', '.join(diff)}"
            raise OnnxImportError(f"{where}: the model's metadata and {src[5:] if src.startswith('json:') else src} "
                                  f"disagree ({what}); a policy runs only in the world it was trained in: drop --world-json")
        return wm, tm, "metadata"
    if from_meta is not None:
        return from_meta[0], from_meta[1], "metadata"
    if given is not None:
        return given[0], given[1], src
    raise OnnxImportError(f"{where}: no kiloforge metadata ('{META_WORLD}', '{META_T_PREV}'); give the world with "
                          f"--world-json W.json ({{\"world\": \"kilobot\" or {{...}}, \"t_prev\": N}})")


# --- the graph walk ----------------------------------------------------------------------------
class _Layer:
    __slots__ = ("w", "b", "act", "node")

    def __init__(self, w: np.ndarray, b: np.ndarray, node: str) -> None:
        self.w, self.b, self.act, self.node = w, b, "identity", node


def _node_label(node: Any, idx: int) -> str:
    return f"node '{node.name}' ({node.op_type})" if node.name else f"node #{idx} ({node.op_type})"


def _attrs(node: Any) -> dict[str, Any]:
    from onnx import helper

    return {a.name: helper.get_attribute_value(a) for a in node.attribute}


def _as_bias(c: np.ndarray, n_out: int, label: str, err: Any) -> np.ndarray:
    """A constant that broadcasts over the batch to (n_out,): shape (), (1,), (n_out,), (1, n_out)."""
    if c.ndim > 2 or (c.ndim == 2 and c.shape[0] != 1) or c.size not in (1, n_out):
        raise err(f"{label}: bias of shape {tuple(c.shape)} does not broadcast to ({n_out},) per sample")
    return np.broadcast_to(c.reshape(-1), (n_out,)).astype(np.float64)


#: TensorProto element types a weight or constant may have (others: strings, complex, bfloat16, float8,
#: int4 ... are refused by name before their data is read)
_READABLE_TYPES = {1: np.float32, 10: np.float16, 11: np.float64, 2: np.uint8, 3: np.int8, 4: np.uint16,
                   5: np.int16, 6: np.int32, 7: np.int64, 12: np.uint32, 13: np.uint64, 9: np.bool_}


def _tensor_where(t: Any, what: str) -> str:
    return f"{what} '{t.name}'" if t.name else what


def _model_tensors(model: Any) -> Any:
    """Every TensorProto of ``model`` that a reader could load, with where it is: initializers, sparse
    initializers, node attributes (``Constant`` values, any tensor / sparse tensor attribute) and the
    same inside nested subgraphs, functions and training graphs. Yields (where, TensorProto, sparse)."""
    def graph(g: Any, where: str) -> Any:
        for t in g.initializer:
            yield _tensor_where(t, f"{where}initializer"), t, False
        for sp in g.sparse_initializer:
            yield _tensor_where(sp.values, f"{where}sparse initializer"), sp.values, True
            yield _tensor_where(sp.indices, f"{where}sparse initializer indices"), sp.indices, True
        yield from nodes(g.node, where)

    def nodes(ns: Any, where: str) -> Any:
        for idx, node in enumerate(ns):
            label = f"{where}{_node_label(node, idx)} attribute"
            for at in node.attribute:
                if at.HasField("t"):
                    yield f"{label} '{at.name}'", at.t, False
                for t in at.tensors:
                    yield f"{label} '{at.name}'", t, False
                for sp in ([at.sparse_tensor] if at.HasField("sparse_tensor") else []) + list(at.sparse_tensors):
                    yield f"{label} '{at.name}' (sparse)", sp.values, True
                    yield f"{label} '{at.name}' (sparse indices)", sp.indices, True
                for sub in ([at.g] if at.HasField("g") else []) + list(at.graphs):
                    yield from graph(sub, f"{label} '{at.name}' subgraph: ")

    if model.HasField("graph"):
        yield from graph(model.graph, "")
    for f in model.functions:
        yield from nodes(f.node, f"function '{f.name}' ")
    for ti in model.training_info:
        for g, what in ((ti.initialization, "initialization"), (ti.algorithm, "algorithm")):
            yield from graph(g, f"training {what} graph: ")


def _check_tensors(model: Any, err: Any) -> None:
    """Refuse, before any tensor data is read: external data anywhere in the model, sparse tensors,
    and element types other than :data:`_READABLE_TYPES`."""
    from onnx import TensorProto

    for where, t, sparse in _model_tensors(model):
        if t.data_location == TensorProto.EXTERNAL or len(t.external_data) > 0:
            raise err(f"{where} is stored in an external data file, which is never read; re-save the model with "
                      "all weights inside the .onnx (onnx.save(model, path, save_as_external_data=False))")
        if sparse:
            raise err(f"{where} is a sparse tensor: not supported (store it dense)")
        if int(t.data_type) not in _READABLE_TYPES:
            name = _TYPE_NAMES.get(int(t.data_type), f"type {int(t.data_type)}")
            raise err(f"{where} has element type {name}: not supported (only numeric real types)")


def _tensor_array(t: Any, where: str, err: Any) -> np.ndarray:
    """The contents of TensorProto ``t`` (already passed :func:`_check_tensors`): its declared size
    bounded by :data:`MAX_PARAMS` before anything is materialised, the data checked against its dims."""
    from onnx import TensorProto, numpy_helper

    if t.data_location == TensorProto.EXTERNAL or len(t.external_data) > 0 or int(t.data_type) not in _READABLE_TYPES:
        raise err(f"{where}: external data or an unsupported element type")  # _check_tensors said which
    if any(int(d) < 0 for d in t.dims):
        raise err(f"{where} has negative dims {list(t.dims)}")
    n = math.prod(int(d) for d in t.dims) if len(t.dims) else 1
    if n > MAX_PARAMS:
        raise err(f"{where}: {n:,} values: the Kilobot (32 KB flash) cannot hold it")
    try:
        val = numpy_helper.to_array(t)
    except Exception:
        raise err(f"{where} is corrupt (its data does not match dims {list(t.dims)})") from None
    return np.asarray(val, dtype=_READABLE_TYPES[int(t.data_type)])


def _constant_value(node: Any, label: str, err: Any) -> np.ndarray:
    from onnx import helper

    for at in node.attribute:
        if at.name == "value":
            return _tensor_array(at.t, f"{label} value", err)
        if at.name in ("value_float", "value_floats", "value_int", "value_ints"):
            val = np.asarray(helper.get_attribute_value(at))
            if val.size > MAX_PARAMS:
                raise err(f"{label}: {val.size:,} values: the Kilobot (32 KB flash) cannot hold it")
            return val
    raise err(f"{label}: unsupported Constant (only tensor / float / int values)")


#: ONNX TensorProto element types a constant may be cast to, and their NumPy types
_CAST_TO = {1: np.float32, 10: np.float16, 11: np.float64, 2: np.uint8, 3: np.int8, 4: np.uint16, 5: np.int16,
            6: np.int32, 7: np.int64, 12: np.uint32, 13: np.uint64, 9: np.bool_}
_TYPE_NAMES = {0: "UNDEFINED", 1: "FLOAT", 2: "UINT8", 3: "INT8", 4: "UINT16", 5: "INT16", 6: "INT32", 7: "INT64",
               8: "STRING", 9: "BOOL", 10: "FLOAT16", 11: "DOUBLE", 12: "UINT32", 13: "UINT64", 14: "COMPLEX64",
               15: "COMPLEX128", 16: "BFLOAT16"}


def _cast(x: np.ndarray, to: int, label: str, err: Any) -> np.ndarray:
    """ONNX Cast of a constant: float rounding to nearest even, float -> integer truncation toward zero
    (refused when a value is not finite or out of the target's range: ONNX leaves that undefined),
    anything -> bool is ``x != 0``; the other element types are refused by name."""
    target = _CAST_TO.get(int(to))
    if target is None:
        raise err(f"{label}: Cast to {_TYPE_NAMES.get(int(to), f'type {to}')} is not supported "
                  f"(only {', '.join(_TYPE_NAMES[k] for k in sorted(_CAST_TO))})")
    if x.dtype.kind not in "fiub":
        raise err(f"{label}: Cast of a {x.dtype} constant is not supported")
    if target is np.bool_:
        return x != 0
    if np.issubdtype(target, np.integer) and x.dtype.kind == "f":
        info = np.iinfo(target)
        t = np.trunc(x.astype(np.float64))
        if not np.all(np.isfinite(t)) or t.size and (t.min() < info.min or t.max() > info.max):
            raise err(f"{label}: Cast to {_TYPE_NAMES[int(to)]} of values outside its range (undefined in ONNX)")
        return t.astype(target)
    if np.issubdtype(target, np.integer) and x.dtype.kind in "iub":
        info = np.iinfo(target)
        xi = x.astype(np.int64) if x.dtype != np.uint64 else x
        if xi.size and (int(xi.min()) < info.min or int(xi.max()) > info.max):
            raise err(f"{label}: Cast to {_TYPE_NAMES[int(to)]} of values outside its range")
        return x.astype(target)
    return x.astype(target)


def _fold_constant(node: Any, a: dict[str, Any], vals: list[np.ndarray], label: str, err: Any) -> np.ndarray:
    """Evaluate a node whose inputs are all constants (weight preprocessing some exporters emit)."""
    op, x0 = node.op_type, vals[0]
    try:
        if op == "Identity":
            return x0
        if op == "Transpose":
            return np.transpose(x0, a.get("perm"))
        if op == "Cast":
            return _cast(x0, a.get("to", 0), label, err)
        if op == "Reshape" and len(vals) == 2:
            if int(a.get("allowzero", 0)):
                raise err(f"{label}: Reshape with allowzero=1 is not supported")
            return x0.reshape([x0.shape[i] if s == 0 else int(s) for i, s in enumerate(vals[1].reshape(-1))])
    except OnnxImportError:
        raise
    except (ValueError, IndexError, TypeError) as e:
        raise err(f"{label}: cannot fold constant {op}: {e}") from None
    raise err(f"{label}: constant computation with {op} is not supported; fold constants before exporting "
              "(e.g. onnx-simplifier, or torch.onnx.export(..., do_constant_folding=True))")


def load_onnx_policy(path: str | os.PathLike, world_json: Any = None) -> Any:
    """Read an ONNX MLP actor and return a :class:`kiloforge.actors.mlp.MLPPolicy` (float weights, its world).

    ``world_json``: a path to a JSON file (or a dict) with ``world`` and ``t_prev``, for models
    without kiloforge metadata. Raises :class:`OnnxImportError` with a one-line message.
    """
    onnx = _need_onnx()

    path = Path(path)
    where = str(path)

    def err(msg: str) -> OnnxImportError:
        return OnnxImportError(f"{where}: {msg}")

    # ---- read the file --------------------------------------------------------------------
    try:
        data = read_regular_file(path, "ONNX model", MAX_FILE_BYTES)
    except InputError as e:
        raise OnnxImportError(str(e)) from None
    if not data:
        raise err("empty file (not an ONNX model)")
    model = onnx.ModelProto()
    try:
        model.ParseFromString(data)
    except Exception:  # protobuf DecodeError and friends
        raise err("not a valid ONNX file (truncated or corrupt protobuf)") from None
    if not model.HasField("graph") or (not model.graph.node and not model.graph.output):
        raise err("not a valid ONNX model (no graph; truncated or not an .onnx file?)")
    g = model.graph

    # external data (anywhere: initializers, Constant values, subgraphs), sparse tensors and non-numeric
    # element types are refused before anything reads tensor contents (the checker included)
    _check_tensors(model, err)
    if len(g.node) > MAX_NODES:
        raise err(f"{len(g.node)} nodes: far more than any Kilobot MLP")

    # parameter bound from the declared dims, before materialising anything
    n_params = 0
    for t in g.initializer:
        n = math.prod(int(d) for d in t.dims) if len(t.dims) else 1
        if any(int(d) < 0 for d in t.dims):
            raise err(f"initializer '{t.name}' has negative dims {list(t.dims)}")
        n_params += n
        if n_params > MAX_PARAMS:
            raise err(f"more than {MAX_PARAMS:,} parameters (initializer '{t.name}' alone has {n:,}): "
                      "the Kilobot (32 KB flash) cannot hold it; use a small MLP (e.g. 2 x 64 hidden units)")

    try:
        onnx.checker.check_model(model)
    except Exception as e:  # onnx.checker.ValidationError, or anything its C++ raises
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise err(f"invalid ONNX model: {first}") from None

    opsets = {o.domain or "ai.onnx": o.version for o in model.opset_import}
    opset = opsets.get("ai.onnx", 0)
    if opset < MIN_OPSET:
        raise err(f"opset {opset} is older than {MIN_OPSET}, the oldest whose Gemm, Dropout and broadcasting rules "
                  "the importer models (re-export with a newer opset)")
    newest = onnx.defs.onnx_opset_version()
    if opset > newest:  # an operator's rules in a future opset are unknown (and onnxruntime refuses the model)
        raise err(f"opset {opset} is newer than {newest}, the newest the installed onnx defines (re-export with "
                  f"opset {newest} or older)")
    meta = {p.key: p.value for p in model.metadata_props}

    # ---- constants --------------------------------------------------------------------------
    const: dict[str, np.ndarray] = {}
    for t in g.initializer:
        const[t.name] = _tensor_array(t, f"initializer '{t.name}'", err)
    init_names = set(const)

    # ---- the single data input ----------------------------------------------------------------
    inputs = [i for i in g.input if i.name not in init_names]
    if len(inputs) != 1:
        raise err(f"the actor must have exactly one input (the history), found {len(inputs)}: "
                  f"{', '.join(i.name for i in inputs) or 'none'}")
    inp = inputs[0]
    tt = inp.type.tensor_type
    if not inp.type.HasField("tensor_type") or tt.elem_type not in _FLOAT_TYPES:
        raise err(f"input '{inp.name}' must be a float tensor [N, history_dim]")
    width: int | None = None
    if tt.HasField("shape"):
        dims = tt.shape.dim
        if len(dims) != 2:
            raise err(f"input '{inp.name}' has rank {len(dims)}; the actor input must be [N, history_dim]")
        if dims[1].HasField("dim_value"):
            width = int(dims[1].dim_value)
    in_width = width

    if len(g.output) != 1:
        raise err(f"the actor must have exactly one output (the action), found {len(g.output)}: "
                  f"{', '.join(o.name for o in g.output)}; export the actor network only")
    out_name = g.output[0].name

    # ---- walk the chain -----------------------------------------------------------------------
    # chain: ("dense", _Layer) | ("act", name, label) | ("clip_wide", label), in graph order
    cur = inp.name
    chain: list[tuple] = []

    def const_in(node: Any, i: int, label: str) -> np.ndarray | None:
        if i >= len(node.input) or node.input[i] == "":
            return None
        if node.input[i] not in const:
            raise err(f"{label}: input '{node.input[i]}' must be a constant (initializer)")
        return const[node.input[i]]

    for idx, node in enumerate(g.node):
        label = _node_label(node, idx)
        op = node.op_type
        if node.domain not in ("", "ai.onnx"):
            raise err(f"{label}: op from domain '{node.domain}' is not supported (standard ONNX ops only)")
        a = _attrs(node)
        ins = [x for x in node.input if x != ""]

        # constants and constant-only subgraphs (e.g. an exporter's Transpose of a weight) are folded
        if op == "Constant":
            const[node.output[0]] = _constant_value(node, label, err)
            continue
        if ins and all(x in const for x in ins):
            const[node.output[0]] = _fold_constant(node, a, [const[x] for x in ins], label, err)
            continue

        data_ins = [x for x in ins if x not in const]
        if len(data_ins) != 1 or data_ins[0] != cur:
            raise err(f"{label}: the graph is not a single chain of layers (this node reads "
                      f"{', '.join(data_ins) or 'no data'}; expected '{cur}'); only plain MLPs are supported")
        if node.input[0] != cur and op != "Add":
            raise err(f"{label}: the data must be the first input of {op} (x @ W, x - b)")

        if op in ("Gemm", "MatMul"):
            if op == "Gemm" and int(a.get("transA", 0)) != 0:
                raise err(f"{label}: transA=1 is not supported (the data must be [N, D])")
            b_mat = const_in(node, 1, label)
            if b_mat is None or b_mat.ndim != 2:
                raise err(f"{label}: the weight must be a constant 2-D matrix, got shape "
                          f"{None if b_mat is None else tuple(b_mat.shape)}")
            w = b_mat if (op == "Gemm" and int(a.get("transB", 0))) else b_mat.T  # (out, in)
            b = np.zeros(w.shape[0], np.float64)
            if op == "Gemm":
                alpha, beta = float(a.get("alpha", 1.0)), float(a.get("beta", 1.0))
                if alpha != 1.0:
                    w = w.astype(np.float64) * alpha
                c = const_in(node, 2, label)
                if c is not None:
                    b = _as_bias(c, w.shape[0], label, err) * beta
            if width is not None and w.shape[1] != width:
                raise err(f"{label}: weight {tuple(b_mat.shape)} expects {w.shape[1]} inputs but its input has width {width}")
            chain.append(("dense", _Layer(w, b, label)))
            width = w.shape[0]
        elif op in ("Add", "Sub"):
            if not chain or chain[-1][0] != "dense":
                raise err(f"{label}: {op} of a constant is supported only as the bias right after MatMul/Gemm")
            lay = chain[-1][1]
            cname = node.input[1] if node.input[0] == cur else node.input[0]
            c = _as_bias(const[cname], lay.w.shape[0], label, err)
            lay.b = lay.b + c if op == "Add" else lay.b - c
        elif op in _ACT_OPS:
            if op == "Elu" and float(a.get("alpha", 1.0)) != 1.0:
                raise err(f"{label}: Elu with alpha={a['alpha']:g} is not supported (only alpha=1, torch.nn.ELU())")
            chain.append(("act", _ACT_OPS[op], label))
        elif op == "Clip":
            if opset < 11:
                lo, hi = float(a.get("min", -np.inf)), float(a.get("max", np.inf))
            else:
                c_lo, c_hi = const_in(node, 1, label), const_in(node, 2, label)
                for c in (c_lo, c_hi):
                    if c is not None and np.asarray(c).size != 1:
                        raise err(f"{label}: Clip bounds must be scalars")
                lo = -np.inf if c_lo is None else float(np.asarray(c_lo).reshape(-1)[0])
                hi = np.inf if c_hi is None else float(np.asarray(c_hi).reshape(-1)[0])
            if lo == 0.0 and math.isinf(hi) and hi > 0:
                chain.append(("act", "relu", label))
            elif lo <= 0.0 and hi >= 1.0:
                chain.append(("clip_wide", label))
            else:
                raise err(f"{label}: Clip({lo:g}, {hi:g}) is not supported: the Kilobot's output is the linear "
                          "layer clipped to [0, 1], so only Clip(min<=0, max>=1) after the last layer, or "
                          "Clip(0, inf) as a ReLU, can be imported")
        elif op == "Identity":
            pass
        elif op == "Dropout":
            tm = const_in(node, 2, label)
            if tm is not None and bool(np.asarray(tm).reshape(-1)[0]):
                raise err(f"{label}: Dropout in training mode; export the model in eval mode")
            if len(node.output) > 1 and node.output[1] and any(node.output[1] in n.input for n in g.node):
                raise err(f"{label}: Dropout's mask output is used; only plain MLPs are supported")
        elif op == "Flatten":
            if int(a.get("axis", 1)) not in (1, -1):
                raise err(f"{label}: Flatten(axis={a.get('axis')}) changes the [N, D] layout")
        elif op == "Reshape":
            if int(a.get("allowzero", 0)):
                raise err(f"{label}: Reshape with allowzero=1 is not supported")
            shape = const_in(node, 1, label)
            s = [int(v) for v in np.asarray(shape).reshape(-1)]
            if not (len(s) == 2 and s[0] in (-1, 0) and (s[1] == -1 or width is None or s[1] == width)):
                raise err(f"{label}: Reshape to {s} changes the [N, D] layout; only [-1, D] / [0, D] are no-ops")
        else:
            raise err(f"{label}: op {op} is not supported; kiloforge imports MLPs built from Gemm / MatMul+Add "
                      "with Relu, Elu, Tanh, Sigmoid (see docs/onnx.md)")
        cur = node.output[0]

    if cur != out_name:
        raise err(f"graph output '{out_name}' is not the end of the layer chain ('{cur}')")
    dense_at = [i for i, c in enumerate(chain) if c[0] == "dense"]
    if not dense_at:
        raise err("no dense layer (Gemm or MatMul) found")

    # ---- assemble layers: one activation between dense layers; harmless ops after the last ------
    if dense_at[0] != 0:
        raise err(f"{chain[0][-1]}: activation before any dense layer; the actor must start with Gemm or MatMul")
    layers: list[_Layer] = []
    for k, i in enumerate(dense_at):
        lay = chain[i][1]
        end = dense_at[k + 1] if k + 1 < len(dense_at) else len(chain)
        between = chain[i + 1:end]
        if k + 1 < len(dense_at):  # hidden layer
            if any(c[0] == "clip_wide" for c in between):
                lbl = next(c[1] for c in between if c[0] == "clip_wide")
                raise err(f"{lbl}: a Clip that is not Clip(0, inf) is only supported after the last layer")
            if len(between) > 1:
                raise err(f"{between[1][2]}: two activations in a row; each dense layer has one activation")
            lay.act = between[0][1] if between else "identity"
        else:  # output layer: clip01(relu(y)) == clip01(clip(y, lo<=0, hi>=1)) == clip01(y)
            for c in between:
                if c[0] == "act" and c[1] != "relu":
                    raise err(f"{c[2]}: the last layer ends in {c[1]}; the Kilobot's output layer is linear, "
                              "clipped to [0, 1]: re-export with a linear last layer (optionally + Clip(0, 1))")
            lay.act = "identity"
            tail = [c[-1] for c in between]
        layers.append(lay)
    last = layers[-1]

    # ---- shapes, values, world -----------------------------------------------------------
    if last.w.shape[0] != ACTION_DIM:
        raise err(f"the actor outputs {last.w.shape[0]} values; the Kilobot needs {ACTION_DIM} (u_left, u_right)")
    out_t = g.output[0].type.tensor_type
    if out_t.HasField("shape") and len(out_t.shape.dim) == 2 and out_t.shape.dim[1].HasField("dim_value") \
            and out_t.shape.dim[1].dim_value != ACTION_DIM:
        raise err(f"the declared output width is {out_t.shape.dim[1].dim_value}, not {ACTION_DIM}")
    weights = [np.asarray(l.w, np.float32) for l in layers]
    biases = [np.asarray(l.b, np.float32) for l in layers]
    for i, (w, b) in enumerate(zip(weights, biases)):
        if not (np.all(np.isfinite(w)) and np.all(np.isfinite(b))):
            raise err(f"layer {i} ({layers[i].node}) has NaN or infinite weights")
    acts = [l.act for l in layers]

    try:  # types and shapes as a runtime infers them (e.g. a float16 weight on float32 data is refused)
        onnx.checker.check_model(model, full_check=True)
    except Exception as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise err(f"invalid ONNX model: {first}") from None

    world, t_prev, world_src = _resolve_world(meta, world_json, path)
    got = weights[0].shape[1] if in_width is None else in_width
    if t_prev is None:  # a world JSON without t_prev (a run's world.json): the input width gives it
        if got % world.tuple_dim or not 1 <= got // world.tuple_dim <= MAX_T_PREV:
            src = world_src[5:] if world_src.startswith("json:") else world_src
            raise err(f"{src} gives no 't_prev' and the model's input ({got} features) is not a whole "
                      f"number of {world.tuple_dim}-feature tuples of world '{world.name}'; add \"t_prev\": N")
        t_prev = got // world.tuple_dim
    need = world.history_dim(t_prev)
    if got != need:
        raise err(f"the model's input has {got} features but world '{world.name}' with t_prev={t_prev} needs "
                  f"{need} = {t_prev} tuples x {world.tuple_dim} ([a_prev_left, a_prev_right, wall, target, "
                  f"nbr_sensing, {world.n_rbf} RBF bins], oldest first)")

    provenance = {
        "source": "onnx",
        "onnx_file": path.name,
        "onnx_sha256": hashlib.sha256(data).hexdigest(),
        "onnx_producer": f"{model.producer_name} {model.producer_version}".strip(),
        "onnx_opset": int(opset),
        "world_source": world_src,
    }
    if tail:
        provenance["onnx_output_ops_subsumed_by_clip01"] = tail
    if META_VERSION in meta:
        provenance["kiloforge_version_onnx"] = meta[META_VERSION]

    try:
        return MLPPolicy(weights=weights, biases=biases, activations=acts, t_prev=t_prev, world=world,
                         provenance=provenance)
    except (AssertionError, ValueError, TypeError, PolicyError) as e:
        if isinstance(e, OnnxImportError):
            raise
        raise err(f"not a valid kiloforge policy: {e}") from None


def _main(argv: list[str] | None = None) -> int:
    """``python -m export.interop.onnx_import MODEL.onnx [--world-json W.json] --out policy.npz``."""
    import sys

    from kiloforge.cliparse import ArgumentParser, error_line

    ap = ArgumentParser(prog="python -m export.interop.onnx_import",
                                 description="Convert an ONNX MLP actor into a kiloforge policy artifact (.npz).")
    ap.add_argument("model", help="the .onnx file (one input [N, history_dim], one output [N, 2])")
    ap.add_argument("--world-json", default=None, help="JSON with 'world' (dict or preset name) and 't_prev', "
                    "or a run's world.json, for models without kiloforge metadata")
    ap.add_argument("--out", required=True, help="policy artifact to write (.npz)")
    args = ap.parse_args(argv)
    try:
        pol = load_onnx_policy(args.model, args.world_json)
        save_policy(pol, args.out)
    except PolicyError as e:
        print(error_line(ap.prog, e), file=sys.stderr)
        return 2
    shapes = " -> ".join([str(pol.weights[0].shape[1])] + [f"{w.shape[0]} {a}" for w, a in zip(pol.weights, pol.activations)])
    print(f"wrote {args.out}: {shapes}; world '{pol.world.name}', t_prev {pol.t_prev}")
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
