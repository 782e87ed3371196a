"""The packing ceiling is localisation's: :mod:`sim.tasks.ceiling`. This name stays for scripts that import it."""
import sys

from .tasks import ceiling as _ceiling

sys.modules[__name__] = _ceiling
