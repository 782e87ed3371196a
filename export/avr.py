"""Real AVR builds and simavr runs: exact flash / SRAM budgets, cycle counts, bit-exact checks.

Everything here shells out to Debian's AVR toolchain (``gcc-avr``, ``binutils-avr``, ``avr-libc``)
and, for runs, to a small simavr runner (``export/simavr_run.c`` linked with ``libsimavr-dev``)
that this module compiles once into a cache directory.

* :func:`build` compiles C sources with kilolib's flags (:data:`KILOLIB_CFLAGS`) into an ELF and
  reports its exact sizes (:class:`Sizes`).
* :func:`exact_budget` builds the rendered firmware against our kilolib stand-in
  (``firmware_templates/avr/``) and returns the figures :class:`export.budget.Budget` merges in
  (``Budget.with_exact``): the stand-in's own size is replaced by kilolib's (see below).
* :func:`run_elf` runs an ELF in simavr (ATmega328P, 8 MHz) with a byte stream in and out, cycle
  marks and the painted-stack high-water mark.
* :func:`kernel_program` / :func:`run_kernel` run ``kf_dense`` layers in simavr (tests, benchmark).

The kilolib correction. kilolib has no licence, so we never build against it by default: the
stand-in implements its documented API (our own code) and the figures of a program built with it
are corrected by ``kilolib size - stand-in size``, both measured as a program with empty
``setup``/``loop``. kilolib's figures, :data:`KILOLIB_FLASH_B` / :data:`KILOLIB_SRAM_B`, are the
platform notes' (``shared/reference/kilobot-platform.md``: kilolib alone with empty setup/loop,
7,028 B flash and 110 B static SRAM, measured with Debian's avr-gcc 5.4 / avr-libc 2.0 and the
flags below). With a real kilolib checkout (``kilolib_dir``) no correction is applied.
"""
from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from .budget import FLASH_LIMIT_B, KILOLIB_FLASH_B, KILOLIB_SRAM_STATIC_B, SRAM_LIMIT_B

#: kilolib's build regime (platform notes): it changes the ABI (char signedness, enum and struct sizes)
KILOLIB_CFLAGS = ("-mmcu=atmega328p", "-O3", "-funsigned-char", "-funsigned-bitfields", "-fpack-struct",
                  "-fshort-enums", "-DF_CPU=8000000")
OBJCOPY_HEX = ("-O", "ihex", "-R", ".eeprom", "-R", ".fuse", "-R", ".lock", "-R", ".signature")
MCU = "atmega328p"
F_CPU = 8_000_000
RAMEND = 0x08FF
KILOLIB_FLASH = KILOLIB_FLASH_B  #: 7,028 B: kilolib with empty setup/loop (platform notes)
KILOLIB_SRAM = KILOLIB_SRAM_STATIC_B  #: 110 B .data + .bss of kilolib (platform notes)
TOOLS = ("avr-gcc", "avr-size", "avr-nm", "avr-objcopy")

ROOT = Path(__file__).resolve().parent.parent
TEMPLATES = ROOT / "firmware_templates"
STANDIN_DIR = TEMPLATES / "avr"
RUNNER_SRC = Path(__file__).resolve().parent / "simavr_run.c"
SIMAVR_INCLUDE = Path("/usr/include/simavr")

MARK_BEGIN, MARK_END = 1, 2  #: kernel program: marks around each kf_dense2 call
MARK_CAL_A, MARK_CAL_B = 3, 4  #: back-to-back marks: the cost of marking itself


class AvrError(RuntimeError):
    """A build or a simulator run failed (the message carries the tool's output)."""


# --------------------------------------------------------------------------------------------
# Tools
# --------------------------------------------------------------------------------------------
def missing_tools(simulate: bool = False) -> str | None:
    """None when the AVR toolchain (and, with ``simulate``, simavr's library) is usable, else why not."""
    gone = [t for t in TOOLS if shutil.which(t) is None]
    if gone:
        return f"missing {', '.join(gone)} (Debian: apt-get install gcc-avr binutils-avr avr-libc)"
    if simulate:
        if shutil.which("gcc") is None:
            return "missing gcc (needed to build the simavr runner)"
        if not (SIMAVR_INCLUDE / "sim_avr.h").exists():
            return "missing simavr headers (Debian: apt-get install simavr libsimavr-dev)"
    return None


def cache_dir() -> Path:
    """Where the simavr runner is built (``KILOFORGE_CACHE`` or a per-user temp directory)."""
    d = Path(os.environ.get("KILOFORGE_CACHE") or Path(tempfile.gettempdir()) / f"kiloforge-{os.getuid()}")
    d.mkdir(parents=True, exist_ok=True)
    return d


def _run(cmd: Sequence[str], what: str, **kw) -> subprocess.CompletedProcess:
    p = subprocess.run(list(map(str, cmd)), capture_output=True, text=True, **kw)
    if p.returncode != 0:
        raise AvrError(f"{what} failed ({' '.join(map(str, cmd[:3]))} ...): {(p.stderr or p.stdout).strip()[:4000]}")
    return p


def runner() -> Path:
    """The simavr runner binary, compiled from ``export/simavr_run.c`` on first use (cached by hash)."""
    why = missing_tools(simulate=True)
    if why:
        raise AvrError(why)
    src = RUNNER_SRC.read_bytes()
    exe = cache_dir() / f"kf_simavr-{hashlib.sha256(src).hexdigest()[:12]}"
    if not exe.exists():
        tmp = exe.with_name(exe.name + f".tmp{os.getpid()}")
        _run(["gcc", "-O2", "-std=c99", "-I", SIMAVR_INCLUDE, "-o", tmp, RUNNER_SRC, "-lsimavr"], "building the simavr runner")
        os.replace(tmp, exe)
    return exe


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
    them with kilolib's flags into ``out_dir/<name>.elf`` (and ``.hex`` with ``make_hex``)."""
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
        p = subprocess.run([str(exe), "-m", MCU, "-f", str(F_CPU), "-i", str(fin), "-o", str(fout),
                            "-p", str(paint_from), "-c", str(max_cycles), str(elf)],
                           capture_output=True, text=True, timeout=timeout_s)
        output = fout.read_bytes() if fout.exists() else b""
    marks, end = [], None
    for line in p.stdout.splitlines():
        if line.startswith("M "):
            _, mid, cyc = line.split()
            marks.append((int(mid), int(cyc)))
        elif line.startswith("END "):
            end = dict(kv.split("=") for kv in line.split()[1:])
    if p.returncode != 0 or end is None:
        raise AvrError(f"simavr run of {elf.name} did not finish (exit {p.returncode}, "
                       f"{(end or {}).get('cycles', '?')} cycles): {p.stderr.strip()[-2000:]}")
    return SimResult(output=output, marks=marks, cycles=int(end["cycles"]), stack_low=int(end["stack_low"]),
                     stack_paint_from=paint_from, underrun=int(end["underrun"]))


def mark_overhead(res: SimResult) -> int:
    """Cycles a begin/end mark pair adds to a span (measured by the program's calibration pair)."""
    cal = res.spans(MARK_CAL_A, MARK_CAL_B)
    return int(cal[0]) if cal.size else 0


# --------------------------------------------------------------------------------------------
# Kernel programs (tests and benchmark)
# --------------------------------------------------------------------------------------------
def kernel_sources() -> dict[str, str]:
    """kf_dense.h / kf_dense.c / kf_sim_io.h texts, to be written beside a test program."""
    return {"kf_dense.h": (TEMPLATES / "kf_dense.h").read_text(),
            "kf_dense_impl.h": (TEMPLATES / "kf_dense.c").read_text(),
            "kf_sim_io.h": (STANDIN_DIR / "kf_sim_io.h").read_text()}


def kernel_program(layers: Sequence["KernelLayer"]) -> str:  # noqa: F821 (export.kernel.KernelLayer)
    """C source of a simavr program that runs ``kf_dense2`` on requests from the input stream.

    Input records: ``op`` (1 byte; 0xFF ends), then for ``op = l`` (a layer index) the split
    ``n1`` (uint16 LE) and ``n_in`` int8 inputs; for ``op = 0x80 | l`` no more bytes: layer l runs
    on the previous call's outputs (a chained network). Output: the ``n_out`` int16 results (LE).
    Marks 1 / 2 surround every call; marks 3 / 4 (once, first) measure the marking itself.
    """
    max_in = max(l.n_in for l in layers)
    max_out = max(l.n_out for l in layers)
    parts = ["#include <stdint.h>", '#include "kf_sim_io.h"', '#include "kf_dense.h"', '#include "kf_dense_impl.h"', ""]
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


def run_kernel(layers: Sequence["KernelLayer"], requests: Sequence[tuple[int, int | None, np.ndarray | None]],  # noqa: F821
               *, portable: bool = False, work_dir: Path | None = None) -> KernelRun:
    """Run requests ``(layer, n1, x)`` (``x`` None: chained on the previous outputs) in simavr.

    ``portable`` builds the plain C kernel instead of the assembly one (the baseline).
    """
    stream = bytearray()
    for li, n1, x in requests:
        if x is None:
            stream.append(0x80 | li)
        else:
            stream.append(li)
            stream += int(n1).to_bytes(2, "little")
            stream += np.asarray(x, np.int64).astype(np.int8).tobytes()
    stream.append(0xFF)
    with tempfile.TemporaryDirectory(prefix="kf_kernel_") as td:
        d = Path(work_dir) if work_dir else Path(td)
        b = build({**kernel_sources(), "kernel_test.c": kernel_program(layers)}, d, name="kernel_test",
                  defines=("KF_DENSE_PORTABLE",) if portable else ())
        res = run_elf(b.elf, bytes(stream))
    raw = np.frombuffer(res.output, dtype="<i2").astype(np.int64)
    outs, pos = [], 0
    for li, _, _ in requests:
        n = layers[li].n_out
        outs.append(raw[pos:pos + n])
        pos += n
    if pos != raw.size or res.underrun:
        raise AvrError(f"kernel program returned {raw.size} values, expected {pos} (underrun {res.underrun})")
    return KernelRun(outputs=outs, cycles=res.spans() - mark_overhead(res), sizes=b.sizes,
                     stack_peak=res.stack_peak, result=res)
