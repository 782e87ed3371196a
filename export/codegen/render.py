"""Render a quantised actor into Kilobot C: ``kilobot_policy.c`` and, in worlds with an emitter (a robot of the task's
that only transmits, with a role), the emitter's own program (the task names its file: ``Task.emitter_program``).

:func:`render_firmware` is a pure function (no I/O besides reading the templates). The shared
program (``firmware_templates/kilobot_policy.c.j2``: radio, observation, motor schedule, message,
LED) is the same for every actor kind; the kind's template partial extends it with the actor's
state, scratch and forward step, and the kind's :class:`~kiloforge.actors.base.RenderSpec` gives
its defines, tables and dense layers, which this module formats with :mod:`export.codegen.cformat`
(dense layers through :mod:`export.codegen.kernel`). The hand-written C (``kf_runtime.h``,
``kf_dense.h``, ``kf_dense.c`` and the kind's kernel header) is inlined, so each program is one
self-contained C file that needs only ``kilolib.h`` (and avr-libc on the robot).

What the program does is the control-step contract (docs/design.md); :mod:`export.verify.emulator`
is its bit-exact NumPy model, and :mod:`export.contract.firmware` holds the constants both share.
Tables are stored trimmed where that is exact: the target table up to the first distance from which
it is constant (the C clamps the index), each RBF row only over its non-zero window.

The emitter's role is the task's: its firmware partials (``firmware_templates/tasks/<Task.firmware>/``) give the
role's C names and code in the policy program (``emitter.c.j2``, imported by the shared template) and the emitter's
own program (``program.c.j2``); this module only fills in the uids, LED and message constants under those names.

The observation is the world's (``WorldConfig.obs_features``, chosen by the task): ``kf_observe`` is
rendered from each feature's block (``firmware_templates/features/<name>.c.j2``, :mod:`sim.features`),
and only what the layout and the emitter need is rendered: a world without an emitter gets no emitter
role, no target slot, table or uids, no message flags and no emitter program.
"""
from __future__ import annotations

import re
from pathlib import PurePath
from typing import Any, Iterable

import numpy as np

from kiloforge import numfmt
from kiloforge.actors.base import CDefine, CDense, QuantizedActor, RenderSpec
from kiloforge.actors.registry import kind_of
from kiloforge.errors import QuantizeError
from kiloforge.xorshift import SEED_ADD, SEED_MUL
from sim.config import ACTION_DIM, WorldConfig
from sim.features import emitter_sends_light, feature
from sim.light import ADC_MAX
from sim.motion import MODE_LEFT, MODE_RIGHT, MODE_STOP, MODE_STRAIGHT, SCHEDULE_SHIFT, schedule_constants
from sim.tasks import DEFAULT_TASK, Task, get_task
from sim.tasks.base import TASK_NAME
from sim.tasks.emitter import task_emitter

from ..contract import crc
from ..contract import firmware as fw
from ..errors import ExportError
from . import kernel
from .cformat import c_array, c_comment, c_hex_digest, c_ident, c_int, clamp_index_table, nonzero_windows
from .manifest import generator_version as installed_version
from .templates import TEMPLATE_DIR, environment, inline_sources

POLICY_FILE = "kilobot_policy.c"
TASK_PARTIALS = "tasks"  #: the folder of firmware_templates/ holding each task's firmware partials
#: hand-written C inlined into the programs, in this order (their local #includes are pasted in place)
RUNTIME_SOURCES = ("kf_runtime.h",)
DENSE_SOURCES = ("kf_dense.h", "kf_dense.c")
MAX_EMITTER_UIDS = 32


def _define(name: str, value: str, comment: str = "") -> dict[str, str]:
    return {"name": c_ident(name), "value": value, "comment": c_comment(comment) if comment else ""}


def _u(v: int, ctype: str = "uint8_t") -> str:
    return c_int(int(v), ctype)


def _kind_define(d: CDefine) -> dict[str, str]:
    return _define(d.name, c_int(int(d.value), d.ctype), d.comment)


def _check_uids(emitter_uids: Iterable[int]) -> tuple[int, ...]:
    try:
        uids = tuple(int(u) for u in emitter_uids)
    except (TypeError, ValueError):
        raise ExportError(f"emitter uids must be integers, got {emitter_uids!r}") from None
    if not 1 <= len(uids) <= MAX_EMITTER_UIDS:
        raise ExportError(f"give 1..{MAX_EMITTER_UIDS} emitter uids, got {len(uids)}")
    bad = [u for u in uids if not 0 <= u <= 0xFFFF]
    if bad:
        raise ExportError(f"emitter uids must be kilo_uid values 0..65535, got {bad}")
    return tuple(dict.fromkeys(uids))


class EmitterFirmware:
    """A task's emitter firmware: its partials' folder, the C names of its role (``emitter.c.j2``'s variables) and
    the file its own program is written to. Raises :class:`ExportError` when the task has no emitter, or gives no
    partials or a bad file name."""

    def __init__(self, task: Task) -> None:
        declared = task_emitter(task)
        if declared is None:
            raise ExportError(f"task '{task.name}' has no emitter: it has no emitter firmware")
        folder, program = declared.firmware, declared.program
        where = f"task '{task.name}' has an emitter"
        if not (isinstance(folder, str) and TASK_NAME.fullmatch(folder)
                and (TEMPLATE_DIR / TASK_PARTIALS / folder / "emitter.c.j2").is_file()):
            raise ExportError(f"{where} but no firmware partials: Task.firmware must name a folder of "
                              f"firmware_templates/{TASK_PARTIALS}/ with emitter.c.j2 and program.c.j2, got {folder!r}")
        if not (isinstance(program, str) and re.fullmatch(r"[A-Za-z0-9_]{1,64}\.c", program) and program != POLICY_FILE):
            raise ExportError(f"{where}: Task.emitter_program must be a C file name (letters, digits, _) other than "
                              f"{POLICY_FILE}, got {program!r}")
        self.partial = f"{TASK_PARTIALS}/{folder}/emitter.c.j2"
        self.program_template = f"{TASK_PARTIALS}/{folder}/program.c.j2"
        self.program = program
        self.role_name = declared.role
        module = environment().get_template(self.partial).module
        self.uids_table, self.n_uids, self.led = (str(getattr(module, n)) for n in ("uids_table", "n_uids", "led"))

    @property
    def stem(self) -> str:
        return PurePath(self.program).stem


def emitter_firmware(world: WorldConfig, task: Task | None = None) -> EmitterFirmware | None:
    """The emitter firmware of ``task`` (default: the default task) in ``world``; None in a world without an emitter."""
    return EmitterFirmware(task or get_task(DEFAULT_TASK)) if world.has_roles else None


def _banner(file_name: str, qp: QuantizedActor, generator_version: str, role_lines: list[str],
            uids: tuple[int, ...], msg_type: int, role_name: str) -> list[str]:
    w = qp.world
    lines = [
        f"{file_name}: Kilobot firmware generated by kiloforge {c_comment(generator_version, 40)}.",
        "DO NOT EDIT: regenerate it with `python -m export` from the policy below.",
        "",
        *role_lines,
        "",
        f"policy sha256   {c_hex_digest(qp.policy_hash)}",
        f"number format   {numfmt.FORMAT_NAME} (int8, power-of-two exponents, int32 accumulator, "
        f"rounding {numfmt.ROUNDING})",
        f"world           {c_comment(w.name, 40)}: control period {w.period_ticks} kilo_ticks, comm radius "
        f"{w.comm_radius_mm:g} mm, {w.n_rbf} RBF bins, neighbour table {w.neighbour_table_size}",
        f"actor           {qp.describe()}",
        *([f"emitter uids    {', '.join(str(u) for u in uids)} (these robots act as {c_comment(role_name, 40)})"]
          if uids else [f"observation     {c_comment(w.obs_features, 60)} (no emitter)"]),
        f"message         type {msg_type:#04x}, version {fw.MSG_VERSION}",
        "",
        "Robot: avr-gcc -mmcu=atmega328p -O3 -funsigned-char -funsigned-bitfields -fpack-struct",
        "       -fshort-enums -DF_CPU=8000000 -I<kilolib> -o prog.elf this.c <kilolib>/kilolib.a",
        "Kilombo: add -DKILOMBO. Host replay: export/verify/hostbuild.py with firmware_templates/host/.",
    ]
    for ln in lines:  # every part above is escaped or ours; checked anyway, as text from a file reaches C here
        if "*/" in ln or "/*" in ln:
            raise ExportError(f"banner line is not comment-safe: {ln!r}")
    return lines


def _common_defines(msg_type: int, world: WorldConfig, emitter: EmitterFirmware | None) -> list[dict[str, str]]:
    """The message and LED constants: the role and sensing bits and their LEDs only where the world has an emitter."""
    roles = emitter is not None
    nbr = world.has_feature("nbr_sensing")
    light = emitter_sends_light(world)
    defines = [
        _define("KF_MSG_TYPE", _u(msg_type), "message type of ours (a user type: < 0x80, not 1)"),
        _define("KF_MSG_VERSION", _u(fw.MSG_VERSION), "data[0] of our messages; others are dropped"),
        _define("KF_READY", _u(fw.STATE_READY, "uint16_t"),
                "kf_state_t.ready once setup() has finished (the callbacks idle until then)"),
        _define("KF_MSG_DATA_BYTES", _u(fw.MSG_DATA_BYTES), "message_t payload bytes (the CRC covers them and the type)"),
        _define("KF_MSG_USED_BYTES", _u(fw.MSG_USED_BYTES), "data[0..3] carry version, uid and info; the rest is 0"),
        _define("KF_MSG_INFO_BYTE", _u(fw.MSG_INFO_BYTE), "data[] index of role | sensing << 1"),
        (roles, _define("KF_ROLE_BIT", _u(fw.ROLE_BIT), "data[3] bit: the sender is the emitter")),
        (roles, _define("KF_SENSING_BIT", _u(fw.SENSING_BIT), "data[3] bit: the sender heard the target last period")),
        (light, _define("KF_MSG_LIGHT_BYTE", _u(fw.MSG_LIGHT_BYTE), "data[] index of the emitter's light reading (2 bytes, LE)")),
        (light, _define("KF_LIGHT_NONE", _u(fw.LIGHT_NONE, "uint16_t"), "the emitter's light reading before its first")),
        (light, _define("KF_ADC_MAX", _u(ADC_MAX, "uint16_t"), "the largest ambient-light reading (10-bit ADC)")),
        (True, _define("KF_LED_OFF", "(RGB({}, {}, {}))".format(*fw.LED_OFF), "searcher, nothing to show")),
        *([(True, _define(emitter.led, "(RGB({}, {}, {}))".format(*fw.LED_EMITTER), "blue: the emitter"))]
          if emitter else []),
        (roles, _define("KF_LED_SENSING", "(RGB({}, {}, {}))".format(*fw.LED_SENSING),
                         "green: heard the target during the last period")),
        (roles and nbr, _define("KF_LED_NBR_SENSING", "(RGB({}, {}, {}))".format(*fw.LED_NBR_SENSING),
                                 "yellow: a neighbour heard last period senses the target")),
    ]
    return [d if isinstance(d, dict) else d[1] for d in defines if isinstance(d, dict) or d[0]]


def runtime_defines() -> dict[str, str]:
    """What the hand-written runtime (kf_runtime.h) needs defined before it: the CRC of
    export/contract/crc.py. The programs define them; a build of other C that includes kf_runtime.h
    (the host and simavr harnesses, tests/c/test_runtime.c) passes them as ``-D``."""
    return {"KF_CRC_POLY": c_int(crc.POLY_REFLECTED, "uint16_t"), "KF_CRC_INIT": c_int(crc.INIT, "uint16_t")}


def _runtime_defines() -> list[dict[str, str]]:
    comments = {"KF_CRC_POLY": "CRC-16/MCRF4XX: reflected polynomial", "KF_CRC_INIT": "CRC-16/MCRF4XX: initial value"}
    return [_define(name, value, comments[name]) for name, value in runtime_defines().items()]


def _io_context(qp: QuantizedActor, uids: tuple[int, ...], spec: RenderSpec,
                emitter: EmitterFirmware | None) -> tuple[list[dict[str, str]], list[str]]:
    """(defines, tables) every policy program has: timing, queues, observation layout, sensing and
    motor constants, the sensing tables; the kind's ``memory`` defines go after the uid count, its
    ``scratch`` defines after the motor modes."""
    w = qp.world
    P = w.period_ticks
    D = w.tuple_dim
    k_turn, k_straight = schedule_constants(P)
    one = int(qp.one_q)
    assert 1 <= one <= numfmt.INT8_MAX, f"1.0 at e_in {qp.e_in} does not fit int8"

    defines = [
        _define("KF_PERIOD_TICKS", _u(P), f"control period in kilo_ticks ({P / 30.52:.3f} s at 30.52 Hz)"),
        _define("KF_RXQ_CAPACITY", _u(fw.RXQ_CAPACITY),
                "messages buffered between the rx ISR and loop(); one arriving when full is dropped"),
        _define("KF_NBR_CAPACITY", _u(w.neighbour_table_size),
                "neighbour-table entries per period; further new senders are dropped"),
        *([_define(emitter.n_uids, _u(len(uids)), f"robots with these kilo_uids act as {emitter.role_name}")]
          if emitter else []),
        *map(_kind_define, spec.memory),
        _define("KF_ACTION_DIM", _u(ACTION_DIM), "tuple = [ACT[q_left], ACT[q_right], observation]"),
        _define("KF_OBS_DIM", _u(w.obs_dim), "observation entries"),
        _define("KF_TUPLE_DIM", _u(D), "history tuple entries"),
        *[_define(f"KF_OBS_{name.upper()}", _u(w.obs_index(name)),
                  "observation layout (the world's obs_features)" if k == 0 else "")
          for k, name in enumerate(w.features)],
        *([_define("KF_N_RBF", _u(w.n_rbf), "RBF histogram bins")] if w.has_feature("rbf") else []),
        *([_define("KF_LIGHT_THRESHOLD", f"((int16_t){c_int(w.light_threshold, 'int16_t')})",
                   "ambient-light ADC counts: wall flag = reading >= this")] if w.has_feature("wall") else []),
        *([_define("KF_RAND_SEED_MUL", c_int(SEED_MUL, "uint32_t"),
                   "random feature: xorshift32 seed = (kilo_uid * MUL + ADD) ^ rand_hard() (never 0)"),
           _define("KF_RAND_SEED_ADD", c_int(SEED_ADD, "uint32_t"))] if w.has_feature("random") else []),
        _define("KF_ONE", f"((int8_t){c_int(one, 'int8_t')})", f"1.0 at the input exponent e_in = {qp.e_in}"),
        *([_define("KF_MINUS_ONE", f"((int8_t){c_int(-one, 'int8_t')})", "-1.0: target not heard")]
          if w.has_feature("target") or w.has_feature("object_light") else []),
        _define("KF_SCHED_SHIFT", _u(SCHEDULE_SHIFT), "motor schedule (sim/motion.py): ticks = (x * K + half) >> shift"),
        _define("KF_SCHED_HALF", c_int(1 << (SCHEDULE_SHIFT - 1), "uint32_t")),
        _define("KF_K_TURN", c_int(k_turn, "uint32_t"), "turn ticks per unit of |q_left - q_right|"),
        _define("KF_K_STRAIGHT", c_int(k_straight, "uint32_t"), "straight ticks per unit of q_left + q_right"),
        _define("KF_MODE_STOP", _u(MODE_STOP), "motor modes"),
        _define("KF_MODE_STRAIGHT", _u(MODE_STRAIGHT)),
        _define("KF_MODE_LEFT", _u(MODE_LEFT), "pivot counter-clockwise: set_motors(kilo_turn_left, 0)"),
        _define("KF_MODE_RIGHT", _u(MODE_RIGHT), "pivot clockwise: set_motors(0, kilo_turn_right)"),
        *map(_kind_define, spec.scratch),
    ]

    # --- sensing tables (trimmed where exact), those the layout reads ---
    tables = []
    if emitter:
        tables.append(c_array(emitter.uids_table, "uint16_t", uids, comment=f"kilo_uids of {emitter.role_name}'s role"))
    tables.append(c_array("KF_ACT", "int8_t", qp.action_table,
                          comment=f"ACT[q]: motor command q / 255 at exponent e_in = {qp.e_in} (history entries)"))
    if w.has_feature("target"):
        tgt, tgt_last = clamp_index_table(np.asarray(qp.target_table))
        defines.append(_define("KF_TGT_LAST", _u(tgt_last),
                               "target table index clamp: distances above it read this entry"))
        tables.append(c_array("KF_TGT", "int8_t", tgt,
                              comment=f"TGT[d]: min(d / comm radius, 1) at e_in for d = 0..{tgt_last} mm"))
    if w.has_feature("rbf"):
        lo, length, off, packed = nonzero_windows(np.asarray(qp.rbf_table))
        tables += [
            c_array("KF_RBF_LO", "uint8_t", lo, comment="RBF bin k is non-zero for d = LO[k] .. LO[k] + LEN[k] - 1 mm"),
            c_array("KF_RBF_LEN", "uint16_t", length),
            c_array("KF_RBF_OFF", "uint16_t", off, comment="offset of bin k's window in KF_RBF"),
            c_array("KF_RBF", "uint8_t", packed,
                    comment="psi_k(d) / rbf_norm at e_in over each bin's window (0 beyond the comm radius)"),
        ]
    return defines, tables


def _layout_context(w: WorldConfig, emitter: EmitterFirmware | None) -> dict[str, Any]:
    """What the shared template renders from the world's roles and observation layout (``roles``: one robot of the
    task transmits with a role bit, the others track whether they heard it; ``emitter_partial``: the task's role)."""
    counters = {c for f in w.features for c in feature(f).counters}
    return {"roles": emitter is not None, "emitter_partial": emitter.partial if emitter else "",
            "obs_features": list(w.features),
            "uses_flag": any(feature(f).uses_flag for f in w.features),
            "reads_light": any(feature(f).reads_light for f in w.features),
            "msg_light": emitter_sends_light(w),
            "observe_counters": ", ".join(sorted(counters))}


def _dense_arrays(d: CDense) -> tuple[list[str], dict[str, str]]:
    """The W, B, S arrays of one dense layer in the kernel's order, and its template entry."""
    layer = d.layer
    n_out, n_in = (int(s) for s in layer.w.shape)
    kl = kernel.kernel_layer(layer)
    assert kl.b.shape == (n_out,) and kl.w.size == n_out * n_in, f"{d.descriptor}: kernel arrays have wrong shapes"
    arrays = [
        c_array(d.w, "int8_t", kl.w, comment=f"{d.what}: {n_out} x {n_in} weights in kernel order "
                                             f"(export/codegen/kernel.py), input exponent {layer.e_in}"),
        c_array(d.b, "int32_t", kl.b, per_line=8, comment=f"{d.label}: folded int32 biases (export/codegen/kernel.py)"),
        c_array(d.s, "uint8_t", kl.shift, comment=f"{d.label}: requantisation shifts to exponent {layer.e_out}"),
    ]
    entry = {"name": c_ident(d.descriptor), "init": kl.c_initializer(d.w, d.b, d.s), "n_out": _u(n_out, "uint16_t"),
             **d.extra, "fast": "yes" if kl.fast else "no"}
    return arrays, entry


def _policy_context(qp: QuantizedActor, uids: tuple[int, ...], emitter: EmitterFirmware | None) -> dict[str, Any]:
    kind = kind_of(qp)
    try:
        spec = kind.render_spec(qp)
    except QuantizeError as e:
        raise ExportError(str(e)) from None
    defines, tables = _io_context(qp, uids, spec, emitter)
    layers = []
    for t in spec.tables:
        if isinstance(t, CDense):
            arrays, entry = _dense_arrays(t)
            tables += arrays
            layers.append(entry)
        else:
            tables.append(c_array(t.name, t.ctype, t.values, per_line=t.per_line, comment=t.comment))
    return {"defines": defines, "tables": tables, "layers": layers, "actor_c": inline_sources(kind.c_sources),
            **_layout_context(qp.world, emitter), **spec.variables}


def _dense_c(qp: QuantizedActor) -> str:
    """The dense kernels, inlined when the actor has dense layers (a rule-based actor has none)."""
    if not qp.layers:
        return "/* (no dense layers: the kernel is left out) */\n"
    return ("#define KF_DENSE_ALL_FAST 1 /* every layer runs the 24-bit AVR kernel: "
            "the portable kernel is left out of AVR builds */\n"
            if kernel.all_fast(qp.layers) else "") + inline_sources(DENSE_SOURCES)


def render_firmware(qpolicy: QuantizedActor, emitter_uids: Iterable[int] | None = None,
                    msg_type: int = fw.DEFAULT_MSG_TYPE, generator_version: str | None = None,
                    task: Task | None = None) -> dict[str, str]:
    """The generated programs: ``{"kilobot_policy.c": ..., <the task's emitter program>: ...}`` (the second only when
    the world has an emitter).

    ``emitter_uids`` (default the world's emitter uid): robots with these kilo_uids run the emitter role of the
    policy program (refused for a world without an emitter). ``msg_type``: the message type of ours (< 0x80, not 1).
    ``generator_version`` goes into the banner (default: the installed kiloforge version). ``task``: whose emitter
    firmware to render (default the default task; only read in a world with an emitter).
    Raises :class:`ExportError` with a one-line message for bad arguments.
    """
    qp = qpolicy
    w = qp.world
    if not w.has_roles and emitter_uids is not None:
        raise ExportError(f"the policy's world '{w.name}' has no emitter: emitter uids do not apply")
    emitter = emitter_firmware(w, task)
    uids = _check_uids((w.emitter_uid,) if emitter_uids is None else emitter_uids) if emitter else ()
    try:
        msg_type = fw.check_msg_type(msg_type)
        c_hex_digest(qp.policy_hash)
    except ValueError as e:
        raise ExportError(str(e)) from None
    if generator_version is None:
        generator_version = installed_version()
    env = environment()
    common = {"defines_common": _common_defines(msg_type, w, emitter), "defines_runtime": _runtime_defines(),
              "runtime_c": inline_sources(RUNTIME_SOURCES), "msg_light": emitter_sends_light(w)}
    role = emitter.role_name if emitter else ""
    policy_ctx = dict(common, **_policy_context(qp, uids, emitter),
                      banner=_banner(POLICY_FILE, qp, generator_version,
                                     ["One program for every robot: robots whose kilo_uid is an emitter uid act",
                                      f"as {c_comment(role, 40)}, all others run the policy."] if emitter
                                     else ["One program for every robot: each runs the policy (the world has no emitter)."],
                                     uids, msg_type, role),
                      dense_c=_dense_c(qp))
    policy_c = env.get_template(kind_of(qp).template).render(**policy_ctx)
    if emitter is None:
        return {POLICY_FILE: policy_c}
    target_ctx = dict(common, defines_target=[_define("KF_PERIOD_TICKS", _u(w.period_ticks),
                                                      "the emitter reads the light every this many kilo_ticks")],
                      banner=_banner(emitter.program, qp, generator_version,
                                     [f"Emitter-only program: whatever its kilo_uid, this robot is {c_comment(role, 40)}",
                                      "(it never moves and sends role = 1)."],
                                     uids, msg_type, role))
    return {POLICY_FILE: policy_c, emitter.program: env.get_template(emitter.program_template).render(**target_ctx)}
