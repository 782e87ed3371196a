"""Post-training quantisation of a GRU actor (:mod:`export.gru`) into the int8 GRU cell of :mod:`export.numfmt`.

Pipeline (``export.quantize.calibrate`` / ``quantize_policy`` / ``error_report`` dispatch here for a
policy of kind ``"gru"``)::

    calib = calibrate_gru(policy, episodes=1, n_robots=(4, 16), seed=0)   # simulator rollouts
    qp = quantize_gru(policy, calib)                                       # -> QuantizedGRU
    print(gru_error_report(policy, qp, calib).table())

* :func:`calibrate_gru` runs the float GRU in its own world and records, per robot-episode, every
  input tuple and the hidden state before each step, and every intermediate of the cell.
* :func:`quantize_gru` chooses the input exponent ``e_in`` as the MLP quantiser does (at most
  ``DEFAULT_INPUT_EXP``), one exponent per gate pre-activation (``e_r``, ``e_z``, ``e_nx`` for
  ``W_in x + b_in``, ``e_nh`` for ``W_hn h + b_hn``, ``e_n`` for the candidate's sum) from the
  calibrated ranges (the table inputs ``e_r``, ``e_z``, ``e_n`` at least ``numfmt.SIGMOID_SAT_EXP`` /
  ``TANH_SAT_EXP``: only the range where the function still changes needs covering), and per row
  the weight exponent with the overflow proof of :mod:`export.quantize`; the hidden state is at the
  fixed ``numfmt.HIDDEN_EXP``, gates at ``numfmt.GATE_EXP``.
* :class:`QuantizedGRU` is what the renderer (``kilobot_policy_gru.c.j2``) and the emulator consume:
  ``step_int`` is the firmware's control step on int8 tuples.
* :func:`gru_error_report` compares the integer cell with the float one, step by step from the
  float states (teacher forcing) and free-running over whole recorded episodes.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from sim.config import ACTION_DIM, WorldConfig

from . import numfmt
from .errors import QuantizeError
from .gru import GRUPolicy
from .numfmt import (DEFAULT_INPUT_EXP, FORMAT_NAME, GATE_EXP, HIDDEN_EXP, INT8_MAX, INT8_MIN, QuantGRUCell,
                     QuantLayer, choose_exp)
from .quantize import ACC32_LIMIT, _quantize_layer, _range

#: which float value each exponent must cover (gates.keys() of GRUPolicy)
LAYER_NAMES = ("r", "z", "nx", "nh", "out")


@dataclass(frozen=True, eq=False)
class QuantizedGRU:
    """An int8 GRU actor plus the sensing tables, exactly as the firmware holds them.

    Per control step: ``x = [ACT[q_left], ACT[q_right], obs]`` int8 at ``e_in``; ``h`` int8 at
    ``HIDDEN_EXP`` (zero after setup); ``h' = cell.step(x, h)``; ``q = out(h')`` uint8.
    """

    cell: QuantGRUCell
    out: QuantLayer  #: (2, H) on h' at HIDDEN_EXP -> uint8 motor commands
    e_in: int
    world: WorldConfig
    rbf_table: np.ndarray
    target_table: np.ndarray
    action_table: np.ndarray
    policy_hash: str
    acc24_safe: tuple[bool, ...]  #: per layer of :attr:`layers`
    acc_max: tuple[int, ...]  #: per layer: max |acc| + rounding over every int8 input
    format_name: str = FORMAT_NAME
    rounding: str = numfmt.ROUNDING
    kind: str = "gru"

    def __post_init__(self) -> None:
        c, w = self.cell, self.world
        assert self.kind == "gru", "a QuantizedGRU has kind 'gru'"
        assert 0 <= self.e_in <= DEFAULT_INPUT_EXP, f"e_in must be in 0..{DEFAULT_INPUT_EXP}, got {self.e_in}"
        assert c.in_dim == w.tuple_dim, f"cell input {c.in_dim} != tuple width {w.tuple_dim}"
        assert c.r.e_in == self.e_in, "the gates read x at e_in"
        o = self.out
        assert o.w.shape == (ACTION_DIM, c.hidden), f"output layer must be ({ACTION_DIM}, {c.hidden})"
        assert (o.lo, o.hi, o.e_in, o.e_out, o.activation) == (0, 255, HIDDEN_EXP, 0, "identity"), \
            "output layer: h at HIDDEN_EXP -> uint8 commands (exponent 0, clamp 0..255)"
        assert len(self.acc_max) == len(self.layers) == len(self.acc24_safe), "one proof per layer"
        assert all(a < ACC32_LIMIT for a in self.acc_max), "int32 overflow proof failed"
        assert self.rbf_table.shape == (w.n_rbf, 256) and self.rbf_table.dtype == np.uint8, "rbf_table shape/dtype"
        assert self.target_table.shape == (256,) and self.target_table.dtype == np.int8, "target_table shape/dtype"
        assert self.action_table.shape == (256,) and self.action_table.dtype == np.int8, "action_table shape/dtype"

    # --- shapes -----------------------------------------------------------------------------
    @property
    def layers(self) -> list[QuantLayer]:
        """The five dense layers in firmware order: r, z, nx, nh, out."""
        return [self.cell.r, self.cell.z, self.cell.nx, self.cell.nh, self.out]

    @property
    def t_prev(self) -> int:
        """1: the firmware keeps one input tuple (the hidden state carries the past)."""
        return 1

    @property
    def hidden_size(self) -> int:
        return self.cell.hidden

    @property
    def in_dim(self) -> int:
        return self.world.tuple_dim

    @property
    def obs_dim(self) -> int:
        return self.world.obs_dim

    @property
    def tuple_dim(self) -> int:
        return self.world.tuple_dim

    @property
    def layer_sizes(self) -> list[int]:
        """[input tuple, hidden, 2]."""
        return [self.in_dim, self.hidden_size, ACTION_DIM]

    @property
    def one_q(self) -> int:
        return 1 << self.e_in

    @property
    def n_weights(self) -> int:
        return int(sum(l.w.size for l in self.layers))

    # --- integer inference ------------------------------------------------------------------
    def initial_state(self, n: int) -> np.ndarray:
        """Zero hidden states (n, H) int64: what setup() leaves."""
        return np.zeros((int(n), self.hidden_size), np.int64)

    def step_int(self, x: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One control step: int8 tuples (R, D) and states (R, H) -> (uint8 commands (R, 2), new states)."""
        h2 = self.cell.step(x, h)
        o = self.out
        q = numfmt.dense_int(h2, o.w, o.b, o.shift, o.lo, o.hi)
        return q.astype(np.uint8), h2

    def quantize_tuple(self, x: np.ndarray) -> np.ndarray:
        """Float tuples (..., D) -> int8 at e_in (the error report; the firmware builds them from tables)."""
        return numfmt.quantize(x, self.e_in)

    def step_float_io(self, x: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """float tuples in, integer state carried, u = q / 255 out (firmware behaviour seen from floats)."""
        q, h2 = self.step_int(self.quantize_tuple(x), h)
        return q.astype(np.float64) / 255.0, h2

    def summary(self) -> dict[str, Any]:
        """JSON-ready description (exponents, shifts, flags) for the manifest."""
        layers = []
        for name, l, safe, amax in zip(LAYER_NAMES, self.layers, self.acc24_safe, self.acc_max):
            layers.append({"name": name, "n_in": int(l.w.shape[1]), "n_out": int(l.w.shape[0]),
                           "e_in": int(l.e_in), "e_out": int(l.e_out), "lo": int(l.lo), "hi": int(l.hi),
                           "shift_min": int(l.shift.min()), "shift_max": int(l.shift.max()),
                           "acc24_safe": bool(safe), "acc_max": int(amax)})
        return {"format": self.format_name, "rounding": self.rounding, "kind": "gru", "e_in": int(self.e_in),
                "hidden": self.hidden_size, "hidden_exp": HIDDEN_EXP, "gate_exp": GATE_EXP,
                "rn_shift": int(self.cell.rn_shift), "nx_shift": int(self.cell.nx_shift), "e_n": int(self.cell.e_n),
                "layer_sizes": self.layer_sizes, "layers": layers,
                "policy_hash": self.policy_hash, "world": self.world.name}

    def banner_actor(self) -> str:
        """The actor line of the C banner."""
        c = self.cell
        return (f"GRU: input {self.in_dim} ([a_prev, obs]), {self.hidden_size} hidden units int8 at exponent "
                f"{HIDDEN_EXP}, linear output 2; e_in {self.e_in}, e_r {c.r.e_out}, e_z {c.z.e_out}, "
                f"e_nx {c.nx.e_out}, e_nh {c.nh.e_out}, e_n {c.e_n}")


# --------------------------------------------------------------------------------------------
# Calibration
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class GRUCalibration:
    """What the float GRU saw: input tuples and states per robot-episode, and every intermediate."""

    seqs: np.ndarray  #: (S, T, D) float32 input tuples, one row per robot-episode
    states: np.ndarray  #: (S, T, H) float64 hidden state before each step
    values: dict[str, np.ndarray]  #: GRUPolicy.gates() over every (S*T) step, flattened
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.seqs.shape[0] * self.seqs.shape[1])

    @property
    def inputs(self) -> np.ndarray:
        """(S*T, D) every input tuple."""
        return self.seqs.reshape(-1, self.seqs.shape[-1])


def calibration_from_sequences(policy: GRUPolicy, seqs: np.ndarray, info: dict | None = None) -> GRUCalibration:
    """Run the float GRU over recorded input sequences (S, T, D) from zero states; keep everything."""
    seqs = np.asarray(seqs, np.float32)
    assert seqs.ndim == 3 and seqs.shape[-1] == policy.in_dim and seqs.shape[1] >= 1, \
        f"sequences must be (S, T, {policy.in_dim}), got {seqs.shape}"
    S, T, _ = seqs.shape
    h = policy.initial_state((S,))
    states = np.empty((S, T, policy.hidden_size))
    vals: dict[str, list[np.ndarray]] = {}
    for t in range(T):
        states[:, t] = h
        g = policy.gates(seqs[:, t], h)
        for k, v in g.items():
            vals.setdefault(k, []).append(v)
        h = g["h"]
    values = {k: np.stack(v, 1).reshape(S * T, -1) for k, v in vals.items()}  # (S*T, ...) row s*T + t
    return GRUCalibration(seqs=seqs, states=states, values=values, info=dict(info or {}))


def calibrate_gru(policy: GRUPolicy, episodes: int = 1, n_robots: int | Sequence[int] = (4, 16), seed: int = 0,
                  steps: int | None = None, n_envs: int = 1, progress: bool = False) -> GRUCalibration:
    """Roll the float GRU out in its own world and record its inputs (deterministic given ``seed``)."""
    from sim.env import SwarmEnv  # lazy: the exporter's other parts do not need the simulator

    counts = [int(n_robots)] if np.isscalar(n_robots) else [int(m) for m in n_robots]
    assert counts and all(m >= 1 for m in counts), f"robot counts must be >= 1, got {counts}"
    assert episodes >= 1 and n_envs >= 1, "episodes and n_envs must be >= 1"
    world = policy.world
    T = int(steps if steps is not None else world.episode_steps)
    assert T >= 1, f"steps must be >= 1, got {T}"
    seeds = np.random.SeedSequence(seed).spawn(len(counts) * episodes)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(counts) * episodes * T, desc="calibrating", unit="step", leave=False)
    chunks: list[np.ndarray] = []
    try:
        for ci, m in enumerate(counts):
            for ep in range(episodes):
                env = SwarmEnv(world, n_envs, m, seed=int(seeds[ci * episodes + ep].generate_state(1)[0]))
                obs, _ = env.reset()  # (B, M, obs_dim)
                prev = np.zeros((n_envs, m, ACTION_DIM), np.float32)
                h = policy.initial_state((n_envs * m,))
                xs = np.empty((n_envs * m, T, world.tuple_dim), np.float32)
                for t in range(T):
                    x = np.concatenate([prev, obs.astype(np.float32)], -1).reshape(n_envs * m, -1)
                    xs[:, t] = x
                    u, h = policy.step(x, h)
                    prev = u.reshape(n_envs, m, ACTION_DIM).astype(np.float32)
                    obs, _, _, _, _ = env.step(prev.astype(np.float64))
                    if bar is not None:
                        bar.update(1)
                chunks.append(xs)
    finally:
        if bar is not None:
            bar.close()
    info = {"episodes": episodes, "n_robots": counts, "seed": seed, "steps": T, "n_envs": n_envs, "world": world.name}
    return calibration_from_sequences(policy, np.concatenate(chunks, 0), info)


# --------------------------------------------------------------------------------------------
# Quantisation
# --------------------------------------------------------------------------------------------
def _gate_layer(name: str, W: np.ndarray, b: np.ndarray, e_in: int, e_out: int, may_lower: bool = True
                ) -> tuple[QuantLayer, bool, int]:
    """A requantising dense layer (identity activation, int8 clamp) from float W (n_out, n_in), b."""
    wq, bq, shift, e_out, amax = _quantize_layer(name, W, b, e_in, e_out, may_lower_e_out=may_lower)
    layer = QuantLayer(w=wq, b=bq, shift=shift, lo=INT8_MIN, hi=INT8_MAX, activation="identity",
                       e_in=e_in, e_out=e_out, e_act=e_out, table=None)
    return layer, numfmt.fits_acc24(wq, bq), amax


def quantize_gru(policy: GRUPolicy, calib: GRUCalibration, *, percentile: float = 100.0, headroom: float = 1.0,
                 e_in: int | None = None, gate_exp_max: int | None = None) -> QuantizedGRU:
    """Quantise ``policy`` with exponents from the calibration ranges (see the module doc).

    ``gate_exp_max`` caps the gate pre-activation exponents (a smaller exponent covers a wider range
    of the sigmoid / tanh tables at a coarser step).
    """
    if not 0.0 < percentile <= 100.0:
        raise QuantizeError(f"percentile must be in (0, 100], got {percentile}")
    if headroom <= 0.0:
        raise QuantizeError(f"headroom must be > 0, got {headroom}")
    assert calib.seqs.shape[-1] == policy.in_dim, "calibration was recorded for another input width"
    assert calib.states.shape[-1] == policy.hidden_size, "calibration was recorded for another hidden size"
    if e_in is None:
        e_in = min(DEFAULT_INPUT_EXP, max(0, choose_exp(_range(calib.inputs, percentile, headroom))))
    if not 0 <= e_in <= DEFAULT_INPUT_EXP:
        raise QuantizeError(f"input exponent must be in 0..{DEFAULT_INPUT_EXP} (flags are 1 << e_in), got {e_in}")
    v = calib.values
    H = policy.hidden_size
    cap = 14 if gate_exp_max is None else int(gate_exp_max)

    def exp_of(*keys: str, finest_needed: int | None = None) -> int:
        e = choose_exp(max(_range(v[k], percentile, headroom) for k in keys))
        if finest_needed is not None:  # a table input: beyond its saturation every value reads the same entry
            e = max(e, finest_needed)
        return min(cap, e)

    W_ih, W_hh = policy.w_ih.astype(np.float64), policy.w_hh.astype(np.float64)
    b_ih, b_hh = policy.b_ih.astype(np.float64), policy.b_hh.astype(np.float64)
    h_scale = 2.0 ** (e_in - HIDDEN_EXP)  # h columns: real h = h_int 2^-7, read at the nominal exponent e_in
    blk = [slice(0, H), slice(H, 2 * H), slice(2 * H, 3 * H)]
    layers, acc24, amax = [], [], []
    for g, name in ((0, "r"), (1, "z")):
        W = np.concatenate([W_ih[blk[g]], W_hh[blk[g]] * h_scale], 1)  # (H, D + H)
        e = exp_of(f"a_{name}", finest_needed=numfmt.SIGMOID_SAT_EXP)
        l, f, a = _gate_layer(f"gate {name}", W, b_ih[blk[g]] + b_hh[blk[g]], e_in, e)
        layers.append(l), acc24.append(f), amax.append(a)
    e_n = exp_of("pre_n", finest_needed=numfmt.TANH_SAT_EXP)  # the tanh table's input
    l_nx, f, a = _gate_layer("n (input part)", W_ih[blk[2]], b_ih[blk[2]], e_in, min(exp_of("nx"), e_n))
    layers.append(l_nx), acc24.append(f), amax.append(a)
    e_n = max(e_n, l_nx.e_out)  # nx_shift = e_n - e_nx >= 0 (l_nx may have chosen a coarser grid)
    if e_n - l_nx.e_out > 7:  # pragma: no cover - weights far larger than any trained GRU's
        raise QuantizeError("the candidate's input part needs a much coarser exponent than its table")
    e_nh = max(exp_of("nh"), e_n - GATE_EXP)  # rn_shift = 8 + e_nh - e_n >= 0
    l_nh, f, a = _gate_layer("n (hidden part)", W_hh[blk[2]], b_hh[blk[2]], HIDDEN_EXP, e_nh)
    if l_nh.e_out < e_n - GATE_EXP:  # pragma: no cover - needs weights ~2^8 larger than the input part's
        raise QuantizeError("the candidate's hidden part needs a coarser exponent than the format allows")
    layers.append(l_nh), acc24.append(f), amax.append(a)
    r, z = layers[0], layers[1]
    cell = QuantGRUCell(r=r, z=z, nx=l_nx, nh=l_nh, r_table=numfmt.gate_table(r.e_out),
                        k_table=numfmt.gate_table(z.e_out, complement=True),
                        n_table=numfmt.act_table("tanh", e_n, HIDDEN_EXP),
                        rn_shift=GATE_EXP + l_nh.e_out - e_n, nx_shift=e_n - l_nx.e_out)
    wq, bq, shift, _, a = _quantize_layer("output", policy.w_out.astype(np.float64) * 255.0,
                                          policy.b_out.astype(np.float64) * 255.0, HIDDEN_EXP, 0,
                                          may_lower_e_out=False)
    out = QuantLayer(w=wq, b=bq, shift=shift, lo=0, hi=255, activation="identity", e_in=HIDDEN_EXP, e_out=0,
                     e_act=0, table=None)
    acc24.append(numfmt.fits_acc24(wq, bq)), amax.append(a)
    w = policy.world
    return QuantizedGRU(
        cell=cell, out=out, e_in=int(e_in), world=w,
        rbf_table=numfmt.rbf_table(w.rbf_centres_mm, w.rbf_sigma_mm, w.rbf_norm, w.comm_radius_mm, e_in),
        target_table=numfmt.target_table(w.comm_radius_mm, e_in), action_table=numfmt.action_table(e_in),
        policy_hash=policy.hash, acc24_safe=tuple(bool(x) for x in acc24), acc_max=tuple(int(x) for x in amax))


# --------------------------------------------------------------------------------------------
# Error report
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GRUErrorReport:
    """Float vs integer GRU: one step from the float state (teacher forcing) and free-running episodes."""

    step_err: dict[str, tuple[float, float]]  #: component -> (max |err|, mean |err|), teacher forcing
    saturated: dict[str, float]  #: gate pre-activation -> fraction at -128 or 127 (teacher forcing)
    du_max: float  #: free-running: max |u_int - u_float|
    du_mean: float
    same_command: float  #: free-running: fraction of commands with q == action_to_u8(u_float)
    h_drift_max: float  #: free-running: max |h_int / 128 - h_float|
    h_drift_mean: float
    n_samples: int
    n_sequences: int
    e_in: int
    input_saturated: float

    def table(self) -> str:
        """A printable report."""
        lines = [f"GRU quantisation error over {self.n_samples} calibration steps ({self.n_sequences} robot-episodes, "
                 f"e_in {self.e_in}, {100 * self.input_saturated:.2f}% of inputs saturated)",
                 "  one step from the float state:  component  max|err|  mean|err|   sat%"]
        for k, (mx, mn) in self.step_err.items():
            sat = self.saturated.get(k)
            lines.append(f"  {'':31}{k:>9} {mx:>9.5f} {mn:>10.5f} {'' if sat is None else f'{100 * sat:6.2f}'}")
        lines.append(f"  free-running episodes: max |du| = {self.du_max:.5f}, mean |du| = {self.du_mean:.5f}, "
                     f"same uint8 command {100 * self.same_command:.2f}%; hidden-state drift max "
                     f"{self.h_drift_max:.4f}, mean {self.h_drift_mean:.5f}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "gru", "step_err": {k: list(v) for k, v in self.step_err.items()},
                "saturated": dict(self.saturated), "du_max": self.du_max, "du_mean": self.du_mean,
                "same_command": self.same_command, "h_drift_max": self.h_drift_max,
                "h_drift_mean": self.h_drift_mean, "n_samples": self.n_samples, "n_sequences": self.n_sequences,
                "e_in": self.e_in, "input_saturated": self.input_saturated}


def gru_error_report(policy: GRUPolicy, qp: QuantizedGRU, calib: GRUCalibration) -> GRUErrorReport:
    """Compare the float and the integer cell on every calibration step (see :class:`GRUErrorReport`)."""
    from sim.motion import action_to_u8

    S, T, D = calib.seqs.shape
    xq = qp.quantize_tuple(calib.inputs)  # (S*T, D)
    hq = numfmt.quantize(calib.states.reshape(S * T, -1), HIDDEN_EXP)
    gi = qp.cell.gates(xq, hq)
    o = qp.out
    q = numfmt.dense_int(gi["h"], o.w, o.b, o.shift, o.lo, o.hi)
    v = calib.values
    err = {"r": np.abs(gi["r"] / 2.0 ** GATE_EXP - v["r"]), "1-z": np.abs(gi["k"] / 2.0 ** GATE_EXP - (1.0 - v["z"])),
           "n": np.abs(gi["n"] / 2.0 ** HIDDEN_EXP - v["n"]), "h'": np.abs(gi["h"] / 2.0 ** HIDDEN_EXP - v["h"]),
           "u": np.abs(q / 255.0 - v["u"])}
    step_err = {k: (float(e.max()), float(e.mean())) for k, e in err.items()}
    sat = {k: float(np.mean((gi[a] == INT8_MIN) | (gi[a] == INT8_MAX)))
           for k, a in (("r", "a_r"), ("1-z", "a_z"), ("n", "pre_n"))}
    # free-running: the integer cell carries its own state over each recorded episode
    h = qp.initial_state(S)
    xs = qp.quantize_tuple(calib.seqs)  # (S, T, D)
    qs = np.empty((S, T, ACTION_DIM), np.int64)
    hs = np.empty((S, T, qp.hidden_size), np.int64)
    for t in range(T):
        qs[:, t], h = qp.step_int(xs[:, t], h)
        hs[:, t] = h
    u_f = v["u"].reshape(S, T, ACTION_DIM)
    du = np.abs(qs / 255.0 - u_f)
    drift = np.abs(hs / 2.0 ** HIDDEN_EXP - v["h"].reshape(S, T, -1))
    return GRUErrorReport(step_err=step_err, saturated=sat, du_max=float(du.max()), du_mean=float(du.mean()),
                          same_command=float(np.mean(qs == action_to_u8(u_f))), h_drift_max=float(drift.max()),
                          h_drift_mean=float(drift.mean()), n_samples=S * T, n_sequences=S, e_in=qp.e_in,
                          input_saturated=float(np.mean((xq == INT8_MIN) | (xq == INT8_MAX))))
