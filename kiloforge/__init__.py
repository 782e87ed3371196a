"""kiloforge: swarm policies from simulation to real Kilobot robots (the shared core of sim, learn and export)."""

__version__ = "0.2.0"
