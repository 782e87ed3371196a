"""The analytic flash / SRAM budget (export.codegen.budget) of the MLP actor kind."""
from __future__ import annotations

import pytest

from export.codegen import budget as bud
from tests.fixtures import init_policy
from kiloforge.actors.mlp import MLP, MLPArch
from kiloforge.policies import load_policy
from sim.config import preset

KB = preset("kilobot")


def mlp(t_prev: int, hidden, activations=None) -> bud.Budget:
    """The MLP budget in the kilobot world."""
    return bud.estimate(MLP, KB, MLPArch(t_prev, tuple(hidden), None if activations is None else tuple(activations)))


def item(b: bud.Budget, name: str) -> int:
    return next(i.bytes for i in b.items if i.name == name)


def test_breakdown_numbers():
    """kilobot, t_prev 10, hidden (32, 32) ELU: every data item has its exact size."""
    from kiloforge import numfmt
    from export.codegen.cformat import clamp_index_table, nonzero_windows
    b = mlp(10, (32, 32))
    assert b.layer_sizes == (160, 32, 32, 2)
    assert item(b, "kilolib") == 7028
    assert item(b, "weights int8") == 160 * 32 + 32 * 32 + 32 * 2
    assert item(b, "biases int32") == 4 * (32 + 32 + 2)
    assert item(b, "shifts uint8") == 32 + 32 + 2
    rbf = numfmt.rbf_table(KB.rbf_centres_mm, KB.rbf_sigma_mm, KB.rbf_norm, KB.comm_radius_mm, 6)
    assert item(b, "RBF table") == nonzero_windows(rbf)[3].size + 5 * 11 < 11 * 256
    tgt = clamp_index_table(numfmt.target_table(KB.comm_radius_mm, 6))[0]
    assert item(b, "target, action, uid tables") == tgt.size + 256 + 2
    assert item(b, "activation tables") == 2 * 256
    assert item(b, "history ring buffer") == 10 * 16
    assert item(b, "activation buffers") == 32 + 2 * 32
    assert item(b, "program code (estimate)") == bud.CODE_ESTIMATE_B["base"] + 3 * bud.CODE_ESTIMATE_B["per_layer"]
    assert b.flash_total == sum(i.bytes for i in b.items if i.section == "flash")
    assert b.sram_total == sum(i.bytes for i in b.items if i.section == "sram")
    assert b.ok and b.flash_limit == 28_160 and b.sram_limit == 1_536


def test_for_quantized_counts_shared_tables():
    """A quantised policy whose two ELU layers got the same exponents needs one shared table."""
    import dataclasses

    import numpy as np

    from export.quantize import quantize_policy
    from kiloforge.actors.mlp import calibration_from_inputs
    p = init_policy(KB, 3, (8, 8), "elu", seed=1, out_scale=0.3)
    qp = quantize_policy(p, calibration_from_inputs(p, np.zeros((4, p.in_dim))), e_in=5)
    l0, l1 = qp.layers[0], qp.layers[1]
    same = dataclasses.replace(qp, layers=[l0, dataclasses.replace(l1, e_in=l0.e_act, e_out=l0.e_out,
                                                                   e_act=l0.e_act, table=l0.table),
                                            dataclasses.replace(qp.layers[2], e_in=l0.e_act)])
    assert item(bud.for_quantized(same), "activation tables") == 256
    b = bud.for_quantized(qp)
    n_distinct = len({l.table.tobytes() for l in qp.layers if l.table is not None})
    assert item(b, "activation tables") == 256 * n_distinct
    assert "e_in 5" in next(i.note for i in b.items if i.name == "RBF table")


def test_relu_needs_no_tables():
    """ReLU hidden layers cost no activation tables; tanh costs one per layer."""
    assert item(mlp(5, (16, 16), ["relu", "relu"]), "activation tables") == 0
    assert item(mlp(5, (16, 16), ["tanh", "relu"]), "activation tables") == 256


def test_monotonic_in_history_and_width():
    """More history or wider layers never cost less flash or SRAM."""
    for t in range(1, 30):
        a, b = mlp(t, (32, 32)), mlp(t + 1, (32, 32))
        assert b.flash_total > a.flash_total and b.sram_total > a.sram_total
    a, b = mlp(10, (32, 32)), mlp(10, (33, 33))
    assert b.flash_total > a.flash_total


def test_over_flash_and_suggestions():
    """An over-budget architecture fails and suggest() names a history and a width that fit (and +1 does not)."""
    b = mlp(40, (64, 64))
    assert not b.ok and not b.flash_ok
    t, w = (bud.largest(MLP, KB, r) for r in MLP.resizes(KB, MLPArch(40, (64, 64))))
    assert t >= 1 and mlp(t, (64, 64)).ok and not mlp(t + 1, (64, 64)).ok
    assert w >= 1 and mlp(40, (w, w)).ok and not mlp(40, (w + 1, w + 1)).ok
    s = b.suggest()
    assert s == [f"t_prev <= {t} with hidden [64, 64]", f"hidden [{w}, {w}] with t_prev 40"]
    assert "DOES NOT FIT" in b.table()


def test_over_sram():
    """A very long history with a tiny network fails on SRAM, not flash."""
    b = mlp(100, (2,), ["relu"])
    assert b.flash_ok and not b.sram_ok and not b.ok
    assert item(b, "history ring buffer") == 1600


def test_exact_figures_decide():
    """Real-build figures merged via with_exact() override the analytic totals."""
    b = mlp(10, (32, 32))
    assert b.exact is None
    over = b.with_exact({"flash": 30_000, "sram_user": 500})
    assert not over.ok and over.flash_total == 30_000 and over.flash_analytic == b.flash_analytic
    assert b.with_exact({"flash": 20_000, "sram_user": 1_000}).ok
    assert "avr-gcc build" in over.table()


def test_for_policy_matches_estimate():
    """for_policy uses the policy's world, history, widths and activations."""
    p = init_policy(KB, 6, (12, 7), "tanh", seed=1)
    b = bud.for_policy(p)
    assert b.layer_sizes == tuple(p.layer_sizes) and b.arch.activations == ("tanh", "tanh", "identity")
    assert b.to_dict()["flash"]["total"] == mlp(6, (12, 7), ["tanh", "tanh"]).flash_total


def test_default_policy_fits_with_headroom():
    """The shipped default policy fits with at least the documented flash headroom."""
    from importlib import resources

    from tests.fixtures import FLASH_HEADROOM_B
    with resources.as_file(resources.files("export").joinpath("data", "default_policy.npz")) as path:
        p = load_policy(path)
    b = bud.for_policy(p)
    assert b.ok and b.flash_total + FLASH_HEADROOM_B <= b.flash_limit


def test_bad_arguments():
    """Non-positive history or widths are programming errors (asserts)."""
    with pytest.raises(AssertionError):
        mlp(0, (8,))
    with pytest.raises(AssertionError):
        mlp(3, (0,))
