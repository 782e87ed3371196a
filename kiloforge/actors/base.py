"""The actor-kind interface: what every stage asks of an actor, whatever network it is.

An actor kind (MLP, GRU, LSTM, ...) is one module of :mod:`kiloforge.actors` with one
:class:`ActorKind` instance, registered by name in :mod:`kiloforge.actors.registry` (as
TFLite-Micro's op resolver maps an op type to its kernel). The stages only talk to these types:

* **artifact ↔ float actor**: :meth:`ActorKind.from_arrays` builds the kind's :class:`FloatPolicy`
  from a file's arrays; :meth:`FloatPolicy.arrays` / :meth:`FloatPolicy.kind_meta` go back.
  Every kind's float actor steps one input tuple ``x = [a_prev, obs]`` (``world.tuple_dim`` wide)
  per control step with a state: an MLP's state is its history ring, a GRU's its hidden vector,
  an LSTM's its hidden and cell vectors (:meth:`FloatPolicy.step`); :meth:`ActorKind.swarm_policy`
  drives the simulator with it.
* **quantise**: :meth:`ActorKind.calibration` (from recorded input sequences),
  :meth:`ActorKind.quantize` -> the kind's :class:`QuantizedActor`, :meth:`ActorKind.error_report`.
* **budget**: :meth:`ActorKind.budget_spec` lists the kind's dense layers and its own flash / SRAM
  items; :meth:`ActorKind.resizes` says which sizes to vary for "what would fit";
  :attr:`ActorKind.budget_options` are its flags of ``python -m export budget``.
* **render**: :meth:`ActorKind.render_spec` gives the C the kind adds (defines, tables, dense
  layers, template variables); :attr:`ActorKind.template` is its template partial and
  :attr:`ActorKind.c_sources` its hand-written C kernel header.
* **emulator**: :meth:`QuantizedActor.step_int` is the firmware's control step on int8 tuples.

Everything here is data or NumPy: the shared C emitter (:mod:`export.codegen`) formats what the
kinds describe, as emlearn renders every model family through one C code generator.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Callable, ClassVar, Mapping, NoReturn, Sequence

import numpy as np

from sim.config import ACTION_DIM, WorldConfig
from sim.tasks.base import TaskRef

from .. import artifact, numfmt
from ..errors import PolicyError
from ..numfmt import QuantLayer


# --------------------------------------------------------------------------------------------
# Float actors
# --------------------------------------------------------------------------------------------
class FloatPolicy(ABC):
    """A float actor as plain data; subclasses are frozen dataclasses with ``world`` and ``provenance``."""

    kind: ClassVar[str]  #: the registered kind name (the artifact's "kind")
    world: WorldConfig
    provenance: dict[str, Any]
    #: the task it was trained for (sim.tasks.TaskRef); None only when read from a file written
    #: before tasks existed, which records none (:attr:`task_ref` is then localisation v1)
    task: Any

    @property
    def task_ref(self) -> Any:
        """The task this policy was trained for (a :class:`sim.tasks.TaskRef`)."""
        return artifact.task_or_legacy(self.task)

    @abstractmethod
    def arrays(self) -> dict[str, np.ndarray]:
        """The artifact's float32 arrays, in file (and hash) order."""

    @abstractmethod
    def kind_meta(self) -> dict[str, Any]:
        """The kind's own meta fields (sizes, gate order, ...)."""

    @abstractmethod
    def initial_state(self, n: int) -> Any:
        """The state of ``n`` robots at the start of an episode (what the firmware's setup() leaves)."""

    @abstractmethod
    def step(self, x: np.ndarray, state: Any) -> tuple[np.ndarray, Any]:
        """One control step: tuples ``x`` (n, tuple_dim) -> (u (n, 2) float64 in [0, 1], new state)."""

    @property
    @abstractmethod
    def layer_sizes(self) -> list[int]:
        """[input, hidden..., 2] for printing and manifests."""

    @abstractmethod
    def describe(self) -> str:
        """One line: the architecture (CLI output)."""

    @property
    def n_params(self) -> int:
        return int(sum(a.size for a in self.arrays().values()))

    def meta(self) -> dict[str, Any]:
        """The JSON metadata (without ``policy_hash``)."""
        return dict(artifact.base_meta(self.kind, self.world, self.provenance, self.task), **self.kind_meta())

    def canonical_bytes(self) -> bytes:
        """What :attr:`hash` covers (:func:`kiloforge.artifact.canonical_bytes`)."""
        return artifact.canonical_bytes(self.arrays(), self.meta())

    @cached_property
    def hash(self) -> str:
        """sha256 (hex) of :meth:`canonical_bytes`: the policy's identity in manifests and C banners."""
        return artifact.policy_hash(self.arrays(), self.meta())

    def to_npz_bytes(self) -> bytes:
        """The artifact file (byte-for-byte reproducible)."""
        return artifact.artifact_bytes(self.arrays(), self.meta())

    def act_sequence(self, xs: np.ndarray) -> np.ndarray:
        """Actions (S, T, 2) for input-tuple sequences (S, T, D) from the episode-start state."""
        xs = np.asarray(xs)
        state = self.initial_state(xs.shape[0])
        out = np.empty(xs.shape[:2] + (ACTION_DIM,))
        for t in range(xs.shape[1]):
            out[:, t], state = self.step(xs[:, t], state)
        return out


def invalid(msg: str) -> NoReturn:
    """Raise the PolicyError of an invalid float policy (``policy: <msg>``)."""
    raise PolicyError(f"policy: {msg}")


def check_world_and_task(world: Any, task: Any) -> None:
    """Every float policy carries a WorldConfig, and a TaskRef or None (a file from before tasks)."""
    if not isinstance(world, WorldConfig):
        invalid(f"world must be a WorldConfig, got {type(world).__name__}")
    if task is not None and not isinstance(task, TaskRef):
        invalid(f"task must be a sim.tasks.TaskRef or None, got {type(task).__name__}")


def float_arrays(obj: Any, names: Sequence[str], bad: Callable[[str], None] = invalid) -> dict[str, np.ndarray]:
    """Named attributes of ``obj`` as read-only contiguous float32 arrays, checked numeric and finite."""
    out = {}
    for name in names:
        a = np.asarray(getattr(obj, name))
        if a.dtype.kind not in "fiu":
            bad(f"'{name}' must be numeric, got {a.dtype}")
        a = np.ascontiguousarray(a, dtype=np.float32)
        if not np.all(np.isfinite(a)):
            bad(f"'{name}' holds non-finite values (NaN, inf, or beyond float32)")
        out[name] = a
    return out


def sigmoid(z: np.ndarray) -> np.ndarray:
    """Overflow-free float σ (float64)."""
    return 0.5 * (1.0 + np.tanh(0.5 * np.asarray(z, np.float64)))


class StatefulActor:
    """A :class:`sim.rollout.SwarmPolicy` around ``step(x (R, D), state) -> (u (R, 2), state)``.

    ``init(R)`` gives the state of R robots at an episode start. Per call the input tuple is
    ``[previous action, obs]``: the previous action is what this policy returned last (zero on
    the first step of an episode, as in the firmware and Algorithms 4 and 5).
    """

    def __init__(self, step: Callable[[np.ndarray, Any], tuple[np.ndarray, Any]], init: Callable[[int], Any],
                 world: WorldConfig) -> None:
        self.step_fn, self.init_fn, self.world = step, init, world
        self.state: Any = None
        self.prev: np.ndarray | None = None  # (B, M, 2)

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator | None = None) -> None:
        self.state = self.init_fn(n_envs * n_robots)
        self.prev = np.zeros((n_envs, n_robots, ACTION_DIM), np.float32)

    def act(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, np.float32)
        assert self.prev is not None and obs.shape[:2] == self.prev.shape[:2], "StatefulActor.act before reset"
        B, M, _ = obs.shape
        x = np.concatenate([self.prev, obs], -1).reshape(B * M, -1)  # (R, D)
        u, self.state = self.step_fn(x, self.state)
        u = np.clip(np.asarray(u, np.float64).reshape(B, M, ACTION_DIM), 0.0, 1.0)
        self.prev = u.astype(np.float32)
        return u


# --------------------------------------------------------------------------------------------
# Quantised actors
# --------------------------------------------------------------------------------------------
def sensing_tables(world: WorldConfig, e_in: int) -> dict[str, np.ndarray]:
    """The observation tables every kind's firmware holds, at the input exponent ``e_in``."""
    return {"rbf_table": numfmt.rbf_table(world.rbf_centres_mm, world.rbf_sigma_mm, world.rbf_norm,
                                          world.comm_radius_mm, e_in),
            "target_table": numfmt.target_table(world.comm_radius_mm, e_in),
            "action_table": numfmt.action_table(e_in)}


@dataclass(frozen=True, eq=False, kw_only=True)
class QuantizedActor(ABC):
    """An int8 actor plus the sensing tables, exactly as the firmware holds them.

    Input per control step: the tuple ``x = [ACT[q_left], ACT[q_right], obs]`` int8 at ``e_in``;
    output: the two uint8 motor commands ``q`` (``u = q / 255``).
    """

    kind: ClassVar[str]
    e_in: int  #: exponent of every observation / input entry (0 <= e_in <= DEFAULT_INPUT_EXP)
    world: WorldConfig  #: the world the policy was trained in (every sensing constant)
    rbf_table: np.ndarray  #: (n_rbf, 256) uint8, numfmt.rbf_table(world..., e_in)
    target_table: np.ndarray  #: (256,) int8, numfmt.target_table(world.comm_radius_mm, e_in)
    action_table: np.ndarray  #: (256,) int8, numfmt.action_table(e_in)
    policy_hash: str  #: sha256 of the float policy artifact this was quantised from
    format_name: str = numfmt.FORMAT_NAME  #: numfmt.FORMAT_NAME at quantisation time
    rounding: str = numfmt.ROUNDING  #: numfmt.ROUNDING at quantisation time

    def __post_init__(self) -> None:
        w = self.world
        assert 0 <= self.e_in <= numfmt.DEFAULT_INPUT_EXP, \
            f"e_in must be in 0..{numfmt.DEFAULT_INPUT_EXP}, got {self.e_in}"
        assert self.rbf_table.shape == (w.n_rbf, 256) and self.rbf_table.dtype == np.uint8, "rbf_table shape/dtype"
        assert self.target_table.shape == (256,) and self.target_table.dtype == np.int8, "target_table shape/dtype"
        assert self.action_table.shape == (256,) and self.action_table.dtype == np.int8, "action_table shape/dtype"
        assert all(a < numfmt.ACC32_LIMIT for a in self.acc_max), "int32 overflow proof failed"

    # every kind also has ``layers`` (its dense layers in firmware order, list[QuantLayer]) and
    # ``layer_sizes`` ([input, hidden..., 2]), as a field or a property

    @abstractmethod
    def initial_state(self, n: int) -> Any:
        """The integer state of ``n`` robots after setup()."""

    def setup_state(self, uids: np.ndarray) -> Any:
        """The integer state setup() leaves on robots with these kilo_uids (R,); a kind whose state
        depends on the uid (a random generator seeded from it) overrides this."""
        return self.initial_state(int(np.asarray(uids).shape[0]))

    @abstractmethod
    def step_int(self, x: np.ndarray, state: Any) -> tuple[np.ndarray, Any]:
        """The firmware's control step: int8 tuples (R, D) -> (uint8 commands (R, 2), new state)."""

    @abstractmethod
    def summary(self) -> dict[str, Any]:
        """JSON-ready description (exponents, shifts, flags) for the manifest."""

    @abstractmethod
    def describe(self) -> str:
        """The actor line of the C banner."""

    @property
    def acc24_safe(self) -> tuple[bool, ...]:
        """Per dense layer: the 24-bit accumulator is exact for every int8 input (numfmt.fits_acc)."""
        return tuple(l.acc24_safe for l in self.layers)

    @property
    def acc_max(self) -> tuple[int, ...]:
        """Per dense layer: max |acc + rounding| over every int8 input (the int32 proof's figure)."""
        return tuple(l.acc_max for l in self.layers)

    @property
    def one_q(self) -> int:
        """1.0 at exponent e_in (wall flag, neighbour flag; minus it: target not heard)."""
        return 1 << self.e_in

    @property
    def obs_dim(self) -> int:
        return self.world.obs_dim

    @property
    def tuple_dim(self) -> int:
        return self.world.tuple_dim

    def quantize_tuple(self, x: np.ndarray) -> np.ndarray:
        """Float tuples (..., D) -> int8 values at e_in (error reports; the firmware builds them from tables)."""
        return numfmt.quantize(x, self.e_in)


def dense_summary(name: str, l: QuantLayer) -> dict[str, Any]:
    """One dense layer of a manifest's quantisation summary."""
    return {"name": name, "n_in": int(l.w.shape[1]), "n_out": int(l.w.shape[0]), "activation": l.activation,
            "e_in": int(l.e_in), "e_out": int(l.e_out), "e_act": int(l.e_act), "lo": int(l.lo), "hi": int(l.hi),
            "shift_min": int(l.shift.min()), "shift_max": int(l.shift.max()), "table": l.table is not None,
            "acc24_safe": l.acc24_safe, "acc_max": l.acc_max}


# --------------------------------------------------------------------------------------------
# Budget and render descriptions (formatted by export.codegen)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BudgetItem:
    """One line of a flash / SRAM breakdown."""

    section: str  #: "flash" or "sram"
    name: str
    bytes: int
    note: str = ""


@dataclass(frozen=True)
class BudgetSpec:
    """What a kind adds to the firmware's budget (the shared items are export.codegen.budget's)."""

    header: str  #: the architecture, for the first line of the breakdown
    layer_sizes: tuple[int, ...]  #: (input, hidden..., 2)
    dense: tuple[tuple[int, int], ...]  #: (n_out, n_in) of every dense layer, firmware order
    flash: tuple[BudgetItem, ...] = ()  #: the kind's tables (after the sensing tables)
    memory: tuple[BudgetItem, ...] = ()  #: the kind's per-robot state (first SRAM lines)
    scratch: tuple[BudgetItem, ...] = ()  #: the control step's buffers (after the misc state)
    code_b: int = 0  #: code of the kind's step beyond the dense calls (estimate)
    code_note: str = ""
    arch: Mapping[str, Any] = field(default_factory=dict)  #: JSON-ready sizes (budget to_dict)


@dataclass(frozen=True)
class HiddenArch:
    """The size of a one-layer recurrent actor: its hidden units."""

    hidden: int

    def __post_init__(self) -> None:
        assert int(self.hidden) >= 1, f"hidden must be >= 1, got {self.hidden}"
        object.__setattr__(self, "hidden", int(self.hidden))


@dataclass(frozen=True)
class Resize:
    """One "what would fit" question: the largest ``n <= cap`` for which ``arch(n)`` fits."""

    arch: Callable[[int], Any]
    found: Callable[[int], str]  #: the answer for the largest n, e.g. "t_prev <= 11 with hidden [64, 32]"
    none: str  #: when not even n = 1 fits
    cap: int = 1024


@dataclass(frozen=True)
class BudgetOption:
    """A flag of ``python -m export budget`` that a kind reads (the CLI adds it to its parser)."""

    flag: str  #: e.g. "--gru"
    help: str
    metavar: str | None = None
    nargs: str | None = None  #: argparse nargs ("*" for lists)
    positive: bool = True  #: a positive integer (else a string)
    default: Any = None
    choices: tuple[str, ...] | None = None
    claims: bool = True  #: giving it selects this kind (False for modifiers such as an activation)

    @property
    def dest(self) -> str:
        return self.flag.lstrip("-").replace("-", "_")


@dataclass(frozen=True)
class CDefine:
    """``#define name value /* comment */`` with the value checked against ``ctype``."""

    name: str
    value: int
    ctype: str = "uint8_t"
    comment: str = ""


@dataclass(frozen=True)
class CTable:
    """A ``static const`` PROGMEM array."""

    name: str
    ctype: str
    values: np.ndarray
    comment: str = ""
    per_line: int = 16


@dataclass(frozen=True)
class CDense:
    """A dense layer: its three kernel arrays (W, B, S names) and its ``kf_dense_t`` descriptor."""

    descriptor: str  #: e.g. "KF_L0"
    w: str
    b: str
    s: str
    layer: QuantLayer
    what: str  #: the weights' comment, e.g. "layer 0"
    label: str  #: the biases' and shifts' comment, e.g. "layer 0"
    extra: Mapping[str, str] = field(default_factory=dict)  #: template variables of this layer (the partial's)


@dataclass(frozen=True)
class RenderSpec:
    """What a kind puts into ``kilobot_policy.c`` beside the shared program."""

    memory: tuple[CDefine, ...]  #: defines after the role table (the state's sizes)
    scratch: tuple[CDefine, ...]  #: defines after the motor modes (the control step's buffers)
    tables: tuple[CTable | CDense, ...]  #: in file order; a CDense stands for its W, B, S arrays
    variables: Mapping[str, Any] = field(default_factory=dict)  #: further template variables of the partial


# --------------------------------------------------------------------------------------------
# The kind
# --------------------------------------------------------------------------------------------
class ActorKind(ABC):
    """One actor kind, implemented once in its module and registered by :attr:`name`."""

    name: ClassVar[str]  #: the artifact's "kind"
    template: ClassVar[str]  #: the firmware partial (extends kilobot_policy.c.j2)
    c_sources: ClassVar[tuple[str, ...]] = ()  #: hand-written C of firmware_templates/ the partial needs
    budget_usage: ClassVar[str]  #: how its budget flags read, e.g. "--gru H"
    budget_options: ClassVar[tuple[BudgetOption, ...]] = ()

    # --- artifact <-> float actor ----------------------------------------------------------
    @abstractmethod
    def from_arrays(self, arrays: dict[str, np.ndarray], meta: dict[str, Any], world: WorldConfig,
                    provenance: dict[str, Any]) -> FloatPolicy:
        """The float policy of a file's arrays and meta (raises PolicyError ``policy: ...``)."""

    def swarm_policy(self, policy: FloatPolicy, world: WorldConfig | None = None) -> Any:
        """The float actor as a :class:`sim.rollout.SwarmPolicy` (``world``: e.g. another episode length)."""
        return StatefulActor(policy.step, policy.initial_state, world or policy.world)

    # --- quantise ----------------------------------------------------------------------------
    @abstractmethod
    def calibration(self, policy: FloatPolicy, seqs: np.ndarray, info: dict[str, Any]) -> Any:
        """What the float actor computes over recorded input sequences (S, T, D) from episode starts."""

    @abstractmethod
    def quantize(self, policy: FloatPolicy, calib: Any, *, percentile: float = 100.0, headroom: float = 1.0,
                 e_in: int | None = None) -> QuantizedActor:
        """The int8 actor, exponents from the calibration ranges (raises QuantizeError)."""

    @abstractmethod
    def error_report(self, policy: FloatPolicy, qp: QuantizedActor, calib: Any) -> Any:
        """Float vs int8 over the calibration (``table()``, ``to_dict()``, ``du_max``, ``du_mean``,
        ``same_command``)."""

    # --- budget --------------------------------------------------------------------------------
    @abstractmethod
    def arch_of(self, policy: FloatPolicy) -> Any:
        """The architecture of a float policy (what :meth:`budget_spec` takes)."""

    @abstractmethod
    def arch_of_quantized(self, qp: QuantizedActor) -> Any:
        """The architecture of a quantised policy (it may know more, e.g. which tables are shared)."""

    @abstractmethod
    def budget_spec(self, world: WorldConfig, arch: Any, e_in: int) -> BudgetSpec:
        """The kind's part of the flash / SRAM breakdown."""

    @abstractmethod
    def resizes(self, world: WorldConfig, arch: Any) -> list[Resize]:
        """Sizes to vary when ``arch`` does not fit."""

    @abstractmethod
    def budget_arch(self, values: Mapping[str, Any]) -> Any | None:
        """The architecture given by this kind's budget flags, or None when none of them was given."""

    # --- render --------------------------------------------------------------------------------
    @abstractmethod
    def render_spec(self, qp: QuantizedActor) -> RenderSpec:
        """The kind's defines, tables, dense layers and template variables (raises QuantizeError when the
        firmware cannot hold them)."""
