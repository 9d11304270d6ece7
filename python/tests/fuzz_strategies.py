"""What test_fuzz.py draws and how it checks each call: hypothesis strategies for arrays of
every dtype, shape, memory layout and value class, for scalars and counts of every kind,
seeds, options and dtypes; `call`, which runs one API call and holds it to the contract (it
succeeds with finite results of the documented shape, or raises one of the documented
exception types) and counts it."""

from __future__ import annotations

import math
import os

import numpy as np
from hypothesis import strategies as st

#: Calls made through `call` in this process (the fuzz's figure).
CALLS = {"n": 0}

DTYPES = [np.uint8, np.float32, np.float32, np.uint8, np.float64, np.float16, np.int8, np.int32, np.int64,
          np.uint16, np.bool_, np.complex64]
LAYOUTS = ["c", "c", "c", "fortran", "strided", "transposed", "broadcast", "readonly", "list", "offset"]
VALUES = ["frame", "frame", "normal", "small", "huge", "max", "nan", "inf", "denormal", "zero", "mixed", "mixed"]
SPECIALS = [np.nan, np.inf, -np.inf, 3.4028235e38, -3.4028235e38, 1e38, 1e-45, -0.0, 2.0, -1.5, 1e300]

FRAME = (80, 160, 3)
Z, H, A = 128, 256, 2


def values(shape, dtype, kind, seed, specials):
    """An array of `shape` and `dtype` filled as the value class `kind` says, with `specials`
    special values (NaN, infinities, the float32 limits, a denormal, ...) put at random places."""
    rng = np.random.default_rng(seed)
    n = math.prod(shape)
    if kind == "frame":
        x = rng.integers(0, 256, n).astype(np.float64) if np.dtype(dtype) == np.uint8 else rng.uniform(-1, 1, n)
    elif kind == "normal":
        x = rng.standard_normal(n) * 30
    elif kind == "small":
        x = rng.standard_normal(n) * 1e-3
    elif kind == "huge":
        x = rng.choice([-1.0, 1.0], n) * 10.0 ** rng.uniform(20, 38.5, n)
    elif kind == "max":
        x = np.full(n, 3.4028235e38) * rng.choice([-1.0, 1.0], n)
    elif kind == "nan":
        x = np.full(n, np.nan)
    elif kind == "inf":
        x = np.full(n, np.inf) * rng.choice([-1.0, 1.0], n)
    elif kind == "denormal":
        x = rng.choice([1e-45, -1e-45, 1e-40, 0.0], n)
    elif kind == "zero":
        x = np.zeros(n)
    else:  # "mixed": plausible values with more specials
        x, specials = rng.uniform(-1, 1, n) * 30, specials + 2
    if n:
        for i in rng.integers(0, n, specials):
            x[i] = SPECIALS[int(rng.integers(len(SPECIALS)))]
    with np.errstate(all="ignore"):
        return x.astype(dtype).reshape(shape)


def lay_out(a, layout):
    """`a`'s values in another memory layout (or as a list)."""
    if layout == "fortran":
        return np.asfortranarray(a)
    if layout == "strided" and a.ndim:
        wide = np.repeat(a, 2, axis=-1)
        return wide[..., ::2]
    if layout == "transposed" and a.ndim > 1:
        return np.ascontiguousarray(a.T).T
    if layout == "broadcast" and a.ndim and a.size:
        return np.broadcast_to(a[..., :1], a.shape)
    if layout == "readonly":
        a = a.copy()
        a.setflags(write=False)
        return a
    if layout == "list" and a.size <= 4096:
        return a.tolist()
    if layout == "offset" and a.size:
        # A C-ordered view that does not start at its buffer's start.
        return np.concatenate([a.ravel()[:1], a.ravel()])[1:].reshape(a.shape)
    return a


def near(shape):
    """Shapes near `shape`: itself, or one dimension off by one, one more or one fewer."""
    shape = tuple(shape)
    options = [st.just(shape)]
    if shape:
        i = st.integers(0, len(shape) - 1)
        options.append(i.flatmap(lambda k: st.sampled_from([-1, 1]).map(
            lambda d: shape[:k] + (max(shape[k] + d, 0),) + shape[k + 1:])))
        options.append(st.just(shape[1:]))
    options.append(st.just(shape + (1,)))
    return st.one_of(*options)


def items(tail, most=3):
    """Shapes of items: `tail` alone, or `(n, *tail)` with n from 0 to `most`, or near those."""
    return st.one_of(st.just(tuple(tail)), st.integers(0, most).map(lambda n: (n, *tail))).flatmap(
        lambda s: st.one_of(st.just(s), st.just(s), near(s)))


@st.composite
def arrays(draw, shapes, dtypes=None):
    """An input array: a shape from `shapes`, any dtype (mostly float32 and uint8), layout and
    value class."""
    shape = draw(shapes)
    dtype = draw(st.sampled_from(dtypes or DTYPES))
    kind, layout = draw(st.sampled_from(VALUES)), draw(st.sampled_from(LAYOUTS))
    seed, specials = draw(st.integers(0, 2**32 - 1)), draw(st.sampled_from([0, 0, 0, 1, 3]))
    return lay_out(values(shape, dtype, kind, seed, specials), layout)


def valid(shape, kind="frame", dtype=np.float32, seed=0):
    """A valid C-ordered array (the arguments a call's other positions get)."""
    return values(shape, dtype, kind, seed, 0) + (np.float32([30.0, 0.0]) if shape[-1:] == (2,) and kind == "action" else 0)


ODD = [None, "3", b"3", [], [1], (), {}, object(), 1 + 2j, np.array([1.0, 2.0]), np.array(2.0), True, False]

#: Numbers of every kind: floats (NaN, infinities, denormals), ints beyond any C type, numpy scalars.
numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(-100, 100),
    st.integers(-(2**70), 2**70),
    st.sampled_from([10**400, -(10**400), np.float32(np.nan), np.float64(1e308), np.float32(3e38), np.int64(5),
                     np.uint64(2**64 - 1), 5e-324]),
    st.sampled_from(ODD),
)

#: Counts (batch, threads, drives, ...): small valid ones, 0, negatives, far too large, and non-integers.
counts = st.one_of(
    st.integers(1, 3), st.integers(-3, 0), st.sampled_from([2**40, 2**63, 2**64, 2**70, -(2**64), 1025, 2**32]),
    st.sampled_from([np.int64(2), np.uint8(1), np.int32(-1), 2.0, float("nan"), "2", None, [2], 1 + 0j]),
)

#: Gymnasium seeds: None, integers, numpy integers, sequences, and what is none of these.
seeds = st.one_of(
    st.none(), st.integers(0, 2**64 + 5), st.integers(-(2**65), -1),
    st.sampled_from([np.int64(4), np.uint64(7), np.int32(-2), 4.0, "4", [], [3], [3, 4], (5,), np.array([1, 2]),
                     np.array([], np.int64), True, [-1], ["a"], {}, b"x"]),
)

#: The `dtype` argument of the calls that return frames.
frame_dtypes = st.sampled_from([None, np.uint8, np.float32, "uint8", "float32", "f4", np.float64, np.int64, "float64",
                                "nonsense", 3, object(), [1], np.dtype("u1")])

bools = st.sampled_from([False, True, np.bool_(True), 0, 1, None, "yes"])


def finite(x):
    """Whether every number in `x` (arrays, tuples, lists, dicts, scalars) is finite."""
    if isinstance(x, np.ndarray):
        return x.dtype.kind not in "fc" or bool(np.isfinite(x).all())
    if isinstance(x, (tuple, list)):
        return all(finite(v) for v in x)
    if isinstance(x, dict):
        return all(finite(v) for v in x.values())
    if isinstance(x, (float, np.floating, complex)):
        return bool(np.isfinite(x))
    return True


def call(fn, *args, raises=(ValueError, TypeError, MemoryError), shape=None, **kwargs):
    """Runs `fn(*args, **kwargs)`: a success must give finite results (of `shape`, when given:
    the result's shape, or a function of the result that returns True); an exception must be
    one of `raises` (anything else, a PanicException included, fails the test). Returns the
    result, or None when the call raised."""
    CALLS["n"] += 1
    try:
        out = fn(*args, **kwargs)
    except raises:
        return None
    assert finite(out), f"non-finite result of {getattr(fn, '__qualname__', fn)}"
    if shape is not None:
        ok = shape(out) if callable(shape) else getattr(out, "shape", None) == tuple(shape)
        assert ok, f"{getattr(fn, '__qualname__', fn)}: unexpected result shape {getattr(out, 'shape', out)}"
    return out


def lead(a, tail):
    """The leading dimensions of `a` when it could be a valid input ending in `tail`."""
    shape = np.shape(a) if isinstance(a, np.ndarray) else None
    return None if shape is None or shape[len(shape) - len(tail):] != tuple(tail) else shape[: len(shape) - len(tail)]


def report(path=None):
    """Writes the count of calls (to `DRIVESIM_FUZZ_REPORT`, when set)."""
    path = path or os.environ.get("DRIVESIM_FUZZ_REPORT")
    if path:
        with open(path, "w") as f:
            f.write(f"{CALLS['n']}\n")
