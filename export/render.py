"""Render a quantised policy into Kilobot C: ``kilobot_policy.c`` and the beacon-only ``kilobot_target.c``.

:func:`render_firmware` is a pure function (no I/O besides reading the templates): it fills the
Jinja templates of ``firmware_templates/`` (``StrictUndefined``; thin templates that only loop and
place names) with numbers and text formatted by :mod:`export.cformat`, and inlines the hand-written
C (``kf_runtime.h``, ``kf_dense.h``, ``kf_dense.c``) so that each program is one self-contained C
file that needs only ``kilolib.h`` (and avr-libc on the robot).

What the program does is the DESIGN.md control-step contract; :mod:`export.emulator` is its
bit-exact NumPy model, and :mod:`export.fwspec` holds the constants both share (message layout,
LED colours, rx-queue capacity). Tables are stored trimmed where that is exact: the target table up
to the first distance from which it is constant (the C clamps the index), each RBF row only over
its non-zero window.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable

import jinja2
import numpy as np

from sim.config import ACTION_DIM, OBS_NBR_SENSING, OBS_RBF, OBS_TARGET, OBS_WALL
from sim.motion import MODE_LEFT, MODE_RIGHT, MODE_STOP, MODE_STRAIGHT, SCHEDULE_SHIFT, schedule_constants

from . import fwspec, kernel, numfmt
from .cformat import (c_array, c_comment, c_hex_digest, c_ident, c_int, clamp_index_table, nonzero_windows,
                      sizes_comment)
from .errors import ExportError

if TYPE_CHECKING:  # pragma: no cover
    from .quantize import QuantizedPolicy

TEMPLATE_DIR = Path(__file__).resolve().parent.parent / "firmware_templates"
POLICY_FILE = "kilobot_policy.c"
TARGET_FILE = "kilobot_target.c"
#: hand-written C inlined into the programs, in this order (their local #includes are pasted in place)
RUNTIME_SOURCES = ("kf_runtime.h",)
DENSE_SOURCES = ("kf_dense.h", "kf_dense.c")
MAX_TARGET_UIDS = 32

_LOCAL_INCLUDE = re.compile(r'^\s*#\s*include\s+"([A-Za-z0-9_./]+)"\s*$')


class _RecordingLoader(jinja2.FileSystemLoader):
    """A FileSystemLoader that remembers which templates were loaded (tests check coverage)."""

    loaded: set[str] = set()

    def get_source(self, environment: jinja2.Environment, template: str) -> tuple[str, str, Any]:
        _RecordingLoader.loaded.add(template)
        return super().get_source(environment, template)


def _environment() -> jinja2.Environment:
    return jinja2.Environment(loader=_RecordingLoader(str(TEMPLATE_DIR)), undefined=jinja2.StrictUndefined,
                              autoescape=False, keep_trailing_newline=True, trim_blocks=True,
                              lstrip_blocks=True)


def templates_loaded() -> frozenset[str]:
    """Names of every template loaded by a render in this process (for the coverage test)."""
    return frozenset(_RecordingLoader.loaded)


def inline_sources(names: Iterable[str], template_dir: Path = TEMPLATE_DIR) -> str:
    """Hand-written C files concatenated, each local ``#include "..."`` replaced by the included file.

    A tiny preprocessor for our own files only: a file of ``template_dir`` is pasted where it is
    first included (or named in ``names``) and its later includes are dropped, so the result needs
    no file of ours beside it. System includes (``<...>``) stay.
    """
    done: set[Path] = set()
    root = template_dir.resolve()

    def paste(path: Path) -> str:
        path = path.resolve()
        if path in done:
            return ""
        done.add(path)
        out = [f"/* ---- firmware_templates/{path.relative_to(root).as_posix()} ---- */"]
        for line in path.read_text(encoding="utf-8").splitlines():
            m = _LOCAL_INCLUDE.match(line)
            if m:
                inc = (path.parent / m.group(1)).resolve()
                if inc.is_file() and root in inc.parents:
                    out.append(paste(inc).rstrip("\n"))
                    continue
            out.append(line)
        return "\n".join(out).strip("\n") + "\n"

    return "\n".join(paste(template_dir / name) for name in names)


def _define(name: str, value: str, comment: str = "") -> dict[str, str]:
    return {"name": c_ident(name), "value": value, "comment": c_comment(comment) if comment else ""}


def _u(v: int, ctype: str = "uint8_t") -> str:
    return c_int(int(v), ctype)


def _check_uids(target_uids: Iterable[int]) -> tuple[int, ...]:
    try:
        uids = tuple(int(u) for u in target_uids)
    except (TypeError, ValueError):
        raise ExportError(f"target uids must be integers, got {target_uids!r}") from None
    if not 1 <= len(uids) <= MAX_TARGET_UIDS:
        raise ExportError(f"give 1..{MAX_TARGET_UIDS} target uids, got {len(uids)}")
    bad = [u for u in uids if not 0 <= u <= 0xFFFF]
    if bad:
        raise ExportError(f"target uids must be kilo_uid values 0..65535, got {bad}")
    return tuple(dict.fromkeys(uids))


def _banner(file_name: str, qp: "QuantizedPolicy", generator_version: str, role_lines: list[str],
            uids: tuple[int, ...], msg_type: int) -> list[str]:
    w = qp.world
    acts = ", ".join(l.activation for l in qp.layers)
    actor = (qp.banner_actor() if getattr(qp, "kind", "mlp") == "gru"  # recurrent: export/gru_quantize.py
             else f"t_prev {qp.t_prev}, {sizes_comment(qp.layer_sizes)} ({acts}), e_in {qp.e_in}")
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
        f"actor           {actor}",
        f"target uids     {', '.join(str(u) for u in uids)} (these robots act as the beacon)",
        f"message         type {msg_type:#04x}, version {fwspec.MSG_VERSION}",
        "",
        "Robot: avr-gcc -mmcu=atmega328p -O3 -funsigned-char -funsigned-bitfields -fpack-struct",
        "       -fshort-enums -DF_CPU=8000000 -I<kilolib> -o prog.elf this.c <kilolib>/kilolib.a",
        "Kilombo: add -DKILOMBO. Host replay: export/hostbuild.py with firmware_templates/host/.",
    ]
    for ln in lines:
        assert "*/" not in ln and "/*" not in ln, f"banner line is not comment-safe: {ln!r}"
    return lines


def _common_defines(msg_type: int) -> list[dict[str, str]]:
    return [
        _define("KF_MSG_TYPE", _u(msg_type), "message type of ours (a user type: < 0x80, not 1)"),
        _define("KF_MSG_VERSION", _u(fwspec.MSG_VERSION), "data[0] of our messages; others are dropped"),
        _define("KF_READY", _u(fwspec.STATE_READY, "uint16_t"),
                "kf_state_t.ready once setup() has finished (the callbacks idle until then)"),
        _define("KF_ROLE_BIT", _u(fwspec.ROLE_BIT), "data[3] bit: the sender is the target beacon"),
        _define("KF_SENSING_BIT", _u(fwspec.SENSING_BIT), "data[3] bit: the sender heard the target last period"),
        _define("KF_LED_OFF", "(RGB({}, {}, {}))".format(*fwspec.LED_OFF), "searcher, nothing to show"),
        _define("KF_LED_BEACON", "(RGB({}, {}, {}))".format(*fwspec.LED_BEACON), "blue: target beacon"),
        _define("KF_LED_SENSING", "(RGB({}, {}, {}))".format(*fwspec.LED_SENSING),
                "green: heard the target during the last period"),
        _define("KF_LED_NBR_SENSING", "(RGB({}, {}, {}))".format(*fwspec.LED_NBR_SENSING),
                "yellow: a neighbour heard last period senses the target"),
    ]


def _io_context(qp: Any, uids: tuple[int, ...], memory: list[dict[str, str]],
                scratch: list[dict[str, str]]) -> tuple[list[dict[str, str]], list[str]]:
    """(defines, tables) every policy program has: timing, queues, observation layout, sensing and
    motor constants, the sensing tables; ``memory`` defines go after the uid count, ``scratch``
    defines after the motor modes (the actor's own sizes: MLP history, GRU hidden state)."""
    w = qp.world
    P = w.period_ticks
    D = w.tuple_dim
    k_turn, k_straight = schedule_constants(P)
    one = int(qp.one_q)
    assert 1 <= one <= numfmt.INT8_MAX, f"1.0 at e_in {qp.e_in} does not fit int8"

    defines = [
        _define("KF_PERIOD_TICKS", _u(P), f"control period in kilo_ticks ({P / 30.52:.3f} s at 30.52 Hz)"),
        _define("KF_RXQ_CAPACITY", _u(fwspec.RXQ_CAPACITY),
                "messages buffered between the rx ISR and loop(); one arriving when full is dropped"),
        _define("KF_NBR_CAPACITY", _u(w.neighbour_table_size),
                "neighbour-table entries per period; further new senders are dropped"),
        _define("KF_N_TARGET_UIDS", _u(len(uids)), "robots with these kilo_uids act as the beacon"),
        *memory,
        _define("KF_ACTION_DIM", _u(ACTION_DIM), "tuple = [ACT[q_left], ACT[q_right], observation]"),
        _define("KF_OBS_DIM", _u(w.obs_dim), "observation entries"),
        _define("KF_TUPLE_DIM", _u(D), "history tuple entries"),
        _define("KF_OBS_WALL", _u(OBS_WALL), "observation layout (sim/config.py)"),
        _define("KF_OBS_TARGET", _u(OBS_TARGET)),
        _define("KF_OBS_NBR_SENSING", _u(OBS_NBR_SENSING)),
        _define("KF_OBS_RBF", _u(OBS_RBF)),
        _define("KF_N_RBF", _u(w.n_rbf), "RBF histogram bins"),
        _define("KF_LIGHT_THRESHOLD", f"((int16_t){c_int(w.light_threshold, 'int16_t')})",
                "ambient-light ADC counts: wall flag = reading >= this"),
        _define("KF_ONE", f"((int8_t){c_int(one, 'int8_t')})", f"1.0 at the input exponent e_in = {qp.e_in}"),
        _define("KF_MINUS_ONE", f"((int8_t){c_int(-one, 'int8_t')})", "-1.0: target not heard"),
        _define("KF_SCHED_SHIFT", _u(SCHEDULE_SHIFT), "motor schedule (sim/motion.py): ticks = (x * K + half) >> shift"),
        _define("KF_SCHED_HALF", c_int(1 << (SCHEDULE_SHIFT - 1), "uint32_t")),
        _define("KF_K_TURN", c_int(k_turn, "uint32_t"), "turn ticks per unit of |q_left - q_right|"),
        _define("KF_K_STRAIGHT", c_int(k_straight, "uint32_t"), "straight ticks per unit of q_left + q_right"),
        _define("KF_MODE_STOP", _u(MODE_STOP), "motor modes"),
        _define("KF_MODE_STRAIGHT", _u(MODE_STRAIGHT)),
        _define("KF_MODE_LEFT", _u(MODE_LEFT), "pivot counter-clockwise: set_motors(kilo_turn_left, 0)"),
        _define("KF_MODE_RIGHT", _u(MODE_RIGHT), "pivot clockwise: set_motors(0, kilo_turn_right)"),
        *scratch,
    ]

    # --- sensing tables (trimmed where exact) ---
    tgt, tgt_last = clamp_index_table(np.asarray(qp.target_table))
    defines.append(_define("KF_TGT_LAST", _u(tgt_last),
                           "target table index clamp: distances above it read this entry"))
    lo, length, off, packed = nonzero_windows(np.asarray(qp.rbf_table))
    tables = [
        c_array("KF_TARGET_UIDS", "uint16_t", uids, comment="kilo_uids of the target beacon role"),
        c_array("KF_ACT", "int8_t", qp.action_table,
                comment=f"ACT[q]: motor command q / 255 at exponent e_in = {qp.e_in} (history entries)"),
        c_array("KF_TGT", "int8_t", tgt,
                comment=f"TGT[d]: min(d / comm radius, 1) at e_in for d = 0..{tgt_last} mm"),
        c_array("KF_RBF_LO", "uint8_t", lo, comment="RBF bin k is non-zero for d = LO[k] .. LO[k] + LEN[k] - 1 mm"),
        c_array("KF_RBF_LEN", "uint16_t", length),
        c_array("KF_RBF_OFF", "uint16_t", off, comment="offset of bin k's window in KF_RBF"),
        c_array("KF_RBF", "uint8_t", packed,
                comment="psi_k(d) / rbf_norm at e_in over each bin's window (0 beyond the comm radius)"),
    ]
    return defines, tables


def _policy_context(qp: "QuantizedPolicy", uids: tuple[int, ...]) -> dict[str, Any]:
    w = qp.world
    T, D = qp.t_prev, w.tuple_dim
    if T > 255:
        raise ExportError(f"t_prev {T} is too long for the firmware's uint8 ring index (at most 255)")
    if D * T > 0xFFFF:
        raise ExportError(f"history of {D * T} entries is too large")
    hidden = [int(l.w.shape[0]) for l in qp.layers[:-1]]
    defines, tables = _io_context(qp, uids, [_define("KF_T_PREV", _u(T), "history length (tuples)")], [
        _define("KF_Y_LEN", _u(max(int(l.w.shape[0]) for l in qp.layers), "uint16_t"),
                "scratch: the widest layer output (int16)"),
        _define("KF_X_LEN", _u(max(hidden, default=1), "uint16_t"), "scratch: the widest hidden activation (int8)"),
    ])

    # --- layers ---
    act_tables: dict[bytes, str] = {}
    layers = []
    for k, layer in enumerate(qp.layers):
        n_out, n_in = (int(s) for s in layer.w.shape)
        last = k == len(qp.layers) - 1
        if last:
            assert (layer.lo, layer.hi, layer.activation) == (0, 255, "identity"), "output layer must give uint8"
        act, table_name = "output", ""
        if not last:
            if layer.table is not None:
                key = np.asarray(layer.table, np.int8).tobytes()
                if key not in act_tables:
                    act_tables[key] = c_ident(f"KF_ACTFN{len(act_tables)}")
                    tables.append(c_array(act_tables[key], "int8_t", layer.table,
                                          comment=f"{layer.activation} table: z at exponent {layer.e_out} "
                                                  f"(index z + 128) -> exponent {layer.e_act}"))
                act, table_name = "table", act_tables[key]
            elif layer.activation == "relu":
                act = "relu"
            else:
                assert layer.activation == "identity", f"layer {k}: activation {layer.activation} needs a table"
                act = "identity"
        kl = kernel.kernel_layer(layer)  # the arrays in the kernel's own order (export/kernel.py)
        assert kl.b.shape == (n_out,) and kl.w.size == n_out * n_in, f"layer {k}: kernel arrays have wrong shapes"
        tables.append(c_array(f"KF_W{k}", "int8_t", kl.w,
                              comment=f"layer {k}: {n_out} x {n_in} weights in kernel order (export/kernel.py), "
                                      f"input exponent {layer.e_in}"))
        tables.append(c_array(f"KF_B{k}", "int32_t", kl.b, per_line=8,
                              comment=f"layer {k}: folded int32 biases (export/kernel.py)"))
        tables.append(c_array(f"KF_S{k}", "uint8_t", kl.shift,
                              comment=f"layer {k}: requantisation shifts to exponent {layer.e_out}"))
        layers.append({
            "name": f"KF_L{k}", "init": kl.c_initializer(f"KF_W{k}", f"KF_B{k}", f"KF_S{k}"),
            "n_out": _u(n_out, "uint16_t"), "act": act, "table": table_name,
            "fast": "yes" if kl.fast else "no",
        })
    return {"defines": defines, "tables": tables, "layers": layers}


def render_firmware(qpolicy: "QuantizedPolicy", target_uids: Iterable[int] | None = None,
                    msg_type: int = fwspec.DEFAULT_MSG_TYPE, generator_version: str | None = None
                    ) -> dict[str, str]:
    """The generated programs: ``{"kilobot_policy.c": ..., "kilobot_target.c": ...}``.

    ``target_uids`` (default ``(world.target_uid,)``): robots with these kilo_uids run the beacon
    role of the policy program. ``msg_type``: the message type of ours (< 0x80, not 1).
    ``generator_version`` goes into the banner (default: the installed kiloforge version).
    Raises :class:`ExportError` with a one-line message for bad arguments.
    """
    qp = qpolicy
    uids = _check_uids((qp.world.target_uid,) if target_uids is None else target_uids)
    try:
        msg_type = fwspec.check_msg_type(msg_type)
        c_hex_digest(qp.policy_hash)
    except ValueError as e:
        raise ExportError(str(e)) from None
    if generator_version is None:
        from .manifest import generator_version as _gv
        generator_version = _gv()
    env = _environment()
    runtime_c = inline_sources(RUNTIME_SOURCES)
    common = {"defines_common": _common_defines(msg_type), "runtime_c": runtime_c}
    template, context = "kilobot_policy.c.j2", _policy_context
    if getattr(qp, "kind", "mlp") == "gru":  # the recurrent program extends the MLP one (export/gru_render.py)
        from .gru_render import TEMPLATE as template, gru_policy_context as context
    policy_ctx = dict(common, **context(qp, uids),
                      banner=_banner(POLICY_FILE, qp, generator_version,
                                     ["One program for every robot: robots whose kilo_uid is a target uid act",
                                      "as the beacon, all others as searchers running the policy."],
                                     uids, msg_type),
                      dense_c=("#define KF_DENSE_ALL_FAST 1 /* every layer runs the 24-bit AVR kernel: "
                               "the portable kernel is left out of AVR builds */\n"
                               if kernel.all_fast(qp.layers) else "") + inline_sources(DENSE_SOURCES))
    target_ctx = dict(common, banner=_banner(TARGET_FILE, qp, generator_version,
                                             ["Beacon-only program: whatever its kilo_uid, this robot is the target",
                                              "(it never moves, shines blue and sends role = 1)."],
                                             uids, msg_type))
    return {
        POLICY_FILE: env.get_template(template).render(**policy_ctx),
        TARGET_FILE: env.get_template("kilobot_target.c.j2").render(**target_ctx),
    }


def verify_host(qpolicy: "QuantizedPolicy", files: dict[str, str], **kwargs: Any) -> Any:
    """Host check used by ``python -m export --verify host`` (see :func:`export.hostbuild.verify_host`)."""
    from .hostbuild import verify_host as _verify

    return _verify(qpolicy, files, **kwargs)
