"""The argument checks the package's Python code shares: each returns the value it checked
(converted: a Python float or int, a C-ordered array) or raises ``TypeError`` for the wrong
kind of value and ``ValueError`` for a value out of range, naming the argument."""

from __future__ import annotations

import math
import operator
from typing import Any, Optional

import numpy as np


def _kind(value: Any) -> str:
    return type(value).__name__


def number(name: str, value: Any, low: Optional[float] = None, high: Optional[float] = None, above: bool = False) -> float:
    """``value`` as a finite float in ``[low, high]`` (``(low, high]`` when ``above``)."""
    if isinstance(value, (str, bytes)) or np.ndim(value) != 0:
        raise TypeError(f"{name}: expected a number, got {_kind(value)}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name}: expected a number, got {_kind(value)}") from None
    except OverflowError:  # an integer beyond any float
        raise ValueError(f"{name}: {value} is beyond any float") from None
    below = low is not None and (v <= low if above else v < low)
    if not math.isfinite(v) or below or (high is not None and v > high):
        span = f"{'>' if above else '>='} {low}" if low is not None else "finite"
        if high is not None:
            span = f"{span} and <= {high}" if low is not None else f"<= {high}"
        raise ValueError(f"{name} is {value!r}: expected a finite number {span}")
    return v


def flag(name: str, value: Any) -> bool:
    """``value`` as a bool: True or False, or an integer 1 or 0 (TypeError for what is not a
    number, ValueError for another number)."""
    if not isinstance(value, (int, float, np.number)):  # bool is an int
        raise TypeError(f"{name}: expected True or False, got {_kind(value)}")
    if not isinstance(value, (int, np.integer)) or value not in (0, 1):
        raise ValueError(f"{name}: expected True or False, got {value!r}")
    return bool(value)


def integer(name: str, value: Any, low: int = 0, high: Optional[int] = None) -> int:
    """``value`` as an int in ``[low, high]``; anything with ``__index__`` (``np.int64``)."""
    if isinstance(value, bool):
        raise TypeError(f"{name}: expected an integer, got bool")
    try:
        v = operator.index(value)
    except TypeError:
        raise TypeError(f"{name}: expected an integer, got {_kind(value)}") from None
    if v < low or (high is not None and v > high):
        span = f"from {low}" + (f" to {high}" if high is not None else "")
        raise ValueError(f"{name} is {v}: expected an integer {span}")
    return v


def floats(name: str, value: Any, dtype: Any = np.float64) -> np.ndarray:
    """``value`` as an array of ``dtype`` (real numbers: ValueError for complex or text,
    TypeError for objects that are not numbers; values beyond ``dtype`` become infinities, for
    the caller's finiteness check)."""
    if np.iscomplexobj(value):
        raise ValueError(f"{name}: expected real numbers, got complex ones")
    try:
        with np.errstate(all="ignore"):
            return np.asarray(value, dtype)
    except OverflowError:  # an integer beyond any float
        raise ValueError(f"{name}: a value beyond any float") from None


def frame(value: Any, shape: tuple[int, ...], name: str = "frame") -> np.ndarray:
    """An 8-bit frame of ``shape`` as a C-ordered array (a copy only when it is not one)."""
    if not isinstance(value, np.ndarray):
        raise ValueError(f"{name}: expected a numpy uint8 array of shape {shape}, got {_kind(value)}")
    if value.dtype != np.uint8 or value.shape != tuple(shape):
        raise ValueError(f"{name}: expected a uint8 array of shape {shape}, got {value.dtype} {value.shape}")
    return np.ascontiguousarray(value)


def seed(value: Any, name: str = "seed") -> Optional[int]:
    """A gymnasium seed: None or an integer >= 0 (``np.int64`` too)."""
    return None if value is None else integer(name, value, 0)
