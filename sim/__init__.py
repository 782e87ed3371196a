"""kiloforge simulator: a vectorised Kilobot swarm world on NumPy arrays (B envs, M robots, ...)."""
from .config import KILOBOT, PRESETS, THESIS, WorldConfig, preset

__all__ = ["WorldConfig", "PRESETS", "THESIS", "KILOBOT", "preset"]
