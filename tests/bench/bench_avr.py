"""AVR benchmark: exact flash / SRAM / peak stack and cycles of real avr-gcc builds run in simavr.

    python -m tests.bench.bench_avr [--steps N]

For the shipped default policy and two random (initialised, calibrated, quantised) networks,
320-64-32-2 and 32-32-32-2, in the ``kilobot`` world: the generated firmware's exact budget
(kilolib correction applied), its peak stack and cycles of ``loop()`` at a control step in
simavr (bit-exact check against the emulator included), and the dense layers' cycles per
multiply-accumulate with the assembly kernel and with the plain C kernel. Prints a Markdown table.
Needs avr-gcc, avr-libc, simavr and libsimavr-dev.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from export.codegen import kernel
from export.codegen.budget import FLASH_LIMIT_B
from export.codegen.render import render_firmware
from export.quantize import calibrate, quantize_policy
from export.verify import avr
from tests.fixtures import init_policy
from kiloforge import numfmt
from kiloforge.policies import load_policy
from sim.config import preset


def networks():
    """(name, QuantizedPolicy) of the benchmark networks."""
    world = preset("kilobot")
    default = load_policy(ROOT / "export" / "data" / "default_policy.npz")
    out = [("default " + "-".join(map(str, [default.in_dim, *[w.shape[0] for w in default.weights]])), default)]
    for t_prev, hidden in ((20, (64, 32)), (2, (32, 32))):
        p = init_policy(world, t_prev, hidden, "elu", seed=7)
        out.append(("-".join(map(str, [p.in_dim, *hidden, 2])), p))
    return [(name, quantize_policy(p, calibrate(p, episodes=1, n_robots=(4,), seed=0))) for name, p in out]


def kernel_cycles(qp, portable: bool) -> tuple[float, list[int]]:
    """Dense-layer cycles per MAC of the chained network (one random input, kernel program)."""
    kls = [kernel.kernel_layer(l) for l in qp.layers]
    rng = np.random.default_rng(np.random.SeedSequence(0))
    x = rng.integers(-128, 128, kls[0].n_in)
    reqs = [(0, kls[0].n_in, x)] + [(i, None, None) for i in range(1, len(kls))]
    run = avr.run_kernel(kls, reqs, portable=portable)
    want = x
    for l, o in zip(qp.layers, run.outputs):  # the chain (identity between layers) is bit-exact too
        want = numfmt.dense_int(want, l.w, l.b, l.shift, l.lo, l.hi)
        assert np.array_equal(o, want), "kernel chain differs from numfmt"
    macs = sum(k.n_in * k.n_out for k in kls)
    return float(run.cycles.sum()) / macs, [int(c) for c in run.cycles]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=8, help="control periods per robot in the simavr run")
    args = ap.parse_args(argv)
    why = avr.missing_tools(simulate=True)
    if why:
        print(f"skipped: {why}")
        return 0
    rows = []
    for name, qp in networks():
        files = render_firmware(qp)
        eb = avr.exact_budget(files, qp, stack_steps=20)
        check = avr.verify_simavr(qp, files, n_robots=8, n_steps=args.steps, seed=1)
        plain = avr.verify_simavr(qp, files, n_robots=4, n_steps=3, seed=1, portable=True)
        asm_mac, asm_layers = kernel_cycles(qp, portable=False)
        c_mac, c_layers = kernel_cycles(qp, portable=True)
        per_mac = [c / l.w.size for c, l in zip(asm_layers, qp.layers)]
        rows.append((name, sum(l.w.size for l in qp.layers), eb, check, plain, asm_mac, c_mac,
                     (asm_layers, per_mac), all(kernel.is_fast(l) for l in qp.layers)))
    print("| network | MACs | flash (of 28,160) | SRAM static + peak stack (of 1,536) | loop() at a control step "
          "| dense cycles/MAC asm | plain C | simavr vs emulator |")
    print("|---|---:|---:|---:|---:|---:|---:|---|")
    for name, macs, eb, check, plain, asm_mac, c_mac, _, fast in rows:
        step = int(np.median(check.cycles_step))
        step_c = int(np.median(plain.cycles_step))
        over = "" if eb["flash"] <= FLASH_LIMIT_B else " (does not fit)"
        print(f"| {name} | {macs:,} | {eb['flash']:,} B{over} | {eb['sram_static']:,} + {eb['stack']} = "
              f"{eb['sram_user']:,} B | {step:,} cyc = {step / 8e3:.1f} ms (plain C {step_c / 8e3:.1f} ms) "
              f"| {asm_mac:.2f} | {c_mac:.1f} | {'bit-exact' if check.ok and plain.ok else 'MISMATCH'}, "
              f"{check.control_steps + plain.control_steps:,} steps |")
    print()
    for name, _, _, _, _, _, _, (layers, per_mac), fast in rows:
        print(f"{name}: cycles per kf_dense call (assembly) {layers}, per MAC "
              f"{' / '.join(f'{m:.2f}' for m in per_mac)}; all layers 24-bit fast: {fast}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
