"""kiloforge simulator: a vectorised Kilobot swarm world on NumPy arrays (B envs, M robots, ...)."""
from __future__ import annotations

from typing import Any

__all__ = ["WorldConfig", "PRESETS", "THESIS", "KILOBOT", "preset"]


def __getattr__(name: str) -> Any:
    # loaded on first use, so `python -m sim` imports nothing before its own Ctrl-C handling starts
    if name in __all__:
        from . import config

        return getattr(config, name)
    raise AttributeError(f"module 'sim' has no attribute '{name}'")
