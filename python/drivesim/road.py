"""The road in the models' view, measured on frames and predicted from codes.

In the 80x160 view the car sits at the bottom centre (column 80, around row 72) and the road
ahead runs up the frame: grey pixels whose channels agree, against green grass. ``measure``
reads, in three bands of rows ahead of the car (near, middle, far), the road's centre minus
the car's column in pixels (positive: the road is to the right), and whether road lies under
the car. ``RoadCost`` maps a latent code to the same figures linearly (ridge least squares
fitted on measured frames), so that a planner can score dreamed futures from codes alone,
without generating a frame.
"""

from __future__ import annotations

import os

import numpy as np

from . import _checks
from ._batches import batched

# Rows of each band in an 80-row frame (near to far) and the car's column.
BANDS = ((50, 60), (36, 46), (22, 32))
CAR_ROWS = (62, 70)
FIGURES = ("near", "middle", "far", "on_road")


def road_mask(frames: np.ndarray) -> np.ndarray:
    """Road pixels of uint8 frames ``(..., H, W, 3)``: grey (channels within 25 of each
    other), neither dark nor bright (kerbs and markings are excluded). Returns bool ``(..., H, W)``."""
    f = frames.astype(np.int16)
    hi, lo = f.max(axis=-1), f.min(axis=-1)
    return (hi - lo < 25) & (hi > 60) & (hi < 170)


def centre(frame: np.ndarray, rows: int = 60) -> float | None:
    """The mean column of the road pixels in the top ``rows`` rows of one uint8 frame
    ``(H, W, 3)``, or None where they show no road: the steering probe's road centre
    (``weights/drivesim_reference/futures.py``)."""
    xs = np.nonzero(road_mask(frame[:rows]))[1]
    return float(xs.mean()) if len(xs) else None


def measure(frames: np.ndarray) -> np.ndarray:
    """Road figures of uint8 frames ``(N, 80, 160, 3)``: ``(N, 4)`` float32, the offsets of the
    road's centre in the near, middle and far bands (pixels; where a band shows no road, the
    offset is +-width/2 on the side of the frame's edge nearer the last road seen, or 0) and the
    share of the car's columns over road just ahead of it (0 to 1)."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames: expected uint8 (N, H, W, 3), got {frames.dtype} {frames.shape}")
    n, h, w, _ = frames.shape
    if h < 10 or w < 8:
        # Fewer and the rows under the car (scaled from 80) would be none: no share to give.
        raise ValueError(f"frames: expected at least 10 rows and 8 columns, got {frames.shape}")
    mask = road_mask(frames)
    cols = np.arange(w, dtype=np.float32) - w / 2
    out = np.zeros((n, 4), np.float32)
    for b, (r0, r1) in enumerate(BANDS):
        r0, r1 = r0 * h // 80, r1 * h // 80
        band = mask[:, r0:r1, :].sum(axis=1).astype(np.float32)  # (N, W) road rows per column
        count = band.sum(axis=1)
        centre = (band * cols).sum(axis=1) / np.maximum(count, 1)
        out[:, b] = np.where(count > 0, centre, np.nan)
    # A band without road: as far out as the frame goes on the side the nearer band saw.
    for b in range(len(BANDS)):
        prev = out[:, b - 1] if b else np.zeros(n, np.float32)
        out[:, b] = np.where(np.isnan(out[:, b]), np.sign(prev) * w / 2, out[:, b])
    c0, c1 = CAR_ROWS[0] * h // 80, CAR_ROWS[1] * h // 80
    under = mask[:, c0:c1, w // 2 - 4 : w // 2 + 4]
    out[:, 3] = under.mean(axis=(1, 2))
    return out


class RoadCost:
    """A linear map from latent codes to the road figures of ``measure``: ``predict(z)`` gives
    ``(..., 4)`` (near, middle, far offsets in pixels; the share of road under the car).
    ``weight`` ``(z_dim, k)`` and ``bias`` ``(k,)`` must be finite (ValueError otherwise).

    ``RoadCost.default()`` is the one fitted for the built-in default model (shipped with the
    package); ``RoadCost.fit(codes, figures)`` fits one for any model, e.g. on the codes and
    measured figures of recorded frames (``python -m drivesim.road --help``).
    """

    def __init__(self, weight: np.ndarray, bias: np.ndarray):
        self.weight = np.ascontiguousarray(weight, dtype=np.float32)  # (z_dim, 4)
        self.bias = np.ascontiguousarray(bias, dtype=np.float32)  # (4,)
        if self.weight.ndim != 2 or self.bias.shape != (self.weight.shape[1],):
            raise ValueError(f"RoadCost: weight (z_dim, k) and bias (k,), got {self.weight.shape} and {self.bias.shape}")
        if not (np.isfinite(self.weight).all() and np.isfinite(self.bias).all()):
            raise ValueError("RoadCost: weight and bias must be finite")

    @classmethod
    def fit(cls, codes: np.ndarray, figures: np.ndarray, ridge: float = 1e-2) -> "RoadCost":
        """Ridge least squares from ``codes`` ``(N, z_dim)`` to ``figures`` ``(N, k)``, finite,
        with ``ridge`` finite and > 0 (ValueError otherwise, or where the fit overflows)."""
        x, y = _checks.floats("codes", codes), _checks.floats("figures", figures)
        if x.ndim != 2 or y.ndim != 2 or len(x) != len(y) or len(x) < 2:
            raise ValueError(f"fit: codes (N, z_dim) and figures (N, k) with N >= 2, got {x.shape} and {y.shape}")
        if not (np.isfinite(x).all() and np.isfinite(y).all()):
            raise ValueError("fit: codes and figures must be finite")
        ridge = _checks.number("ridge", ridge)
        if not ridge > 0:
            raise ValueError(f"fit: ridge is {ridge}: expected a finite number > 0")
        mean_x, mean_y = x.mean(axis=0), y.mean(axis=0)
        xc, yc = x - mean_x, y - mean_y
        gram = xc.T @ xc + ridge * len(x) * np.eye(x.shape[1])
        with np.errstate(all="ignore"):
            weight = np.linalg.solve(gram, xc.T @ yc)
            bias = mean_y - mean_x @ weight
            if not (np.isfinite(weight.astype(np.float32)).all() and np.isfinite(bias.astype(np.float32)).all()):
                raise ValueError("fit: the fitted weights overflow float32 (scale the codes or figures down)")
        return cls(weight, bias)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "RoadCost":
        """Reads a cost saved by ``save`` (an ``.npz`` with ``weight`` and ``bias``)."""
        with np.load(path) as data:
            return cls(data["weight"], data["bias"])

    @classmethod
    def default(cls) -> "RoadCost":
        """The cost fitted for the built-in default model."""
        return cls.load(os.path.join(os.path.dirname(__file__), "data", "road_default.npz"))

    def save(self, path: str | os.PathLike) -> None:
        """Writes ``weight`` and ``bias`` to an ``.npz`` file, atomically (a temporary file in
        the same directory, flushed, then renamed over ``path``)."""
        from ._files import atomic_write

        with atomic_write(path) as f:
            np.savez(f, weight=self.weight, bias=self.bias)

    def predict(self, codes: np.ndarray) -> np.ndarray:
        """The road figures of codes ``(..., z_dim)``: ``(..., 4)`` float32. Each code's figures
        are summed in one order whatever the batch (no BLAS), so that a drive gets the same
        bits in a vector environment as alone. ValueError for codes of another shape, not
        finite, or so large that the figures overflow float32 (no result is ever NaN or
        infinite)."""
        codes = _checks.floats("codes", codes, np.float32)
        with np.errstate(all="ignore"):
            if codes.ndim < 1 or codes.shape[-1] != self.weight.shape[0]:
                raise ValueError(f"codes: expected shape (..., {self.weight.shape[0]}), got {codes.shape}")
            out = (codes[..., :, None] * self.weight).sum(axis=-2) + self.bias
        if not np.isfinite(out).all():
            if not np.isfinite(codes).all():
                raise ValueError("codes: not finite (NaN or infinite)")
            raise ValueError("codes: too large: their road figures overflow float32")
        return out


def samples(sim, episodes, dream_steps: int = 8, every: int = 4, seeds: int = 5, rng=None):
    """Codes and measured road figures to fit a ``RoadCost`` on: every frame of ``episodes``
    (encoded), and the frames the model dreams ``dream_steps`` steps on from every ``every``-th
    frame under the recorded actions with their steering perturbed (generated, measured, and
    their predicted codes), so that the cost is fitted where a planner reads it: on dreamed
    codes. Returns ``(codes (N, z_dim), figures (N, 4))``."""
    rng = rng or np.random.default_rng(0)
    codes, figures = [], []
    for frames, actions in episodes:
        codes.append(batched(sim.encode, frames, sim.batch))
        figures.append(measure(frames))
        for t in range(seeds, len(frames) - dream_steps - seeds, every):
            plan = actions[t - seeds : t - 1 + dream_steps].copy()
            plan[seeds - 1 :, 1] = np.clip(plan[seeds - 1 :, 1] + rng.normal(0, 0.5), -1, 1)
            z, dreamed = sim.rollout(frames[t - seeds : t], plan, frames=True)
            codes.append(z)
            figures.append(measure(dreamed))
    return np.concatenate(codes), np.concatenate(figures)


def main(argv=None):
    import argparse

    from ._drivesim import Model, Simulator, load_episodes

    p = argparse.ArgumentParser(prog="python -m drivesim.road", description="Fit a RoadCost for a model on recorded episodes.")
    p.add_argument("--episodes", required=True, help="episodes file to fit on (python -m drivesim record writes them)")
    p.add_argument("--heldout", help="episodes file to report the fit's R^2 on")
    p.add_argument("--weights", help="weight file (default: the built-in model)")
    p.add_argument("--out", required=True, help="where to write the cost (.npz)")
    p.add_argument("--dream-steps", type=int, default=8, help="dreamed steps measured after each start")
    args = p.parse_args(argv)
    sim = Simulator(Model.load(args.weights), batch=16)
    codes, figures = samples(sim, load_episodes(args.episodes), args.dream_steps)
    cost = RoadCost.fit(codes, figures)
    print(f"fitted on {len(codes)} codes: R^2 {np.round(r_squared(cost, codes, figures), 3)} ({', '.join(FIGURES)})")
    if args.heldout:
        codes, figures = samples(sim, load_episodes(args.heldout), args.dream_steps)
        print(f"held out, {len(codes)} codes: R^2 {np.round(r_squared(cost, codes, figures), 3)}")
    cost.save(args.out)
    print(f"wrote {args.out}")


def r_squared(cost: RoadCost, codes: np.ndarray, figures: np.ndarray) -> np.ndarray:
    """The share of each figure's variance that ``cost`` explains on ``codes``."""
    residual = ((cost.predict(codes) - figures) ** 2).mean(axis=0)
    return 1 - residual / np.maximum(figures.var(axis=0), 1e-12)


if __name__ == "__main__":
    main()
