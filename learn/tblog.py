"""TensorBoard scalars of a run (``--tensorboard``): every metrics row, tagged by its column name.

Events go to ``run_dir/tensorboard`` with the row's ``env_steps`` as the step; a resumed run purges
the events written after its checkpoint (``purge_step``), so a killed and resumed run shows one curve.
Watch with ``tensorboard --logdir runs``.
"""
from __future__ import annotations

import math
from pathlib import Path

TB_DIR = "tensorboard"


class TensorBoardLog:
    def __init__(self, run_dir: Path, purge_step: int | None = None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(log_dir=str(Path(run_dir) / TB_DIR), purge_step=purge_step)

    def row(self, row: dict) -> None:
        """The row's finite numbers as scalars at step ``row['env_steps']``."""
        step = int(row["env_steps"])
        for k, v in row.items():
            if k != "env_steps" and isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
                self.writer.add_scalar(k, v, global_step=step)
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()
