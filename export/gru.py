"""The recurrent actor as plain data: a GRU cell and a linear output layer (policy kind ``"gru"``).

Per control step a robot feeds one tuple ``x = [a_prev(2), obs(obs_dim)]`` (the tuple of
:mod:`sim.history`, ``world.tuple_dim`` wide) and its hidden state ``h`` (``hidden`` floats, zero at
the start of an episode; Algorithm 5: ``a_0 = 0``, hidden state zero) into PyTorch's GRU cell, gate
order r, z, n::

    r  = σ(W_ir x + b_ir + W_hr h + b_hr)
    z  = σ(W_iz x + b_iz + W_hz h + b_hz)
    n  = tanh(W_in x + b_in + r ⊙ (W_hn h + b_hn))
    h' = (1 − z) ⊙ n + z ⊙ h
    u  = clip01(W_out h' + b_out)                        (u_left, u_right) in [0, 1]

File format (one ``.npz`` in the layout of :func:`export.artifact.npz_bytes`): ``w_ih`` (3H, D),
``w_hh`` (3H, H), ``b_ih`` (3H,), ``b_hh`` (3H,), ``w_out`` (2, H), ``b_out`` (2,) float32 (rows in
gate order r, z, n exactly as ``torch.nn.GRUCell`` stores them) and ``meta`` (UTF-8 JSON: format
"kiloforge-policy", format_version 1, kind "gru", hidden, input_dim, gate_order "rzn",
input "a_prev+obs", action_mapping "clip01", world, provenance, policy_hash). ``load_policy``
(:mod:`export.artifact`) dispatches here and validates shapes, finiteness, the world and the hash.

:class:`GRUSwarmPolicy` runs any step function of this form (the float policy, the int8 one of
:mod:`export.gru_quantize`) as a :class:`sim.rollout.SwarmPolicy`.
"""
from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Callable

import numpy as np

from sim.config import ACTION_DIM, WorldConfig

from .artifact import ACTION_MAPPING, FORMAT, FORMAT_VERSION, _canonical_json, npz_bytes
from .errors import PolicyError

KIND = "gru"
GATE_ORDER = "rzn"  #: PyTorch's order of the three row blocks of w_ih, w_hh, b_ih, b_hh
INPUT_LAYOUT = "a_prev+obs"  #: one sim.history tuple per step
ARRAYS = ("w_ih", "w_hh", "b_ih", "b_hh", "w_out", "b_out")
MAX_HIDDEN = 255  #: the firmware indexes hidden units with uint8


def _sigmoid(z: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * z))  # overflow-free σ


@dataclass(frozen=True, eq=False)
class GRUPolicy:
    """A float GRU actor (see the module doc); invalid contents raise :class:`PolicyError`."""

    w_ih: np.ndarray  #: (3H, D) float32, gate blocks r, z, n
    w_hh: np.ndarray  #: (3H, H)
    b_ih: np.ndarray  #: (3H,)
    b_hh: np.ndarray  #: (3H,)
    w_out: np.ndarray  #: (2, H)
    b_out: np.ndarray  #: (2,)
    world: WorldConfig
    provenance: dict[str, Any] = field(default_factory=dict)
    kind: str = KIND

    def __post_init__(self) -> None:
        def bad(msg: str) -> None:
            raise PolicyError(f"policy: {msg}")

        if self.kind != KIND:
            bad(f"a GRUPolicy has kind '{KIND}', got '{self.kind}'")
        if not isinstance(self.world, WorldConfig):
            bad(f"world must be a WorldConfig, got {type(self.world).__name__}")
        arrs = {}
        for name in ARRAYS:
            a = np.asarray(getattr(self, name))
            if a.dtype.kind not in "fiu":
                bad(f"'{name}' must be numeric, got {a.dtype}")
            a = np.ascontiguousarray(a, dtype=np.float32)
            if not np.all(np.isfinite(a)):
                bad(f"'{name}' holds non-finite values (NaN, inf, or beyond float32)")
            arrs[name] = a
        w_ih, w_hh = arrs["w_ih"], arrs["w_hh"]
        if w_hh.ndim != 2 or w_hh.shape[0] != 3 * w_hh.shape[1] or w_hh.shape[1] < 1:
            bad(f"w_hh must be (3H, H), got {w_hh.shape}")
        H = w_hh.shape[1]
        if H > MAX_HIDDEN:
            bad(f"hidden size {H} > {MAX_HIDDEN} (the firmware indexes hidden units with uint8)")
        D = self.world.tuple_dim
        want = {"w_ih": (3 * H, D), "b_ih": (3 * H,), "b_hh": (3 * H,), "w_out": (ACTION_DIM, H),
                "b_out": (ACTION_DIM,)}
        for name, shape in want.items():
            if arrs[name].shape != shape:
                extra = (f" = (3 x hidden {H}, tuple {D}: 2 actions + {self.world.obs_dim} observations of world "
                         f"'{self.world.name}')") if name == "w_ih" else ""
                bad(f"'{name}' has shape {arrs[name].shape}, expected {shape}{extra}")
        del w_ih
        if not isinstance(self.provenance, dict):
            bad(f"provenance must be a dict, got {type(self.provenance).__name__}")
        try:
            _canonical_json(self.provenance)
        except (TypeError, ValueError) as e:
            bad(f"provenance is not plain JSON data ({e})")
        for name, a in arrs.items():
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        object.__setattr__(self, "provenance", json.loads(_canonical_json(self.provenance)))

    # --- shapes -----------------------------------------------------------------------------
    @property
    def hidden_size(self) -> int:
        return int(self.w_hh.shape[1])

    @property
    def in_dim(self) -> int:
        """Input width per step: one tuple, ``world.tuple_dim``."""
        return int(self.w_ih.shape[1])

    @property
    def t_prev(self) -> int:
        """1: the actor reads one tuple per step (its hidden state carries the past)."""
        return 1

    @property
    def hidden(self) -> list[int]:
        return [self.hidden_size]

    @property
    def layer_sizes(self) -> list[int]:
        """[in_dim, hidden, 2] (printing and manifests)."""
        return [self.in_dim, self.hidden_size, ACTION_DIM]

    @property
    def activations(self) -> tuple[str, ...]:
        return ("gru", "identity")

    @property
    def n_params(self) -> int:
        return int(sum(getattr(self, n).size for n in ARRAYS))

    # --- inference --------------------------------------------------------------------------
    def initial_state(self, shape: tuple[int, ...]) -> np.ndarray:
        """Zero hidden states (``shape`` + (H,), float64): the start of an episode."""
        return np.zeros(tuple(shape) + (self.hidden_size,))

    def gates(self, x: np.ndarray, h: np.ndarray) -> dict[str, np.ndarray]:
        """Every intermediate of one step in float64 (calibration): pre-activations and gates, h' and u."""
        x = np.asarray(x, np.float64)
        h = np.asarray(h, np.float64)
        assert x.shape[-1] == self.in_dim, f"input width {x.shape[-1]} != {self.in_dim}"
        assert h.shape[-1] == self.hidden_size, f"hidden width {h.shape[-1]} != {self.hidden_size}"
        H = self.hidden_size
        gi = x @ self.w_ih.astype(np.float64).T + self.b_ih  # (..., 3H)
        gh = h @ self.w_hh.astype(np.float64).T + self.b_hh  # (..., 3H)
        a_r = gi[..., :H] + gh[..., :H]
        a_z = gi[..., H:2 * H] + gh[..., H:2 * H]
        nx, nh = gi[..., 2 * H:], gh[..., 2 * H:]
        r, z = _sigmoid(a_r), _sigmoid(a_z)
        pre_n = nx + r * nh
        n = np.tanh(pre_n)
        h2 = (1.0 - z) * n + z * h
        out = h2 @ self.w_out.astype(np.float64).T + self.b_out  # (..., 2)
        return {"a_r": a_r, "a_z": a_z, "nx": nx, "nh": nh, "r": r, "z": z, "pre_n": pre_n, "n": n,
                "h": h2, "out": out, "u": np.clip(out, 0.0, 1.0)}

    def step(self, x: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One control step: tuples (..., D) and states (..., H) -> (u (..., 2) in [0, 1], new states)."""
        g = self.gates(x, h)
        return g["u"], g["h"]

    def act_sequence(self, xs: np.ndarray) -> np.ndarray:
        """Actions (..., T, 2) for input sequences (..., T, D) from a zero state (tests, plots)."""
        xs = np.asarray(xs, np.float64)
        h = self.initial_state(xs.shape[:-2])
        out = np.empty(xs.shape[:-1] + (ACTION_DIM,))
        for t in range(xs.shape[-2]):
            out[..., t, :], h = self.step(xs[..., t, :], h)
        return out

    # --- serialisation ----------------------------------------------------------------------
    def meta(self) -> dict[str, Any]:
        """The JSON metadata (without ``policy_hash``)."""
        return {"format": FORMAT, "format_version": FORMAT_VERSION, "kind": KIND, "hidden": self.hidden_size,
                "input_dim": self.in_dim, "gate_order": GATE_ORDER, "input": INPUT_LAYOUT,
                "action_mapping": ACTION_MAPPING, "world": self.world.to_dict(), "provenance": self.provenance}

    def canonical_bytes(self) -> bytes:
        """What :attr:`hash` covers: every array (little-endian float32, with its shape) and the meta."""
        h = io.BytesIO()
        for name in ARRAYS:
            arr = getattr(self, name)
            h.write(f"{name}:{'x'.join(map(str, arr.shape))}:<f4\n".encode("ascii"))
            h.write(np.ascontiguousarray(arr, "<f4").tobytes())
        h.write(_canonical_json(self.meta()))
        return h.getvalue()

    @cached_property
    def hash(self) -> str:
        """sha256 (hex) of :meth:`canonical_bytes`."""
        return hashlib.sha256(self.canonical_bytes()).hexdigest()

    def to_npz_bytes(self) -> bytes:
        """The file :func:`export.artifact.save_policy` writes (byte-for-byte reproducible)."""
        meta = dict(self.meta(), policy_hash=self.hash)
        arrays = {name: getattr(self, name) for name in ARRAYS}
        arrays["meta"] = np.frombuffer(json.dumps(meta, sort_keys=True, indent=1).encode("utf-8"), np.uint8)
        return npz_bytes(arrays)


def gru_policy_from_arrays(arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> GRUPolicy:
    """Build a :class:`GRUPolicy` from a loaded file's arrays and meta (raises :class:`PolicyError`)."""
    missing = [n for n in ARRAYS if n not in arrays]
    if missing:
        raise PolicyError(f"policy: lacks array(s) {', '.join(missing)} of a '{KIND}' policy")
    extra = sorted(set(arrays) - set(ARRAYS))
    if extra:
        raise PolicyError(f"policy: has unexpected arrays: {', '.join(extra)}")
    for key in ("hidden", "world", "gate_order", "input"):
        if key not in meta:
            raise PolicyError(f"policy: 'meta' lacks '{key}'")
    if meta["gate_order"] != GATE_ORDER:
        raise PolicyError(f"policy: gate order {meta['gate_order']!r} is not supported (only '{GATE_ORDER}')")
    if meta["input"] != INPUT_LAYOUT:
        raise PolicyError(f"policy: input layout {meta['input']!r} is not supported (only '{INPUT_LAYOUT}')")
    try:
        world = WorldConfig.from_dict(meta["world"])
    except (TypeError, ValueError) as e:
        raise PolicyError(f"policy: invalid world config ({e})") from None
    p = GRUPolicy(**{n: arrays[n] for n in ARRAYS}, world=world, provenance=meta.get("provenance", {}))
    if meta["hidden"] != p.hidden_size or meta.get("input_dim", p.in_dim) != p.in_dim:
        raise PolicyError(f"policy: meta says hidden {meta['hidden']}, input {meta.get('input_dim')} but the "
                          f"arrays have hidden {p.hidden_size}, input {p.in_dim}")
    return p


StepFn = Callable[[np.ndarray, Any], tuple[np.ndarray, Any]]


class GRUSwarmPolicy:
    """A :class:`sim.rollout.SwarmPolicy` around ``step(x (R, D), state) -> (u (R, 2), state)``.

    ``init(R)`` gives the zero state of R robots. Per call the input tuple is
    ``[previous action, obs]``: the previous action is what this policy returned last (zero on
    the first step of an episode, as in the firmware and Algorithm 5).
    """

    def __init__(self, step: StepFn, init: Callable[[int], Any], world: WorldConfig) -> None:
        self.step_fn, self.init_fn, self.world = step, init, world
        self.state: Any = None
        self.prev: np.ndarray | None = None  # (B, M, 2)

    @classmethod
    def float_policy(cls, policy: GRUPolicy) -> "GRUSwarmPolicy":
        """The float actor of an artifact."""
        return cls(policy.step, lambda R: policy.initial_state((R,)), policy.world)

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator | None = None) -> None:
        self.state = self.init_fn(n_envs * n_robots)
        self.prev = np.zeros((n_envs, n_robots, ACTION_DIM), np.float32)

    def act(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, np.float32)
        assert self.prev is not None and obs.shape[:2] == self.prev.shape[:2], "GRUSwarmPolicy.act before reset"
        B, M, _ = obs.shape
        x = np.concatenate([self.prev, obs], -1).reshape(B * M, -1)  # (R, D)
        u, self.state = self.step_fn(x, self.state)
        u = np.clip(np.asarray(u, np.float64).reshape(B, M, ACTION_DIM), 0.0, 1.0)
        self.prev = u.astype(np.float32)
        return u


def random_gru_policy(world: WorldConfig, hidden: int, seed: int = 0, scale: float = 1.0,
                      out_bias: float = 0.5, out_scale: float = 1.0, provenance: dict | None = None) -> GRUPolicy:
    """A deterministic untrained GRU policy (tests, benchmarks): cell weights U(±scale/√H), output
    weights U(±out_scale/√H) and biases ``out_bias`` so that the commands spread over [0, 1]."""
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    D, H = world.tuple_dim, int(hidden)
    b = scale / np.sqrt(H)
    u = lambda *shape, lim=b: rng.uniform(-lim, lim, size=shape).astype(np.float32)  # noqa: E731
    return GRUPolicy(w_ih=u(3 * H, D), w_hh=u(3 * H, H), b_ih=u(3 * H), b_hh=u(3 * H),
                     w_out=u(ACTION_DIM, H, lim=out_scale / np.sqrt(H)), b_out=np.full(ACTION_DIM, out_bias, np.float32),
                     world=world, provenance=dict(provenance or {"notes": f"random_gru_policy seed {seed}"}))


def swarm_policy(policy: Any, world: WorldConfig | None = None) -> Any:
    """The float actor of any policy artifact as a SwarmPolicy: GRUSwarmPolicy for kind "gru", else
    :class:`sim.rollout.HistoryActor` around ``policy.act`` (``world``: an override, e.g. episode length)."""
    if getattr(policy, "kind", "mlp") == KIND:
        return GRUSwarmPolicy.float_policy(policy)
    from sim.rollout import HistoryActor
    return HistoryActor(policy.act, policy.t_prev, world or policy.world)
