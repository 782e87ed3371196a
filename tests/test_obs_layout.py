"""The observation layout is the world's (WorldConfig.obs_features), chosen by the task (sim.features)."""
import numpy as np
import pytest

from kiloforge.errors import InputError
from sim.config import WorldConfig, preset
from sim.env import SwarmEnv
from sim.tasks import get_task

AGG = get_task("aggregation")


def _run_both(cfg, B, M, steps, seed=11, task=None):
    """(fast, events-path) observations of the same episode, every step."""
    fast = SwarmEnv(cfg, B, M, seed=seed, fast_observe=True, task=task)
    slow = SwarmEnv(cfg, B, M, seed=seed, fast_observe=False, task=task)
    out = [(fast.reset()[0], slow.reset()[0])]
    rng = np.random.default_rng(1)
    for _ in range(steps):
        a = rng.random((B, M, 2))
        out.append((fast.step(a)[0], slow.step(a)[0]))
    return out


@pytest.mark.parametrize("world,overrides", [("thesis", {"neighbour_table_size": 3, "light_dropout": 0.3}),
                                             ("kilobot", {"arena_half_mm": 150.0, "neighbour_table_size": 3})])
def test_fast_observe_equals_events_path_for_aggregation(world, overrides):
    """Aggregation's layout (wall, RBF): the fast observation equals sim.events.observe bit for bit."""
    cfg = AGG.world(preset(world, **overrides))
    assert cfg.obs_dim == 1 + cfg.n_rbf and cfg.obs_index("rbf") == 1
    for o1, o2 in _run_both(cfg, 3, 20, 5, task=AGG):
        assert o1.shape[-1] == cfg.obs_dim
        np.testing.assert_array_equal(o1, o2)


def test_permuted_layout_carries_the_same_inputs():
    """A task listing the features in another order observes the same numbers, in that order."""
    from sim.tasks.localisation import Localisation

    class Permuted(Localisation):
        features = ("rbf", "nbr_sensing", "wall", "target")

    legacy = preset("thesis", light_dropout=0.2)
    perm = Permuted().world(legacy)
    assert perm.obs_features == "rbf,nbr_sensing,wall,target"
    for fast in (True, False):
        a = SwarmEnv(legacy, 2, 12, seed=3, fast_observe=fast)
        b = SwarmEnv(perm, 2, 12, seed=3, fast_observe=fast, task=Permuted())
        oa, ob = a.reset()[0], b.reset()[0]
        rng = np.random.default_rng(0)
        for _ in range(4):
            for name in legacy.features:
                np.testing.assert_array_equal(oa[..., legacy.obs_slice(name)], ob[..., perm.obs_slice(name)])
            act = rng.random((2, 12, 2))
            oa, ob = a.step(act)[0], b.step(act)[0]


def test_world_task_mismatch_is_one_line():
    """A world whose beacon or layout differs from the task's is refused in one line naming both."""
    with pytest.raises(InputError, match=r"^world 'kilobot' has emitter True and observation wall,target,nbr_sensing,rbf; "
                                         r"task 'aggregation' needs emitter False and observation wall,rbf") as e:
        SwarmEnv(preset("kilobot"), 1, 4, task=AGG)
    assert "\n" not in str(e.value)
    with pytest.raises(InputError, match="task 'localisation' needs emitter True"):
        SwarmEnv(AGG.world(preset("thesis")), 1, 4)


def test_legacy_layout_leaves_the_world_dict_unchanged():
    """Localisation's beacon and layout are omitted from to_dict (old hashes hold); others round-trip."""
    loc = get_task("localisation").world(preset("kilobot"))
    assert loc is preset("kilobot") and "beacon" not in loc.to_dict() and "obs_features" not in loc.to_dict()
    agg = AGG.world(preset("kilobot"))
    d = agg.to_dict()
    assert d["beacon"] is False and d["obs_features"] == "wall,rbf"
    assert WorldConfig.from_dict(d) == agg and WorldConfig.from_dict(d).obs_dim == 12


@pytest.mark.parametrize("fields,msg", [({"obs_features": "wall,compass"}, "unknown observation feature"),
                                        ({"obs_features": "wall,wall"}, "lists a feature twice"),
                                        ({"obs_features": ""}, "obs_features is empty"),
                                        ({"beacon": False}, r"target, nbr_sensing need an emitter")])
def test_bad_layout_is_refused(fields, msg):
    """Unknown, repeated or missing features, and beacon features without a beacon, are one-line errors."""
    with pytest.raises(InputError, match=msg):
        WorldConfig.from_dict({**preset("thesis").to_dict(), **fields})
