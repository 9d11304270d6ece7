import os

import numpy as np
import pytest

import drivesim

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


@pytest.fixture(scope="session")
def model():
    return drivesim.Model.load()


@pytest.fixture(scope="session")
def clip():
    """The built-in seed clip's first episode: (frames (T, 80, 160, 3) uint8, actions (T, 2))."""
    return drivesim.load_episodes()[0]


def fixture(name):
    return os.path.join(REPO, "tests", "fixtures", name)


def relative_error(found, expected):
    return float(np.abs(found - expected).max() / np.abs(expected).max())
