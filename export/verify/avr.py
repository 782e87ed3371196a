"""Real AVR builds and simavr runs: exact flash / SRAM budgets, cycle counts, bit-exact checks.

Everything here shells out to Debian's AVR toolchain (``gcc-avr``, ``binutils-avr``, ``avr-libc``)
and, for runs, to a small simavr runner (``export/verify/simavr_run.c`` linked with ``libsimavr-dev``)
that this module compiles once into the private build cache (:mod:`export.verify.buildcache`).

* :func:`build` compiles C sources with kilolib's flags (:data:`KILOLIB_CFLAGS`) into an ELF and
  reports its exact sizes (:class:`Sizes`).
* :func:`exact_budget` builds the rendered firmware against our kilolib stand-in
  (``firmware_templates/avr/``) and returns the figures :class:`export.codegen.budget.Budget` merges in
  (``Budget.with_exact``): the stand-in's own size is replaced by kilolib's (see below).
* :func:`run_elf` runs an ELF in simavr (ATmega328P, 8 MHz) with a byte stream in and out, cycle
  marks and the painted-stack high-water mark.
* :func:`verify_simavr` is rung 3 of the verification ladder (``python -m export --verify avr``):
  the AVR build of the generated program, driven by the replay harness of
  ``firmware_templates/host/`` with simavr I/O (``firmware_templates/avr/kf_avr_io.c``), must equal
  :class:`export.verify.emulator.FirmwareEmulator` byte for byte; it also reports cycles per control
  step, cycles per MAC of the dense layers and the peak stack of ``loop()``.
* :func:`robot_images` builds ``.elf`` / ``.hex`` (for KiloGUI) against a real kilolib checkout.
* :func:`kernel_program` / :func:`run_kernel` run ``kf_dense`` layers in simavr (tests, benchmark).

The kilolib correction. kilolib has no licence, so we never build against it by default: the
stand-in implements its documented API (our own code) and the figures of a program built with it
are corrected by ``kilolib size - stand-in size``, both measured as a program with empty
``setup``/``loop``. kilolib's figures, :data:`~export.codegen.budget.KILOLIB_FLASH_B` / :data:`~export.codegen.budget.KILOLIB_SRAM_STATIC_B`, are the
platform notes' (``shared/reference/kilobot-platform.md``: kilolib alone with empty setup/loop,
7,028 B flash and 110 B static SRAM, measured with Debian's avr-gcc 5.4 / avr-libc 2.0 and the
flags below). With a real kilolib checkout (``kilolib_dir``) no correction is applied.
"""
from __future__ import annotations

import hashlib
import re
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from kiloforge.actors.base import QuantizedActor

from ..codegen.budget import CONTROL_STACK_B, KILOLIB_FLASH_B
from ..codegen.kernel import KernelLayer
from ..codegen.render import POLICY_FILE
from ..codegen.templates import TEMPLATE_DIR
from ..contract import firmware as fw
from ..errors import ExportError
from . import buildcache, tools
from .emulator import FirmwareEmulator, FirmwareInputs, FirmwareOutputs
from .hostbuild import HOST_DIR, StreamSpec, compare, decode_output, encode_stream, random_inputs, runtime_flags

#: kilolib's build regime (platform notes): it changes the ABI (char signedness, enum and struct sizes)
KILOLIB_CFLAGS = ("-mmcu=atmega328p", "-O3", "-funsigned-char", "-funsigned-bitfields", "-fpack-struct",
                  "-fshort-enums", "-DF_CPU=8000000")
OBJCOPY_HEX = ("-O", "ihex", "-R", ".eeprom", "-R", ".fuse", "-R", ".lock", "-R", ".signature")
MCU = "atmega328p"
F_CPU = 8_000_000
RAMEND = 0x08FF

STANDIN_DIR = TEMPLATE_DIR / "avr"
RUNNER_SRC = Path(__file__).resolve().parent / "simavr_run.c"

MARK_BEGIN, MARK_END = 1, 2  #: kernel program: marks around each kf_dense2 call
MARK_CAL_A, MARK_CAL_B = 3, 4  #: back-to-back marks: the cost of marking itself


class AvrError(ExportError):
    """A build or a simulator run failed (one line; it carries the tool's output)."""


# --------------------------------------------------------------------------------------------
# Tools
# --------------------------------------------------------------------------------------------
def missing_tools(simulate: bool = False) -> str | None:
    """None when the AVR toolchain (and, with ``simulate``, a host C compiler and simavr's headers) is usable,
    else why not (:func:`export.verify.tools.avr_problem`)."""
    return tools.avr_problem(simulate)


def _run(cmd: Sequence[str], what: str, **kw) -> subprocess.CompletedProcess:
    p = tools.run(cmd, what, capture_output=True, text=True, **kw)
    if p.returncode != 0:
        raise AvrError(f"{what} failed ({' '.join(map(str, cmd[:3]))} ...): {(p.stderr or p.stdout).strip()[:4000]}")
    return p


RUNNER_NAME = "kf_simavr"
RUNNER_CFLAGS = ("-O2", "-std=c99")


def runner_key(cc: Sequence[str]) -> str:
    """The cache key of the simavr runner built with compiler ``cc``: a hash of its source, the compiler and flags."""
    return hashlib.sha256(RUNNER_SRC.read_bytes() + "\0".join([*cc, *RUNNER_CFLAGS]).encode()).hexdigest()[:12]


def runner() -> Path:
    """The simavr runner, compiled from ``export/verify/simavr_run.c`` into the private build cache on
    first use and verified before every use (:mod:`export.verify.buildcache`)."""
    why = missing_tools(simulate=True)
    if why:
        raise AvrError(why)
    cc = tools.host_cc()
    return buildcache.cached_program(RUNNER_NAME, runner_key(cc), lambda out: _run(
        [*cc, *RUNNER_CFLAGS, "-I", tools.SIMAVR_INCLUDE, "-o", out, RUNNER_SRC, "-lsimavr"],
        "building the simavr runner"))


# --------------------------------------------------------------------------------------------
# Builds and sizes
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Sizes:
    """Section sizes of a linked ELF (bytes)."""

    text: int
    data: int
    bss: int

    @property
    def flash(self) -> int:
        """What is uploaded: text + data (the initial values of .data live in flash)."""
        return self.text + self.data

    @property
    def sram_static(self) -> int:
        return self.data + self.bss


def sizes(elf: Path) -> Sizes:
    """Parse ``avr-size -A`` (sysv format) for .text, .data, .bss."""
    out = _run(["avr-size", "-A", elf], "avr-size").stdout
    sec = {m.group(1): int(m.group(2)) for m in re.finditer(r"^(\.\w+)\s+(\d+)\s+\d+", out, re.M)}
    return Sizes(text=sec.get(".text", 0), data=sec.get(".data", 0), bss=sec.get(".bss", 0))


def symbol(elf: Path, name: str) -> int:
    """Address of a symbol (data addresses without avr-gcc's 0x800000 offset)."""
    out = _run(["avr-nm", elf], "avr-nm").stdout
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[2] == name:
            return int(parts[0], 16) & 0xFFFF
    raise AvrError(f"symbol {name} not found in {elf}")


@dataclass(frozen=True)
class Build:
    """One linked program."""

    elf: Path
    sizes: Sizes
    hex: Path | None = None


def build(sources: dict[str, str], out_dir: Path, *, name: str = "prog", include_dirs: Sequence[Path] = (),
          defines: Sequence[str] = (), extra_objects: Sequence[Path] = (), make_hex: bool = False,
          cflags: Sequence[str] = KILOLIB_CFLAGS) -> Build:
    """Write ``sources`` (file name -> text; the ``.c`` ones are compiled) into ``out_dir`` and link
    them with kilolib's flags into ``out_dir/<name>.elf`` (and ``.hex`` with ``make_hex``).

    ``extra_objects``: further ``.c`` files or objects / archives (e.g. ``kilolib.a``), linked after.
    """
    why = missing_tools()
    if why:
        raise AvrError(why)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for fname, text in sources.items():
        (out_dir / fname).write_text(text)
    c_files = [out_dir / f for f in sources if f.endswith(".c")]
    elf = out_dir / f"{name}.elf"
    cmd = ["avr-gcc", *cflags, "-Wall", "-Wextra", *[f"-I{d}" for d in (out_dir, *include_dirs)],
           *[f"-D{d}" for d in defines], "-o", elf, *c_files, *extra_objects]
    _run(cmd, "avr-gcc")
    hexfile = None
    if make_hex:
        hexfile = out_dir / f"{name}.hex"
        _run(["avr-objcopy", *OBJCOPY_HEX, elf, hexfile], "avr-objcopy")
    return Build(elf=elf, sizes=sizes(elf), hex=hexfile)


# --------------------------------------------------------------------------------------------
# simavr runs
# --------------------------------------------------------------------------------------------
@dataclass
class SimResult:
    """What a simavr run produced."""

    output: bytes  #: bytes the program wrote to GPIOR1
    marks: list[tuple[int, int]]  #: (id, cycle) of every GPIOR0 mark, in order
    cycles: int  #: cycles simulated
    stack_low: int  #: lowest SRAM address the program wrote above .bss (RAMEND + 1: none)
    stack_paint_from: int  #: where the painting started (the ELF's _end)
    underrun: int  #: input bytes read past the end of the input (a harness bug if > 0)
    scans: list[tuple[int, int]] = field(default_factory=list)  #: (lowest written, SP at paint) per 0xFD

    @property
    def stack_peak(self) -> int:
        """Deepest stack use in bytes (RAMEND + 1 - lowest written address)."""
        return RAMEND + 1 - self.stack_low

    def spans(self, begin: int = MARK_BEGIN, end: int = MARK_END) -> np.ndarray:
        """Cycles between each ``begin`` mark and the following ``end`` mark (int64)."""
        out, start = [], None
        for mid, cyc in self.marks:
            if mid == begin:
                start = cyc
            elif mid == end and start is not None:
                out.append(cyc - start)
                start = None
        return np.asarray(out, np.int64)


def run_elf(elf: Path, input_bytes: bytes = b"", *, max_cycles: int = 2_000_000_000,
            timeout_s: float = 600.0) -> SimResult:
    """Run ``elf`` in simavr (ATmega328P, 8 MHz) until it writes 0xFF to GPIOR0."""
    exe = runner()
    paint_from = symbol(elf, "_end")
    with tempfile.TemporaryDirectory(prefix="kf_sim_") as td:
        fin, fout = Path(td) / "in.bin", Path(td) / "out.bin"
        fin.write_bytes(bytes(input_bytes))
        p = tools.run([str(exe), "-m", MCU, "-f", str(F_CPU), "-i", str(fin), "-o", str(fout),
                       "-p", str(paint_from), "-c", str(max_cycles), str(elf)],
                      "the simavr run", capture_output=True, text=True, timeout=timeout_s)
        output = fout.read_bytes() if fout.exists() else b""
    marks, scans, end = [], [], None
    for line in p.stdout.splitlines():
        if line.startswith("M "):
            _, mid, cyc = line.split()
            marks.append((int(mid), int(cyc)))
        elif line.startswith("S "):
            _, low, top = line.split()
            scans.append((int(low), int(top)))
        elif line.startswith("END "):
            end = dict(kv.split("=") for kv in line.split()[1:])
    if p.returncode != 0 or end is None:
        raise AvrError(f"simavr run of {elf.name} did not finish (exit {p.returncode}, "
                       f"{(end or {}).get('cycles', '?')} cycles): {p.stderr.strip()[-2000:]}")
    return SimResult(output=output, marks=marks, cycles=int(end["cycles"]), stack_low=int(end["stack_low"]),
                     stack_paint_from=paint_from, underrun=int(end["underrun"]), scans=scans)


def mark_overhead(res: SimResult) -> int:
    """Cycles a begin/end mark pair adds to a span (measured by the program's calibration pair)."""
    cal = res.spans(MARK_CAL_A, MARK_CAL_B)
    return int(cal[0]) if cal.size else 0


# --------------------------------------------------------------------------------------------
# Kernel programs (tests and benchmark)
# --------------------------------------------------------------------------------------------
def kernel_sources() -> dict[str, str]:
    """kf_dense.h / kf_dense.c / kf_sim_io.h texts, to be written beside a test program (kf_dense.c
    under another name: :func:`build` compiles every ``.c`` it is given, the program includes it)."""
    return {"kf_dense.h": (TEMPLATE_DIR / "kf_dense.h").read_text(),
            "kf_dense_impl.h": (TEMPLATE_DIR / "kf_dense.c").read_text(),
            "kf_sim_io.h": (STANDIN_DIR / "kf_sim_io.h").read_text()}


HOST_IO_SHIM = """#ifdef __AVR__
#include "kf_sim_io.h"
#else /* the same program on a PC: stdin / stdout */
#include <stdio.h>
#include <stdlib.h>
static uint8_t kf_sim_in(void) { int c = getchar(); return (uint8_t)(c < 0 ? 0 : c); }
static uint16_t kf_sim_in16(void) { uint16_t lo = kf_sim_in(); return (uint16_t)(lo | ((uint16_t)kf_sim_in() << 8)); }
static void kf_sim_out16(uint16_t v) { putchar(v & 0xFF); putchar(v >> 8); }
static void kf_sim_mark(uint8_t id) { (void)id; }
static void kf_sim_exit(void) { fflush(stdout); exit(0); }
#endif"""


def kernel_program(layers: Sequence[KernelLayer]) -> str:
    """C source of a simavr program that runs ``kf_dense2`` on requests from the input stream.

    Input records: ``op`` (1 byte; 0xFF ends), then for ``op = l`` (a layer index) the split
    ``n1`` (uint16 LE) and ``n_in`` int8 inputs; for ``op = 0x80 | l`` no more bytes: layer l runs
    on the previous call's outputs (a chained network). Output: the ``n_out`` int16 results (LE).
    Marks 1 / 2 surround every call; marks 3 / 4 (once, first) measure the marking itself.
    """
    max_in = max(l.n_in for l in layers)
    max_out = max(l.n_out for l in layers)
    fast = "#define KF_DENSE_ALL_FAST 1" if all(l.fast for l in layers) else "/* some layers use the int32 path */"
    parts = ["#include <stdint.h>", HOST_IO_SHIM, fast, '#include "kf_dense.h"', '#include "kf_dense_impl.h"', ""]
    for i, l in enumerate(layers):
        parts.append(l.c_source(f"KF_L{i}"))
    names = ", ".join(f"&KF_L{i}" for i in range(len(layers)))
    parts.append(f"""
static const kf_dense_t *const kf_layers[{len(layers)}] = {{ {names} }};
static int8_t kf_x[{max(max_in, max_out)}];
static int16_t kf_y[{max_out}];

int main(void)
{{
    uint16_t i, n1;
    kf_sim_mark({MARK_CAL_A});
    kf_sim_mark({MARK_CAL_B});
    for (;;) {{
        const uint8_t op = kf_sim_in();
        const kf_dense_t *L;
        if (op == 0xFFu || (op & 0x7Fu) >= {len(layers)}u) {{
            break;
        }}
        L = kf_layers[op & 0x7Fu];
        if (op & 0x80u) {{
            for (i = 0u; i < L->n_in; ++i) {{
                kf_x[i] = (int8_t)kf_y[i];
            }}
            n1 = L->n_in;
        }} else {{
            n1 = kf_sim_in16();
            for (i = 0u; i < L->n_in; ++i) {{
                kf_x[i] = (int8_t)kf_sim_in();
            }}
        }}
        kf_sim_mark({MARK_BEGIN});
        kf_dense2(L, kf_x, n1, kf_x + n1, kf_y);
        kf_sim_mark({MARK_END});
        for (i = 0u; i < L->n_out; ++i) {{
            kf_sim_out16((uint16_t)kf_y[i]);
        }}
    }}
    kf_sim_exit();
    return 0;
}}
""")
    return "\n".join(parts)


@dataclass
class KernelRun:
    """Outputs and costs of :func:`run_kernel`."""

    outputs: list[np.ndarray]  #: per request, int64 (n_out,)
    cycles: np.ndarray  #: per request, cycles of the kf_dense2 call (mark overhead removed)
    sizes: Sizes
    stack_peak: int
    result: SimResult = field(repr=False)


def _kernel_stream(requests) -> bytes:
    stream = bytearray()
    for li, n1, x in requests:
        if x is None:
            stream.append(0x80 | li)
        else:
            stream.append(li)
            stream += int(n1).to_bytes(2, "little")
            stream += np.asarray(x, np.int64).astype(np.int8).tobytes()
    stream.append(0xFF)
    return bytes(stream)


def _split_outputs(layers, requests, output: bytes) -> list[np.ndarray]:
    raw = np.frombuffer(output, dtype="<i2").astype(np.int64)
    outs, pos = [], 0
    for li, _, _ in requests:
        n = layers[li].n_out
        outs.append(raw[pos:pos + n])
        pos += n
    if pos != raw.size:
        raise AvrError(f"kernel program returned {raw.size} values, expected {pos}")
    return outs


def run_kernel_host(layers, requests, *, cc: Sequence[str] | None = None) -> list[np.ndarray]:
    """The same kernel program built for the host (``-std=c99 -Wall -Wextra -Werror``): the portable C."""
    with tempfile.TemporaryDirectory(prefix="kf_kernel_host_") as td:
        d = Path(td)
        for fname, text in {**kernel_sources(), "kernel_test.c": kernel_program(layers)}.items():
            (d / fname).write_text(text)
        exe = d / "kernel_test"
        _run([*(cc or tools.host_cc()), "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-I", d, "-o", exe, d / "kernel_test.c"],
             "host build of the kernel program")
        p = tools.run([str(exe)], "the host kernel program", input=_kernel_stream(requests), capture_output=True,
                      timeout=120)
    if p.returncode != 0:
        raise AvrError(f"host kernel program failed: {p.stderr.decode(errors='replace')[:500]}")
    return _split_outputs(layers, requests, p.stdout)


def run_kernel(layers: Sequence[KernelLayer], requests: Sequence[tuple[int, int | None, np.ndarray | None]],
               *, portable: bool = False, work_dir: Path | None = None) -> KernelRun:
    """Run requests ``(layer, n1, x)`` (``x`` None: chained on the previous outputs) in simavr.

    ``portable`` builds the plain C kernel instead of the assembly one (the baseline).
    """
    stream = _kernel_stream(requests)
    with tempfile.TemporaryDirectory(prefix="kf_kernel_") as td:
        d = Path(work_dir) if work_dir else Path(td)
        b = build({**kernel_sources(), "kernel_test.c": kernel_program(layers)}, d, name="kernel_test",
                  defines=("KF_DENSE_PORTABLE",) if portable else ())
        res = run_elf(b.elf, bytes(stream))
    if res.underrun:
        raise AvrError(f"kernel program read {res.underrun} bytes past its input")
    outs = _split_outputs(layers, requests, res.output)
    return KernelRun(outputs=outs, cycles=res.spans() - mark_overhead(res), sizes=b.sizes,
                     stack_peak=res.stack_peak, result=res)


# --------------------------------------------------------------------------------------------
# Generated firmware: exact budgets, robot builds, simavr verification (rung 3)
# --------------------------------------------------------------------------------------------
EMPTY_PROGRAM = """#include <kilolib.h>
static void setup(void) {}
static void loop(void) {}
int main(void) { kilo_init(); kilo_start(setup, loop); return 0; }
"""
#: marks the firmware build for simavr emits (firmware_templates/avr/kf_avr_io.c, kf_dense.c)
MARK_STEP_BEGIN, MARK_STEP_END, MARK_FAIL = 10, 11, 12
LAYER_MARK_BASE = 20  #: kf_dense.c marks 1 and 2 around each layer: LAYER_MARK_BASE + 1, + 2 in simavr
MARK_LAYER_BEGIN, MARK_LAYER_END = LAYER_MARK_BASE + 1, LAYER_MARK_BASE + 2
LAYER_MARK_DEFINE = f"KF_DENSE_MARK(id)=(*(volatile unsigned char *)0x3E = (unsigned char)({LAYER_MARK_BASE}u + (id)))"
#: the marks of kf_avr_io.c, defined from here
MARK_DEFINES = (f"KF_MARK_STEP_BEGIN={MARK_STEP_BEGIN}u", f"KF_MARK_STEP_END={MARK_STEP_END}u", f"KF_MARK_FAIL={MARK_FAIL}u")
IO_CALL_RETURN_B = 2  #: return address of the harness's kf_io_read call (the paint is inside it)


_STANDIN_SIZES: list[Sizes] = []  #: the empty program's sizes, measured once per process


def _standin_sizes(work: Path) -> Sizes:
    """Sizes of the empty-setup/loop program built with our stand-in."""
    if not _STANDIN_SIZES:
        b = build({"empty.c": EMPTY_PROGRAM}, work / "empty", name="empty", include_dirs=(STANDIN_DIR,),
                  extra_objects=(STANDIN_DIR / "kilolib_avr.c",))
        _STANDIN_SIZES.append(b.sizes)
    return _STANDIN_SIZES[0]


@dataclass(frozen=True)
class ProgramBudget:
    """Exact figures of one generated program (bytes)."""

    name: str
    flash: int  #: text + data of the whole program with kilolib (corrected as in the module doc)
    sram_static: int  #: user .data + .bss (kilolib's own excluded)
    sizes: Sizes  #: raw sizes of the stand-in build
    standin: Sizes  #: raw sizes of the empty program with the stand-in


def program_budget(name: str, c_source: str, work: Path) -> ProgramBudget:
    """Build one generated program against the stand-in and apply the kilolib correction."""
    b = build({name: c_source}, work / Path(name).stem, name=Path(name).stem, include_dirs=(STANDIN_DIR,),
              extra_objects=(STANDIN_DIR / "kilolib_avr.c",))
    e = _standin_sizes(work)
    return ProgramBudget(name=name, flash=b.sizes.flash - e.flash + KILOLIB_FLASH_B,
                         sram_static=b.sizes.sram_static - e.sram_static, sizes=b.sizes, standin=e)


def exact_budget(rendered_files: dict[str, str], qpolicy: QuantizedActor | None = None, *,
                 stack_steps: int = 40, seed: int = 0) -> dict:
    """Exact flash / SRAM of the rendered programs from real avr-gcc builds (kilolib's flags).

    Returns the dict :meth:`export.codegen.budget.Budget.with_exact` takes: ``flash`` and ``sram_user`` of
    ``kilobot_policy.c`` (the program that must fit), ``sram_static`` and ``stack`` (its parts),
    ``stack_source`` and ``<other program>_flash`` (the emitter's program). ``sram_user`` is user
    .data + .bss + the peak stack of ``loop()`` at control steps, measured in simavr when
    ``qpolicy`` is given and simavr is installed (``stack_steps`` control steps of a random event
    stream, which is also checked against the emulator); otherwise the analytic stack estimate of
    :mod:`export.codegen.budget` is added and ``stack_source`` says ``"estimate"``. Raises
    :class:`AvrError` when avr-gcc is missing or fails, or the AVR build disagrees with the emulator.
    """
    with tempfile.TemporaryDirectory(prefix="kf_budget_") as td:
        progs = {name: program_budget(name, text, Path(td)) for name, text in sorted(rendered_files.items())
                 if name.endswith(".c")}
    main = progs[POLICY_FILE]
    result: dict = {"flash": main.flash}
    stack, how = CONTROL_STACK_B, "estimate"
    if qpolicy is not None and missing_tools(simulate=True) is None:
        n_robots = 4  # a random stream: some robots may be emitters, whose loop() runs no policy
        check = verify_simavr(qpolicy, rendered_files, n_robots=n_robots, n_steps=max(2, stack_steps // n_robots),
                              seed=seed)
        if not check.ok:
            raise AvrError(f"the AVR build does not match the emulator: {check.detail}")
        if check.cycles_step.size:
            stack, how = check.stack_peak, "simavr"
    result.update(sram_user=main.sram_static + stack, sram_static=main.sram_static, stack=stack, stack_source=how)
    result.update({f"{Path(n).stem}_flash": p.flash for n, p in progs.items() if n != POLICY_FILE})
    return result


KILOLIB_URL = "https://github.com/acornejo/kilolib"  #: where kilolib comes from (it has no licence: never shipped)


def find_kilolib(kilolib_dir: Path) -> tuple[Path, Path]:
    """(include dir holding kilolib.h, kilolib.a) of a kilolib checkout built with its Makefile; an
    :class:`AvrError` saying what to do for anything else (checked before an export starts its work)."""
    d = Path(kilolib_dir)
    why = missing_tools()
    if why:
        raise AvrError(f"--kilolib needs the AVR toolchain to build the .hex images: {why}")
    if not d.is_dir():
        raise AvrError(f"--kilolib {d}: no such directory (get kilolib: git clone {KILOLIB_URL}, then run `make` in it)")
    heads = [p.parent for p in (d / "kilolib.h", d / "include" / "kilolib.h") if p.exists()]
    libs = [p for p in (d / "build" / "kilolib.a", d / "kilolib.a", d / "lib" / "kilolib.a") if p.exists()]
    if not heads and not (d / "Makefile").exists():
        raise AvrError(f"--kilolib {d}: not a kilolib checkout (no kilolib.h or Makefile; get it: git clone "
                       f"{KILOLIB_URL}, then run `make` in it)")
    if not heads or not libs:
        raise AvrError(f"--kilolib {d}: not a built kilolib checkout (need kilolib.h and build/kilolib.a; run `make` there)")
    return heads[0], libs[0]


def robot_images(rendered_files: dict[str, str], kilolib_dir: Path) -> tuple[dict[str, bytes], dict[str, Sizes]]:
    """Every rendered program built against a real kilolib checkout: the files as bytes
    (``{"kilobot_policy.hex": ..., "kilobot_policy.elf": ..., ...}``; the CLI writes them atomically beside the
    C files; upload the ``.hex`` with KiloGUI) and each program's ELF sizes (``{"kilobot_policy.c": Sizes}``:
    the real flash figure)."""
    with tempfile.TemporaryDirectory(prefix="kf_robot_") as td:
        builds = build_for_robot(rendered_files, kilolib_dir, Path(td))
        out = {}
        for b in builds.values():
            out[b.elf.name] = b.elf.read_bytes()
            out[b.hex.name] = b.hex.read_bytes()
    return out, {name: b.sizes for name, b in builds.items()}


def build_for_robot(rendered_files: dict[str, str], kilolib_dir: Path, out_dir: Path) -> dict[str, Build]:
    """Build every rendered program against a real kilolib: ``<name>.elf`` and ``<name>.hex`` (KiloGUI)."""
    inc, lib = find_kilolib(kilolib_dir)
    builds = {}
    for name, text in sorted(rendered_files.items()):
        if name.endswith(".c"):
            stem = Path(name).stem
            builds[name] = build({name: text}, Path(out_dir), name=stem, include_dirs=(inc,),
                                 extra_objects=(lib,), make_hex=True)
    return builds


@dataclass(frozen=True)
class SimavrCheck:
    """Result of :func:`verify_simavr`."""

    ok: bool
    control_steps: int  #: searcher control steps compared
    ticks: int  #: robot-ticks compared
    detail: str  #: '' or where the first difference is
    stack_peak: int  #: peak stack of loop() at control steps (bytes, including its return address)
    cycles_step: np.ndarray  #: cycles of loop() at every control step (harness glue included, ~60)
    cycles_net: np.ndarray  #: cycles of the dense layers per control step (sum of kf_dense calls)
    macs: int  #: multiply-accumulates of the network
    sizes: Sizes

    @property
    def cycles_step_max(self) -> int:
        return int(self.cycles_step.max()) if self.cycles_step.size else 0

    @property
    def cycles_per_mac(self) -> float:
        return float(np.median(self.cycles_net)) / self.macs if self.cycles_net.size else float("nan")

    def __str__(self) -> str:
        verdict = "bit-exact" if self.ok else "MISMATCH"
        cyc = (f"; loop() at a control step {int(np.median(self.cycles_step)):,} cycles median, "
               f"{self.cycles_step_max:,} max ({self.cycles_step_max / F_CPU * 1e3:.1f} ms); dense layers "
               f"{self.cycles_per_mac:.2f} cycles/MAC; peak stack {self.stack_peak} B") if self.cycles_step.size else ""
        return (f"simavr (ATmega328P, 8 MHz) vs emulator: {verdict} over {self.control_steps:,} control steps "
                f"({self.ticks:,} robot-ticks){cyc}{': ' + self.detail if self.detail else ''}")


def build_simavr_firmware(c_source: str, out_dir: Path, *, portable: bool = False) -> Build:
    """The generated program + the host stand-in + the replay harness, for the AVR under simavr."""
    defines = ["KF_HARNESS_CUSTOM_IO", LAYER_MARK_DEFINE, *MARK_DEFINES, *(f.removeprefix("-D") for f in runtime_flags())] \
        + (["KF_DENSE_PORTABLE"] if portable else [])
    return build({POLICY_FILE: c_source}, out_dir, name="kilobot_policy_sim", include_dirs=(HOST_DIR, STANDIN_DIR),
                 defines=defines, extra_objects=(HOST_DIR / "kilolib_host.c", HOST_DIR / "harness.c",
                                                 STANDIN_DIR / "kf_avr_io.c"))


def run_firmware(elf: Path, inputs: FirmwareInputs, period_ticks: int, obs_dim: int) -> tuple[FirmwareOutputs, SimResult]:
    """Replay ``inputs`` through a simavr firmware build."""
    res = run_elf(elf, encode_stream(inputs, period_ticks, obs_dim))
    outs = decode_output(res.output, inputs.n_robots, inputs.n_ticks, period_ticks, obs_dim)
    return outs, res


def verify_simavr(qpolicy: QuantizedActor, files: dict[str, str], *, emitter_uids: tuple[int, ...] | None = None,
                  msg_type: int | None = None, seed: int = 0, n_robots: int = 64, n_steps: int = 40,
                  portable: bool = False, inputs: FirmwareInputs | None = None) -> SimavrCheck:
    """Rung 3: the AVR build of ``files["kilobot_policy.c"]`` in simavr vs the emulator, byte for byte.

    A random event stream (``export.verify.hostbuild.random_inputs``: bursts, duplicate senders, full
    tables, distances 0..255, foreign / malformed messages, light -1) of ``n_robots`` robots and
    ``n_steps`` control periods (or ``inputs``) is replayed through the firmware on the simulated
    ATmega328P and through :class:`export.verify.emulator.FirmwareEmulator`; every output byte must agree.
    Also measures cycles of ``loop()`` at each control step, cycles of the dense layers and the
    peak stack of ``loop()``.
    """
    qp = qpolicy
    msg_type = fw.DEFAULT_MSG_TYPE if msg_type is None else msg_type
    roles = qp.world.has_roles
    if not roles:  # no emitter role: no robot is one (the stream's role bits are neighbours')
        emitters: tuple[int, ...] = ()
    else:
        emitters = (qp.world.emitter_uid,) if emitter_uids is None else tuple(emitter_uids)
    P, obs_dim = qp.world.period_ticks, qp.world.obs_dim
    if inputs is None:
        rng = np.random.default_rng(np.random.SeedSequence(seed))
        inputs = random_inputs(rng, P, emitters, StreamSpec(n_robots=n_robots, n_steps=n_steps), msg_type,
                               qp.world.comm_radius_mm, qp.world.light_threshold)
    with tempfile.TemporaryDirectory(prefix="kf_simavr_") as td:
        b = build_simavr_firmware(files[POLICY_FILE], Path(td), portable=portable)
        outs, res = run_firmware(b.elf, inputs, P, obs_dim)
    emu = FirmwareEmulator(qp, inputs.uids, inputs.calib, emitter_uids=emitters if roles else None,
                           msg_type=msg_type).run(inputs)
    detail = compare(emu, outs)
    steps = int((~np.isin(inputs.uids, emitters)).sum()) * inputs.n_steps(P)
    step_cycles, net_cycles, stack = _step_profile(res)
    macs = int(sum(l.w.size for l in qp.layers))
    return SimavrCheck(ok=not detail, control_steps=steps, ticks=inputs.n_robots * inputs.n_ticks, detail=detail,
                       stack_peak=stack, cycles_step=step_cycles, cycles_net=net_cycles, macs=macs, sizes=b.sizes)


def _step_profile(res: SimResult) -> tuple[np.ndarray, np.ndarray, int]:
    """Per searcher control step: cycles of loop() and inside kf_dense calls; the deepest stack of loop()."""
    steps, nets = [], []
    start = layer_start = None
    net = 0
    for mid, cyc in res.marks:
        if mid == MARK_STEP_BEGIN:
            start, net = cyc, 0
        elif mid == MARK_LAYER_BEGIN and start is not None:
            layer_start = cyc
        elif mid == MARK_LAYER_END and layer_start is not None:
            net += cyc - layer_start
            layer_start = None
        elif mid == MARK_STEP_END and start is not None:
            if net:  # a searcher's control step (an emitter's loop() returns at once)
                steps.append(cyc - start)
                nets.append(net)
            start = None
    deepest = max((top + IO_CALL_RETURN_B + 1 - low for low, top in res.scans), default=0)
    return np.asarray(steps, np.int64), np.asarray(nets, np.int64), int(deepest)
