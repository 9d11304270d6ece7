"""Record CarRacing driving as an episodes file (see drivesim.episodes).

A scripted driver follows the track centre line with pure pursuit; `--driver` picks its style:

- `steady` (the default model's training data): the point it aims at drifts across the road
  (smooth random lateral offset), the steering gets coloured noise and the target speed
  changes every few seconds, so the controls vary while the car mostly stays on the road.
- `varied` (data that teaches steering): every few seconds a new manoeuvre, drawn at random:
  steady driving with a random steering gain (soft or hard turns), a swerve that aims up to
  one and a half half-roads to one side (off the road sometimes) and then recovers to the
  centre, as the recovery laps of behavioural-cloning data; target speeds from crawling to
  fast.
- `varied-noise` (data that teaches steering, with unsteady hands): `varied`, and every
  manoeuvre also draws how much coloured noise the steering gets, from a third to two and a
  half times `steady`'s, so the steering is often not what the road ahead calls for.
- `varied-holds` (data that teaches what steering does on its own): `varied`, and a fifth of
  the manoeuvres are holds: a constant steering of 0.1 to 0.7 either way for 0.2 to 0.8 s,
  whatever the road does, then a recovery to the centre. Pure pursuit steers with the road, so
  in the other styles the road's bend and the steering come together; a hold separates them
  (open-loop steps, as a system-identification experiment).
- `holds` (the same experiment at full strength): hold after hold, each followed by a
  recovery of 0.4 to 1.2 s and until the car is back within half a half-road of the centre
  line, so that holds start on the road and make about a quarter of the frames, where
  `varied-holds` has one in 25; the steering gain stays `steady`'s and the speeds are 15 to 45,
  so that the car comes back to the road after each hold.
- `expert-holds` (the same at racing pace): the expert (expert.py) with a hold of 0.05 to 0.3
  for 0.2 to 0.5 s after every 1 to 3 s of its own driving (`expert.ExpertHolds`).
- `expert-speeds` (what speed does in a bend): the expert's steering with its speed profile
  times 0.6 to 1.7, redrawn every 1 to 3 s (`expert.ExpertSpeeds`): bends of every kind taken
  slower and faster than the grip allows, with the slides, spins and recoveries that follow.
- `hard` (a second style, held out for evaluation): 1.4 times the steering gain, 1.5 times the
  steering noise and slower (steering sd about 0.4 against `steady`'s 0.23), as a nervous
  human driver.
- `jerky` (a third style, held out for evaluation): looks at the road only every 0.12 to 0.3 s
  and holds its steering in between (half the steering gain), with a random error redrawn at
  each look and no coloured noise; target speeds 20 to 50, as a late, jerky driver (steering
  sd about 0.3).

`--colours random` redraws the road and grass colours for every episode (gymnasium's
`domain_randomize`); `mixed` does so for every other seed.

  python -m drivesim record --seeds 0-39 --frames 600 --out data/train.safetensors.gz
  python -m drivesim record --seeds 100-139 --driver varied --colours mixed --out data/varied.safetensors.gz
"""

import argparse
import math
import os
import sys
from multiprocessing import Pool

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # pygame renders off-screen
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import numpy as np
from gymnasium.envs.box2d import car_racing

from .. import episodes
from . import expert, view


HEIGHT, WIDTH = view.HEIGHT, view.WIDTH
WARMUP_STEPS = 60  # the env zooms in during its first second; skip it
GAIN = 1.5  # steering per radian between heading and aim point
HALF_ROAD = car_racing.TRACK_WIDTH  # centre line to edge, world units


parse_seeds = view.parse_seeds


class OU:
    """Ornstein-Uhlenbeck noise: smooth, mean-reverting random drift."""

    def __init__(self, rng, theta, sigma, x=0.0):
        self.rng, self.theta, self.sigma, self.x = rng, theta, sigma, x

    def __call__(self):
        self.x += -self.theta * self.x + self.sigma * self.rng.standard_normal()
        return self.x


DRIVERS = ("steady", "varied", "varied-noise", "varied-holds", "holds", "hard", "jerky", "expert", "expert-holds", "expert-speeds")
COLOURS = ("default", "random", "mixed")


class Driver(expert.CentreLine):
    """Pure pursuit on a point ahead of the car, shifted sideways, in one of `DRIVERS`' styles;
    `Driver(track, rng, "expert")` is the racing-pace teacher of expert.py, with the same `act`."""

    def __new__(cls, track, rng, style="steady"):
        experts = {"expert": expert.Expert, "expert-holds": expert.ExpertHolds,
                   "expert-speeds": expert.ExpertSpeeds}
        if style in experts:
            return experts[style](track, rng, style)
        return super().__new__(cls)

    def __init__(self, track, rng, style="steady"):
        super().__init__(track)
        self.rng, self.style = rng, style
        self.offset = OU(rng, theta=0.02, sigma=0.08)
        self.steer_noise = OU(rng, theta=0.15, sigma={"hard": 0.09, "jerky": 0.0}.get(style, 0.06))
        self.gain = {"hard": 1.4 * GAIN, "jerky": 0.5 * GAIN}.get(style, GAIN)
        self.speeds = {"steady": (25, 60), "varied": (10, 70), "varied-noise": (10, 70),
                       "varied-holds": (10, 70), "holds": (15, 45), "hard": (15, 40),
                       "jerky": (20, 50)}[style]
        self.target_speed = rng.uniform(*self.speeds)
        # `varied`: the current manoeuvre's lateral aim (half-roads; None follows the drift)
        # and the seconds it has left.
        self.aim, self.manoeuvre_left = None, 0.0
        # `jerky`: the steering held until the next look at the road, and the seconds until then.
        self.held_steer, self.look_left = 0.0, 0.0
        # `varied-holds` and `holds`: the steering of the current hold and the seconds it has left.
        self.hold_steer, self.hold_left = 0.0, 0.0
        self.off_centre = 0.0  # half-roads from the centre line, as `act` last measured it

    def lateral(self, frame_seconds):
        """Where across the road to aim, in half-roads (positive: left of the centre line)."""
        drift = float(np.clip(self.offset(), -0.6, 0.6))
        if not self.style.startswith("varied") and self.style != "holds":
            return drift
        self.manoeuvre_left -= frame_seconds
        if self.manoeuvre_left <= 0 and self.style == "holds" and self.off_centre > 0.5:
            return 0.0  # recover to the centre line before the next hold
        if self.manoeuvre_left <= 0:
            if self.style == "holds":
                kind = "hold"
            elif self.style == "varied-holds":
                kind = self.rng.choice(["follow", "swerve", "recover", "hold"], p=[0.4, 0.25, 0.15, 0.2])
            else:  # `varied`'s draws, unchanged, so its recordings stay reproducible
                kind = self.rng.choice(["follow", "swerve", "recover"], p=[0.5, 0.3, 0.2])
            if kind == "hold":
                self.hold_steer = float(self.rng.choice([-1, 1]) * self.rng.uniform(0.1, 0.7))
                self.hold_left = self.rng.uniform(0.2, 0.8)
                kind = "recover"  # what follows the hold
            if self.style != "holds":  # whose recoveries keep the calm gain: hard ones spin out
                self.gain = GAIN * self.rng.uniform(0.6, 2.5)  # soft or hard turns
            if self.style == "varied-noise":  # steady or unsteady hands
                self.steer_noise.sigma = 0.06 * self.rng.uniform(1 / 3, 2.5)
            self.aim = {"follow": None, "swerve": self.rng.choice([-1, 1]) * self.rng.uniform(0.7, 1.5),
                        "recover": 0.0}[kind]
            self.manoeuvre_left = self.rng.uniform(1.0, 4.0)
            if self.style == "holds":  # the hold, then a short recovery
                self.manoeuvre_left = self.hold_left + self.rng.uniform(0.4, 1.2)
        return drift if self.aim is None else self.aim

    def act(self, car, frame_seconds):
        pos = np.array(car.hull.position)
        speed = float(np.linalg.norm(car.hull.linearVelocity))
        i, off_centre = self.nearest(pos)
        self.off_centre = off_centre / HALF_ROAD

        if self.rng.random() < frame_seconds / 3.0:  # new target speed every ~3 s
            self.target_speed = self.rng.uniform(*self.speeds)
        # Slow down before bends: heading change over the next 40 units of track.
        j = self.ahead(i, 40.0)
        bend = abs(math.remainder(self.heading[j] - self.heading[i], 2 * math.pi))
        target_speed = min(self.target_speed, 60.0 / (1.0 + 3.0 * bend))

        # Pure pursuit on a point ahead, shifted sideways.
        lookahead = 6.0 + 0.35 * speed
        j = self.ahead(i, lookahead)
        target = self.centre[j] + self.lateral(frame_seconds) * HALF_ROAD * self.left[j]
        forward = np.array([-math.sin(car.hull.angle), math.cos(car.hull.angle)])
        left = np.array([-forward[1], forward[0]])
        to = target - pos
        alpha = math.atan2(float(to @ left), float(to @ forward))
        steer = float(np.clip(-self.gain * alpha + self.steer_noise(), -1.0, 1.0))  # env: -1 steers left
        if self.hold_left > 0:
            self.hold_left -= frame_seconds
            steer = self.hold_steer
        if self.style == "jerky":
            self.look_left -= frame_seconds
            if self.look_left <= 0:
                self.look_left = self.rng.uniform(0.12, 0.3)
                self.held_steer = float(np.clip(steer + self.rng.uniform(-0.1, 0.1), -1.0, 1.0))
            steer = self.held_steer

        gas = float(np.clip(0.05 * (target_speed - speed), 0.0, 0.5))
        brake = float(np.clip(0.05 * (speed - target_speed - 5.0), 0.0, 0.8))
        return np.array([steer, gas, brake], dtype=np.float32), speed, off_centre


def off_playfield(car):
    return max(abs(car.hull.position[0]), abs(car.hull.position[1])) > car_racing.PLAYFIELD


def record_episode(seed, frames, frame_skip, style="steady", random_colours=False):
    """One episode from a seed: (frames [M,H,W,3], actions [M,2], fraction of frames on the road,
    rewards: episodes.REWARDS' per-decision arrays: the env's reward over each decision's
    frames, the tiles it first visited, whether a wheel touched the road; labels [M,2] for the
    expert: the speed it drove to and its steering, as DAgger labels, else None)."""
    env = car_racing.CarRacing(domain_randomize=random_colours)
    env.reset(seed=seed)
    driver = Driver(env.track, np.random.default_rng(seed), style)
    for _ in range(WARMUP_STEPS):
        env.step(np.array([0.0, 0.3, 0.0], dtype=np.float32))
    out_frames, out_actions, on_road = [], [], 0
    rewards = {"reward": [], "tiles": [], "on_road": []}
    labels = [] if style == "expert" else None
    while len(out_frames) < frames and not off_playfield(env.car):
        action, speed, off_centre = driver.act(env.car, frame_skip / car_racing.FPS)
        if labels is not None:
            labels.append((driver.target, action[0]))
        out_frames.append(view.observe(env))
        out_actions.append((speed, action[0]))
        on_road += off_centre < HALF_ROAD
        rewards["on_road"].append(wheel_on_road(env.car))
        tiles, total = env.tile_visited_count, 0.0
        # `terminated` also fires on a finished lap: keep driving.
        total += sum(float(step[1]) for step in view.decision_steps(env, action, frame_skip))
        rewards["reward"].append(total)
        rewards["tiles"].append(env.tile_visited_count - tiles)
    env.close()
    n = len(out_frames)
    rewards = {k: np.array(v, dtype=episodes.REWARDS[k]) for k, v in rewards.items()}
    labels = None if labels is None else np.array(labels, dtype=np.float32)
    return np.stack(out_frames), np.array(out_actions, dtype=np.float32), on_road / n, rewards, labels


def wheel_on_road(car):
    """1 if any wheel touches a road tile (the env's friction test), else 0."""
    return int(any(len(w.tiles) > 0 for w in car.wheels))


def decision(env, action, frame_skip):
    """One decision's env steps (``view.decision_steps``): the env's reward over them, the tiles
    the car first visited and whether the episode ended."""
    car, reward = env.unwrapped, 0.0
    tiles = car.tile_visited_count
    for _, r, terminated, truncated, _ in view.decision_steps(env, action, frame_skip):
        reward += float(r)
        if terminated or truncated:
            return reward, car.tile_visited_count - tiles, True
    return reward, car.tile_visited_count - tiles, False


def drive_agent(env, agent, label=None, adjust=None):
    """``agent`` (a reset agent of ``drivesim.carracing``) drives ``env`` (reset) to the end of the
    episode; every decision after the agent's warm-up (its zoom frames are no example) is
    recorded. ``label()``, called at every decision before the agent acts, gives that decision's
    label (the expert's, which keeps its place on the track so); ``adjust(action)`` changes a
    recorded decision's action before it is applied. Returns the drive's lists (`one_episode`'s
    ``out``, with "labels" where ``label`` is given) and the env's reward over the whole drive."""
    out = {"frames": [], "actions": [], "reward": [], "tiles": [], "on_road": []}
    if label is not None:
        out["labels"] = []
    total, done = 0.0, False
    while not done:
        frame, now = view.observe(env), view.speed(env)
        labelled = label() if label is not None else None
        action = agent.act(frame, now)
        keep = agent.decisions > agent.warmup
        if keep:
            action = adjust(action) if adjust is not None else action
            out["frames"].append(frame)
            out["actions"].append((now, action[0]))
            out["on_road"].append(wheel_on_road(env.unwrapped.car))
            if label is not None:
                out["labels"].append(labelled)
        reward, tiles, done = decision(env, action, agent.frame_skip)
        total += reward
        if keep:
            out["reward"].append(reward)
            out["tiles"].append(tiles)
    env.close()
    return out, total


def one_episode(out, labels=None):
    """An `episodes.Episodes` of one episode from a drive's lists: ``out`` holds "frames",
    "actions" and every name of `episodes.REWARDS`, one entry a decision."""
    rewards = {k: np.array(out[k], dtype=episodes.REWARDS[k]) for k in episodes.REWARDS}
    return episodes.Episodes(np.stack(out["frames"]), np.array(out["actions"], np.float32), np.zeros(1, np.int64),
                             rewards, labels)


def score_episode(seed, style="steady", frame_skip=4, limit=1000, top_speed=None):
    """The env's own reward for the driver on one track, as the agents are scored
    (`python -m drivesim.carracing`): driving from the first frame, `limit` frames at most, the
    episode ending early when the env says so (a lap done, or off the playfield). `top_speed`:
    the expert's speed profile held under it (style "expert" only): what a driver held to a
    speed range at best scores."""
    if top_speed is not None and style != "expert":
        raise ValueError(f"top_speed is the expert's, not the {style!r} driver's")
    env = car_racing.CarRacing()
    env.reset(seed=seed)
    # The env draws its 96x96 state on every step, and the score reads none of it: drawing
    # changes nothing in the physics (checked: the same scores) and takes most of the time.
    env._render = lambda *args, **kwargs: None
    rng = np.random.default_rng(seed)
    driver = Driver(env.track, rng, style) if top_speed is None else expert.Expert(env.track, rng, style, top_speed)
    total, frames = 0.0, 0
    while frames < limit:
        action, _, _ = driver.act(env.car, frame_skip / car_racing.FPS)
        for _ in range(frame_skip):
            _, reward, terminated, truncated, _ = env.step(action)
            total, frames = total + float(reward), frames + 1
            if terminated or truncated or frames >= limit:
                env.close()
                return total
    env.close()
    return total


def _score(job):
    seed, style, top_speed = job
    return seed, score_episode(seed, style, top_speed=top_speed)


def _record(job):
    seed, frames, frame_skip, style, random_colours = job
    f, a, on_road, rewards, labels = record_episode(seed, frames, frame_skip, style, random_colours)
    colours = ", random colours" if random_colours else ""
    print(f"seed {seed}{colours}: {len(f)} frames, {on_road:.0%} on the road, "
          f"speed {a[:, 0].mean():.1f}±{a[:, 0].std():.1f}, steering ±{np.abs(a[:, 1]).mean():.2f}",
          flush=True)
    return episodes.Episodes(f, a, np.zeros(1, dtype=np.int64), rewards, labels)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=parse_seeds, required=True, help="track seeds, e.g. 0-39 or 1,5,9")
    p.add_argument("--frames", type=int, default=600, help="frames per episode")
    p.add_argument("--frame-skip", type=int, default=4, help="env steps (50 Hz) per recorded frame")
    p.add_argument("--workers", type=int, default=os.cpu_count(), help="parallel processes")
    p.add_argument("--driver", choices=DRIVERS, default="steady", help="driving style (see above)")
    p.add_argument("--colours", choices=COLOURS, default="default",
                   help="road and grass colours: the env's, random per episode, or random for every other seed")
    p.add_argument("--out", help="episodes file (.safetensors or .safetensors.gz)")
    p.add_argument("--score", action="store_true",
                   help="record nothing: print the env's reward for the driver on each track (1000 frames)")
    p.add_argument("--top-speed", type=float,
                   help="with --score --driver expert: its speed profile held under this (units/s, 10 to 95)")
    args = p.parse_args(argv)
    if args.top_speed is not None and not (args.score and args.driver == "expert" and 10 <= args.top_speed <= 95):
        p.error("--top-speed is for --score --driver expert, from 10 to 95")
    if args.score:
        with Pool(min(args.workers, len(args.seeds))) as pool:
            scores = pool.map(_score, [(s, args.driver, args.top_speed) for s in args.seeds], chunksize=1)
        for seed, score in scores:
            print(f"seed {seed}: {score:.1f}")
        r = np.array([score for _, score in scores])
        print(f"{args.driver}: {r.mean():.1f} ± {r.std():.1f} over {len(r)} tracks (min {r.min():.1f}, max {r.max():.1f})")
        return 0
    if args.out is None:
        p.error("--out is required (or --score)")
    if args.frames < 1 or args.frame_skip < 1 or args.workers < 1:
        p.error("--frames, --frame-skip and --workers must be positive")

    random = {"default": lambda s: False, "random": lambda s: True, "mixed": lambda s: s % 2 == 1}[args.colours]
    jobs = [(s, args.frames, args.frame_skip, args.driver, random(s)) for s in args.seeds]
    with Pool(min(args.workers, len(jobs))) as pool:
        parts = pool.map(_record, jobs, chunksize=1)
    data = episodes.Episodes.concat(parts)
    meta = {"source": "gymnasium CarRacing-v3 scripted driver", "seeds": ",".join(map(str, args.seeds)),
            "driver": args.driver, "colours": args.colours,
            "frame_hz": str(car_racing.FPS / args.frame_skip)}
    episodes.write(args.out, data, meta)
    print(f"wrote {args.out}: {len(data)} episodes, {len(data.frames)} frames")


if __name__ == "__main__":
    sys.exit(main())
