"""Rung 3 of the verification ladder: the AVR build of the generated C, run in simavr (ATmega328P,
8 MHz), equals the emulator byte for byte; cycles and the painted-stack high-water mark are measured."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.avr_tools import require_avr
from export.contract import firmware as fwspec
from export.verify import avr
from export.verify.hostbuild import StreamSpec, random_inputs
from export.codegen.render import render_firmware
from tests.fixtures import synthetic_qpolicy
from sim.config import preset

pytestmark = pytest.mark.avr

WORLD = preset("kilobot", period_ticks=6, neighbour_table_size=4)


@pytest.fixture(scope="module")
def qp():
    return synthetic_qpolicy(WORLD, 4, (32, 16), ("elu", "relu"), seed=11)


def test_runner_counts_cycles_and_finds_the_stack_high_water_mark(tmp_path):
    """Marks measure an exact 1000-cycle delay; a 150-byte stack buffer shows in the peak stack."""
    require_avr(simulate=True)
    src = """#include <stdint.h>
#include "kf_sim_io.h"
static void __attribute__((noinline)) deep(void)
{
    volatile uint8_t buf[150];
    uint8_t i;
    for (i = 0; i < sizeof buf; ++i) buf[i] = i;
}
int main(void)
{
    kf_sim_mark(3); kf_sim_mark(4);
    kf_sim_mark(5); __builtin_avr_delay_cycles(1000); kf_sim_mark(6);
    deep();
    kf_sim_out(kf_sim_in() + 1u);
    kf_sim_exit();
    return 0;
}
"""
    b = avr.build({"t.c": src, "kf_sim_io.h": (avr.STANDIN_DIR / "kf_sim_io.h").read_text()}, tmp_path, name="t")
    res = avr.run_elf(b.elf, bytes([41]))
    assert res.output == bytes([42]) and res.underrun == 0
    assert int(res.spans(5, 6)[0]) - avr.mark_overhead(res) == 1000
    assert 150 < res.stack_peak < 200


def test_firmware_is_bit_exact_in_simavr(qp):
    """A random stream with every edge case replays identically on the AVR and in the emulator."""
    require_avr(simulate=True)
    files = render_firmware(qp)
    rng = np.random.default_rng(np.random.SeedSequence(5))
    inputs = random_inputs(rng, WORLD.period_ticks, (WORLD.emitter_uid,), StreamSpec(n_robots=24, n_steps=25),
                           fwspec.DEFAULT_MSG_TYPE, WORLD.comm_radius_mm, WORLD.light_threshold)
    ev = inputs.events
    assert (ev["type"] != fwspec.DEFAULT_MSG_TYPE).any() and (ev["version"] != fwspec.MSG_VERSION).any()
    assert (inputs.light < 0).any() and (ev["dist"] < 33).any() and (ev["dist"] > 200).any()
    check = avr.verify_simavr(qp, files, inputs=inputs)
    assert check.ok, check.detail
    assert check.control_steps >= 400
    assert check.cycles_step.size > 0 and check.cycles_net.size == check.cycles_step.size
    assert np.all(check.cycles_net < check.cycles_step)
    assert 40 < check.stack_peak < 600
    assert check.macs == sum(l.w.size for l in qp.layers)


def test_portable_kernel_firmware_is_bit_exact_and_slower(qp):
    """The plain-C kernel build is bit-exact too, and the assembly kernel needs fewer cycles per MAC."""
    require_avr(simulate=True)
    files = render_firmware(qp)
    fast = avr.verify_simavr(qp, files, n_robots=6, n_steps=6, seed=2)
    plain = avr.verify_simavr(qp, files, n_robots=6, n_steps=6, seed=2, portable=True)
    assert fast.ok and plain.ok, (fast.detail, plain.detail)
    assert fast.cycles_per_mac < plain.cycles_per_mac


def test_verify_simavr_catches_a_wrong_firmware(qp):
    """Firmware rendered from a policy with one changed output bias does not pass as the original."""
    require_avr(simulate=True)
    out = qp.layers[-1]
    b = out.b.copy()
    b[0] += np.int32(1) << (int(out.shift[0]) + 5)  # +32 on the left motor command
    other = replace(qp, layers=qp.layers[:-1] + [replace(out, b=b)])
    check = avr.verify_simavr(qp, render_firmware(other), n_robots=6, n_steps=6, seed=3)
    assert not check.ok and check.detail


@pytest.mark.slow
def test_default_policy_bit_exact_over_2000_control_steps():
    """The shipped default policy, quantised, is bit-exact in simavr over more than 2,000 control steps."""
    require_avr(simulate=True)
    from kiloforge.policies import load_policy
    from export.quantize import calibrate, quantize_policy
    p = load_policy(Path(__file__).resolve().parents[1] / "export" / "data" / "default_policy.npz")
    q = quantize_policy(p, calibrate(p, episodes=1, n_robots=(4,), seed=0))
    check = avr.verify_simavr(q, render_firmware(q), n_robots=60, n_steps=40, seed=1)
    assert check.ok, check.detail
    assert check.control_steps >= 2000


def test_stack_paint_point_has_no_frame(tmp_path):
    """kf_io_read (where the stack is painted before loop()) pushes nothing, so the peak is exact."""
    require_avr()
    import subprocess
    obj = tmp_path / "io.o"
    subprocess.run(["avr-gcc", *avr.KILOLIB_CFLAGS, *(f"-D{d}" for d in avr.MARK_DEFINES), "-I", str(avr.STANDIN_DIR),
                    "-c", "-o", str(obj), str(avr.STANDIN_DIR / "kf_avr_io.c")], check=True)
    dis = subprocess.run(["avr-objdump", "-d", str(obj)], capture_output=True, text=True, check=True).stdout
    body = dis.split("<kf_io_read>:")[1].split("\n\n")[0]
    assert "ret" in body and "push" not in body and "rcall" not in body
