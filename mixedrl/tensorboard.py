"""TensorBoard scalars beside a run's metrics files (the optional extra ``tensorboard``).

``train(..., tensorboard=True)`` (``mixedrl train --tensorboard``) writes every metrics row into
``<run>/tb/``, the keys of ``metrics.jsonl`` as tags and the iteration as the step. View with
``tensorboard --logdir <run>/tb``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

__all__ = ["TensorBoardLogger", "TB_DIR"]

#: Sub-directory of a run directory that holds the event files.
TB_DIR = "tb"


class TensorBoardLogger:
    """Write metrics rows as TensorBoard scalars into ``logdir``.

    Parameters
    ----------
    logdir : str or Path
        Directory of the event files (created if missing).

    Raises
    ------
    ImportError
        The optional dependency is missing; the message says how to install it.
    """

    def __init__(self, logdir: str | Path) -> None:
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError as exc:
            raise ImportError("tensorboard: TensorBoard logging needs the optional extra; install it with "
                              "pip install 'mixedrl[tensorboard]'") from exc
        self.logdir = Path(logdir)
        self._writer = SummaryWriter(log_dir=str(self.logdir))

    def write(self, rows: list[dict[str, Any]]) -> None:
        """Add every finite real scalar of each row (except ``iteration``, the step) and flush."""
        for row in rows:
            for key, value in row.items():
                if key != "iteration" and isinstance(value, (int, float)) and not isinstance(value, bool) \
                        and math.isfinite(value):
                    self._writer.add_scalar(key, float(value), int(row["iteration"]))
        self._writer.flush()

    def close(self) -> None:
        """Flush and close the event file."""
        self._writer.close()
