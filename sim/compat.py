"""The names files and commands kept from before tasks were plug-ins, mapped to the generic code's names.

Generic code calls a robot that only transmits and has a task role the *emitter* (localisation's
beacon, transport's object robot). Policy artifacts, world JSON files, result tables and CLI values
written before that keep localisation's words, and they must keep working unchanged: a policy's hash
covers its world's JSON keys, so those keys stay what they were. This module is the one place that
maps the old names to the new ones; nothing else in the generic layers spells them.
"""
from __future__ import annotations

from typing import Any

from kiloforge.errors import InputError

#: WorldConfig attribute -> its key in world JSON (policy artifacts, world.json, evaluation.json); the keys are
#: the file format's (version 1), so every stored hash stays valid
WORLD_KEYS: dict[str, str] = {"emitter": "beacon", "emitter_mobility": "beacon_mobility", "emitter_uid": "target_uid"}

#: the robustness variants that tape the emitter down / let collisions push it, by their names in result tables
EMITTER_FIXED_VARIANT = "beacon fixed"
EMITTER_PUSHED_VARIANT = "beacon pushed"
#: the "table" randomisation with the emitter pushed like a robot in every episode, by its ``--randomise`` name
FREE_EMITTER_RANDOMISATION = "table-free-beacon"


def world_to_file(d: dict[str, Any]) -> dict[str, Any]:
    """A WorldConfig's fields (attribute names) under their world-JSON keys, in the same order."""
    return {WORLD_KEYS.get(k, k): v for k, v in d.items()}


def world_from_file(d: dict[str, Any], where: str) -> dict[str, Any]:
    """World JSON (keys of either name) as WorldConfig fields; InputError when a field is given under both names."""
    both = [f"{new!r} and {old!r}" for new, old in WORLD_KEYS.items() if new in d and old in d]
    if both:
        raise InputError(f"{where}: give {both[0]} once, under one name (they are the same field)")
    back = {old: new for new, old in WORLD_KEYS.items()}
    return {back.get(k, k): v for k, v in d.items()}
