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


def measure(frames: np.ndarray) -> np.ndarray:
    """Road figures of uint8 frames ``(N, 80, 160, 3)``: ``(N, 4)`` float32, the offsets of the
    road's centre in the near, middle and far bands (pixels; where a band shows no road, the
    offset is +-width/2 on the side of the frame's edge nearer the last road seen, or 0) and the
    share of the car's columns over road just ahead of it (0 to 1)."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames: expected uint8 (N, H, W, 3), got {frames.dtype} {frames.shape}")
    n, h, w, _ = frames.shape
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

    ``RoadCost.default()`` is the one fitted for the built-in default model (shipped with the
    package); ``RoadCost.fit(codes, figures)`` fits one for any model, e.g. on the codes and
    measured figures of recorded frames (``python -m drivesim.road --help``).
    """

    def __init__(self, weight: np.ndarray, bias: np.ndarray):
        self.weight = np.ascontiguousarray(weight, dtype=np.float32)  # (z_dim, 4)
        self.bias = np.ascontiguousarray(bias, dtype=np.float32)  # (4,)
        if self.weight.ndim != 2 or self.bias.shape != (self.weight.shape[1],):
            raise ValueError(f"RoadCost: weight (z_dim, k) and bias (k,), got {self.weight.shape} and {self.bias.shape}")

    @classmethod
    def fit(cls, codes: np.ndarray, figures: np.ndarray, ridge: float = 1e-2) -> "RoadCost":
        """Ridge least squares from ``codes`` ``(N, z_dim)`` to ``figures`` ``(N, k)``."""
        x = np.asarray(codes, np.float64)
        y = np.asarray(figures, np.float64)
        if x.ndim != 2 or y.ndim != 2 or len(x) != len(y) or len(x) < 2:
            raise ValueError(f"fit: codes (N, z_dim) and figures (N, k) with N >= 2, got {x.shape} and {y.shape}")
        mean_x, mean_y = x.mean(axis=0), y.mean(axis=0)
        xc, yc = x - mean_x, y - mean_y
        gram = xc.T @ xc + ridge * len(x) * np.eye(x.shape[1])
        weight = np.linalg.solve(gram, xc.T @ yc)
        return cls(weight, mean_y - mean_x @ weight)

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
        """The road figures of codes ``(..., z_dim)``: ``(..., 4)`` float32."""
        return np.asarray(codes, np.float32) @ self.weight + self.bias
