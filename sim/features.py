"""Observation features: the registry of what a robot can compute from one control period.

A world's observation (``WorldConfig.obs_features``, chosen by its task: :meth:`sim.tasks.Task.world`) is
a list of these features, concatenated in the listed order; ``WorldConfig.obs_index(name)`` is a
feature's first input. Each feature has

* a width (1, or ``n_rbf`` for the RBF histogram);
* a float reference (:func:`reference`, on :class:`sim.events.PeriodSummary`, the receive rules'
  result) that :func:`sim.events.observe` writes; :func:`sim.radio.observe_fast` computes the same bits
  straight from the message arrays;
* its integer firmware block, ``firmware_templates/features/<name>.c.j2`` (rendered into ``kf_observe``),
  and the block's bit-exact emulator twin (:data:`export.verify.emulator.INT_FEATURES`);
* what it needs of the world and the message: ``target`` the emitter (the task's transmitting robot:
  a target slot, the emitter role), ``nbr_sensing`` the emitter and the message's "I sense the target" bit.

``wall``: 1 when the ambient light is at least ``light_threshold`` (a reading of -1 keeps the last flag).
``light`` (2 inputs, what run-and-tumble needs): the *held* reading h (the latest reading >= 0: a
reading of -1, receiving, keeps the last one, as the firmware does) as ``h / 1024``, and its change
since the last control step ``(h - h_prev) / 1024`` (0 when this step's reading is -1 or no reading
was held before). The firmware block quantises both at the input exponent: level ``(h · ONE) >> 10``,
change the difference of levels.
A task may bring features of its own, computed from the neighbour table (:mod:`sim.table_features`); resolving
the task registers them in :data:`TASK_FEATURES`, and :func:`feature` finds a built-in or a task's feature by name.

``target``: ``min(d / comm_radius, 1)`` when the emitter was heard this period, else -1.
``object_light``: the emitter's own ambient-light reading, which it puts in its messages (it reads at its control
ticks and sends its held reading: :data:`export.contract.firmware.MSG_LIGHT_BYTE`), as ``L / 1024`` with L the
reading of the latest emitter message that carried one, held between messages and periods; -1 before any. The
firmware block writes ``(L · ONE) >> 10`` (the ``light`` level's scale, so a policy can compare the two).
``nbr_sensing``: 1 when a table entry's latest message says its sender senses the target.
``random``: ``b / 128`` with b the signed top byte of the robot's xorshift32 word (:mod:`kiloforge.xorshift`),
stepped once per control step; the word starts at ``rng_seed(kilo_uid, rand_hard)`` (searcher i has kilo_uid
i + 1; the simulator draws each robot's rand_hard byte from the env's init stream at reset). The firmware
block writes ``(b · ONE) >> 7``: the same draw at the input exponent. Symmetry breaking for rule kinds.
``rbf``: bin k is ``Σ ψ_k(d) / rbf_norm`` over the table entries within the communication radius,
``ψ_k(d) = exp(-(d - μ_k)² / (2σ²))`` (summed in sender order).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from kiloforge.errors import InputError
from kiloforge.xorshift import top_byte

from .table_features import NeighbourTable, check

#: annotations only: sim.config imports this module, so it cannot import sim.config or sim.events
WorldConfig = PeriodSummary = Any

@dataclass(frozen=True)
class Feature:
    """One observation feature (see the module doc)."""

    name: str
    doc: str  #: one line: what the input says
    needs_emitter: bool = False  #: reads the emitter's messages: only in worlds with an emitter
    uses_flag: bool = False  #: reads the message's "I sense the target" bit
    per_rbf: bool = False  #: ``n_rbf`` inputs, else one
    input_name: str = ""  #: the input's name in ONNX metadata (default: the feature's name)
    parts: tuple[str, ...] = ()  #: several named inputs (``<name>_<part>``), else one
    reads_light: bool = False  #: reads get_ambientlight() (the program reads it once per control step)
    random: bool = False  #: reads the robot's xorshift32 word (stepped once per control step)
    emitter_light: bool = False  #: reads the emitter's light reading in its messages (the emitter reads and sends it)
    table: Any = None  #: a task's own feature (:class:`sim.table_features.TableFeature`): computed from the table
    counters: tuple[str, ...] = ()  #: the loop counters (uint8_t) its firmware block uses in kf_observe

    def width(self, cfg: WorldConfig) -> int:
        return cfg.n_rbf if self.per_rbf else max(len(self.parts), 1)


FEATURES: dict[str, Feature] = {f.name: f for f in (
    Feature("wall", "1 when the ambient light says a wall is near, else 0", reads_light=True),
    Feature("light", "the held ambient-light reading / 1024 and its change since the last control period",
            parts=("level", "change"), reads_light=True),
    Feature("target", "distance to the emitter / comm radius in [0, 1] when heard this period, else -1",
            needs_emitter=True, input_name="target_dist"),
    Feature("object_light", "the emitter's broadcast light reading / 1024, the latest heard (held), else -1",
            needs_emitter=True, emitter_light=True),
    Feature("nbr_sensing", "1 when a heard robot's latest message says it senses the emitter, else 0",
            needs_emitter=True, uses_flag=True, counters=("i",)),
    Feature("random", "a uniform draw in [-1, 1) from the robot's xorshift32 stream, new each control period",
            random=True),
    Feature("rbf", "the RBF histogram of the neighbours' distances (n_rbf bins)", per_rbf=True, counters=("i", "k")),
)}

#: the features tasks brought (:attr:`sim.tasks.Task.own_features`), registered when a task is resolved
TASK_FEATURES: dict[str, Feature] = {}


def feature(name: str) -> Feature:
    """The built-in or task feature ``name`` (KeyError when neither knows it)."""
    f = FEATURES.get(name)
    return f if f is not None else TASK_FEATURES[name]


def _origin(obj: Any) -> tuple[str, str]:
    """Where ``obj``'s class is defined: a task file imported again defines the same class anew."""
    return type(obj).__module__, type(obj).__qualname__


def register(table_feature: Any, where: str) -> None:
    """Make a task's own feature (checked: :func:`sim.table_features.check`) known by its name; InputError when
    another task already brought a different feature of that name."""
    tf = check(table_feature, where, set(FEATURES))
    known = TASK_FEATURES.get(tf.name)
    if known is not None and _origin(known.table) != _origin(tf):
        raise InputError(f"{where}: feature {tf.name!r} is already defined by {'.'.join(_origin(known.table))}; "
                         "choose another name")
    parts = tuple(str(k) for k in range(tf.width)) if tf.width > 1 else ()
    TASK_FEATURES[tf.name] = Feature(tf.name, tf.doc, parts=parts, table=tf, counters=("i",))


#: localisation's layout (the thesis's 14 inputs), the layout of every world written before layouts were chosen
LEGACY_FEATURES = "wall,target,nbr_sensing,rbf"


def parse_features(spec: str, emitter: bool, where: str) -> tuple[str, ...]:
    """The feature names of ``spec`` (comma-separated, in input order), checked: known, each once, and
    the emitter's features only with an emitter. InputError naming ``where`` otherwise."""
    names = tuple(spec.split(",")) if spec else ()
    if not names:
        raise InputError(f"{where}: obs_features is empty; choose from: {', '.join(FEATURES)}")
    unknown = [n for n in names if n not in FEATURES and n not in TASK_FEATURES]
    if unknown:
        raise InputError(f"{where}: unknown observation feature(s) {', '.join(map(repr, unknown[:4]))}; "
                         f"choose from: {', '.join([*FEATURES, *TASK_FEATURES])} (a task's own features are known "
                         "once its --task is given)")
    if len(set(names)) != len(names):
        raise InputError(f"{where}: obs_features lists a feature twice: {spec!r}")
    if not emitter:
        need = [n for n in names if feature(n).needs_emitter]
        if need:
            raise InputError(f"{where}: observation feature(s) {', '.join(need)} need an emitter (emitter is False)")
    return names


def emitter_sends_light(cfg: WorldConfig) -> bool:
    """True when the emitter puts its light reading in its messages: the world's layout reads it (``object_light``)."""
    return bool(cfg.emitter) and any(feature(f).emitter_light for f in cfg.features)


def rbf(cfg: WorldConfig, d_mm: np.ndarray) -> np.ndarray:
    """ψ_k(d) / rbf_norm for every k, zero beyond the communication radius. Shape d.shape + (n_rbf,)."""
    d = np.asarray(d_mm, dtype=np.float64)[..., None]
    psi = np.exp(-((d - cfg.rbf_centres_mm) ** 2) / (2.0 * cfg.rbf_sigma_mm ** 2)) / cfg.rbf_norm
    return np.where(d <= cfg.comm_radius_mm, psi, 0.0)


def wall_flag(light: np.ndarray, prev_wall: np.ndarray, cfg: WorldConfig) -> np.ndarray:
    """(B, M) float64 wall flag: ``light >= light_threshold``; a reading of -1 keeps ``prev_wall``."""
    wall = (light >= cfg.light_threshold).astype(np.float64)
    return np.where(light < 0, prev_wall, wall)


def held_light(light: np.ndarray, prev_held: np.ndarray) -> np.ndarray:
    """(B, M) the held reading after this step: ``light`` where >= 0, else ``prev_held`` (-1: none yet)."""
    return np.where(light >= 0, light, prev_held)


def light_feature(light: np.ndarray, prev_held: np.ndarray) -> np.ndarray:
    """(B, M, 2) float64 ``light`` feature: held level / 1024 and its change (module doc)."""
    h = held_light(light, prev_held).astype(np.float64)
    change = np.where((light >= 0) & (prev_held >= 0), h - prev_held, 0.0)
    return np.stack([np.maximum(h, 0.0), change], axis=-1) / 1024.0


def held_object_light(target_light: np.ndarray, prev_held: np.ndarray) -> np.ndarray:
    """(B, M) the emitter reading each robot holds after this period: ``target_light`` (the period's latest emitter
    message's reading, -1 where none was heard or carried one) where >= 0, else ``prev_held`` (-1: none yet)."""
    return np.where(target_light >= 0, target_light, prev_held)


def object_light_feature(held: np.ndarray) -> np.ndarray:
    """(B, M, 1) float64 ``object_light`` feature from the held emitter readings (-1: none)."""
    return np.where(held >= 0, held / 1024.0, -1.0)[..., None]


def random_feature(rand_word: np.ndarray) -> np.ndarray:
    """(B, M, 1) float64 ``random`` feature: the words' signed top bytes / 128."""
    return (top_byte(rand_word) / 128.0)[..., None]


def reference(name: str, summ: PeriodSummary, light: np.ndarray, prev_wall: np.ndarray, cfg: WorldConfig,
              prev_light: np.ndarray | None = None, rand_word: np.ndarray | None = None,
              prev_object_light: np.ndarray | None = None) -> np.ndarray:
    """Feature ``name`` of every robot in float64, shape (B, M, width): the definition the firmware block
    and the fast path follow. ``prev_light`` (B, M): the held reading before this step (-1: none).
    ``rand_word`` (B, M) uint32: the robots' xorshift32 words after this step's draw (``random``).
    ``prev_object_light`` (B, M): the emitter reading held before this step (-1: none; ``object_light``)."""
    B, M = light.shape
    tf = feature(name).table
    if tf is not None:
        table = NeighbourTable.of(summ.table_env * M + summ.table_rx, summ.table_dist_mm, B * M)
        return tf.float_values(table, cfg).reshape(B, M, -1)
    if name == "wall":
        return wall_flag(light, prev_wall, cfg)[..., None]
    if name == "light":
        return light_feature(light, np.full((B, M), -1) if prev_light is None else prev_light)
    if name == "target":
        return np.where(summ.target_heard, np.minimum(summ.target_dist_mm / cfg.comm_radius_mm, 1.0), -1.0)[..., None]
    if name == "object_light":
        prev = np.full((B, M), -1) if prev_object_light is None else prev_object_light
        return object_light_feature(held_object_light(summ.target_light, prev))
    if name == "nbr_sensing":
        sensing_nbr = np.zeros(B * M)
        np.maximum.at(sensing_nbr, summ.table_env * M + summ.table_rx, summ.table_flag.astype(np.float64))
        return sensing_nbr.reshape(B, M, 1)
    if name == "random":
        assert rand_word is not None, "the random feature needs the robots' xorshift32 words"
        return random_feature(rand_word)
    if name == "rbf":
        hist = np.zeros((B * M, cfg.n_rbf))
        np.add.at(hist, summ.table_env * M + summ.table_rx, rbf(cfg, summ.table_dist_mm))
        return hist.reshape(B, M, cfg.n_rbf)
    raise KeyError(name)


def input_names(cfg: WorldConfig) -> list[str]:
    """A name per observation input, in order (``rbf_0`` .. for the histogram)."""
    out: list[str] = []
    for n in cfg.features:
        f = feature(n)
        name = f.input_name or f.name
        if f.per_rbf:
            out += [f"{name}_{k}" for k in range(cfg.n_rbf)]
        else:
            out += [f"{name}_{p}" for p in f.parts] or [name]
    return out


