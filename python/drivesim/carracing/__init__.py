"""The bridge to gymnasium's real CarRacing: what the models see (``observe``, ``speed``) and
agents that drive it from that alone (``make_agent``). ``python -m drivesim.carracing`` scores
an agent with the env's own reward.

>>> import gymnasium, numpy as np
>>> from drivesim import carracing
>>> env = gymnasium.make("CarRacing-v3")
>>> agent = carracing.make_agent("mpc")
>>> _ = env.reset(seed=0)
>>> action = np.zeros(3, np.float32)
>>> for _ in range(20):
...     for _ in range(agent.frame_skip):
...         _, reward, terminated, truncated, _ = env.step(action)
...     action = agent.act(carracing.observe(env), carracing.speed(env))
"""

from .agents import MPCAgent, make_agent, speed_control
from .view import observe, speed

__all__ = ["observe", "speed", "make_agent", "MPCAgent", "speed_control"]
