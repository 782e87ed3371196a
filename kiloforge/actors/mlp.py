"""Actor kind ``"mlp"``: a feed-forward actor on the last ``t_prev`` (previous action, observation) tuples.

Float actor (thesis §3.3, Algorithm 4)::

    u = clip01(act_L(W_L ... act_0(W_0 h + b_0) ... + b_L))     h = the flat history, oldest tuple first

Its state is the history ring: the first tuple ``(a_0 = 0, o_1)`` of an episode fills all
``t_prev`` slots, each later step drops the oldest tuple and appends ``[a_prev, obs]``.

Artifact arrays: ``w0, b0, w1, b1, ...`` float32 weights (out, in) and biases (out,), layer 0 first;
meta: ``layer_sizes [in, hidden..., 2]``, ``activations`` (one per layer, the last one the output's),
``t_prev``.

int8 network (the number format of :mod:`kiloforge.numfmt`): every layer a requantising dense layer,
hidden layers followed by ReLU (``max``) or a 256-entry table (ELU, tanh, sigmoid; identical tables
shared), the output layer producing the uint8 motor commands directly. The firmware keeps the int8
history in a ring buffer read oldest -> newest without copying (``kf_dense2``'s two segments);
template partial ``firmware_templates/actors/mlp.c.j2``, kernels ``kf_dense`` and the activations
of ``kf_runtime.h``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np

from sim.config import ACTION_DIM, WorldConfig
from sim.motion import action_to_u8
from sim.rollout import HistoryActor
from sim.tasks.base import TaskRef

from .. import numfmt
from ..artifact import plain_provenance
from ..errors import PolicyError, QuantizeError
from ..validate import show
from ..numfmt import ACTIVATIONS, INT8_MAX, INT8_MIN, OUTPUT_ACTIVATIONS, TABLE_ACTIVATIONS, QuantLayer, act_float
from .base import (ActorKind, BudgetItem, BudgetOption, BudgetSpec, CDefine, CDense, CTable, FloatPolicy,
                   QuantizedActor, RenderSpec, Resize, check_world_and_task, dense_summary, invalid, sensing_tables)
from .dense import (check_range_options, dense_weights, input_exponent, is_output_layer, output_layer,
                    saturated_fraction, value_range)

MAX_T_PREV = 255  #: the firmware's ring index is a uint8
MAX_HISTORY = 0xFFFF  #: history entries addressed with uint16


# --------------------------------------------------------------------------------------------
# The float actor
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class MLPPolicy(FloatPolicy):
    """A float MLP actor (see the module doc). ``weights[k]`` is (out, in) float32, ``biases[k]``
    (out,), ``activations[k]`` one of ``numfmt.ACTIVATIONS``; the input is the flat history of
    ``t_prev`` tuples, ``world.history_dim(t_prev)`` wide. Invalid contents raise :class:`PolicyError`."""

    kind: ClassVar[str] = "mlp"
    weights: Sequence[np.ndarray]
    biases: Sequence[np.ndarray]
    activations: Sequence[str]
    t_prev: int
    world: WorldConfig
    provenance: dict[str, Any] = field(default_factory=dict)
    task: TaskRef | None = None  #: the task it was trained for (None: a file from before tasks)

    def __post_init__(self) -> None:
        bad = invalid
        check_world_and_task(self.world, self.task)
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
        prov = plain_provenance(self.provenance)
        for w in ws + bs:
            w.setflags(write=False)
        object.__setattr__(self, "weights", tuple(ws))
        object.__setattr__(self, "biases", tuple(bs))
        object.__setattr__(self, "activations", tuple(str(a) for a in self.activations))
        object.__setattr__(self, "t_prev", int(self.t_prev))
        object.__setattr__(self, "provenance", prov)

    # --- shapes -----------------------------------------------------------------------------
    @property
    def in_dim(self) -> int:
        """Network input width: the flat history, ``world.history_dim(t_prev)``."""
        return int(self.weights[0].shape[1])

    @property
    def layer_sizes(self) -> list[int]:
        """[in_dim, hidden..., 2]."""
        return [self.in_dim] + [int(w.shape[0]) for w in self.weights]

    @property
    def hidden(self) -> list[int]:
        return self.layer_sizes[1:-1]

    def describe(self) -> str:
        return (f"t_prev {self.t_prev}, layers {' -> '.join(map(str, self.layer_sizes))} "
                f"({', '.join(self.activations)})")

    # --- artifact ---------------------------------------------------------------------------
    def arrays(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {}
        for k, (w, b) in enumerate(zip(self.weights, self.biases)):
            out[f"w{k}"] = w
            out[f"b{k}"] = b
        return out

    def kind_meta(self) -> dict[str, Any]:
        return {"layer_sizes": self.layer_sizes, "activations": list(self.activations), "t_prev": self.t_prev}

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

    def initial_state(self, n: int) -> None:
        """None: no history yet (the first step fills the ring with its tuple, Algorithm 4)."""
        return None

    def step(self, x: np.ndarray, state: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Tuples (n, D) and the history ring (n, t_prev, D) -> (u (n, 2), the new ring)."""
        hist = push_history(np.asarray(x), state, self.t_prev)
        return self.act(hist.reshape(hist.shape[0], -1)), hist


def push_history(x: np.ndarray, state: np.ndarray | None, t_prev: int) -> np.ndarray:
    """The history ring after appending tuples ``x`` (n, D): ``x`` repeated when ``state`` is None."""
    if state is None:
        return np.repeat(x[:, None, :], t_prev, axis=1)
    return np.concatenate([state[:, 1:], x[:, None, :]], axis=1)


def histories(seqs: np.ndarray, t_prev: int) -> np.ndarray:
    """(S, T, t_prev * D) flat histories of recorded tuple sequences (S, T, D), as the ring holds them."""
    S, T, D = seqs.shape
    idx = np.maximum(np.arange(T)[:, None] - t_prev + 1 + np.arange(t_prev)[None, :], 0)  # (T, t_prev)
    return seqs[:, idx].reshape(S, T, t_prev * D)


# --------------------------------------------------------------------------------------------
# The int8 actor
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False, kw_only=True)
class QuantizedMLP(QuantizedActor):
    """The int8 MLP: input the flat int8 history at exponent ``e_in`` (``t_prev`` tuples oldest first);
    output the two uint8 motor commands."""

    kind: ClassVar[str] = "mlp"
    layers: list[QuantLayer]  #: dense layers; layers[k+1].e_in == layers[k].e_act
    t_prev: int  #: history length (tuples)

    def __post_init__(self) -> None:
        super().__post_init__()
        L = len(self.layers)
        assert L >= 1, "a quantised policy needs at least one layer"
        assert self.t_prev >= 1, f"t_prev must be >= 1, got {self.t_prev}"
        assert self.layers[0].e_in == self.e_in, "first layer's input exponent must equal e_in"
        assert self.layers[0].w.shape[1] == self.in_dim, \
            f"first layer takes {self.layers[0].w.shape[1]} inputs, history is {self.in_dim}"
        for k in range(1, L):
            prev, cur = self.layers[k - 1], self.layers[k]
            assert cur.w.shape[1] == prev.w.shape[0], f"layer {k}: input width != layer {k - 1} output width"
            assert cur.e_in == prev.e_act, f"layer {k}: e_in {cur.e_in} != layer {k - 1} e_act {prev.e_act}"
            assert prev.lo == INT8_MIN and prev.hi == INT8_MAX, f"hidden layer {k - 1} must saturate to int8"
        out = self.layers[-1]
        assert out.w.shape[0] == ACTION_DIM, f"output layer must have {ACTION_DIM} rows"
        assert is_output_layer(out), "output layer must be identity, exponent 0, clamp 0..255 (the uint8 motor command)"

    @property
    def in_dim(self) -> int:
        """Network input width, ``world.history_dim(t_prev)``."""
        return self.world.history_dim(self.t_prev)

    @property
    def layer_sizes(self) -> list[int]:
        """[in_dim, hidden..., 2]."""
        return [self.layers[0].w.shape[1]] + [int(l.w.shape[0]) for l in self.layers]

    def quantize_history(self, history: np.ndarray) -> np.ndarray:
        """Float history (..., in_dim) -> int8 at ``e_in`` (half-up, saturating; for the error report)."""
        h = np.asarray(history, np.float64)
        assert h.shape[-1] == self.in_dim, f"history width {h.shape[-1]} != {self.in_dim}"
        return numfmt.quantize(h, self.e_in).astype(np.int8)

    def forward_layers(self, x_q: np.ndarray) -> list[np.ndarray]:
        """Every layer's integer output (after its activation), int64, for x_q (..., in_dim)."""
        x = np.asarray(x_q)
        assert x.shape[-1] == self.in_dim, f"input width {x.shape[-1]} != {self.in_dim}"
        assert np.all((x >= INT8_MIN) & (x <= INT8_MAX)), "inputs must be int8 values"
        outs = []
        for layer in self.layers:
            x = layer.forward(x)  # (..., n_out) int64
            outs.append(x)
        return outs

    def forward_int(self, x_q: np.ndarray) -> np.ndarray:
        """The firmware's network: int8 history (..., in_dim) -> uint8 motor commands (..., 2)."""
        return self.forward_layers(x_q)[-1].astype(np.uint8)

    def act_float(self, history: np.ndarray) -> np.ndarray:
        """Float history -> quantise -> integer actor -> u = q / 255 (float64)."""
        return self.forward_int(self.quantize_history(history)).astype(np.float64) / 255.0

    def initial_state(self, n: int) -> None:
        """None: setup() leaves the ring unstarted; the first control step fills it."""
        return None

    def step_int(self, x: np.ndarray, state: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """int8 tuples (R, D) and the int8 ring (R, t_prev, D) -> (uint8 commands (R, 2), the new ring)."""
        hist = push_history(np.asarray(x, np.int64), state, self.t_prev)
        return self.forward_int(hist.reshape(hist.shape[0], -1)), hist

    def summary(self) -> dict[str, Any]:
        return {"kind": self.kind, "format": self.format_name, "rounding": self.rounding, "e_in": int(self.e_in),
                "t_prev": int(self.t_prev), "layer_sizes": self.layer_sizes,
                "layers": [dense_summary(f"layer {k}", l) for k, l in enumerate(self.layers)],
                "policy_hash": self.policy_hash, "world": self.world.name}

    def describe(self) -> str:
        acts = ", ".join(l.activation for l in self.layers)
        return f"t_prev {self.t_prev}, {' -> '.join(map(str, self.layer_sizes))} ({acts}), e_in {self.e_in}"


# --------------------------------------------------------------------------------------------
# Calibration and error report
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Calibration:
    """What the float actor saw and computed: inputs and every layer's pre-activation/activation."""

    inputs: np.ndarray  #: (N, in_dim) float32 flat histories
    pre: tuple[np.ndarray, ...]  #: per layer (N, n_out) float64, W x + b
    post: tuple[np.ndarray, ...]  #: per layer (N, n_out) float64 activation (last: u clipped to [0, 1])
    info: dict[str, Any] = field(default_factory=dict)  #: episodes, robot counts, seed, steps

    @property
    def n(self) -> int:
        return int(self.inputs.shape[0])


def calibration_from_inputs(policy: MLPPolicy, inputs: np.ndarray, info: dict | None = None) -> Calibration:
    """Run the float actor on recorded inputs (N, in_dim) and keep every layer's values."""
    x = np.asarray(inputs, np.float32).reshape(-1, policy.in_dim)  # (N, in_dim)
    assert x.shape[0] >= 1, "calibration needs at least one input"
    pre, post = zip(*policy.layer_outputs(x))
    return Calibration(inputs=x, pre=tuple(pre), post=tuple(post), info=dict(info or {}))


@dataclass(frozen=True)
class LayerError:
    """Float vs dequantised integer values of one layer's output over the calibration set."""

    index: int
    n_in: int
    n_out: int
    activation: str
    e_in: int
    e_out: int
    e_act: int
    shift_min: int
    shift_max: int
    acc24_safe: bool
    max_abs: float  #: max |float - dequantised int| of the layer's output (last layer: u)
    mean_abs: float
    saturated: float  #: fraction of requantised values at lo or hi (output layer: commands 0 or 255, i.e. clip01)


@dataclass(frozen=True)
class ErrorReport:
    """Per-layer and end-to-end quantisation error (u = q / 255 vs the float actor)."""

    layers: tuple[LayerError, ...]
    du_max: float  #: max |u_int - u_float| over samples and both motors
    du_mean: float
    same_command: float  #: fraction of commands where q == action_to_u8(u_float)
    n_samples: int
    e_in: int
    input_saturated: float  #: fraction of history entries clamped by quantize_history

    def table(self) -> str:
        """A printable table."""
        head = (f"{'layer':>5} {'in':>5} {'out':>4} {'act':>8} {'e_in':>4} {'e_out':>5} {'e_act':>5} "
                f"{'shift':>7} {'acc24':>5} {'max|err|':>9} {'mean|err|':>9} {'sat%':>6}")
        lines = [f"quantisation error over {self.n_samples} calibration inputs (e_in = {self.e_in}, "
                 f"{100 * self.input_saturated:.2f}% of history entries saturated)", head, "-" * len(head)]
        for r in self.layers:
            lines.append(f"{r.index:>5} {r.n_in:>5} {r.n_out:>4} {r.activation:>8} {r.e_in:>4} {r.e_out:>5} "
                         f"{r.e_act:>5} {f'{r.shift_min}..{r.shift_max}':>7} {'yes' if r.acc24_safe else 'no':>5} "
                         f"{r.max_abs:>9.5f} {r.mean_abs:>9.5f} {100 * r.saturated:>6.2f}")
        lines.append(f"end to end: max |du| = {self.du_max:.5f}, mean |du| = {self.du_mean:.5f} "
                     f"(output rounding alone: 0.00196); same uint8 command: {100 * self.same_command:.2f}%")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": MLP.name, "du_max": self.du_max, "du_mean": self.du_mean, "same_command": self.same_command,
                "n_samples": self.n_samples, "e_in": self.e_in, "input_saturated": self.input_saturated,
                "layers": [dict(vars(r)) for r in self.layers]}


def quantize_mlp(policy: MLPPolicy, calib: Calibration, *, percentile: float = 100.0, headroom: float = 1.0,
                 e_in: int | None = None) -> QuantizedMLP:
    """Quantise ``policy`` with exponents from the calibration ranges: the input exponent, per hidden
    layer the pre-activation exponent and, for table activations, the activation exponent; per row
    the weight exponent with the overflow proof (:mod:`kiloforge.actors.dense`); the output layer
    produces the uint8 motor command directly (255 folded into its weights).

    ``percentile`` (<= 100) and ``headroom`` (>= 1 leaves room above the largest value seen) shape
    the range each exponent must cover; ``e_in`` overrides the input exponent.
    """
    check_range_options(percentile, headroom)
    if policy.activations[-1] not in OUTPUT_ACTIVATIONS:
        raise QuantizeError(
            f"output activation '{policy.activations[-1]}' is not supported by the int8 format; "
            f"use one of {', '.join(OUTPUT_ACTIVATIONS)} (actions are clipped to [0, 1])")
    assert calib.inputs.shape[1] == policy.in_dim, "calibration was recorded for another input width"
    assert len(calib.pre) == len(policy.weights), "calibration was recorded for another architecture"
    e_in = input_exponent(calib.inputs, percentile, headroom, e_in)

    L = len(policy.weights)
    layers: list[QuantLayer] = []
    e_prev = e_in
    for k, (W, b, act) in enumerate(zip(policy.weights, policy.biases, policy.activations)):
        if k == L - 1:
            layers.append(output_layer(f"layer {k}", W, b, e_prev))
            break
        e_out = numfmt.choose_exp(value_range(calib.pre[k], percentile, headroom))
        wq, bq, shift, e_out = dense_weights(f"layer {k}", W, b, e_prev, e_out, may_lower_e_out=True)
        if act in TABLE_ACTIVATIONS:
            e_act = numfmt.choose_exp(value_range(calib.post[k], percentile, headroom))
            table = numfmt.act_table(act, e_out, e_act)
        else:
            e_act, table = e_out, None
        layers.append(QuantLayer(w=wq, b=bq, shift=shift, lo=INT8_MIN, hi=INT8_MAX, activation=act,
                                 e_in=e_prev, e_out=e_out, e_act=e_act, table=table))
        e_prev = e_act
    return QuantizedMLP(layers=layers, e_in=e_in, world=policy.world, t_prev=policy.t_prev,
                        policy_hash=policy.hash, **sensing_tables(policy.world, e_in))


def mlp_error_report(policy: MLPPolicy, qp: QuantizedMLP, calib: Calibration) -> ErrorReport:
    """Compare the float actor with the integer actor on every calibration input."""
    x_q = qp.quantize_history(calib.inputs)  # (N, in_dim) int8
    outs = qp.forward_layers(x_q)
    rows = []
    x_int = x_q.astype(np.int64)
    for k, (layer, y_int) in enumerate(zip(qp.layers, outs)):
        got = y_int.astype(np.float64) / 255.0 if k == len(qp.layers) - 1 else numfmt.dequantize(y_int, layer.e_act)
        z = numfmt.dense_int(x_int, layer.w, layer.b, layer.shift, layer.lo, layer.hi)
        err = np.abs(got - calib.post[k])
        rows.append(LayerError(
            index=k, n_in=int(layer.w.shape[1]), n_out=int(layer.w.shape[0]), activation=layer.activation,
            e_in=layer.e_in, e_out=layer.e_out, e_act=layer.e_act, shift_min=int(layer.shift.min()),
            shift_max=int(layer.shift.max()), acc24_safe=layer.acc24_safe,
            max_abs=float(err.max()), mean_abs=float(err.mean()), saturated=saturated_fraction(z, layer.lo, layer.hi)))
        x_int = y_int
    du = np.abs(outs[-1].astype(np.float64) / 255.0 - calib.post[-1])
    same = float(np.mean(outs[-1] == action_to_u8(calib.post[-1])))
    return ErrorReport(layers=tuple(rows), du_max=float(du.max()), du_mean=float(du.mean()), same_command=same,
                       n_samples=calib.n, e_in=qp.e_in, input_saturated=saturated_fraction(x_q))


# --------------------------------------------------------------------------------------------
# The kind
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MLPArch:
    """An MLP's size: history length, hidden widths, activations (one per layer, or per hidden layer)."""

    t_prev: int
    hidden: tuple[int, ...] = ()
    activations: tuple[str, ...] | None = None  #: default: ELU hidden layers, identity output
    n_act_tables: int | None = None  #: distinct activation tables (a quantised policy shares identical ones)

    def __post_init__(self) -> None:
        hidden = tuple(int(h) for h in self.hidden)
        assert self.t_prev >= 1, f"t_prev must be >= 1, got {self.t_prev}"
        assert all(h >= 1 for h in hidden), f"hidden widths must be >= 1, got {list(hidden)}"
        acts = tuple(["elu"] * len(hidden) + ["identity"]) if self.activations is None else tuple(self.activations)
        if len(acts) == len(hidden):  # hidden activations only
            acts = acts + ("identity",)
        assert len(acts) == len(hidden) + 1, f"{len(acts)} activations for {len(hidden) + 1} layers"
        object.__setattr__(self, "t_prev", int(self.t_prev))
        object.__setattr__(self, "hidden", hidden)
        object.__setattr__(self, "activations", acts)

    def layer_sizes(self, world: WorldConfig) -> tuple[int, ...]:
        return (world.history_dim(self.t_prev), *self.hidden, ACTION_DIM)


class MLPKind(ActorKind):
    """The feed-forward actor on a T_prev history (MAGDDPG)."""

    name: ClassVar[str] = "mlp"
    template: ClassVar[str] = "actors/mlp.c.j2"
    c_sources: ClassVar[tuple[str, ...]] = ()  #: kf_dense and kf_runtime.h's activations (always inlined)
    budget_usage: ClassVar[str] = "--history T_PREV [--hidden W ...]"
    budget_options: ClassVar[tuple[BudgetOption, ...]] = (
        BudgetOption("--history", "t_prev: history length in control periods (MLP actor)"),
        BudgetOption("--hidden", "hidden layer widths (MLP actor)", metavar="W", nargs="*", default=[]),
        BudgetOption("--activation", "hidden activation (default elu; elu/tanh/sigmoid cost a 256 B table per layer)",
                     positive=False, default="elu", choices=tuple(a for a in ACTIVATIONS if a != "identity")
                     + ("identity",), claims=False),
    )

    # --- artifact <-> float actor ----------------------------------------------------------
    def from_arrays(self, arrays: dict[str, np.ndarray], meta: dict[str, Any], world: WorldConfig,
                    provenance: dict[str, Any]) -> MLPPolicy:
        for key in ("activations", "t_prev", "layer_sizes"):
            if key not in meta:
                raise PolicyError(f"policy: 'meta' lacks '{key}'")
        acts = meta["activations"]
        if not isinstance(acts, list) or not acts:
            raise PolicyError("policy: 'activations' must be a non-empty list")
        n = len(acts)
        for k in range(n):
            for a in (f"w{k}", f"b{k}"):
                if a not in arrays:
                    raise PolicyError(f"policy: lacks array '{a}' ({n} layers declared)")
        extra = sorted(set(arrays) - {f"{p}{k}" for k in range(n) for p in "wb"})
        if extra:
            raise PolicyError(f"policy: has unexpected arrays: {', '.join(extra)}")
        sizes = meta["layer_sizes"]
        if not isinstance(sizes, list) or any(isinstance(v, bool) or not isinstance(v, int) for v in sizes):
            raise PolicyError(f"policy: layer_sizes must be a list of integers, got {show(sizes)}")
        shapes = [arrays[f"w{k}"].shape for k in range(n)]
        declared = [[sizes[k + 1], sizes[k]] for k in range(len(sizes) - 1)] if isinstance(sizes, list) else None
        if declared != [list(s) for s in shapes]:
            raise PolicyError(f"policy: layer_sizes {sizes} do not match the weight shapes {[tuple(s) for s in shapes]}")
        return MLPPolicy(weights=[arrays[f"w{k}"] for k in range(n)], biases=[arrays[f"b{k}"] for k in range(n)],
                         activations=acts, t_prev=meta["t_prev"], world=world, provenance=provenance)

    def swarm_policy(self, policy: MLPPolicy, world: WorldConfig | None = None) -> HistoryActor:
        """sim's HistoryActor around the float actor (the same history ring)."""
        return HistoryActor(policy.act, policy.t_prev, world or policy.world)

    # --- quantise ----------------------------------------------------------------------------
    def calibration(self, policy: MLPPolicy, seqs: np.ndarray, info: dict[str, Any]) -> Calibration:
        return calibration_from_inputs(policy, histories(np.asarray(seqs, np.float32), policy.t_prev), info)

    def quantize(self, policy: MLPPolicy, calib: Calibration, *, percentile: float = 100.0, headroom: float = 1.0,
                 e_in: int | None = None) -> QuantizedMLP:
        return quantize_mlp(policy, calib, percentile=percentile, headroom=headroom, e_in=e_in)

    def error_report(self, policy: MLPPolicy, qp: QuantizedMLP, calib: Calibration) -> ErrorReport:
        return mlp_error_report(policy, qp, calib)

    # --- budget ------------------------------------------------------------------------------
    def arch_of(self, policy: MLPPolicy) -> MLPArch:
        return MLPArch(policy.t_prev, tuple(policy.hidden), tuple(policy.activations))

    def arch_of_quantized(self, qp: QuantizedMLP) -> MLPArch:
        distinct = {l.table.tobytes() for l in qp.layers if l.table is not None}
        return MLPArch(qp.t_prev, tuple(qp.layer_sizes[1:-1]), tuple(l.activation for l in qp.layers), len(distinct))

    def budget_spec(self, world: WorldConfig, arch: MLPArch, e_in: int) -> BudgetSpec:
        sizes = arch.layer_sizes(world)
        n_tables = (sum(1 for a in arch.activations[:-1] if a in TABLE_ACTIVATIONS) if arch.n_act_tables is None
                    else arch.n_act_tables)
        x_len = max(sizes[1:-1], default=1)  # widest hidden activation (int8)
        y_len = max(sizes[1:])  # widest layer output (int16)
        T = numfmt.TABLE_SIZE
        return BudgetSpec(
            header=f"t_prev {arch.t_prev}, layers {' -> '.join(map(str, sizes))} ({', '.join(arch.activations)})",
            layer_sizes=sizes, dense=tuple((sizes[k + 1], sizes[k]) for k in range(len(sizes) - 1)),
            flash=(BudgetItem("flash", "activation tables", T * n_tables, f"{n_tables} x {T} int8"),),
            memory=(BudgetItem("sram", "history ring buffer", arch.t_prev * world.tuple_dim,
                               f"{arch.t_prev} x {world.tuple_dim} int8"),),
            scratch=(BudgetItem("sram", "activation buffers", x_len + 2 * y_len, f"{x_len} int8 + {y_len} int16"),),
            arch={"t_prev": arch.t_prev, "hidden": list(arch.hidden), "activations": list(arch.activations)})

    def resizes(self, world: WorldConfig, arch: MLPArch) -> list[Resize]:
        hidden, acts_h = list(arch.hidden), arch.activations[:-1]
        out = [Resize(arch=lambda t: MLPArch(t, arch.hidden, acts_h),
                      found=lambda n: f"t_prev <= {n} with hidden {hidden}",
                      none=f"no history length fits with hidden {hidden}")]
        if hidden:
            out.append(Resize(arch=lambda w: MLPArch(arch.t_prev, (w,) * len(hidden), acts_h),
                              found=lambda n: f"hidden {[n] * len(hidden)} with t_prev {arch.t_prev}",
                              none=f"no hidden width fits with t_prev {arch.t_prev}"))
        return out

    def budget_arch(self, values: Mapping[str, Any]) -> MLPArch:
        if values.get("history") is None:
            raise ValueError("--hidden sizes an MLP actor: give --history T_PREV too")
        hidden = tuple(values.get("hidden") or ())
        return MLPArch(int(values["history"]), hidden, (values.get("activation") or "elu",) * len(hidden))

    # --- render --------------------------------------------------------------------------------
    def render_spec(self, qp: QuantizedMLP) -> RenderSpec:
        T, D = qp.t_prev, qp.world.tuple_dim
        if T > MAX_T_PREV:
            raise QuantizeError(f"t_prev {T} is too long for the firmware's uint8 ring index (at most {MAX_T_PREV})")
        if D * T > MAX_HISTORY:
            raise QuantizeError(f"history of {D * T} entries is too large")
        hidden = [int(l.w.shape[0]) for l in qp.layers[:-1]]
        act_tables: dict[bytes, str] = {}
        tables: list[CTable | CDense] = []
        last = len(qp.layers) - 1
        for k, layer in enumerate(qp.layers):
            act, table_name = "output", ""
            if k < last:
                if layer.table is not None:
                    key = np.asarray(layer.table, np.int8).tobytes()
                    if key not in act_tables:
                        act_tables[key] = f"KF_ACTFN{len(act_tables)}"
                        tables.append(CTable(act_tables[key], "int8_t", layer.table,
                                             f"{layer.activation} table: z at exponent {layer.e_out} "
                                             f"(index z + 128) -> exponent {layer.e_act}"))
                    act, table_name = "table", act_tables[key]
                elif layer.activation == "relu":
                    act = "relu"
                else:
                    assert layer.activation == "identity", f"layer {k}: activation {layer.activation} needs a table"
                    act = "identity"
            tables.append(CDense(f"KF_L{k}", f"KF_W{k}", f"KF_B{k}", f"KF_S{k}", layer, f"layer {k}", f"layer {k}",
                                 {"act": act, "table": table_name}))
        return RenderSpec(
            memory=(CDefine("KF_T_PREV", T, comment="history length (tuples)"),),
            scratch=(CDefine("KF_Y_LEN", max(int(l.w.shape[0]) for l in qp.layers), "uint16_t",
                             "scratch: the widest layer output (int16)"),
                     CDefine("KF_X_LEN", max(hidden, default=1), "uint16_t",
                             "scratch: the widest hidden activation (int8)")),
            tables=tuple(tables))


MLP = MLPKind()
