"""The `expert` driver: a privileged racing-pace teacher for CarRacing (see drivesim.carracing.record).

It reads what no agent may: the track's centre line, the car's position, velocity and wheel
speeds. Before the first step it plans a speed profile along the whole lap, the way a racing
line's speed is planned: each point's cornering limit from the curvature there
(``v = sqrt(LATERAL_ACCEL / curvature)``), then a backward pass so that the car can brake from
every speed to the next point's limit (``v_i^2 <= v_{i+1}^2 + 2 BRAKE_ACCEL ds``). At each
decision it steers by pure pursuit on the centre line (so that the wheels touch every tile: a
skipped tile never ends the lap) with a look-ahead that grows with speed, measured from the
car's velocity rather than its body and with the wheels turned by part of the slip angle (a
countersteer as soon as the rear steps out); and it drives to the profile's slowest speed
before the next decision: gas below it, less while the rear wheels spin, the car slides or the
wheels are turned, and braking above it, capped well below 0.9, where the env locks the wheels.

The same ``act(car, frame_seconds)`` as record.Driver's styles, so that it is recorded and
scored like them; it draws no random numbers (the rng is accepted for the common signature).
"""

import math

import numpy as np
from gymnasium.envs.box2d import car_racing

HALF_ROAD = car_racing.TRACK_WIDTH  # centre line to edge, world units
TOP_SPEED = 95.0  # units/s: the profile's cap on straights
LATERAL_ACCEL = 180.0  # units/s^2 the car corners at on the road without sliding away
BRAKE_ACCEL = 70.0  # units/s^2 the profile asks of the brakes (braking below wheel lock)
WHEELBASE = 3.24  # units between the axles (car_dynamics: wheels at y = +80 and -82, x 0.02)
MAX_WHEEL_ANGLE = 0.4  # radians: the front wheels' joint limit
LOOKAHEAD = 5.0  # units: the pursuit's look-ahead at rest
LOOKAHEAD_SECONDS = 0.32  # and its growth with speed
COUNTERSTEER = 0.5  # wheel angle per radian of slip
SLIDE = 0.3  # radians of slip at which the gas is cut to the minimum
TURN_GAS = 0.5  # the share of gas taken off at full lock


class CentreLine:
    """The track's centre line as the privileged drivers read it (record.Driver's styles and
    the expert): points, segment lengths, left normals, headings, and where the car is on it."""

    def __init__(self, track):
        self.centre = np.array([(x, y) for _, _, x, y in track], dtype=np.float64)
        seg = np.roll(self.centre, -1, axis=0) - self.centre
        self.seg_len = np.linalg.norm(seg, axis=1)
        tangent = seg / self.seg_len[:, None]
        self.left = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
        self.heading = np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0]))
        self.i = None

    def nearest(self, pos):
        """The centre-line point nearest the car, searched near the last one so that laps and
        close hairpins do not confuse it; and the distance to it."""
        d = np.linalg.norm(self.centre - pos, axis=1)
        if self.i is not None:
            window = (self.i + np.arange(-10, 40)) % len(self.centre)
            self.i = int(window[np.argmin(d[window])])
        else:
            self.i = int(np.argmin(d))
        return self.i, d[self.i]

    def ahead(self, i, distance):
        """The index of the centre-line point `distance` units of track past point `i`."""
        n, j, run = len(self.centre), i, 0.0
        while run < distance:
            run += self.seg_len[j % n]
            j += 1
        return j % n


class Expert(CentreLine):
    """Pure pursuit on the centre line with a speed profile planned from its curvature."""

    def __init__(self, track, rng=None, style="expert", top_speed=TOP_SPEED):
        super().__init__(track)
        self.curvature = _curvature(self.heading, self.seg_len)
        self.profile = _speed_profile(self.curvature, self.seg_len, top_speed)
        self.style = style
        self.off_centre, self.target = 0.0, 0.0

    def act(self, car, frame_seconds):
        """``([steer, gas, brake] float32, speed, distance from the centre line)``."""
        pos = np.array(car.hull.position)
        vel = np.array(car.hull.linearVelocity)
        speed = float(np.linalg.norm(vel))
        i, off_centre = self.nearest(pos)
        self.off_centre = off_centre / HALF_ROAD

        # Speed: the profile's slowest point between here and where the car will be after the
        # next decision and a little more (the brakes take effect over a decision).
        reach = self.ahead(i, speed * frame_seconds * 2.0 + 2.0)
        span = (np.arange(i, i + (reach - i) % len(self.centre) + 1)) % len(self.centre)
        target = float(self.profile[span].min())
        self.target = target  # the speed it drives to now: DAgger's speed label

        # Steering: pure pursuit on the centre line. (Aiming at the inside of bends was measured
        # slower: the wheels leave tiles behind, or the car runs wide on the way out.)
        lookahead = LOOKAHEAD + LOOKAHEAD_SECONDS * speed
        aim = self.centre[self.ahead(i, lookahead)]
        forward = np.array([-math.sin(car.hull.angle), math.cos(car.hull.angle)])
        left = np.array([-forward[1], forward[0]])
        # Steer along the velocity, not the body: the angle to the aim point is measured from
        # where the car is going, and the wheels also turn by the slip angle (the angle between
        # body and velocity), which countersteers as soon as the rear steps out.
        slip_angle = math.atan2(float(vel @ left), float(vel @ forward)) if speed > 5.0 else 0.0
        to = aim - pos
        alpha = math.atan2(float(to @ left), float(to @ forward)) - slip_angle
        alpha = math.remainder(alpha, 2 * math.pi)
        wheel = math.atan2(2.0 * WHEELBASE * math.sin(alpha), max(float(np.linalg.norm(to)), 1.0))
        wheel += COUNTERSTEER * slip_angle
        steer = float(np.clip(-wheel / MAX_WHEEL_ANGLE, -1.0, 1.0))  # env: -1 steers left

        rear_spin = np.mean([w.omega * w.wheel_rad for w in car.wheels[2:4]])
        wheelspin = rear_spin - float(vel @ forward)  # the rear wheels' speed past the car's
        if speed < target:
            gas = float(np.clip(0.15 * (target - speed) + 0.2, 0.0, 1.0))
            # Traction: less gas while the wheels spin, the car slides or the wheels are turned.
            grip = 1.0 - min(abs(slip_angle) / SLIDE, 1.0) - min(abs(wheel) / MAX_WHEEL_ANGLE, 1.0) * TURN_GAS
            gas *= max(grip, 0.1) * (0.3 if wheelspin > 5.0 else 1.0)
            brake = 0.0
        else:
            gas = 0.0
            brake = float(np.clip(0.06 * (speed - target), 0.0, 0.8))
        return np.array([steer, gas, brake], dtype=np.float32), speed, off_centre


def _curvature(heading, seg_len, half_window=2):
    """Signed curvature (radians per unit, positive turning left) at each centre-line point,
    from the heading change over `half_window` segments either side."""
    n = len(heading)
    # Unwrapped headings wind by 2*pi a lap: extend with that turn so the ends join.
    turn = heading[-1] - heading[0] + math.remainder(heading[0] - heading[-1], 2 * math.pi)
    ext = np.concatenate([heading[-half_window:] - turn, heading, heading[:half_window] + turn])
    dh = ext[2 * half_window:] - ext[: n]
    lengths = np.convolve(np.concatenate([seg_len[-half_window:], seg_len, seg_len[:half_window]]),
                          np.ones(2 * half_window), mode="valid")[:n]
    return dh / lengths


def _speed_profile(curvature, seg_len, top_speed=TOP_SPEED):
    """The fastest speed at each point, at most ``top_speed``, that corners within LATERAL_ACCEL
    and can brake to every later point's speed within BRAKE_ACCEL (two backward passes: the lap
    is a loop)."""
    limit = np.minimum(top_speed, np.sqrt(LATERAL_ACCEL / np.maximum(np.abs(curvature), 1e-6)))
    v = limit.copy()
    n = len(v)
    for _ in range(2):
        for i in range(n - 1, -1, -1):
            nxt = v[(i + 1) % n]
            v[i] = min(limit[i], math.sqrt(nxt * nxt + 2.0 * BRAKE_ACCEL * seg_len[i]))
    return v


class ExpertHolds(Expert):
    """The expert at racing pace with holds (`record --driver expert-holds`): after 1 to 3 s of its
    own driving, back within half a half-road of the centre line, a constant steering of 0.05 to
    0.3 either way for 0.2 to 0.5 s, whatever the road does, its speed rule going on; then it
    recovers. The slow `holds` recordings (15-45 units/s) teach a world what steering does where
    the car has grip to spare; these show it at the clone's speeds and above, where a hold of 0.1
    takes the car off the road in about half a second and a hard one spins it."""

    def __init__(self, track, rng, style="expert-holds"):
        super().__init__(track, rng, style)
        self.rng = rng
        self.hold_steer, self.hold_left, self.free_left = 0.0, 0.0, float(rng.uniform(1.0, 3.0))

    def act(self, car, frame_seconds):
        action, speed, off_centre = super().act(car, frame_seconds)
        if self.hold_left > 0:
            self.hold_left -= frame_seconds
            action[0] = self.hold_steer
        elif self.free_left > 0 or self.off_centre > 0.5:
            self.free_left -= frame_seconds  # the expert's own driving, and its recovery
        else:
            self.hold_steer = float(self.rng.choice([-1, 1]) * self.rng.uniform(0.05, 0.3))
            self.hold_left = float(self.rng.uniform(0.2, 0.5)) - frame_seconds
            self.free_left = float(self.rng.uniform(1.0, 3.0))
            action[0] = self.hold_steer
        return action, speed, off_centre


class ExpertSpeeds(Expert):
    """The expert at the wrong speeds (`record --driver expert-speeds`): its speed profile, the
    whole of it, times a factor of 0.6 to 1.7 drawn again every 1 to 3 s, its steering its own.
    The expert's recordings take every bend at the one speed it plans for it, so a world learnt
    on them cannot tell what speed does in a bend; these take bends of every kind slower and
    faster than the grip allows, and show the slides, spins and recoveries of the fast ones."""

    SCALES = (0.6, 1.7)
    SECONDS = (1.0, 3.0)

    def __init__(self, track, rng, style="expert-speeds"):
        super().__init__(track, rng, style)
        self.rng, self.planned = rng, self.profile
        self.scale_left = 0.0

    def act(self, car, frame_seconds):
        self.scale_left -= frame_seconds
        if self.scale_left <= 0:
            self.profile = self.planned * float(self.rng.uniform(*self.SCALES))
            self.scale_left = float(self.rng.uniform(*self.SECONDS))
        return super().act(car, frame_seconds)
