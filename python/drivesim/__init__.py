"""drivesim: comma.ai's learned driving simulator on the CPU, from Python.

The networks run in the Rust crate (hand-written SIMD kernels, fixed memory); this package
gives them numpy arrays:

- ``Model.load(path=None, driver=None)``: a weight file, or the built-in default model (with
  ``driver``, a driver file's policy in place of its own: ``drivesim.driver``); ``Model.dreamt()``:
  the default driven by the built-in driver learnt in its dream;
- ``Simulator(model, batch=1, threads=1)``: ``encode``, ``generate``, ``transition``,
  ``transition_fed_back``, ``rollout`` and ``rollout_candidates``;
- ``Environment(model, drives, candidates, threads)``: dreamed drives a controller steps;
- ``DreamEnv`` and ``DreamVectorEnv``: the dream as gymnasium environments
  (``gymnasium.make("drivesim/Dream-v0")``);
- ``drivesim.carracing``: the bridge to gymnasium's real CarRacing (``observe`` and the agents).

>>> import numpy as np, drivesim
>>> sim = drivesim.Simulator(drivesim.Model.load())
>>> frames, actions = drivesim.load_episodes()[0]   # the built-in seed clip
>>> codes = sim.rollout(frames[:5], actions[:4 + 10])  # 5 seed frames, then 10 dreamed steps
>>> codes.shape
(10, 128)
"""

from ._drivesim import Environment, Model, Simulator, __version__, load_episodes
from .dream import DreamEnv, DreamVectorEnv, action_bounds
from .road import RoadCost

__all__ = [
    "Environment",
    "Model",
    "Simulator",
    "load_episodes",
    "DreamEnv",
    "DreamVectorEnv",
    "RoadCost",
    "action_bounds",
    "__version__",
]


def _register():
    import gymnasium

    if "drivesim/Dream-v0" not in gymnasium.registry:
        gymnasium.register(id="drivesim/Dream-v0", entry_point="drivesim.dream:DreamEnv")


_register()
