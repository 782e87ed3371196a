"""``python -m kiloforge``: the ``kiloforge`` command (:mod:`kiloforge.cli`)."""
import sys

from .cli import main

sys.exit(main())
