"""What the models see of gymnasium's CarRacing, and how tracks are named: one implementation
for the recorder (``drivesim.carracing.record``) and the agents.

``observe`` reads the env's surface in place and shrinks it in the extension (``box_shrink``,
Pillow's box filter byte for byte): about 0.2 ms where copying the surface to Pillow takes
10-15 ms; Pillow (``observe_reference``) is its oracle and serves surfaces of other layouts.
"""

import argparse
import contextlib
import math

import numpy as np

from .._drivesim import box_shrink

HEIGHT, WIDTH = 80, 160
# The env draws on a 1000x800 surface (car near (500, 600), dashboard below row 700).
# This 2:1 crop keeps the car and 450 px of road ahead; it shrinks exactly 6.25x to 160x80.
CROP = (0, 150, 1000, 650)


def observe(env) -> np.ndarray:
    """The frame the models see: the env's full-resolution surface from its last step, cropped
    and shrunk to ``(80, 160, 3)`` uint8 (exactly as the training data was recorded). ``env``
    is a CarRacing environment (wrapped or not) that has stepped at least once."""
    surf = getattr(env.unwrapped, "surf", None)
    if surf is None:
        raise ValueError("observe: the env has not drawn a frame yet: call reset() and step() first")
    x0, y0, x1, y1 = CROP
    width, height = surf.get_size()
    if surf.get_pitch() == 4 * width and (x0, x1) == (0, width):
        # The surface's rows in place (whole rows: a contiguous block), 4 bytes a pixel; its
        # byte order from the channels' shifts (little-endian).
        pixels = np.frombuffer(surf.get_buffer(), np.uint8).reshape(height, width, 4)
        channels = [shift // 8 for shift in surf.get_shifts()[:3]]
        return box_shrink(pixels[y0:y1], HEIGHT, WIDTH, channels)
    return observe_reference(surf)


@contextlib.contextmanager
def unseen(env):
    """Steps taken inside draw nothing: the env draws its whole 1000x800 surface at every
    step (two thirds of a drive's time), while an agent deciding every 4 frames looks at one
    frame in 4. Drawing changes nothing in the physics or the reward (tested: the same
    drive, reward for reward); the env's state is the last frame drawn until a step outside
    draws again, and ``observe`` must be called after such a step."""
    car_racing = env.unwrapped
    draw = car_racing._render
    # A copy, as gymnasium's checker asks: no two steps share an observation.
    car_racing._render = lambda *args, **kwargs: None if car_racing.state is None else car_racing.state.copy()
    try:
        yield env
    finally:
        car_racing._render = draw


def decision_steps(env, action, frame_skip):
    """The env stepped ``frame_skip`` times with ``action``, one decision's steps: each step's
    result in turn, only the last step's frame drawn (the one ``observe`` reads next; the
    others ``unseen``). Stop iterating to stop stepping (a finished episode)."""
    for i in range(frame_skip):
        with unseen(env) if i + 1 < frame_skip else contextlib.nullcontext():
            result = env.step(action)
        yield result


def observe_reference(surf) -> np.ndarray:
    """``observe``'s frame by Pillow from a copy of the surface: the reference the fast path is
    tested against (and the path without the package)."""
    import pygame
    from PIL import Image

    rgb = pygame.surfarray.array3d(surf).transpose(1, 0, 2)  # surfarray is (x, y)
    img = Image.fromarray(rgb).crop(CROP).resize((WIDTH, HEIGHT), Image.BOX)
    return np.asarray(img, dtype=np.uint8)


def speed(env) -> float:
    """The speedometer: the car's speed in Box2D units per second (what the models' ``speed``
    action means)."""
    v = env.unwrapped.car.hull.linearVelocity
    return float(math.hypot(v[0], v[1]))


def parse_seeds(text: str) -> list:
    """Track seeds as the command lines take them: '0-3,7' -> [0, 1, 2, 3, 7]."""
    seeds = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        try:
            seeds += list(range(int(lo), int(hi or lo) + 1))
        except ValueError:
            raise argparse.ArgumentTypeError(f"bad seed list {text!r}; use e.g. 0-39 or 1,5,9") from None
    if not seeds:
        raise argparse.ArgumentTypeError("no seeds")
    return seeds
