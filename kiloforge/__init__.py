"""kiloforge: swarm policies from simulation to real Kilobot robots.

The top-level package holds what every part shares; the parts themselves are ``sim`` (the
simulator), ``learn`` (the trainer) and ``export`` (quantisation, firmware, verification).
"""

__version__ = "0.2.0"  #: the one definition of the version (pyproject.toml reads it)
