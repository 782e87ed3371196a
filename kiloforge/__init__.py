"""kiloforge: swarm policies from simulation to real Kilobot robots.

The top-level package holds what every part shares; the parts themselves are ``sim`` (the
simulator), ``learn`` (the trainer) and ``export`` (quantisation, firmware, verification). Its modules stand
on two floors (docs/design.md, "Dependencies run one way"; tests/test_imports.py holds them to it): the
foundation below ``sim`` (``errors``, ``validate``, ``io``, ``progress``, ``plotting``, ``numfmt``,
``cliparse``, ``interrupts``, ``sighold``, ``extras``) and the artifact/actor floor above it (``artifact``,
``policies``, ``actors``); the commands (``cli``, ``scripts``, ``sim_cli``) sit on top of every package.
"""

__version__ = "0.2.0"  #: the one definition of the version (pyproject.toml reads it)
