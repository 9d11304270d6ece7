"""Simulator calls a planned batch at a time. A simulator takes no more rows a call than it was
planned for (its memory is sized once, up front), so the Python side cuts longer arrays."""

from __future__ import annotations

import numpy as np


def batched(step, rows: np.ndarray, batch: int, *more: np.ndarray) -> np.ndarray:
    """``step`` (a simulator's `encode`, `generate`, `reward`, ...) on ``rows`` and the ``more``
    arrays beside them, ``batch`` rows at a time, the results joined. No rows are handed to
    ``step`` as they are, so that its own error says what is wrong.

    >>> batched(lambda x: x * 2, np.arange(5), 2)
    array([0, 2, 4, 6, 8])
    """
    return np.concatenate([step(*(np.ascontiguousarray(x[a:a + batch]) for x in (rows, *more)))
                           for a in range(0, max(len(rows), 1), batch)])
