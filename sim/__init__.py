"""kiloforge simulator: a vectorised Kilobot swarm world on NumPy arrays (B envs, M robots, ...)."""

__all__ = ["WorldConfig", "PRESETS", "THESIS", "KILOBOT", "preset"]


def __getattr__(name: str):
    # loaded on first use (and nothing imported here), so `python -m sim` loads nothing before its own
    # Ctrl-C handling starts
    if name in __all__:
        from . import config

        return getattr(config, name)
    raise AttributeError(f"module 'sim' has no attribute '{name}'")
