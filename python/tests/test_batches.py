"""Simulator calls a planned batch at a time (drivesim._batches): every row once, in order, the
arrays beside them cut alike, never more than the batch a call."""

import numpy as np

from drivesim._batches import batched


def test_rows_and_the_arrays_beside_them_go_a_batch_at_a_time_in_order():
    calls = []

    def step(a, b):
        calls.append(len(a))
        assert len(a) == len(b) and a.flags.c_contiguous and b.flags.c_contiguous
        return a[:, :1] + b[:, None]

    rows, beside = np.arange(14.0).reshape(7, 2), np.arange(7.0) * 10
    out = batched(step, rows[:, ::-1], 3, beside)  # a strided view is made contiguous a chunk at a time
    assert calls == [3, 3, 1]
    assert np.array_equal(out, rows[:, 1:] + beside[:, None])


def test_no_rows_are_handed_to_the_step_for_its_own_error():
    import pytest

    def step(a):
        raise ValueError(f"frames: empty (shape {a.shape})")

    with pytest.raises(ValueError, match=r"frames: empty \(shape \(0, 3\)\)"):
        batched(step, np.zeros((0, 3)), 4)


def test_the_module_docstring_runs():
    import doctest

    import drivesim._batches

    assert doctest.testmod(drivesim._batches).failed == 0
