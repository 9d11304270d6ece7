"""`observe`'s fast path: the extension's `box_shrink` against Pillow's box filter, its oracle."""

import os

import numpy as np
import pytest
from PIL import Image

from drivesim._drivesim import box_shrink
from drivesim.carracing import view


@pytest.mark.parametrize("shape, size", [
    ((500, 1000, 4), (80, 160)),  # CarRacing's view: 6.25x
    ((37, 53, 4), (5, 7)),  # odd sizes, uneven windows
    ((19, 23, 3), (19, 7)),  # one axis kept
    ((64, 64, 4), (1, 1)),  # one window of 4096 pixels (past the 16-bit lanes)
    ((9, 301, 4), (3, 1)),  # a window of 301 pixels in a row (past 257)
    ((30, 40, 3), (7, 9)),
])
def test_box_shrink_is_pillows_box_filter(shape, size):
    rng = np.random.default_rng(sum(shape))
    image = rng.integers(0, 256, shape, dtype=np.uint8)
    image[: shape[0] // 3] = 255  # saturated areas: the rounding's upper end
    height, width = size
    # Pillow shrinks RGBA premultiplied by alpha: the oracle is RGB, and "L" for a 4th channel.
    expected = np.asarray(Image.fromarray(image[:, :, :3].copy(), "RGB").resize((width, height), Image.BOX))
    if shape[2] == 4:
        alpha = Image.fromarray(image[:, :, 3].copy(), "L").resize((width, height), Image.BOX)
        expected = np.concatenate([expected, np.asarray(alpha)[:, :, None]], axis=2)
    channels = list(range(shape[2]))
    np.testing.assert_array_equal(box_shrink(image, height, width, channels), expected)
    # Channels picked and reordered, as the surface's byte order asks.
    np.testing.assert_array_equal(box_shrink(image, height, width, [2, 1, 0]), expected[:, :, [2, 1, 0]])


def test_observe_is_byte_identical_to_the_pillow_reference():
    pytest.importorskip("Box2D")
    import gymnasium

    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    env = gymnasium.make("CarRacing-v3", domain_randomize=True)
    env.reset(seed=3)
    for i in range(120):
        env.step(np.float32([0.6 * np.sin(i / 9), 0.5, 0.0]))
        if i % 8 == 0:  # (the env draws each frame on a new surface)
            np.testing.assert_array_equal(view.observe(env), view.observe_reference(env.unwrapped.surf))
            assert not env.unwrapped.surf.get_locked()  # the buffer released: drawing can go on
    env.close()


@pytest.mark.parametrize("args, message", [
    ((np.zeros((10, 10, 4), np.float32), 5, 5, [0]), "uint8"),
    ((np.zeros((10, 10), np.uint8), 5, 5, [0]), r"\(H, W, C\)"),
    ((np.zeros((10, 10, 4), np.uint8), 11, 5, [0]), "at most the image's"),
    ((np.zeros((10, 10, 4), np.uint8), 0, 5, [0]), "positive"),
    ((np.zeros((10, 10, 4), np.uint8), 5, 5, [4]), "channels"),
    ((np.zeros((10, 10, 4), np.uint8), 5, 5, []), "channels"),
    ((np.zeros((10, 10, 4), np.uint8)[:, ::2], 5, 5, [0]), "C-ordered"),
    ((np.zeros((1, (1 << 22) + 1, 1), np.uint8), 1, 1, [0]), "at most 4194304 pixels a side"),
])
def test_box_shrink_rejects_bad_input(args, message):
    with pytest.raises(ValueError, match=message):
        box_shrink(*args)


def test_steps_unseen_draw_nothing_and_change_nothing():
    pytest.importorskip("Box2D")
    import contextlib

    import gymnasium

    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    runs = []
    for skip_drawing in (False, True):
        env = gymnasium.make("CarRacing-v3")
        env.reset(seed=5)
        frames, rewards = [], []
        for i in range(160):
            unseen = view.unseen(env) if skip_drawing and i % 4 != 3 else contextlib.nullcontext()
            with unseen:
                _, reward, _, _, _ = env.step(np.float32([0.4 * np.sin(i / 11), 0.6, 0.0]))
            rewards.append(reward)
            if i % 4 == 3:
                frames.append(view.observe(env))
        drawn = env.unwrapped._render
        env.close()
        runs.append((np.array(frames), np.array(rewards)))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])  # every seen frame, byte for byte
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    assert drawn.__name__ == "_render"  # the env's own drawing is back after the block
