"""Build a generated Kilobot program for the host and replay event streams through it.

The program is compiled with ``gcc -std=c99 -Wall -Wextra -Werror -O2`` against kiloforge's own
kilolib stand-in (``firmware_templates/host/kilolib.h``, ``kilolib_host.c``) and the replay harness
(``host/harness.c``, which implements ``kilo_start``). :func:`encode_stream` writes the harness's
binary input, :func:`decode_output` reads its output (formats in ``host/harness.c``), and
:func:`run_host` does both around one process. :func:`verify_host` is the check behind
``python -m export --verify host``: random streams through the build and the emulator, compared
byte for byte.

On the host each robot's state is malloc'd and filled with garbage before setup() (``fill``, 0xA5
unless told otherwise), and the callbacks are called before setup() as kilolib may; with
``sanitize`` the build runs under AddressSanitizer and UndefinedBehaviorSanitizer.
"""
from __future__ import annotations

import hashlib
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kiloforge.actors.base import QuantizedActor
from sim.tasks import Task

from ..codegen.render import POLICY_FILE, emitter_firmware, runtime_defines
from ..codegen.templates import TEMPLATE_DIR
from ..contract import firmware as fw
from ..contract.firmware import EVENT_DTYPE, TICK_RECORD_BYTES
from ..errors import ExportError
from . import buildcache, tools
from .emulator import FirmwareEmulator, FirmwareInputs, FirmwareOutputs, n_control_steps

HOST_DIR = TEMPLATE_DIR / "host"
HOST_CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-O2")
#: AddressSanitizer and UndefinedBehaviorSanitizer; any finding ends the run with an error
SANITIZE_CFLAGS = ("-fsanitize=address,undefined", "-fno-sanitize-recover=all", "-fno-omit-frame-pointer", "-g")
#: the harness fills each robot's state with this before setup() unless told otherwise (host/harness.c)
DEFAULT_FILL = "0xA5"
STREAM_MAGIC = b"KFS1"
MSG_RECORD_BYTES = 10  #: one message in the input stream (host/harness.c)


class HostBuildError(ExportError):
    """The host compiler is missing or rejected the generated program."""


def runtime_flags() -> list[str]:
    """``-D`` flags of :func:`export.codegen.render.runtime_defines` for C that includes kf_runtime.h."""
    return [f"-D{name}={value}" for name, value in runtime_defines().items()]


def compiler() -> list[str] | None:
    """The host C compiler's argv (``$CC`` split like a shell would, or gcc), or None when there is no working
    one (:func:`export.verify.tools.host_cc` says why)."""
    try:
        return tools.host_cc()
    except tools.ToolError:
        return None


def build_host(c_source: str, workdir: Path | str, name: str = "kilobot_policy", *,
               sanitize: bool = False) -> Path:
    """Compile ``c_source`` with the stand-in and the harness; returns the executable's path.

    ``sanitize`` adds :data:`SANITIZE_CFLAGS` (ASan + UBSan, the first finding aborts the run). The
    build is cached in ``workdir`` (a private directory: created 0700, else refused) by the hash of the
    compiler, the source, the flags and the stand-in files, and verified before it is returned like the
    simavr runner (:func:`export.verify.buildcache.cached_program`).
    """
    cc = tools.host_cc()
    workdir = buildcache.private_dir(workdir)
    sources = [HOST_DIR / "kilolib_host.c", HOST_DIR / "harness.c"]
    flags = (*HOST_CFLAGS, *(SANITIZE_CFLAGS if sanitize else ()), *runtime_flags())
    h = hashlib.sha256(c_source.encode() + "\0".join([*cc, *flags]).encode())
    for p in sorted(HOST_DIR.parent.glob("kf_*.h")) + sorted(HOST_DIR.glob("*")):
        h.update(p.read_bytes())

    def compile_to(out: Path) -> None:
        src = workdir / f"{name}.c"
        src.write_text(c_source, encoding="utf-8")
        cmd = [*cc, *flags, "-I", str(HOST_DIR), "-o", str(out), str(src), *map(str, sources)]
        res = tools.run(cmd, "the host build", capture_output=True, text=True)
        if res.returncode != 0:
            raise HostBuildError(f"host build of {src.name} failed:\n{res.stderr.strip()}")

    return buildcache.cached_program(name, h.hexdigest()[:16], compile_to, directory=workdir)


# --- binary streams ---------------------------------------------------------------------------
def encode_stream(inputs: FirmwareInputs, period_ticks: int, obs_dim: int) -> bytes:
    """The harness's input for ``inputs`` (format in ``firmware_templates/host/harness.c``)."""
    R, T, P = inputs.n_robots, int(inputs.n_ticks), int(period_ticks)
    n_steps = inputs.n_steps(P)
    assert inputs.light.shape == (R, n_steps), f"light must be (R, {n_steps})"
    assert 1 <= P <= 255 and 0 <= obs_dim <= 253 and R <= 0xFFFF and T < 2 ** 32, "stream header out of range"
    ev = inputs.events[np.lexsort((inputs.events["tick"], inputs.events["robot"]))]  # stable: order kept
    cell = ev["robot"].astype(np.int64) * T + ev["tick"]  # (N,) index of (robot, tick)
    count = np.bincount(cell, minlength=R * T).reshape(R, T)  # messages per robot and tick
    if count.max(initial=0) > 255:
        raise ValueError("more than 255 messages for one robot in one tick")
    ctrl = (np.arange(T) % P == 0) & (np.arange(T) > 0)  # (T,) control ticks P, 2P, ...
    size = 1 + 2 * ctrl[None, :] + MSG_RECORD_BYTES * count  # (R, T) bytes of each tick's chunk
    robot_bytes = 8 + size.sum(axis=1)  # (R,)
    robot_start = 16 + np.r_[0, np.cumsum(robot_bytes)[:-1]]  # (R,)
    tick_start = robot_start[:, None] + 8 + np.cumsum(size, axis=1) - size  # (R, T)
    buf = np.zeros(16 + int(robot_bytes.sum()), np.uint8)
    buf[:16] = np.frombuffer(STREAM_MAGIC + int(R).to_bytes(2, "little") + bytes([P, obs_dim])
                             + int(T).to_bytes(4, "little") + bytes(4), np.uint8)
    hdr = np.zeros((R, 8), np.uint8)
    hdr[:, 0] = inputs.uids & 0xFF
    hdr[:, 1] = inputs.uids >> 8
    hdr[:, 2:6] = inputs.calib
    buf[robot_start[:, None] + np.arange(8)] = hdr
    light = inputs.light.astype("<i2").view(np.uint8).reshape(R, n_steps, 2)
    ls = tick_start[:, ctrl]  # (R, n_steps)
    buf[ls[..., None] + np.arange(2)] = light
    buf[tick_start + 2 * ctrl[None, :]] = count
    if ev.size:
        first = np.r_[0, np.flatnonzero(np.diff(cell)) + 1]
        slot = np.arange(cell.size) - np.repeat(first, np.diff(np.r_[first, cell.size]))  # rank in its tick
        r, t = ev["robot"].astype(np.int64), ev["tick"].astype(np.int64)
        pos = tick_start[r, t] + 2 * ctrl[t] + 1 + MSG_RECORD_BYTES * slot  # (N,)
        rec = np.zeros((ev.size, MSG_RECORD_BYTES), np.uint8)
        rec[:, 0] = ev["uid"] & 0xFF
        rec[:, 1] = ev["uid"] >> 8
        for j, field in enumerate(("role", "flag", "type", "version", "dist")):
            rec[:, 2 + j] = ev[field]
        rec[:, 8] = ev["light"] & 0xFF
        rec[:, 9] = ev["light"] >> 8
        buf[pos[:, None] + np.arange(MSG_RECORD_BYTES)] = rec
    return buf.tobytes()


def decode_output(data: bytes, n_robots: int, n_ticks: int, period_ticks: int, obs_dim: int) -> FirmwareOutputs:
    """Split the harness's output into per-tick and per-step records."""
    P, T, S = int(period_ticks), int(n_ticks), 2 + int(obs_dim)
    n_steps = n_control_steps(T, P)
    per_robot = T * TICK_RECORD_BYTES + n_steps * S
    if len(data) != n_robots * per_robot:
        raise HostBuildError(f"harness wrote {len(data)} bytes, expected {n_robots * per_robot}")
    raw = np.frombuffer(data, np.uint8).reshape(n_robots, per_robot)
    t = np.arange(T)
    tick_off = t * TICK_RECORD_BYTES + S * np.maximum((t + P - 1) // P - 1, 0)  # after earlier step records
    k = np.arange(1, n_steps + 1)  # control step k at tick k * P
    step_off = k * P * TICK_RECORD_BYTES + TICK_RECORD_BYTES + (k - 1) * S
    ticks = raw[:, tick_off[:, None] + np.arange(TICK_RECORD_BYTES)]  # (R, T, 16)
    steps = raw[:, step_off[:, None] + np.arange(S)]  # (R, n_steps, S)
    return FirmwareOutputs(ticks=np.ascontiguousarray(ticks), steps=np.ascontiguousarray(steps))


def run_host(exe: Path | str, inputs: FirmwareInputs, period_ticks: int, obs_dim: int,
             timeout: float = 300.0, fill: str = DEFAULT_FILL) -> FirmwareOutputs:
    """Replay ``inputs`` through a host build; every output byte.

    ``fill``: the garbage each robot's state holds before setup(): a byte (``"0x5A"``) or
    ``"random:SEED"`` (different bytes per robot).
    """
    stream = encode_stream(inputs, period_ticks, obs_dim)
    env = dict(os.environ, KF_HOST_FILL=fill)
    res = tools.run([str(exe)], "the host harness", input=stream, capture_output=True, timeout=timeout, env=env)
    if res.returncode != 0:
        raise HostBuildError(f"{Path(exe).name} exited with {res.returncode}: "
                             f"{res.stderr.decode(errors='replace').strip()}")
    return decode_output(res.stdout, inputs.n_robots, inputs.n_ticks, period_ticks, obs_dim)


# --- random streams -------------------------------------------------------------------------
@dataclass(frozen=True)
class StreamSpec:
    """Shape of a random event stream (:func:`random_inputs`)."""

    n_robots: int = 64
    n_steps: int = 50
    rate: float = 0.35  #: mean messages per robot and tick outside bursts
    burst_p: float = 0.02  #: probability that a (robot, tick) is a burst
    burst_max: int = 14  #: messages in a burst: up to this (more than the rx queue holds)
    n_senders: int = 24  #: distinct searcher uids each robot may hear (more than a neighbour table)
    target_p: float = 0.08  #: fraction of messages with the target role
    foreign_p: float = 0.05  #: fraction with a foreign type
    bad_version_p: float = 0.03  #: fraction with another version byte
    emitter_p: float = 0.1  #: fraction of robots whose uid is an emitter uid
    light_busy_p: float = 0.1  #: fraction of -1 light readings


def random_inputs(rng: np.random.Generator, period_ticks: int, emitter_uids: tuple[int, ...],
                  spec: StreamSpec = StreamSpec(), msg_type: int = fw.DEFAULT_MSG_TYPE,
                  comm_radius_mm: float = 85.0, light_threshold: int = 500) -> FirmwareInputs:
    """A random stream that exercises every rule of the firmware (see :class:`StreamSpec`).

    Includes bursts beyond the rx queue, duplicate senders, more senders than a neighbour table,
    distances 0..255 (dense near the comm radius), foreign types, other version bytes, emitter uids
    among the robots and as senders, light readings -1 / around the threshold, and zero calibration
    values.
    """
    R, P = spec.n_robots, int(period_ticks)
    T = (spec.n_steps + 1) * P - int(rng.integers(0, P))  # the listening period, steps, often a partial last one
    n_steps = n_control_steps(T, P)
    uids = rng.choice(np.arange(1, 0x10000), size=R, replace=False).astype(np.uint16)
    emitter = (rng.random(R) < spec.emitter_p) & bool(emitter_uids)  # no emitter uids: none is an emitter
    if emitter_uids:
        uids[emitter] = rng.choice(np.asarray(emitter_uids, np.uint16), size=int(emitter.sum()))
    calib = rng.integers(0, 256, size=(R, 4)).astype(np.uint8)
    calib[rng.random((R, 4)) < 0.1] = 0
    light = rng.integers(0, 1024, size=(R, n_steps))
    near = rng.random((R, n_steps)) < 0.3
    light[near] = light_threshold + rng.integers(-2, 2, size=int(near.sum()))
    light[rng.random((R, n_steps)) < spec.light_busy_p] = -1
    count = rng.poisson(spec.rate, size=(R, T))
    burst = rng.random((R, T)) < spec.burst_p
    count[burst] = rng.integers(spec.burst_max // 2, spec.burst_max + 1, size=int(burst.sum()))
    count = np.minimum(count, 255)
    robot = np.repeat(np.repeat(np.arange(R), T), count.ravel())
    tick = np.repeat(np.tile(np.arange(T), R), count.ravel())
    N = robot.size
    ev = np.zeros(N, EVENT_DTYPE)
    ev["robot"], ev["tick"] = robot, tick
    pool = rng.integers(1, 0x10000, size=(R, spec.n_senders))  # each robot's neighbours
    ev["uid"] = pool[robot, rng.integers(0, spec.n_senders, size=N)]
    is_t = rng.random(N) < spec.target_p
    ev["role"] = is_t
    ev["uid"][is_t] = rng.choice(np.asarray(tuple(emitter_uids) + (1234,), np.uint16), size=int(is_t.sum()))
    ev["flag"] = rng.random(N) < 0.3
    d = np.where(rng.random(N) < 0.6, rng.normal(comm_radius_mm * 0.7, comm_radius_mm * 0.4, N),
                 rng.integers(0, 256, N))
    ev["dist"] = np.clip(np.round(d), 0, 255).astype(np.uint8)
    ev["type"] = msg_type
    foreign = rng.random(N) < spec.foreign_p
    ev["type"][foreign] = rng.choice(np.array([0, 1, 0x29, 0x2B, 0x7F, 0x80, 0xFF], np.uint8), size=int(foreign.sum()))
    ev["version"] = fw.MSG_VERSION
    bad = rng.random(N) < spec.bad_version_p
    ev["version"][bad] = rng.choice(np.array([0, 2, 0xFF], np.uint8), size=int(bad.sum()))
    # drawn last (the draws before stay those of older streams): data[4..5], an emitter's reading, none (LIGHT_NONE)
    # or out of the ADC's range (ignored), in every message
    ev["light"] = np.where(rng.random(N) < 0.8, rng.integers(0, 1024, N),
                           rng.choice(np.array([fw.LIGHT_NONE, 1024, 0x8000, 0xFFFE], np.uint16), size=N))
    return FirmwareInputs(uids=uids, calib=calib, light=light.astype(np.int16), events=ev, n_ticks=T)


@dataclass(frozen=True)
class HostCheck:
    """Result of :func:`verify_host` (``ok`` and a printable summary)."""

    ok: bool
    control_steps: int
    ticks: int
    detail: str

    def __str__(self) -> str:
        verdict = "bit-exact" if self.ok else "MISMATCH"
        return (f"host build vs emulator: {verdict} over {self.control_steps:,} control steps "
                f"({self.ticks:,} robot-ticks){': ' + self.detail if self.detail else ''}")


def compare(emu: FirmwareOutputs, host: FirmwareOutputs) -> str:
    """'' when equal, else where the first difference is."""
    for name in ("ticks", "steps"):
        a, b = getattr(emu, name), getattr(host, name)
        if a.shape != b.shape:
            return f"{name}: shapes {a.shape} vs {b.shape}"
        diff = np.argwhere(a != b)
        if diff.size:
            r, i, j = diff[0]
            return (f"{name}[robot {r}, {'tick' if name == 'ticks' else 'step'} {i}, byte {j}]: "
                    f"emulator {a[r, i, j]} host {b[r, i, j]} ({len(diff)} bytes differ)")
    return ""


def rendered_params(c_text: str, uids_table: str | None) -> tuple[tuple[int, ...], int]:
    """(emitter uids, message type) of a rendered kilobot_policy.c, read back from its constants: ``uids_table`` the
    C name of the task's emitter uid table (None: the program of a world without an emitter, no uids)."""
    m_type = re.search(r"^#define KF_MSG_TYPE (\d+)u\b", c_text, re.M)
    m_uids = re.search(re.escape(uids_table) + r"\[\d+\] PROGMEM = \{([^}]*)\}", c_text) if uids_table else None
    if not (m_type and (m_uids or not uids_table)):
        raise HostBuildError(f"not a kiloforge policy program (KF_MSG_TYPE / {uids_table} not found)")
    uids = tuple(int(v.strip().rstrip("u")) for v in m_uids.group(1).split(",") if v.strip()) if m_uids else ()
    return uids, int(m_type.group(1))


def verify_host(qp: QuantizedActor, files: dict[str, str], *, seed: int = 0,
                spec: StreamSpec = StreamSpec(n_robots=64, n_steps=40), task: Task | None = None) -> HostCheck:
    """Build the rendered programs on the host, replay random streams, compare with the emulator.

    The emitter uids and message type are read back from ``kilobot_policy.c``; the emitter's own program (in
    worlds with an emitter; ``task``: whose, default the default task) is replayed with every robot an emitter.
    Without an emitter the stream still carries messages with the role bit, which the program must take as a
    neighbour's.
    """
    w = qp.world
    emitter = emitter_firmware(w, task)
    emitters, msg_type = rendered_params(files[POLICY_FILE], emitter.uids_table if emitter else None)
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    inputs = random_inputs(rng, w.period_ticks, emitters, spec, msg_type, w.comm_radius_mm, w.light_threshold)
    with tempfile.TemporaryDirectory(prefix="kiloforge-host-") as tmp:
        host = run_host(build_host(files[POLICY_FILE], tmp), inputs, w.period_ticks, w.obs_dim)
        host_t = run_host(build_host(files[emitter.program], tmp, name=emitter.stem), inputs,
                          w.period_ticks, w.obs_dim) if emitter else None
    emu = FirmwareEmulator(qp, inputs.uids, inputs.calib, emitter_uids=emitters if emitter else None,
                           msg_type=msg_type).run(inputs)
    detail = compare(emu, host)
    detail_t = ""
    if host_t is not None:
        emu_t = FirmwareEmulator(qp, inputs.uids, inputs.calib, emitter_uids=tuple(int(u) for u in inputs.uids),
                                 msg_type=msg_type).run(inputs)
        detail_t = compare(emu_t, host_t)
    detail = "; ".join(d for d in (detail and f"policy program: {detail}",
                                   detail_t and f"emitter program: {detail_t}") if d)
    steps = int((~np.isin(inputs.uids, emitters)).sum()) * inputs.n_steps(w.period_ticks)
    return HostCheck(ok=not detail, control_steps=steps,
                     ticks=(1 + (emitter is not None)) * inputs.n_robots * inputs.n_ticks, detail=detail)
