"""Sweeps: a grid of training configurations × seeds on Ray Tune, resumable, aggregated over seeds.

* :mod:`learn.sweep.grid` — the grid (command line, JSON / TOML file), validation, trials and names;
* :mod:`learn.sweep.trial` — how one trial trains, resumes or is skipped (the only module that
  calls a trainer);
* :mod:`learn.sweep.execute` — Ray Tune (imported only when trials run; ``pip install 'kiloforge[sweep]'``);
* :mod:`learn.sweep.aggregate` — statistics over seeds, tables, learning curves, evaluations;
* :mod:`learn.sweep.cli` — ``python -m learn sweep``. See docs/sweeps.md.
"""
from .cli import main_sweep

__all__ = ["main_sweep"]
