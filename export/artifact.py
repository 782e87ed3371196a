"""The policy artifact: a float MLP actor plus its world, as plain data (no pickle, no torch).

File format (one ``.npz`` in :func:`numpy.savez`'s layout, byte-for-byte reproducible)::

    w0, b0, w1, b1, ...   float32 weights (out, in) and biases (out,), layer 0 first
    meta                  uint8 array holding UTF-8 JSON:
        format "kiloforge-policy", format_version 1, kind "mlp",
        layer_sizes [in, hidden..., 2], activations [one per layer], t_prev,
        action_mapping "clip01", world (WorldConfig.to_dict()), provenance {...},
        policy_hash (sha256 of the canonical bytes of the weights and of meta without this field)

Kind ``"gru"`` (a recurrent actor: GRU cell + linear output) has its own arrays and checks in
:mod:`export.gru` (:class:`export.gru.GRUPolicy`); ``load_policy`` returns one for such a file.

``load_policy`` reads it with ``allow_pickle=False`` and validates everything (structure, version,
shapes against the world's history width, finite values, activations, world config, hash); every
problem raises :class:`PolicyError` with one line that names the file and the problem.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from sim.config import ACTION_DIM, WorldConfig

from .atomic import write_bytes_atomic
from .errors import ExportError, PolicyError
from .numfmt import ACTIVATIONS, act_float

__all__ = ["Policy", "save_policy", "load_policy", "PolicyError", "FORMAT", "FORMAT_VERSION", "npz_bytes"]

FORMAT = "kiloforge-policy"
FORMAT_VERSION = 1
KINDS = ("mlp", "gru")  #: "gru": the recurrent actor of export/gru.py (GRUPolicy)
MLP_KINDS = ("mlp",)  #: kinds this module's Policy class holds
ACTION_MAPPING = "clip01"  #: actions are the output layer's values clipped to [0, 1]


def _canonical_json(obj: Any) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True,
                      allow_nan=False).encode("ascii")


@dataclass(frozen=True, eq=False)
class Policy:
    """A float MLP actor: ``u = clip01(act_L(W_L ... act_0(W_0 h + b_0) ... + b_L))``.

    ``weights[k]`` is (out, in) float32, ``biases[k]`` (out,), ``activations[k]`` one of
    ``numfmt.ACTIVATIONS`` (the last one is the output layer's). The input is the flat history of
    ``t_prev`` tuples (oldest first), ``world.history_dim(t_prev)`` wide; the output has 2 columns.
    Invalid contents raise :class:`PolicyError`.
    """

    weights: Sequence[np.ndarray]
    biases: Sequence[np.ndarray]
    activations: Sequence[str]
    t_prev: int
    world: WorldConfig
    provenance: dict[str, Any] = field(default_factory=dict)
    kind: str = "mlp"

    def __post_init__(self) -> None:
        def bad(msg: str) -> None:
            raise PolicyError(f"policy: {msg}")

        if self.kind not in MLP_KINDS:
            hint = " (a recurrent actor is an export.gru.GRUPolicy)" if self.kind == "gru" else ""
            bad(f"unknown kind '{self.kind}' (supported: {', '.join(MLP_KINDS)}){hint}")
        if not isinstance(self.world, WorldConfig):
            bad(f"world must be a WorldConfig, got {type(self.world).__name__}")
        if isinstance(self.t_prev, bool) or not isinstance(self.t_prev, (int, np.integer)) or self.t_prev < 1:
            bad(f"t_prev must be an integer >= 1, got {self.t_prev!r}")
        n = len(self.weights)
        if n < 1:
            bad("no layers")
        if len(self.biases) != n or len(self.activations) != n:
            bad(f"{n} weight matrices but {len(self.biases)} biases and {len(self.activations)} activations")
        ws, bs = [], []
        for k, (w, b, a) in enumerate(zip(self.weights, self.biases, self.activations)):
            w = np.asarray(w)
            b = np.asarray(b)
            if w.dtype.kind not in "fiu" or b.dtype.kind not in "fiu":
                bad(f"layer {k}: weights and biases must be numeric, got {w.dtype} and {b.dtype}")
            if w.ndim != 2:
                bad(f"layer {k}: weight matrix must be 2-D (out, in), got shape {w.shape}")
            if b.shape != (w.shape[0],):
                bad(f"layer {k}: bias shape {b.shape} does not match weight shape {w.shape} (expected ({w.shape[0]},))")
            if w.size == 0:
                bad(f"layer {k}: empty weight matrix {w.shape}")
            if not (np.all(np.isfinite(w)) and np.all(np.isfinite(b))):
                bad(f"layer {k}: non-finite (NaN or inf) weight or bias")
            if not isinstance(a, str) or a not in ACTIVATIONS:
                bad(f"layer {k}: unknown activation {a!r} (supported: {', '.join(ACTIVATIONS)})")
            ws.append(np.ascontiguousarray(w, dtype=np.float32))
            bs.append(np.ascontiguousarray(b, dtype=np.float32))
            if not (np.all(np.isfinite(ws[-1])) and np.all(np.isfinite(bs[-1]))):
                bad(f"layer {k}: weight or bias overflows float32")
        for k in range(1, n):
            if ws[k].shape[1] != ws[k - 1].shape[0]:
                bad(f"layer {k} takes {ws[k].shape[1]} inputs but layer {k - 1} produces {ws[k - 1].shape[0]}")
        want_in = self.world.history_dim(int(self.t_prev))
        if ws[0].shape[1] != want_in:
            bad(f"input width {ws[0].shape[1]} != history width {want_in} = t_prev {int(self.t_prev)} x tuple "
                f"{self.world.tuple_dim} (2 actions + {self.world.obs_dim} observations of world "
                f"'{self.world.name}')")
        if ws[-1].shape[0] != ACTION_DIM:
            bad(f"output width {ws[-1].shape[0]} != {ACTION_DIM} (u_left, u_right)")
        if not isinstance(self.provenance, dict):
            bad(f"provenance must be a dict, got {type(self.provenance).__name__}")
        try:
            _canonical_json(self.provenance)
        except (TypeError, ValueError) as e:
            bad(f"provenance is not plain JSON data ({e})")
        for w in ws + bs:
            w.setflags(write=False)
        object.__setattr__(self, "weights", tuple(ws))
        object.__setattr__(self, "biases", tuple(bs))
        object.__setattr__(self, "activations", tuple(str(a) for a in self.activations))
        object.__setattr__(self, "t_prev", int(self.t_prev))
        object.__setattr__(self, "provenance", json.loads(_canonical_json(self.provenance)))

    # --- shapes -----------------------------------------------------------------------------
    @property
    def in_dim(self) -> int:
        return int(self.weights[0].shape[1])

    @property
    def layer_sizes(self) -> list[int]:
        """[in_dim, hidden..., 2]."""
        return [self.in_dim] + [int(w.shape[0]) for w in self.weights]

    @property
    def hidden(self) -> list[int]:
        return self.layer_sizes[1:-1]

    @property
    def n_params(self) -> int:
        return int(sum(w.size + b.size for w, b in zip(self.weights, self.biases)))

    # --- inference --------------------------------------------------------------------------
    def layer_outputs(self, history: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """[(pre-activation, activation)] per layer in float64; the last activation is clipped to [0, 1]."""
        x = np.asarray(history, np.float64)
        assert x.shape[-1] == self.in_dim, f"history width {x.shape[-1]} != policy input width {self.in_dim}"
        out = []
        for k, (w, b, a) in enumerate(zip(self.weights, self.biases, self.activations)):
            z = x @ w.astype(np.float64).T + b.astype(np.float64)  # (..., n_out)
            x = act_float(a, z)
            if k == len(self.weights) - 1:
                x = np.clip(x, 0.0, 1.0)  # action mapping "clip01"
            out.append((z, x))
        return out

    def act(self, history: np.ndarray) -> np.ndarray:
        """Flat history (..., in_dim) -> actions (..., 2) float64 in [0, 1]."""
        return self.layer_outputs(history)[-1][1]

    # --- serialisation ----------------------------------------------------------------------
    def meta(self) -> dict[str, Any]:
        """The JSON metadata (without ``policy_hash``)."""
        return {
            "format": FORMAT, "format_version": FORMAT_VERSION, "kind": self.kind,
            "layer_sizes": self.layer_sizes, "activations": list(self.activations), "t_prev": self.t_prev,
            "action_mapping": ACTION_MAPPING, "world": self.world.to_dict(), "provenance": self.provenance,
        }

    def canonical_bytes(self) -> bytes:
        """What :attr:`hash` covers: every array (little-endian float32, with its shape) and the meta."""
        h = io.BytesIO()
        for k, (w, b) in enumerate(zip(self.weights, self.biases)):
            for name, arr in ((f"w{k}", w), (f"b{k}", b)):
                h.write(f"{name}:{'x'.join(map(str, arr.shape))}:<f4\n".encode("ascii"))
                h.write(np.ascontiguousarray(arr, "<f4").tobytes())
        h.write(_canonical_json(self.meta()))
        return h.getvalue()

    @cached_property
    def hash(self) -> str:
        """sha256 (hex) of :meth:`canonical_bytes`: the policy's identity in manifests and C banners."""
        return hashlib.sha256(self.canonical_bytes()).hexdigest()

    def to_npz_bytes(self) -> bytes:
        meta = dict(self.meta(), policy_hash=self.hash)
        arrays: dict[str, np.ndarray] = {}
        for k, (w, b) in enumerate(zip(self.weights, self.biases)):
            arrays[f"w{k}"] = w
            arrays[f"b{k}"] = b
        arrays["meta"] = np.frombuffer(json.dumps(meta, sort_keys=True, indent=1).encode("utf-8"), np.uint8)
        return npz_bytes(arrays)


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """The layout of numpy.savez (one .npy member per array, stored, in the given order), with fixed
    member timestamps so that the same arrays always give the same bytes."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            with zf.open(info, "w") as f:
                np.lib.format.write_array(f, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()


def save_policy(policy: Policy, path: str | os.PathLike) -> Path:
    """Write ``policy`` to one ``.npz`` file atomically (temp file + rename); returns the path."""
    path = Path(path)
    try:
        write_bytes_atomic(path, policy.to_npz_bytes())
    except ExportError as e:
        raise PolicyError(str(e)) from None
    return path


def load_policy(path: str | os.PathLike) -> Policy:
    """Read and validate a policy artifact; raises :class:`PolicyError` (one line naming the file)."""
    path = Path(path)
    name = f"policy file '{path}'"

    def bad(msg: str) -> PolicyError:
        return PolicyError(f"{name}: {msg}")

    if not path.exists():
        raise bad("does not exist")
    if path.is_dir():
        raise bad("is a directory, not a .npz file")
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise bad(f"cannot be read ({e.strerror or e})") from None
    if not raw:
        raise bad("is empty")
    if not zipfile.is_zipfile(io.BytesIO(raw)):
        raise bad("is not a .npz (zip) archive; truncated or not a policy")
    try:
        with np.load(io.BytesIO(raw), allow_pickle=False) as z:
            names = set(z.files)
            if "meta" not in names:
                raise bad("has no 'meta' entry; not a kiloforge policy")
            arrays = {n: z[n] for n in names}
    except PolicyError:
        raise
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, KeyError) as e:
        raise bad(f"is corrupt or truncated ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    except Exception as e:  # zlib.error and friends from a damaged member
        raise bad(f"is corrupt or truncated ({type(e).__name__})") from None

    meta_arr = arrays.pop("meta")
    if meta_arr.dtype != np.uint8 or meta_arr.ndim != 1:
        raise bad(f"'meta' must be a 1-D uint8 array of UTF-8 JSON, got {meta_arr.dtype} {meta_arr.shape}")
    try:
        meta = json.loads(meta_arr.tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise bad(f"'meta' is not valid UTF-8 JSON ({e})") from None
    if not isinstance(meta, dict):
        raise bad("'meta' must be a JSON object")
    if meta.get("format") != FORMAT:
        raise bad(f"format is {meta.get('format')!r}, expected '{FORMAT}'")
    version = meta.get("format_version")
    if version != FORMAT_VERSION:
        raise bad(f"format version {version!r} is not supported (this kiloforge reads version {FORMAT_VERSION})")
    kind = meta.get("kind")
    if kind not in KINDS:
        raise bad(f"unknown kind {kind!r} (supported: {', '.join(KINDS)})")
    if meta.get("action_mapping", ACTION_MAPPING) != ACTION_MAPPING:
        raise bad(f"action mapping {meta.get('action_mapping')!r} is not supported (only '{ACTION_MAPPING}')")
    if kind == "gru":  # the recurrent actor: its own arrays and checks (export/gru.py)
        from .gru import gru_policy_from_arrays
        try:
            gru = gru_policy_from_arrays(arrays, meta)
        except PolicyError as e:
            raise bad(str(e).removeprefix("policy: ")) from None
        return _check_hash(gru, meta, bad)
    for key in ("activations", "t_prev", "world", "layer_sizes"):
        if key not in meta:
            raise bad(f"'meta' lacks '{key}'")
    acts = meta["activations"]
    if not isinstance(acts, list) or not acts:
        raise bad("'activations' must be a non-empty list")
    n = len(acts)
    for k in range(n):
        for a in (f"w{k}", f"b{k}"):
            if a not in arrays:
                raise bad(f"lacks array '{a}' ({n} layers declared)")
    extra = sorted(set(arrays) - {f"{p}{k}" for k in range(n) for p in "wb"})
    if extra:
        raise bad(f"has unexpected arrays: {', '.join(extra)}")
    sizes = meta["layer_sizes"]
    shapes = [arrays[f"w{k}"].shape for k in range(n)]
    declared = [[sizes[k + 1], sizes[k]] for k in range(len(sizes) - 1)] if isinstance(sizes, list) else None
    if declared != [list(s) for s in shapes]:
        raise bad(f"layer_sizes {sizes} do not match the weight shapes {[tuple(s) for s in shapes]}")
    try:
        world = WorldConfig.from_dict(meta["world"])
    except (TypeError, ValueError) as e:
        raise bad(f"invalid world config ({e})") from None
    prov = meta.get("provenance", {})
    try:
        policy = Policy(weights=[arrays[f"w{k}"] for k in range(n)], biases=[arrays[f"b{k}"] for k in range(n)],
                        activations=acts, t_prev=meta["t_prev"], world=world, provenance=prov, kind=kind)
    except PolicyError as e:
        raise bad(str(e).removeprefix("policy: ")) from None
    return _check_hash(policy, meta, bad)


def _check_hash(policy: Any, meta: dict, bad: Any) -> Any:
    """The loaded policy, unless the stored ``policy_hash`` disagrees with its contents."""
    stored = meta.get("policy_hash")
    if stored is not None and stored != policy.hash:
        raise bad(f"policy_hash {str(stored)[:12]}... does not match the contents ({policy.hash[:12]}...); "
                  "the file was modified")
    return policy
