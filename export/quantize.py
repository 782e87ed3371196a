"""Post-training quantisation of a float policy into the int8 format of :mod:`export.numfmt`.

Pipeline::

    calib = calibrate(policy, episodes=2, n_robots=(4, 16), seed=0)   # simulator rollouts
    qp = quantize_policy(policy, calib)                                # -> QuantizedPolicy
    report = error_report(policy, qp, calib); print(report.table())

* :func:`calibrate` runs the float policy itself in its own world (``sim.env.SwarmEnv`` +
  ``sim.history.History``) and records every actor input (the flat history) and every layer's float
  pre-activation and activation.
* :func:`quantize_policy` chooses power-of-two exponents from those ranges: the input exponent
  ``e_in`` (at most ``numfmt.DEFAULT_INPUT_EXP`` so that the 0/1 flags are exact), per hidden layer
  the pre-activation exponent ``e_out`` and, for table activations, the activation exponent
  ``e_act``; per output row the weight exponent ``ew[j]`` (largest that keeps the row in int8),
  int32 biases at the accumulator exponent ``ew[j] + e_in``, and the shift ``ew[j] + e_in - e_out``
  kept in ``0..MAX_SHIFT`` (``ew`` is lowered where needed). The output layer has 255 folded into its
  weights and produces the uint8 motor command directly (exponent 0, clamp 0..255). Every row is
  proven free of int32 overflow for every int8 input, rounding constant included
  (``|acc| + 2**(s-1) < 2**31``, the same proof the C kernel relies on); the proof's bound and the
  24-bit-accumulator flag (:func:`numfmt.fits_acc24`) are stored per layer.
* :class:`QuantizedPolicy` is what the firmware renderer and the emulator consume.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from sim.config import ACTION_DIM, WorldConfig

from . import numfmt
from .errors import QuantizeError
from .numfmt import (DEFAULT_INPUT_EXP, FORMAT_NAME, INT8_MAX, INT8_MIN, MAX_SHIFT, QuantLayer,
                     acc_bound, choose_exp)

if TYPE_CHECKING:  # pragma: no cover
    from .artifact import Policy

TABLE_ACTIVATIONS = ("elu", "tanh", "sigmoid")  #: activations realised as 256-entry int8 tables
OUTPUT_ACTIVATIONS = ("identity", "relu")  #: output activations the uint8 clamp realises exactly
ACC32_LIMIT = 2 ** 31  #: |acc| must stay below this (int32 reference accumulator)
WEIGHT_EXP_LO = -16  #: smallest per-row weight exponent tried (|w| up to 127 * 2**16)


# --------------------------------------------------------------------------------------------
# The quantised policy (the renderer's and the emulator's input)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class QuantizedPolicy:
    """An int8 actor plus the sensing tables, exactly as the firmware will hold them.

    Input: the flat int8 history at exponent ``e_in`` (``t_prev`` tuples oldest first, each
    ``[ACT[q_left], ACT[q_right], wall, target, nbr_flag, rbf_0..rbf_{n-1}]``); output: the two
    uint8 motor commands ``q`` (``u = q / 255``).
    """

    layers: list[QuantLayer]  #: dense layers; layers[k+1].e_in == layers[k].e_act
    e_in: int  #: exponent of every observation / history entry (0 <= e_in <= DEFAULT_INPUT_EXP)
    world: WorldConfig  #: the world the policy was trained in (every sensing constant)
    t_prev: int  #: history length (tuples)
    rbf_table: np.ndarray  #: (n_rbf, 256) uint8, numfmt.rbf_table(world..., e_in)
    target_table: np.ndarray  #: (256,) int8, numfmt.target_table(world.comm_radius_mm, e_in)
    action_table: np.ndarray  #: (256,) int8, numfmt.action_table(e_in)
    policy_hash: str  #: sha256 of the float policy artifact this was quantised from
    acc24_safe: tuple[bool, ...]  #: per layer: numfmt.fits_acc24(w, b) (any int8 input)
    acc_max: tuple[int, ...]  #: per layer: max over rows of |acc| + 2**(shift-1), any int8 input
    format_name: str = FORMAT_NAME  #: numfmt.FORMAT_NAME at quantisation time
    rounding: str = numfmt.ROUNDING  #: numfmt.ROUNDING at quantisation time

    def __post_init__(self) -> None:
        L = len(self.layers)
        assert L >= 1, "a quantised policy needs at least one layer"
        assert 0 <= self.e_in <= DEFAULT_INPUT_EXP, f"e_in must be in 0..{DEFAULT_INPUT_EXP}, got {self.e_in}"
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
        assert (out.lo, out.hi, out.e_out, out.e_act, out.activation) == (0, 255, 0, 0, "identity"), \
            "output layer must be identity, exponent 0, clamp 0..255 (the uint8 motor command)"
        assert len(self.acc24_safe) == L and len(self.acc_max) == L, "one acc24/acc_max entry per layer"
        assert all(a < ACC32_LIMIT for a in self.acc_max), "int32 overflow proof failed"
        w = self.world
        assert self.rbf_table.shape == (w.n_rbf, 256) and self.rbf_table.dtype == np.uint8, "rbf_table shape/dtype"
        assert self.target_table.shape == (256,) and self.target_table.dtype == np.int8, "target_table shape/dtype"
        assert self.action_table.shape == (256,) and self.action_table.dtype == np.int8, "action_table shape/dtype"

    # --- shapes -----------------------------------------------------------------------------
    @property
    def in_dim(self) -> int:
        """Actor input width, ``world.history_dim(t_prev)``."""
        return self.world.history_dim(self.t_prev)

    @property
    def obs_dim(self) -> int:
        return self.world.obs_dim

    @property
    def tuple_dim(self) -> int:
        return self.world.tuple_dim

    @property
    def layer_sizes(self) -> list[int]:
        """[in_dim, hidden..., 2]."""
        return [self.layers[0].w.shape[1]] + [int(l.w.shape[0]) for l in self.layers]

    @property
    def one_q(self) -> int:
        """1.0 at exponent e_in (wall flag, neighbour flag; minus it: target not heard)."""
        return 1 << self.e_in

    @property
    def n_weights(self) -> int:
        return int(sum(l.w.size for l in self.layers))

    # --- integer inference ------------------------------------------------------------------
    def quantize_history(self, history: np.ndarray) -> np.ndarray:
        """Float history (..., in_dim) -> int8 at ``e_in`` (half-up, saturating).

        Used for the error report; the firmware builds its int8 history from the tables instead.
        """
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
        """The firmware's actor: int8 history (..., in_dim) -> uint8 motor commands (..., 2)."""
        return self.forward_layers(x_q)[-1].astype(np.uint8)

    def act_float(self, history: np.ndarray) -> np.ndarray:
        """Convenience: float history -> quantise -> integer actor -> u = q / 255 (float64)."""
        return self.forward_int(self.quantize_history(history)).astype(np.float64) / 255.0

    def summary(self) -> dict[str, Any]:
        """JSON-ready description (exponents, shifts, flags) for the manifest."""
        layers = []
        for k, l in enumerate(self.layers):
            layers.append({
                "n_in": int(l.w.shape[1]), "n_out": int(l.w.shape[0]), "activation": l.activation,
                "e_in": int(l.e_in), "e_out": int(l.e_out), "e_act": int(l.e_act),
                "lo": int(l.lo), "hi": int(l.hi),
                "shift_min": int(l.shift.min()), "shift_max": int(l.shift.max()),
                "table": l.table is not None,
                "acc24_safe": bool(self.acc24_safe[k]), "acc_max": int(self.acc_max[k]),
            })
        return {"format": self.format_name, "rounding": self.rounding, "e_in": int(self.e_in),
                "t_prev": int(self.t_prev), "layer_sizes": self.layer_sizes, "layers": layers,
                "policy_hash": self.policy_hash, "world": self.world.name}


# --------------------------------------------------------------------------------------------
# Calibration
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


def calibration_from_inputs(policy: "Policy", inputs: np.ndarray, info: dict | None = None) -> Calibration:
    """Run the float actor on recorded inputs (N, in_dim) and keep every layer's values."""
    x = np.asarray(inputs, np.float32).reshape(-1, policy.in_dim)  # (N, in_dim)
    assert x.shape[0] >= 1, "calibration needs at least one input"
    pre, post = zip(*policy.layer_outputs(x))
    return Calibration(inputs=x, pre=tuple(pre), post=tuple(post), info=dict(info or {}))


def calibrate(policy: "Policy", episodes: int = 1, n_robots: int | Sequence[int] = (4, 16),
              seed: int = 0, steps: int | None = None, n_envs: int = 1,
              progress: bool = False) -> Calibration:
    """Roll the float policy out in its own world and record what it sees (see module doc).

    ``episodes`` episodes of ``steps`` control periods (default ``world.episode_steps``) for each
    robot count in ``n_robots``, ``n_envs`` parallel envs each. Deterministic given ``seed``.
    """
    if getattr(policy, "kind", "mlp") == "gru":  # a recurrent actor: export/gru_quantize.py
        from .gru_quantize import calibrate_gru
        return calibrate_gru(policy, episodes, n_robots, seed, steps, n_envs, progress)  # type: ignore[return-value]
    from sim.env import SwarmEnv  # lazy: the exporter's other parts do not need the simulator
    from sim.history import History

    counts = [int(n_robots)] if np.isscalar(n_robots) else [int(m) for m in n_robots]
    assert counts and all(m >= 1 for m in counts), f"robot counts must be >= 1, got {counts}"
    assert episodes >= 1 and n_envs >= 1, "episodes and n_envs must be >= 1"
    world = policy.world
    T = int(steps if steps is not None else world.episode_steps)
    assert T >= 1, f"steps must be >= 1, got {T}"
    seeds = np.random.SeedSequence(seed).spawn(len(counts) * episodes)
    total = len(counts) * episodes * T
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=total, desc="calibrating", unit="step", leave=False)
    chunks: list[np.ndarray] = []
    try:
        for ci, m in enumerate(counts):
            for ep in range(episodes):
                ss = seeds[ci * episodes + ep]
                env = SwarmEnv(world, n_envs, m, seed=int(ss.generate_state(1)[0]))
                obs, _ = env.reset()  # (B, M, obs_dim)
                hist = History(policy.t_prev, world.obs_dim)
                h = hist.reset(obs)  # (B, M, in_dim)
                for _ in range(T):
                    chunks.append(h.reshape(-1, policy.in_dim).astype(np.float32))
                    u = policy.act(h)  # (B, M, 2) float64 in [0, 1]
                    obs, _, _, _, _ = env.step(u)
                    h = hist.push(u.astype(np.float32), obs)
                    if bar is not None:
                        bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    info = {"episodes": episodes, "n_robots": counts, "seed": seed, "steps": T, "n_envs": n_envs,
            "world": world.name}
    return calibration_from_inputs(policy, np.concatenate(chunks, 0), info)


# --------------------------------------------------------------------------------------------
# Quantisation
# --------------------------------------------------------------------------------------------
def _range(a: np.ndarray, percentile: float, headroom: float) -> float:
    """max |a| (or its ``percentile``), times ``headroom``."""
    v = np.abs(np.asarray(a, np.float64)).ravel()
    if v.size == 0:
        return 0.0
    m = float(v.max()) if percentile >= 100.0 else float(np.percentile(v, percentile))
    return m * headroom


def _quantize_layer(k: int, W: np.ndarray, b: np.ndarray, e_in: int, e_out: int, may_lower_e_out: bool
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
    """Per-row weight exponents, int8 weights, int32 biases, shifts; returns (w, b, shift, e_out, acc_max).

    W (n_out, n_in) and b (n_out,) are float64 already scaled to the layer's real output.
    """
    n_out = W.shape[0]
    row_max = np.abs(W).max(axis=1)  # (n_out,)
    ew = np.array([choose_exp(float(m), lo=WEIGHT_EXP_LO, hi=MAX_SHIFT + e_out - e_in) for m in row_max],
                  dtype=np.int64)  # largest exponent keeping each row in int8 and the shift <= MAX_SHIFT
    if np.any(ew + e_in - e_out < 0):
        if not may_lower_e_out:
            j = int(np.argmin(ew))
            raise QuantizeError(
                f"layer {k} row {j}: weights up to {row_max[j]:.4g} are too large for the output exponent "
                f"{e_out} (needs a negative shift); retrain with smaller output weights")
        e_out = int((ew + e_in).min())  # coarser output grid so that every shift is >= 0
    for _ in range(64):
        shift = ew + e_in - e_out
        acc_e = ew + e_in  # accumulator exponent per row
        wq = numfmt.quantize(W * np.ldexp(1.0, ew)[:, None], 0)  # (n_out, n_in), in int8 by choice of ew
        bq = numfmt.round_half_up(b * np.ldexp(1.0, acc_e))  # (n_out,) int64
        rounding = np.where(shift > 0, np.left_shift(np.int64(1), np.maximum(shift - 1, 0)), 0)
        bound = acc_bound(wq, bq) + rounding  # (n_out,) max |acc + 2^(s-1)| over every int8 input
        bad = bound >= ACC32_LIMIT
        if not bad.any():
            return (wq.astype(np.int8), bq.astype(np.int32), shift.astype(np.uint8), e_out, int(bound.max()))
        stuck = bad & (shift <= 0)
        if stuck.any():
            j = int(np.flatnonzero(stuck)[0])
            raise QuantizeError(
                f"layer {k} row {j}: the int32 accumulator could overflow (|acc| up to {int(bound[j])} "
                f">= 2^31, bias {b[j]:.4g}) even at the coarsest weight scale; the policy has weights or "
                f"biases too large for the int8 format")
        ew = np.where(bad, ew - 1, ew)  # halve the scale of the offending rows only
    raise QuantizeError(f"layer {k}: could not remove a possible int32 overflow")  # pragma: no cover


def quantize_policy(policy: "Policy", calib: Calibration, *, percentile: float = 100.0,
                    headroom: float = 1.0, e_in: int | None = None) -> QuantizedPolicy:
    """Quantise ``policy`` with exponents from the calibration ranges (see module doc).

    ``percentile`` (<= 100) and ``headroom`` (>= 1 leaves room above the largest value seen) shape
    the range each exponent must cover; ``e_in`` overrides the input exponent.
    """
    if getattr(policy, "kind", "mlp") == "gru":  # a recurrent actor: export/gru_quantize.py
        from .gru_quantize import quantize_gru
        return quantize_gru(policy, calib, percentile=percentile, headroom=headroom, e_in=e_in)  # type: ignore
    if not 0.0 < percentile <= 100.0:
        raise QuantizeError(f"percentile must be in (0, 100], got {percentile}")
    if headroom <= 0.0:
        raise QuantizeError(f"headroom must be > 0, got {headroom}")
    if policy.activations[-1] not in OUTPUT_ACTIVATIONS:
        raise QuantizeError(
            f"output activation '{policy.activations[-1]}' is not supported by the int8 format; "
            f"use one of {', '.join(OUTPUT_ACTIVATIONS)} (actions are clipped to [0, 1])")
    assert calib.inputs.shape[1] == policy.in_dim, "calibration was recorded for another input width"
    assert len(calib.pre) == len(policy.weights), "calibration was recorded for another architecture"

    if e_in is None:
        e_in = min(DEFAULT_INPUT_EXP, max(0, choose_exp(_range(calib.inputs, percentile, headroom))))
    if not 0 <= e_in <= DEFAULT_INPUT_EXP:
        raise QuantizeError(f"input exponent must be in 0..{DEFAULT_INPUT_EXP} (flags are 1 << e_in), got {e_in}")

    L = len(policy.weights)
    layers: list[QuantLayer] = []
    acc24: list[bool] = []
    acc_max: list[int] = []
    e_prev = e_in
    for k, (W, b, act) in enumerate(zip(policy.weights, policy.biases, policy.activations)):
        W = np.asarray(W, np.float64)
        b = np.asarray(b, np.float64)
        last = k == L - 1
        if last:  # real output 255 * u: the uint8 motor command at exponent 0
            W, b = W * 255.0, b * 255.0
            e_out, lo, hi = 0, 0, 255
        else:
            e_out, lo, hi = choose_exp(_range(calib.pre[k], percentile, headroom)), INT8_MIN, INT8_MAX
        wq, bq, shift, e_out, amax = _quantize_layer(k, W, b, e_prev, e_out, may_lower_e_out=not last)
        if last or act in ("identity", "relu"):
            e_act, table = e_out, None
        else:
            e_act = choose_exp(_range(calib.post[k], percentile, headroom))
            table = numfmt.act_table(act, e_out, e_act)
        layer = QuantLayer(w=wq, b=bq, shift=shift, lo=lo, hi=hi,
                           activation="identity" if last else act,
                           e_in=e_prev, e_out=e_out, e_act=e_act, table=table)
        layers.append(layer)
        acc24.append(numfmt.fits_acc24(wq, bq))
        acc_max.append(amax)
        e_prev = e_act

    w = policy.world
    return QuantizedPolicy(
        layers=layers, e_in=int(e_in), world=w, t_prev=policy.t_prev,
        rbf_table=numfmt.rbf_table(w.rbf_centres_mm, w.rbf_sigma_mm, w.rbf_norm, w.comm_radius_mm, e_in),
        target_table=numfmt.target_table(w.comm_radius_mm, e_in),
        action_table=numfmt.action_table(e_in),
        policy_hash=policy.hash, acc24_safe=tuple(acc24), acc_max=tuple(acc_max))


# --------------------------------------------------------------------------------------------
# Error report
# --------------------------------------------------------------------------------------------
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
        return {"du_max": self.du_max, "du_mean": self.du_mean, "same_command": self.same_command,
                "n_samples": self.n_samples, "e_in": self.e_in, "input_saturated": self.input_saturated,
                "layers": [dict(vars(r)) for r in self.layers]}


def error_report(policy: "Policy", qp: QuantizedPolicy, calib: Calibration) -> ErrorReport:
    """Compare the float actor with the integer actor on every calibration input."""
    if getattr(policy, "kind", "mlp") == "gru":  # a recurrent actor: export/gru_quantize.py
        from .gru_quantize import gru_error_report
        return gru_error_report(policy, qp, calib)  # type: ignore[return-value]
    from sim.motion import action_to_u8

    x_q = qp.quantize_history(calib.inputs)  # (N, in_dim) int8
    sat_in = float(np.mean((x_q == INT8_MIN) | (x_q == INT8_MAX)))
    outs = qp.forward_layers(x_q)
    rows = []
    x_int = x_q.astype(np.int64)
    for k, (layer, y_int) in enumerate(zip(qp.layers, outs)):
        last = k == len(qp.layers) - 1
        if last:
            got, ref = y_int.astype(np.float64) / 255.0, calib.post[k]
        else:
            got, ref = numfmt.dequantize(y_int, layer.e_act), calib.post[k]
        z = numfmt.dense_int(x_int, layer.w, layer.b, layer.shift, layer.lo, layer.hi)
        err = np.abs(got - ref)
        rows.append(LayerError(
            index=k, n_in=int(layer.w.shape[1]), n_out=int(layer.w.shape[0]), activation=layer.activation,
            e_in=layer.e_in, e_out=layer.e_out, e_act=layer.e_act, shift_min=int(layer.shift.min()),
            shift_max=int(layer.shift.max()), acc24_safe=bool(qp.acc24_safe[k]),
            max_abs=float(err.max()), mean_abs=float(err.mean()),
            saturated=float(np.mean((z == layer.lo) | (z == layer.hi)))))
        x_int = y_int
    u_int = outs[-1].astype(np.float64) / 255.0
    du = np.abs(u_int - calib.post[-1])
    same = float(np.mean(outs[-1] == action_to_u8(calib.post[-1])))
    return ErrorReport(layers=tuple(rows), du_max=float(du.max()), du_mean=float(du.mean()),
                       same_command=same, n_samples=calib.n, e_in=qp.e_in, input_saturated=sat_in)
