"""The actor kinds, keyed by the name a policy artifact's meta gives as its "kind".

Adding a kind: write its module (an :class:`~kiloforge.actors.base.ActorKind`), its template
partial and C kernel header, and list it here; no other module names kinds.
"""
from __future__ import annotations

from typing import Any

from ..errors import PolicyError
from .aggregator import AGGREGATOR
from .base import ActorKind
from .gru import GRU
from .lstm import LSTM
from .mlp import MLP
from .run_and_tumble import RUN_AND_TUMBLE
from .searcher import SEARCHER
from .shadow_pusher import SHADOW_PUSHER
from .stop_in_light import STOP_IN_LIGHT

KINDS: dict[str, ActorKind] = {k.name: k for k in (MLP, GRU, LSTM, SEARCHER, AGGREGATOR, STOP_IN_LIGHT, RUN_AND_TUMBLE,
                                                   SHADOW_PUSHER)}


def kind_named(name: object) -> ActorKind:
    """The kind registered as ``name``; raises PolicyError naming the supported ones."""
    try:
        return KINDS[name]  # type: ignore[index]
    except (KeyError, TypeError):
        raise PolicyError(f"unknown kind {name!r} (supported: {', '.join(KINDS)})") from None


def kind_of(obj: Any) -> ActorKind:
    """The kind of a float policy or a quantised actor (its ``kind`` attribute)."""
    return kind_named(getattr(obj, "kind", None))
