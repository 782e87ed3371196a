"""What the recurrent actor kinds (GRU, LSTM) share: PyTorch's cell arrays, their validation, calibration
over recorded sequences, free-running integer replays, the float-vs-integer error report and the kind's common
answers.

A recurrent actor reads one tuple ``x = [a_prev, obs]`` per control step (``world.tuple_dim`` wide)
and carries a state between steps (zero at the start of an episode, Algorithm 5). Its artifact
holds PyTorch's arrays, G gate blocks of H rows each::

    w_ih (G H, D)   w_hh (G H, H)   b_ih (G H,)   b_hh (G H,)   w_out (2, H)   b_out (2,)

(G = 3 for the GRU's r, z, n; 4 for the LSTM's i, f, g, o) and meta ``hidden``, ``input_dim``,
``gate_order``, ``input "a_prev+obs"``.
"""
from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar, Mapping

import numpy as np

from sim.config import ACTION_DIM, WorldConfig
from sim.motion import action_to_u8
from sim.tasks.base import TaskRef

from .. import numfmt
from ..artifact import plain_provenance
from ..errors import PolicyError, QuantizeError
from ..numfmt import HIDDEN_EXP, QuantLayer
from ..validate import show
from .base import (ActorKind, BudgetItem, BudgetOption, BudgetSpec, CDefine, CDense, CTable, FloatPolicy, HiddenArch,
                   QuantizedActor, RenderSpec, Resize, check_world_and_task, float_arrays, invalid)
from .dense import is_output_layer, saturated_fraction

ARRAYS = ("w_ih", "w_hh", "b_ih", "b_hh", "w_out", "b_out")
INPUT_LAYOUT = "a_prev+obs"  #: one sim.history tuple per step
MAX_HIDDEN = 255  #: the firmware indexes hidden units with uint8


@dataclass(frozen=True, eq=False)
class RecurrentPolicy(FloatPolicy):
    """A float recurrent actor as PyTorch's arrays (see the module doc); subclasses name the kind, its
    gate count and order, and the cell's arithmetic (:meth:`gates`)."""

    GATE_COUNT: ClassVar[int]
    GATE_ORDER: ClassVar[str]
    STATE_WIDTH: ClassVar[int]  #: state vector width in units of H (GRU: h; LSTM: [h, c])
    w_ih: np.ndarray  #: (G H, D) float32, gate blocks in GATE_ORDER
    w_hh: np.ndarray  #: (G H, H)
    b_ih: np.ndarray  #: (G H,)
    b_hh: np.ndarray  #: (G H,)
    w_out: np.ndarray  #: (2, H)
    b_out: np.ndarray  #: (2,)
    world: WorldConfig
    provenance: dict[str, Any] = field(default_factory=dict)
    task: TaskRef | None = None  #: the task it was trained for (None: a file from before tasks)

    def __post_init__(self) -> None:
        check_world_and_task(self.world, self.task)
        arrs = float_arrays(self, ARRAYS)
        G, w_hh = self.GATE_COUNT, arrs["w_hh"]
        if w_hh.ndim != 2 or w_hh.shape[0] != G * w_hh.shape[1] or w_hh.shape[1] < 1:
            invalid(f"w_hh must be ({G}H, H), got {w_hh.shape}")
        H = w_hh.shape[1]
        if H > MAX_HIDDEN:
            invalid(f"hidden size {H} > {MAX_HIDDEN} (the firmware indexes hidden units with uint8)")
        D = self.world.tuple_dim
        want = {"w_ih": (G * H, D), "b_ih": (G * H,), "b_hh": (G * H,), "w_out": (ACTION_DIM, H),
                "b_out": (ACTION_DIM,)}
        for name, shape in want.items():
            if arrs[name].shape != shape:
                extra = (f" = ({G} x hidden {H}, tuple {D}: 2 actions + {self.world.obs_dim} observations of world "
                         f"'{self.world.name}')") if name == "w_ih" else ""
                invalid(f"'{name}' has shape {arrs[name].shape}, expected {shape}{extra}")
        prov = plain_provenance(self.provenance)
        for name, a in arrs.items():
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        object.__setattr__(self, "provenance", prov)

    @property
    def hidden_size(self) -> int:
        return int(self.w_hh.shape[1])

    @property
    def in_dim(self) -> int:
        """Input width per step: one tuple, ``world.tuple_dim``."""
        return int(self.w_ih.shape[1])

    @property
    def layer_sizes(self) -> list[int]:
        """[input tuple, hidden, 2] (printing and manifests)."""
        return [self.in_dim, self.hidden_size, ACTION_DIM]

    def describe(self) -> str:
        return (f"{self.kind.upper()}: input {self.in_dim} ([a_prev, obs]), {self.hidden_size} hidden units, "
                f"linear output {ACTION_DIM}")

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in ARRAYS}

    def kind_meta(self) -> dict[str, Any]:
        return {"hidden": self.hidden_size, "input_dim": self.in_dim, "gate_order": self.GATE_ORDER,
                "input": INPUT_LAYOUT}

    def initial_state(self, n: int) -> np.ndarray:
        """Zero states (n, STATE_WIDTH H) float64: the start of an episode."""
        return np.zeros((int(n), self.STATE_WIDTH * self.hidden_size))

    @abstractmethod
    def gates(self, x: np.ndarray, state: np.ndarray) -> dict[str, np.ndarray]:
        """Every intermediate of one step in float64; at least "state" (the new state) and "u"."""

    def step(self, x: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One control step: tuples (..., D) and states (..., STATE_WIDTH H) -> (u (..., 2) in [0, 1], new states)."""
        v = self.gates(x, state)
        return v["u"], v["state"]


def random_recurrent(cls: type[RecurrentPolicy], world: WorldConfig, hidden: int, seed: int = 0, scale: float = 1.0,
                     out_bias: float = 0.5, out_scale: float = 1.0, provenance: dict | None = None) -> RecurrentPolicy:
    """A deterministic untrained policy of ``cls`` (tests, benchmarks): cell weights U(±scale/√H), output
    weights U(±out_scale/√H) and biases ``out_bias`` so that the commands spread over [0, 1]."""
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    D, H, G = world.tuple_dim, int(hidden), cls.GATE_COUNT
    b = scale / np.sqrt(H)
    u = lambda *shape, lim=b: rng.uniform(-lim, lim, size=shape).astype(np.float32)  # noqa: E731
    return cls(w_ih=u(G * H, D), w_hh=u(G * H, H), b_ih=u(G * H), b_hh=u(G * H),
               w_out=u(ACTION_DIM, H, lim=out_scale / np.sqrt(H)), b_out=np.full(ACTION_DIM, out_bias, np.float32),
               world=world, provenance=dict(provenance or {"notes": f"random {cls.kind} policy seed {seed}"}))


@dataclass(frozen=True, eq=False, kw_only=True)
class QuantizedRecurrent(QuantizedActor):
    """An int8 recurrent actor: the kind's cell (``.hidden``, ``.in_dim``, ``.layers``: its dense layers in
    firmware order, the first reading ``[x, h]`` at ``e_in``) and the uint8 output layer on the new h."""

    STATE_WIDTH: ClassVar[int]
    cell: Any
    out: QuantLayer  #: (2, H) on h' at HIDDEN_EXP -> uint8 motor commands

    def __post_init__(self) -> None:
        super().__post_init__()
        c, o = self.cell, self.out
        assert c.in_dim == self.world.tuple_dim, f"cell input {c.in_dim} != tuple width {self.world.tuple_dim}"
        assert c.layers[0].e_in == self.e_in, "the gates read x at e_in"
        assert o.w.shape == (ACTION_DIM, c.hidden), f"output layer must be ({ACTION_DIM}, {c.hidden})"
        assert is_output_layer(o) and o.e_in == HIDDEN_EXP, \
            "output layer: h at HIDDEN_EXP -> uint8 commands (exponent 0, clamp 0..255)"

    @property
    def layers(self) -> list[QuantLayer]:
        """Every dense layer in firmware order: the cell's, then the output."""
        return [*self.cell.layers, self.out]

    @property
    def hidden_size(self) -> int:
        return int(self.cell.hidden)

    @property
    def in_dim(self) -> int:
        return self.world.tuple_dim

    @property
    def layer_sizes(self) -> list[int]:
        """[input tuple, hidden, 2]."""
        return [self.in_dim, self.hidden_size, ACTION_DIM]

    def initial_state(self, n: int) -> np.ndarray:
        """Zero states (n, STATE_WIDTH H) int64: what setup() leaves."""
        return np.zeros((int(n), self.STATE_WIDTH * self.hidden_size), np.int64)


@dataclass(frozen=True, eq=False)
class SequenceCalibration:
    """What a float recurrent actor saw: input tuples and states per robot-episode, and every intermediate."""

    seqs: np.ndarray  #: (S, T, D) float32 input tuples, one row per robot-episode
    states: np.ndarray  #: (S, T, state width) float64 state before each step
    values: dict[str, np.ndarray]  #: the policy's gates() over every (S*T) step, flattened (row s*T + t)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.seqs.shape[0] * self.seqs.shape[1])

    @property
    def inputs(self) -> np.ndarray:
        """(S*T, D) every input tuple."""
        return self.seqs.reshape(-1, self.seqs.shape[-1])


def calibration_from_sequences(policy: RecurrentPolicy, seqs: np.ndarray, info: dict | None = None) -> SequenceCalibration:
    """Run the float actor over recorded input sequences (S, T, D) from zero states; keep everything."""
    seqs = np.asarray(seqs, np.float32)
    assert seqs.ndim == 3 and seqs.shape[-1] == policy.in_dim and seqs.shape[1] >= 1, \
        f"sequences must be (S, T, {policy.in_dim}), got {seqs.shape}"
    S, T, _ = seqs.shape
    state = policy.initial_state(S)
    states = np.empty((S, T, state.shape[-1]))
    vals: dict[str, list[np.ndarray]] = {}
    for t in range(T):
        states[:, t] = state
        v = policy.gates(seqs[:, t], state)
        for k, a in v.items():
            vals.setdefault(k, []).append(a)
        state = v["state"]
    values = {k: np.stack(v, 1).reshape(S * T, -1) for k, v in vals.items()}
    return SequenceCalibration(seqs=seqs, states=states, values=values, info=dict(info or {}))


def free_run(qp: QuantizedActor, seqs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The integer actor over float input sequences (S, T, D) from its setup() state: (commands (S, T, 2)
    int64, states after each step (S, T, state width) int64)."""
    S, T, _ = seqs.shape
    xs = qp.quantize_tuple(seqs)
    state = qp.initial_state(S)
    qs = np.empty((S, T, ACTION_DIM), np.int64)
    ss = np.empty((S, T, state.shape[-1]), np.int64)
    for t in range(T):
        qs[:, t], state = qp.step_int(xs[:, t], state)
        ss[:, t] = state
    return qs, ss


#: a kind's one step from the float state, over every calibration step: (quantised input tuples (S*T, D)) ->
#: (the cell's integer intermediates, "h" the new hidden state; component -> |int - float| per step; gate
#: pre-activation -> fraction saturated)
TeacherStep = Callable[[np.ndarray], tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict[str, float]]]


@dataclass(frozen=True)
class RecurrentErrorReport:
    """Float vs integer recurrent actor: one step from the float state (teacher forcing) and free-running episodes."""

    kind: str
    step_err: dict[str, tuple[float, float]]  #: component -> (max |err|, mean |err|), teacher forcing
    saturated: dict[str, float]  #: gate pre-activation -> fraction at -128 or 127 (teacher forcing)
    du_max: float  #: free-running: max |u_int - u_float|
    du_mean: float
    same_command: float  #: free-running: fraction of commands with q == action_to_u8(u_float)
    drift: dict[str, tuple[float, float]]  #: free-running: state part (h; the LSTM's c) -> (max, mean) |int - float|
    n_samples: int
    n_sequences: int
    e_in: int
    input_saturated: float

    def table(self) -> str:
        """A printable report."""
        lines = [f"{self.kind.upper()} quantisation error over {self.n_samples} calibration steps ({self.n_sequences} "
                 f"robot-episodes, e_in {self.e_in}, {100 * self.input_saturated:.2f}% of inputs saturated)",
                 "  one step from the float state:  component  max|err|  mean|err|   sat%"]
        for k, (mx, mn) in self.step_err.items():
            sat = self.saturated.get(k)
            lines.append(f"  {'':31}{k:>9} {mx:>9.5f} {mn:>10.5f} {'' if sat is None else f'{100 * sat:6.2f}'}")
        drift = ", ".join(f"|{k}| max {mx:.4f} mean {mn:.5f}" for k, (mx, mn) in self.drift.items())
        lines.append(f"  free-running episodes: max |du| = {self.du_max:.5f}, mean |du| = {self.du_mean:.5f}, "
                     f"same uint8 command {100 * self.same_command:.2f}%; state drift {drift}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "step_err": {k: list(v) for k, v in self.step_err.items()},
                "saturated": dict(self.saturated), "du_max": self.du_max, "du_mean": self.du_mean,
                "same_command": self.same_command,
                **{f"{k}_drift_{stat}": v for k, d in self.drift.items() for stat, v in zip(("max", "mean"), d)},
                "n_samples": self.n_samples, "n_sequences": self.n_sequences, "e_in": self.e_in,
                "input_saturated": self.input_saturated}


def recurrent_error_report(kind: str, qp: QuantizedRecurrent, calib: SequenceCalibration, teacher: TeacherStep,
                           parts: Mapping[str, tuple[slice, int]]) -> RecurrentErrorReport:
    """Compare the float and the integer actor on every calibration step: the kind's ``teacher`` step, the
    commands computed from its new hidden state, and free-running episodes (:func:`free_run`) whose states are
    compared part by part (``parts``: name in ``calib.values`` -> (its columns of the state, its exponent))."""
    S, T, _ = calib.seqs.shape
    xq = qp.quantize_tuple(calib.inputs)  # (S*T, D)
    gi, err, sat = teacher(xq)
    o, v = qp.out, calib.values
    q = numfmt.dense_int(gi["h"], o.w, o.b, o.shift, o.lo, o.hi)
    err = {**err, "u": np.abs(q / 255.0 - v["u"])}
    qs, ss = free_run(qp, calib.seqs)  # the integer cell carries its own state over each recorded episode
    u_f = v["u"].reshape(S, T, ACTION_DIM)
    du = np.abs(qs / 255.0 - u_f)
    drift = {name: np.abs(ss[..., cols] / 2.0 ** exp - v[name].reshape(S, T, -1)) for name, (cols, exp) in parts.items()}
    return RecurrentErrorReport(kind=kind, step_err={k: (float(e.max()), float(e.mean())) for k, e in err.items()},
                                saturated=sat, du_max=float(du.max()), du_mean=float(du.mean()),
                                same_command=float(np.mean(qs == action_to_u8(u_f))),
                                drift={k: (float(d.max()), float(d.mean())) for k, d in drift.items()},
                                n_samples=S * T, n_sequences=S, e_in=qp.e_in, input_saturated=saturated_fraction(xq))


class RecurrentKind(ActorKind):
    """The answers a recurrent kind shares: its artifact, calibration, quantiser and error report, size flag and
    resize."""

    policy_type: ClassVar[type[RecurrentPolicy]]
    #: the kind's quantiser: (policy, calibration, *, percentile, headroom, e_in) -> its QuantizedRecurrent
    quantizer: ClassVar[Callable[..., QuantizedRecurrent]]
    #: the kind's error report: (policy, its QuantizedRecurrent, calibration) -> RecurrentErrorReport
    reporter: ClassVar[Callable[..., RecurrentErrorReport]]
    #: the kind's dense layers: (input width, hidden units) -> (n_out, n_in) of each, in firmware order
    sizes: ClassVar[Callable[[int, int], list[tuple[int, int]]]]
    #: (C name suffix, what the layer computes) of the dense layers in firmware order
    c_layers: ClassVar[tuple[tuple[str, str], ...]]
    code_b: ClassVar[int]  #: code of the cell's step beyond the dense calls (gate tables, state update); estimate

    def quantize(self, policy: RecurrentPolicy, calib: SequenceCalibration, *, percentile: float = 100.0,
                 headroom: float = 1.0, e_in: int | None = None) -> QuantizedRecurrent:
        return self.quantizer(policy, calib, percentile=percentile, headroom=headroom, e_in=e_in)

    def error_report(self, policy: RecurrentPolicy, qp: QuantizedRecurrent,
                     calib: SequenceCalibration) -> RecurrentErrorReport:
        return self.reporter(policy, qp, calib)

    @property
    def budget_usage(self) -> str:  # type: ignore[override]
        return f"--{self.name} H"

    @property
    def budget_options(self) -> tuple[BudgetOption, ...]:  # type: ignore[override]
        """Its ``python -m export budget`` flag: ``--<kind> H``."""
        return (BudgetOption(f"--{self.name}", f"a recurrent actor instead: one {self.name.upper()} layer of H units "
                                               f"(learn train-recurrent --cell {self.name})", metavar="H"),)

    def from_arrays(self, arrays: dict[str, np.ndarray], meta: dict[str, Any], world: WorldConfig,
                    provenance: dict[str, Any]) -> RecurrentPolicy:
        missing = [n for n in ARRAYS if n not in arrays]
        if missing:
            raise PolicyError(f"policy: lacks array(s) {', '.join(missing)} of a '{self.name}' policy")
        extra = sorted(set(arrays) - set(ARRAYS))
        if extra:
            raise PolicyError(f"policy: has unexpected arrays: {', '.join(extra)}")
        for key in ("hidden", "gate_order", "input"):
            if key not in meta:
                raise PolicyError(f"policy: 'meta' lacks '{key}'")
        order = self.policy_type.GATE_ORDER
        if meta["gate_order"] != order:
            raise PolicyError(f"policy: gate order {meta['gate_order']!r} is not supported (only '{order}')")
        if meta["input"] != INPUT_LAYOUT:
            raise PolicyError(f"policy: input layout {meta['input']!r} is not supported (only '{INPUT_LAYOUT}')")
        for key in ("hidden", "input_dim"):
            v = meta.get(key, 0)
            if isinstance(v, bool) or not isinstance(v, int):
                raise PolicyError(f"policy: '{key}' must be an integer, got {show(v)}")
        p = self.policy_type(**{n: arrays[n] for n in ARRAYS}, world=world, provenance=provenance)
        if meta["hidden"] != p.hidden_size or meta.get("input_dim", p.in_dim) != p.in_dim:
            raise PolicyError(f"policy: meta says hidden {meta['hidden']}, input {meta.get('input_dim')} but the "
                              f"arrays have hidden {p.hidden_size}, input {p.in_dim}")
        return p

    def calibration(self, policy: RecurrentPolicy, seqs: np.ndarray, info: dict[str, Any]) -> SequenceCalibration:
        return calibration_from_sequences(policy, seqs, info)

    def arch_of(self, policy: RecurrentPolicy) -> HiddenArch:
        return HiddenArch(policy.hidden_size)

    def arch_of_quantized(self, qp: QuantizedActor) -> HiddenArch:
        return HiddenArch(qp.hidden_size)  # type: ignore[attr-defined]

    def resizes(self, world: WorldConfig, arch: HiddenArch) -> list[Resize]:
        return [Resize(arch=HiddenArch, found=lambda n: f"{self._a()} of <= {n} hidden units",
                       none=f"no {self.name.upper()} size fits", cap=MAX_HIDDEN)]

    def _a(self) -> str:
        """"a GRU", "an LSTM"."""
        label = self.name.upper()
        return f"{'an' if label[0] in 'AEFHILMNORSX' else 'a'} {label}"

    def cell_budget(self, world: WorldConfig, arch: HiddenArch, state: str, gate_tables: BudgetItem, memory: BudgetItem,
                    scratch: BudgetItem) -> BudgetSpec:
        """The budget of a cell of ``arch.hidden`` units (``state``: how it keeps its state) with the kind's gate
        tables, state and scratch buffers."""
        D, H, label = world.tuple_dim, arch.hidden, self.name.upper()
        return BudgetSpec(header=f"{label} actor: input {D}, {H} hidden units ({state}), linear output {ACTION_DIM}",
                          layer_sizes=(D, H, ACTION_DIM), dense=tuple(self.sizes(D, H)), flash=(gate_tables,),
                          memory=(memory,), scratch=(scratch,), code_b=self.code_b, code_note=f"{label} step",
                          arch={"hidden": H})

    def cell_render(self, qp: QuantizedRecurrent, gate_tables: list[CTable], state: str,
                    scratch: tuple[CDefine, ...]) -> RenderSpec:
        """What the C of a cell holds: its gate tables, its dense layers (:attr:`c_layers`), ``KF_HIDDEN``
        (``state``: how the state is kept) and its scratch defines; a cell wider than the firmware's uint8 loops
        is refused."""
        H = qp.hidden_size
        if not 1 <= H <= MAX_HIDDEN:
            raise QuantizeError(f"{self._a()} of {H} hidden units does not fit the firmware's uint8 loops "
                                f"(1..{MAX_HIDDEN})")
        dense = [CDense(f"KF_L{name}", f"KF_W_{name}", f"KF_B_{name}", f"KF_S_{name}", layer, what, name)
                 for (name, what), layer in zip(self.c_layers, qp.layers)]
        return RenderSpec(memory=(CDefine("KF_HIDDEN", H, comment=f"{self.name.upper()} hidden units ({state})"),),
                          scratch=scratch, tables=(*gate_tables, *dense))

    def budget_arch(self, values: Mapping[str, Any]) -> HiddenArch:
        return HiddenArch(int(values[self.name]))
