"""The golden-file policy and its regeneration: ``python tests/regen_golden.py``.

tests/test_render.py renders :func:`golden_policy` and compares with the committed
``tests/golden/*.c`` byte for byte. Run this script after an intended change of the templates, the
hand-written C, the kernel layout or the number format, and review the diff of the golden files.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from export.codegen.render import render_firmware  # noqa: E402
from kiloforge import numfmt  # noqa: E402
from kiloforge.actors.base import sensing_tables  # noqa: E402
from kiloforge.actors.mlp import QuantizedMLP  # noqa: E402
from kiloforge.numfmt import QuantLayer  # noqa: E402
from sim.config import preset  # noqa: E402

GOLDEN_DIR = Path(__file__).resolve().parent / "golden"
GOLDEN_VERSION = "golden"  #: generator version written into the golden banner
GOLDEN_TARGET_UIDS = (0, 77)


def _int_pattern(n_out: int, n_in: int, a: int, b: int) -> np.ndarray:
    """Deterministic int8 weights from integer arithmetic only (no RNG, no floats)."""
    j, i = np.meshgrid(np.arange(n_out), np.arange(n_in), indexing="ij")
    return (((j * a + i * b) * 37) % 255 - 127).astype(np.int8)


def golden_policy() -> QuantizedMLP:
    """A tiny fixed policy: thesis world with 3 RBF bins, t_prev 2, one ELU hidden layer of 4."""
    world = preset("thesis", n_rbf=3, neighbour_table_size=4, period_ticks=8)
    e_in = 6
    n_in = world.history_dim(2)
    l0 = QuantLayer(w=_int_pattern(4, n_in, 3, 5), b=np.array([100, -2000, 0, 4095], np.int32),
                    shift=np.array([7, 8, 9, 6], np.uint8), lo=-128, hi=127, activation="elu",
                    e_in=e_in, e_out=5, e_act=6, table=numfmt.act_table("elu", 5, 6))
    l1 = QuantLayer(w=_int_pattern(2, 4, 7, 11), b=np.array([128 << 6, 100 << 6], np.int32),
                    shift=np.array([6, 6], np.uint8), lo=0, hi=255, activation="identity",
                    e_in=6, e_out=0, e_act=0, table=None)
    layers = [l0, l1]
    return QuantizedMLP(layers=layers, e_in=e_in, world=world, t_prev=2, policy_hash="0123456789abcdef" * 4,
                        **sensing_tables(world, e_in))


def golden_files() -> dict[str, str]:
    """What the golden policy renders to."""
    return render_firmware(golden_policy(), target_uids=GOLDEN_TARGET_UIDS, msg_type=0x2A,
                           generator_version=GOLDEN_VERSION)


def main() -> int:
    GOLDEN_DIR.mkdir(exist_ok=True)
    for name, text in golden_files().items():
        path = GOLDEN_DIR / name
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
        print(f"wrote {path} ({len(text):,} bytes)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
