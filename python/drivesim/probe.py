"""The steering probe (issue 31), shared by the dream's (weights/drivesim_reference/futures.py) and the real
environment's (drivesim.carracing.probe_real): PROBE_STARTS starts evenly spaced over held-out
episodes, each the last of SEEDS consecutive frames; from there PROBE_STEPS steps at the start's
speed with constant steering -x, 0 and +x (x in PROBE_STEER); in the last frame, the road's
centre (the mean column of the road pixels of the top PROBE_ROWS rows). The road moves the right
way where left steering's centre is right of right steering's; the symmetry is (centre at 0 -
centre at +x) / (centre at -x - centre at 0), means over the starts whose three frames all show
road."""

import numpy as np

from . import road

SEEDS, PROBE_STARTS, PROBE_STEPS, PROBE_STEER, PROBE_ROWS = 5, 50, 30, (0.3, 0.6), 60
# Steps after which the road's centre is also read (the figures are at PROBE_STEPS):
# in the real CarRacing, 30 steps (2.4 s) of constant steering spin the car off the road. The
# first three show how the answer builds: the real car's grows with every step (the wheels turn
# at a limited rate, then the heading turns), where a dream's may come late or level off
# (docs/judging.md).
READINGS = (1, 2, 3, 5, 10, PROBE_STEPS)


def starts(data):
    """The first frame of each start's SEEDS frames (the probe steers from the last)."""
    first = data.windows(SEEDS)
    return first[np.linspace(0, len(first) - 1, PROBE_STARTS).astype(int)] if len(first) else first


def centre(frame):
    """The road's centre in the top PROBE_ROWS rows of a uint8 frame, or None without road."""
    return road.centre(frame, PROBE_ROWS)


def symmetry(left, straight, right):
    """The right-way share and the symmetry from the road centres after steering -x, 0 and +x
    from each start (None where a frame shows no road)."""
    seen = [(l, s, r) for l, s, r in zip(left, straight, right) if None not in (l, s, r)]
    right_way = np.mean([l is not None and r is not None and l > r for l, r in zip(left, right)])
    # None where no start shows road in all three frames (or the road never moves left).
    moved_right = float(np.mean([s - r for _, s, r in seen])) if seen else None
    moved_left = float(np.mean([l - s for l, s, _ in seen])) if seen else None
    return dict(right_way=float(right_way), symmetry=moved_right / moved_left if seen and moved_left else None,
                road_moves_px_right_steering=moved_right, road_moves_px_left_steering=moved_left,
                starts_with_road=len(seen))


def against_real(dream, real):
    """The dream's probe (futures.steering_probe) against the real car's on the same starts
    (probe_real): for each number of steps and steering, the right-way share's gap in points
    (dream - real), both symmetries, and the road's moves in the dream as a multiple of the
    real ones, for left and right steering (None where either side saw no road)."""
    def ratio(a, b):
        return a / b if a is not None and b else None

    out = {}
    for steps, by_steer in dream.items():
        out[steps] = {}
        for x, d in by_steer.items():
            r = real[steps][x]
            out[steps][x] = dict(
                right_way_gap_points=100 * (d["right_way"] - r["right_way"]),
                symmetry=d["symmetry"], symmetry_real=r["symmetry"],
                moves_left_steering=ratio(d["road_moves_px_left_steering"], r["road_moves_px_left_steering"]),
                moves_right_steering=ratio(d["road_moves_px_right_steering"], r["road_moves_px_right_steering"]))
    return out
