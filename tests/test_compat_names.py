"""The emitter's old names (sim.compat): stored files keep loading with their hashes, both spellings of world JSON load."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from kiloforge.errors import InputError
from kiloforge.policies import load_policy
from sim.compat import WORLD_KEYS
from sim.config import WorldConfig, preset

DATA = Path(__file__).resolve().parents[1] / "export" / "data"


@pytest.mark.parametrize("path", sorted(DATA.glob("*.npz")), ids=lambda p: p.stem)
def test_shipped_policies_keep_their_hash_and_emitter(path):
    """Every shipped policy loads, its recomputed hash is the stored one and its world's emitter is the stored beacon."""
    meta = json.loads(np.load(path)["meta"].tobytes())
    p = load_policy(path)
    assert p.hash == meta["policy_hash"]
    assert p.world.emitter == meta["world"].get("beacon", True)
    assert p.world.emitter_uid == meta["world"]["target_uid"]
    assert p.world.emitter_mobility == meta["world"].get("beacon_mobility", 0.0)


def test_old_and_new_keys_give_the_same_world():
    """World JSON with the old keys and with the attribute names builds one world; to_dict writes the old keys."""
    old = {"beacon": True, "beacon_mobility": 0.5, "target_uid": 7}
    new = {"emitter": True, "emitter_mobility": 0.5, "emitter_uid": 7}
    a, b = WorldConfig.from_dict({**preset("kilobot").to_dict(), **old}), WorldConfig.from_dict(new | {"name": "kilobot"})
    renamed = {k: v for k, v in a.to_dict().items() if k not in old} | new
    assert a.emitter_mobility == 0.5 and a.emitter_uid == 7 and a == WorldConfig.from_dict(renamed)
    assert b.emitter_uid == 7 and set(WORLD_KEYS.values()) - {"beacon"} <= set(a.to_dict())
    assert not set(WORLD_KEYS) & set(a.to_dict())


@pytest.mark.parametrize("new,old", sorted(WORLD_KEYS.items()))
def test_a_field_under_both_names_is_refused(new, old):
    """A world dict naming one field under its old and its new key is a one-line error naming both."""
    value = preset("thesis").to_dict().get(old, 0.0 if "mobility" in new else True)
    with pytest.raises(InputError, match=f"'{new}' and '{old}'") as e:
        WorldConfig.from_dict({new: value, old: value})
    assert "\n" not in str(e.value)
