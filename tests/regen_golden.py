"""The golden-file policies (one per actor kind) and their regeneration: ``python -m tests.regen_golden``.

tests/test_render.py renders :func:`golden_policies` and compares the generated part of each program
with the committed ``tests/golden/<kind>.c`` (and the beacon program with ``target.c``) byte for
byte. The generated part is the program with every inlined hand-written C file (``kf_runtime.h``,
``kf_dense.h``/``.c``, the kind's kernel header) replaced by one marker line: that C is tested on
its own (tests/c/test_runtime.c, the kernel and cell tests) and would otherwise make every golden
change with it. Run this script after an intended change of the templates, the renderer, the kernel
layout or the number format, and review the diff of the golden files.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from tests.fixtures import TARGET_FILE
from export.codegen.render import DENSE_SOURCES, POLICY_FILE, RUNTIME_SOURCES, render_firmware
from export.codegen.templates import inline_sources
from kiloforge import numfmt
from kiloforge.actors.aggregator import QuantizedAggregator
from kiloforge.actors.base import QuantizedActor, sensing_tables
from kiloforge.actors.gru import QuantGRUCell, QuantizedGRU
from kiloforge.actors.lstm import QuantizedLSTM, QuantLSTMCell
from kiloforge.actors.mlp import QuantizedMLP
from kiloforge.actors.registry import kind_of
from kiloforge.actors.run_and_tumble import QuantizedRunAndTumble
from kiloforge.actors.searcher import RUN_TABLE_SIZE, QuantizedSearcher
from kiloforge.actors.shadow_pusher import QuantizedShadowPusher
from kiloforge.actors.stop_in_light import QuantizedStopInLight
from kiloforge.io import write_atomic
from kiloforge.numfmt import HIDDEN_EXP, QuantLayer
from sim.baselines import SearcherParams
from sim.config import preset
from sim.tasks import DEFAULT_TASK, get_task
from sim.tasks.aggregation import NBR_MAX, AggregatorParams
from sim.tasks.phototaxis import RunAndTumbleParams, StopInLightParams

GOLDEN_DIR = Path(__file__).resolve().parent / "golden"
GOLDEN_VERSION = "golden"  #: generator version written into the golden banner
GOLDEN_TARGET_UIDS = (0, 77)
GOLDEN_HASH = "0123456789abcdef" * 4
TARGET_GOLDEN = "target.c"  #: the beacon-only program (the same for every kind)
WORLD = preset("thesis", n_rbf=3, neighbour_table_size=4, period_ticks=8)  #: tuple of 8 entries
E_IN = 6


def _int_pattern(n_out: int, n_in: int, a: int, b: int) -> np.ndarray:
    """Deterministic int8 weights from integer arithmetic only (no RNG, no floats)."""
    j, i = np.meshgrid(np.arange(n_out), np.arange(n_in), indexing="ij")
    return (((j * a + i * b) * 37) % 255 - 127).astype(np.int8)


def _gate(n_out: int, n_in: int, a: int, b: int, shifts, e_in: int, e_out: int) -> QuantLayer:
    """An int8 gate layer (no activation of its own) with a fixed pattern."""
    bias = np.array([(-1) ** j * 300 * (j + 1) for j in range(n_out)], np.int32)
    return QuantLayer(w=_int_pattern(n_out, n_in, a, b), b=bias, shift=np.array(shifts, np.uint8), lo=-128, hi=127,
                      activation="identity", e_in=e_in, e_out=e_out, e_act=e_out, table=None)


def _output(n_in: int, e_in: int) -> QuantLayer:
    """The uint8 output layer (2 rows) with a fixed pattern."""
    return QuantLayer(w=_int_pattern(2, n_in, 7, 11), b=np.array([128 << 6, 100 << 6], np.int32),
                      shift=np.array([6, 6], np.uint8), lo=0, hi=255, activation="identity",
                      e_in=e_in, e_out=0, e_act=0, table=None)


def golden_mlp() -> QuantizedMLP:
    """A tiny fixed MLP: t_prev 2, one ELU hidden layer of 4."""
    n_in = WORLD.history_dim(2)
    l0 = QuantLayer(w=_int_pattern(4, n_in, 3, 5), b=np.array([100, -2000, 0, 4095], np.int32),
                    shift=np.array([7, 8, 9, 6], np.uint8), lo=-128, hi=127, activation="elu",
                    e_in=E_IN, e_out=5, e_act=6, table=numfmt.act_table("elu", 5, 6))
    return QuantizedMLP(layers=[l0, _output(4, l0.e_act)], e_in=E_IN, world=WORLD, t_prev=2, policy_hash=GOLDEN_HASH,
                        **sensing_tables(WORLD, E_IN))


def golden_gru() -> QuantizedGRU:
    """A tiny fixed GRU of 4 hidden units."""
    D, H = WORLD.tuple_dim, 4
    r = _gate(H, D + H, 3, 5, [7, 8, 9, 6], E_IN, 4)
    z = _gate(H, D + H, 5, 3, [8, 8, 7, 9], E_IN, 4)
    nx = _gate(H, D, 2, 7, [6, 7, 8, 9], E_IN, 5)
    nh = _gate(H, H, 7, 2, [9, 8, 7, 6], HIDDEN_EXP, 6)
    cell = QuantGRUCell(r=r, z=z, nx=nx, nh=nh, r_table=numfmt.gate_table(4),
                        k_table=numfmt.gate_table(4, complement=True),
                        n_table=numfmt.act_table("tanh", 5, HIDDEN_EXP),
                        rn_shift=numfmt.GATE_EXP + nh.e_out - 5, nx_shift=0)
    return QuantizedGRU(cell=cell, out=_output(H, HIDDEN_EXP), e_in=E_IN, world=WORLD, policy_hash=GOLDEN_HASH,
                        **sensing_tables(WORLD, E_IN))


def golden_lstm() -> QuantizedLSTM:
    """A tiny fixed LSTM of 4 hidden units."""
    D, H = WORLD.tuple_dim, 4
    i, f, g, o = (_gate(H, D + H, a, b, shifts, E_IN, e) for a, b, shifts, e in
                  ((3, 5, [7, 8, 9, 6], 4), (5, 3, [8, 8, 7, 9], 5), (2, 7, [6, 7, 8, 9], 5), (7, 2, [9, 8, 7, 6], 4)))
    cell = QuantLSTMCell(i=i, f=f, g=g, o=o, i_table=numfmt.gate_table(4), f_table=numfmt.gate_table(5),
                         g_table=numfmt.act_table("tanh", 5, HIDDEN_EXP), o_table=numfmt.gate_table(4),
                         c_table=numfmt.act_table("tanh", 6, HIDDEN_EXP), e_c=6)
    return QuantizedLSTM(cell=cell, out=_output(H, HIDDEN_EXP), e_in=E_IN, world=WORLD, policy_hash=GOLDEN_HASH,
                         **sensing_tables(WORLD, E_IN))


def golden_searcher() -> QuantizedSearcher:
    """The hand-written searcher with non-default integer parameters and a fixed run-length table (no floats)."""
    p = SearcherParams(run_max_steps=700, tumble_max_steps=5, wall_turn_min=2, wall_turn_max=6, wall_cooldown=4,
                       uturn_steps=3, stop_dist=0.625, settle_patience=9, settle_hold=2, nbr_gradient=False, turn_sign=2,
                       push_margin=0.0625, hold_within=True)
    run = (np.arange(RUN_TABLE_SIZE) * 11 % 700 + 1).astype(np.uint16)
    return QuantizedSearcher(params=p, speed_q=200, stop_q=40, margin_q=4, run_table=run, e_in=E_IN,  # 40 = 0.625 * 2**6,
                             world=WORLD, policy_hash=GOLDEN_HASH, **sensing_tables(WORLD, E_IN))  # 4 = 0.0625 * 2**6


def golden_aggregator() -> QuantizedAggregator:
    """The hand-written aggregator with non-default parameters and fixed integer thresholds, in aggregation's layout
    (no beacon)."""
    p = AggregatorParams(stop_base=0.25, stop_per_nbr=0.125, leave_base=0.5, leave_decay=2.0, run_steps=16,
                         turn_max_steps=5, wall_turn_steps=4)
    n = np.arange(NBR_MAX + 1)
    world = get_task("aggregation").world(WORLD)
    return QuantizedAggregator(params=p, nbr_t=(16 + 32 * np.arange(NBR_MAX)).astype(np.uint16),
                               stop_t=np.minimum(16384 + 8192 * n, 65536).astype(np.uint32),
                               leave_t=(32768 // (1 + 2 * n * n)).astype(np.uint32), tumble_t=4096, e_in=E_IN,
                               world=world, policy_hash=GOLDEN_HASH, **sensing_tables(world, E_IN))


def golden_light_rules() -> tuple[QuantizedStopInLight, QuantizedRunAndTumble]:
    """The hand-written light rules with non-default parameters and fixed integer thresholds, in phototaxis's layout
    (no beacon)."""
    world = get_task("phototaxis").world(WORLD)
    common = dict(tumble_t=2048, e_in=E_IN, world=world, policy_hash=GOLDEN_HASH, **sensing_tables(world, E_IN))
    return (QuantizedStopInLight(params=StopInLightParams(threshold=700, run_steps=32, turn_max_steps=3), level_t=44,
                                 **common),  # 44 = ceil(700 * 2**6 / 2**10)
            QuantizedRunAndTumble(params=RunAndTumbleParams(fall=40, run_steps=32, turn_max_steps=7), fall_t=-2,
                                  **common))  # -2 = ceil(-40 * 2**6 / 2**10)


def golden_shadow_pusher() -> QuantizedShadowPusher:
    """The hand-written transport rule with non-default parameters and fixed integer thresholds, in transport's kilobot
    world (a beacon: the object's robot)."""
    from sim.config import preset
    from sim.tasks.transport import ShadowPusherParams

    world = get_task("transport").world(preset("kilobot"))  # a heavy body needs a collision world
    p = ShadowPusherParams(dark=600, fall=40, rise=40, back_mm=6.0, touch_mm=70.0, run_steps=32, turn_max_steps=5,
                           back_steps=3)
    return QuantizedShadowPusher(params=p, tumble_t=2048, dark_t=38, fall_t=-2, rise_t=2, touch_t=52, back_t=4,
                                 e_in=E_IN, world=world, policy_hash=GOLDEN_HASH, **sensing_tables(world, E_IN))


def golden_policies() -> dict[str, QuantizedActor]:
    """Kind name -> its golden quantised policy."""
    return {q.kind: q for q in (golden_mlp(), golden_gru(), golden_lstm(), golden_searcher(), golden_aggregator(),
                                *golden_light_rules(), golden_shadow_pusher())}


#: the task whose emitter firmware a golden policy's programs get (the default task's for the rest)
GOLDEN_TASKS = {"shadow_pusher": "transport"}


def render(qp: QuantizedActor) -> dict[str, str]:
    """The programs of a golden policy (both, or the one of a world without an emitter), rendered as the golden files
    were."""
    return render_firmware(qp, emitter_uids=GOLDEN_TARGET_UIDS if qp.world.has_roles else None, msg_type=0x2A,
                           generator_version=GOLDEN_VERSION, task=get_task(GOLDEN_TASKS.get(qp.kind, DEFAULT_TASK)))


def generated_part(text: str, inlined: tuple[tuple[str, ...], ...]) -> str:
    """The program with each block of inlined hand-written C (``inlined``: the file groups) replaced
    by one marker line."""
    for names in filter(None, inlined):
        block = inline_sources(names)
        assert text.count(block) == 1, f"{names} is not inlined once"
        text = text.replace(block, f"/* [inlined here: {', '.join(names)} (hand-written, tested on its own)] */\n")
    return text


def golden_files() -> dict[str, str]:
    """Golden file name -> the generated part it must hold."""
    out = {}
    for kind, qp in golden_policies().items():
        files = render(qp)
        dense = DENSE_SOURCES if qp.layers else ()  # a rule-based actor leaves the dense kernels out
        out[f"{kind}.c"] = generated_part(files[POLICY_FILE], (RUNTIME_SOURCES, dense, kind_of(qp).c_sources))
    out[TARGET_GOLDEN] = generated_part(render(golden_mlp())[TARGET_FILE], (RUNTIME_SOURCES,))  # its banner names an actor
    return out


def main() -> int:
    GOLDEN_DIR.mkdir(exist_ok=True)
    for name, text in golden_files().items():
        path = write_atomic(GOLDEN_DIR / name, text)
        print(f"wrote {path} ({len(text):,} bytes)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
