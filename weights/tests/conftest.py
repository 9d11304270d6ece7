"""What the tests of weights/ share (pytest loads it)."""

import numpy as np
import pytest

from drivesim import episodes


@pytest.fixture
def tiny_episodes(tmp_path):
    """Two episodes of 20 random 16x32 frames and actions: a file `fit` trains on in seconds."""
    rng = np.random.default_rng(7)
    frames = rng.integers(0, 256, (40, 16, 32, 3), dtype=np.uint8)
    actions = rng.normal(size=(40, 2)).astype(np.float32)
    path = tmp_path / "data.safetensors"
    episodes.write(path, episodes.Episodes(frames, actions, np.array([0, 20])), {"source": "test"})
    return path
