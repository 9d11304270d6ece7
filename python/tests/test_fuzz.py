"""A property-based fuzz of the whole package (issue 46): every public call, given arrays of
every dtype, shape, layout and value class (NaN, infinities, huge, denormal), counts and
seeds of every kind, agent options and gymnasium actions, either succeeds with finite results
of the documented shape or raises a documented exception type (ValueError, TypeError,
MemoryError; gymnasium's ResetNeeded before a reset), and the object stays usable: after
each example a valid call on it gives the bits it gave before.

Profiles (``DRIVESIM_FUZZ_PROFILE``): ``ci`` (the default: fixed seed, a few examples per
test, in the normal pytest run) and ``long`` (``DRIVESIM_FUZZ_EXAMPLES`` examples per test,
2000 by default, random seeds or --hypothesis-seed; ``python python/tests/run_fuzz.py`` runs it in resumable
chunks and reports the calls made). ``fuzz_strategies.CALLS`` counts the calls."""

import operator
import os

import gymnasium
import numpy as np
import pytest
from fuzz_strategies import (A, FRAME, H, Z, arrays, bools, call, counts, finite, frame_dtypes, items, lead, numbers,
                             report, seeds)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import drivesim
from drivesim import carracing, road
from drivesim.carracing import agents

settings.register_profile("ci", derandomize=True, max_examples=20, deadline=None, database=None, print_blob=True,
                          suppress_health_check=list(HealthCheck))
settings.register_profile("long", max_examples=int(os.environ.get("DRIVESIM_FUZZ_EXAMPLES", "2000")), deadline=None,
                          print_blob=True, suppress_health_check=list(HealthCheck))
settings.load_profile(os.environ.get("DRIVESIM_FUZZ_PROFILE", "ci"))

MODEL = drivesim.Model.load()
CLIP = drivesim.load_episodes()[0]
SIM = drivesim.Simulator(MODEL, batch=3)
ENV = drivesim.Environment(MODEL, drives=2, candidates=3)
COST = road.RoadCost.default()

# Valid inputs for the positions a test is not fuzzing, and the bits a valid probe gives.
ZV = SIM.encode(CLIP[0][:2])
HV = np.zeros((2, H), np.float32) + np.float32(0.1)
AV = np.float32([[30.0, -0.2], [25.0, 0.3]])
PROBE = SIM.transition(ZV, HV, AV)
SEEDS2 = np.ascontiguousarray(np.stack([CLIP[0][:3]] * 2, axis=1))
BETWEEN2 = np.ascontiguousarray(np.stack([CLIP[1][:2]] * 2, axis=1))


@pytest.fixture(scope="module", autouse=True)
def count_calls():
    yield
    report()


def usable_simulator():
    """The simulator still works and gives the bits it gave before (sampling off again)."""
    SIM.set_sampling(0.0, 0)
    for found, expected in zip(SIM.transition(ZV, HV, AV), PROBE):
        np.testing.assert_array_equal(found, expected)


def dtype_name(dtype):
    try:
        return np.dtype(dtype if dtype is not None else "u1").name
    except TypeError:
        return None


def frames_shape(lead_dims, dtype):
    """The frames a call returns: `lead_dims` frames of the requested dtype (an unknown one is
    a ValueError, never a result)."""
    kind = dtype_name(dtype)
    return lambda out: out.shape == (*lead_dims, *FRAME) and out.dtype.name == kind


@given(frames=arrays(items(FRAME)), z=arrays(items((Z,))), h=arrays(items((H,))), a=arrays(items((A,))),
       dtype=frame_dtypes)
def test_simulator_calls(frames, z, h, a, dtype):
    """Each array in each position of encode, generate, transition, transition_fed_back, act and
    the reward and value heads."""
    if (n := lead(frames, FRAME)) is not None:
        call(SIM.encode, frames, shape=(*n, Z))
    if (n := lead(z, (Z,))) is not None:
        call(SIM.generate, z, dtype, shape=frames_shape(n, dtype))
        call(SIM.generate, z, shape=frames_shape(n, None))
    call(SIM.encode, z)
    call(SIM.generate, frames)
    z1, h1, a1 = ZV[:1], HV[:1], AV[:1]
    for args in ((z, h1, a1), (z1, h, a1), (z1, h1, a), (z, h, a)):
        n = lead(args[0], (Z,))
        call(SIM.transition, *args, shape=lambda out, n=n: out[0].shape == (*n, Z) and out[1].shape == (*n, H))
    for args in ((h, a1), (h1, a), (h, a)):
        n = lead(args[0], (H,))
        call(SIM.transition_fed_back, *args, shape=lambda out, n=n: out[0].shape == (*n, Z) and out[1].shape == (*n, H))
    for args in ((z, h1), (z1, h), (z, h)):
        n = lead(args[0], (Z,))
        call(SIM.act, *args, shape=lambda out, n=n: out.shape == (*n, A))
        call(SIM.reward, *args, shape=lambda out, n=n: out.shape == (*n, 2) and ((out[..., 1] >= 0) & (out[..., 1] <= 1)).all())
        call(SIM.value, *args, shape=lambda out, n=n: out.shape == (*n, 1))
    usable_simulator()


horizons = st.one_of(st.integers(0, 4), st.just(4 * 10**6))


@given(seed_frames=arrays(st.integers(0, 3).map(lambda s: (s, *FRAME))), plan=arrays(items((A,), 6)),
       steps=horizons, candidates=st.integers(0, 4), h=arrays(items((H,))), z=st.none() | arrays(items((Z,))),
       frames=bools, dtype=frame_dtypes)
def test_rollouts(seed_frames, plan, steps, candidates, h, z, frames, dtype):
    """rollout and rollout_candidates: any seeds, plans and states; a horizon too long to
    allocate (4 million steps of float32 frames) is MemoryError, never a panic."""
    huge = steps > 100
    if huge:  # only where the frames make the result unaffordable: codes alone would compute
        frames, dtype = True, np.float32
    s = np.shape(seed_frames)[0] if isinstance(seed_frames, np.ndarray) and np.ndim(seed_frames) else 1
    actions = np.zeros((max(s - 1, 0) + steps, A), np.float32) + np.float32([30.0, 0.0])
    codes_shape = lambda out, t=steps: (out[0] if isinstance(out, tuple) else out).shape == (t, Z)  # noqa: E731
    call(SIM.rollout, seed_frames, actions, frames, dtype, shape=codes_shape)
    if not huge:
        call(SIM.rollout, CLIP[0][:2], plan, frames, dtype)
    grid = np.zeros((steps, candidates, A), np.float32) + np.float32([30.0, 0.1])
    shaped = lambda out, t=steps, n=candidates: (out[0] if isinstance(out, tuple) else out).shape == (t, n, Z)  # noqa
    call(SIM.rollout_candidates, h, grid, z, frames, dtype, shape=shaped)
    if not huge:
        call(SIM.rollout_candidates, HV[0], plan, ZV[0], frames, dtype)
        scored = lambda out, t=steps, n=candidates: [o.shape for o in out] == [(t, n, Z), (t, n, 2), (t, n)]  # noqa
        call(SIM.rollout_candidates_scored, h, grid, z, shape=scored)
        call(SIM.rollout_candidates_scored, HV[0], plan, ZV[0])
    usable_simulator()


@given(temperature=numbers, seed=numbers | counts, step=numbers | counts, h=arrays(items((H,))), z=arrays(items((Z,))))
def test_sampling_settings(temperature, seed, step, h, z):
    """set_sampling, then sample on any states, steps and codes."""
    call(SIM.set_sampling, temperature, seed)
    call(SIM.set_sampling, temperature, 0)
    call(SIM.sample, h, step, z)
    call(ENV.set_sampling, temperature, seed)
    usable_simulator()
    SIM.set_sampling(0.0, 0)
    ENV.set_sampling(0.0, 0)


@given(batch=counts, threads=counts, drives=counts, candidates=counts)
def test_constructors(batch, threads, drives, candidates):
    """Counts of every kind: a simulator or an environment with what was asked (None: the
    default), or ValueError, TypeError or MemoryError."""
    sim = call(drivesim.Simulator, MODEL, batch, threads)
    if sim is not None:
        asked = lambda n: 1 if n is None else operator.index(n)  # noqa: E731
        assert sim.batch == asked(batch) and sim.threads == asked(threads)
        np.testing.assert_array_equal(call(sim.transition, ZV[:1], HV[:1], AV[:1])[0], PROBE[0][:1])
    call(drivesim.Simulator, MODEL, batch)
    call(drivesim.Simulator, MODEL, threads=threads)
    env = call(drivesim.Environment, MODEL, drives, candidates, threads)
    if env is not None:
        call(lambda: env.codes)  # before a reset: ValueError
        assert env.drives == (1 if drives is None else drives)  # None: the default


def usable_environment():
    """The environment resets and steps as a fresh one does."""
    ENV.set_sampling(0.0, 0)
    ENV.reset_from_codes(np.ascontiguousarray(np.stack([ZV, ZV])), np.ascontiguousarray(AV[None]))
    ENV.step(AV)
    np.testing.assert_array_equal(ENV.codes, ENV_PROBE)


ENV.reset_from_codes(np.ascontiguousarray(np.stack([ZV, ZV])), np.ascontiguousarray(AV[None]))
ENV.step(AV)
ENV_PROBE = ENV.codes


@given(frames=arrays(items((2, *FRAME), 3)), codes=arrays(items((2, Z), 3)), between=arrays(items((2, A), 3)),
       step=arrays(items((A,), 3)), plan=arrays(items((3, A), 3)), drive=counts, dtype=frame_dtypes, frames_too=bools)
def test_environment_calls(frames, codes, between, step, plan, drive, dtype, frames_too):
    """Environment.reset, reset_from_codes, step, codes, hidden, frames, rollout_candidates."""
    if call(ENV.reset, frames, between) is not None:
        assert ENV.codes.shape == (2, Z) and ENV.hidden.shape == (2, H)
    call(ENV.reset, SEEDS2, between)
    call(ENV.reset, frames, BETWEEN2)
    call(ENV.reset_from_codes, codes, between)
    for args in ((codes, np.ascontiguousarray(AV[None])), (np.ascontiguousarray(np.stack([ZV, ZV])), between)):
        call(ENV.reset_from_codes, *args)
    call(ENV.step, step)
    call(lambda: ENV.codes, shape=(2, Z))
    call(lambda: ENV.hidden, shape=(2, H))
    call(ENV.frames, dtype)
    call(ENV.rollout_candidates, drive, plan, frames_too, dtype)
    call(ENV.rollout_candidates, 0, plan)
    usable_environment()


@given(codes=arrays(items((Z,), 3)), frames=arrays(items(FRAME, 2)), figures=arrays(items((4,), 3)),
       ridge=numbers, road_figures=arrays(items((4,), 1)), speed=numbers, target=numbers)
def test_road_and_helpers(codes, frames, figures, ridge, road_figures, speed, target):
    """RoadCost.predict and fit, road.measure and the agents' public helpers."""
    n = lead(codes, (Z,))
    call(COST.predict, codes, shape=None if n is None else (*n, 4))
    call(road.measure, frames, shape=lambda out: out.shape[1:] == (4,))
    if call(road.RoadCost.fit, codes, figures, ridge) is not None:
        fitted = road.RoadCost.fit(codes, figures, ridge)
        call(fitted.predict, ZV)
    call(carracing.speed_control, speed, target, shape=lambda out: len(out) == 2)
    call(carracing.speed_control, speed, target, target, shape=lambda out: len(out) == 2)
    call(agents.proportional_steering, road_figures)
    call(agents.target_speed, road_figures, speed, 80.0)
    np.testing.assert_array_equal(COST.predict(ZV), COST.predict(ZV))


AGENT_OPTIONS = {
    "mpc": ["candidates", "horizon", "futures", "temperature", "steer_noise", "speed_noise", "smooth", "w_off",
            "spread", "seed", "max_speed", "guard", "pace"],
    "mpc-road": ["candidates", "horizon", "iterations", "context", "skip", "max_speed", "road_scale", "search", "w_off",
            "w_prior", "correct"],
    "cloned": ["threads", "pace"],
    "reactive": ["max_speed"],
    "random": ["seed"],
}
small_counts = st.one_of(st.integers(-1, 6), counts)


@st.composite
def agent_options(draw):
    name = draw(st.sampled_from(sorted(AGENT_OPTIONS)))
    chosen = draw(st.lists(st.sampled_from(AGENT_OPTIONS[name]), max_size=3, unique=True))
    options = {}
    for key in chosen:
        integer = key in ("candidates", "horizon", "iterations", "context", "skip", "threads", "seed", "futures")
        options[key] = draw(small_counts if integer else numbers | st.floats(0.1, 60))
    return name, options


@given(agent=agent_options(), warmup=st.integers(0, 2),
       inputs=st.lists(st.tuples(arrays(st.sampled_from([FRAME, FRAME, FRAME, (1, *FRAME), (160, 80, 3)])),
                                 numbers | st.floats(0, 60)), min_size=1, max_size=3))
def test_agents(agent, warmup, inputs):
    """Agents from any options (ValueError or TypeError when made, never at a decision), then
    decisions on any frames and speeds; a valid decision afterwards still gives a finite action."""
    name, options = agent
    made = {"mpc": agents.MPCAgent, "mpc-road": agents.RoadMPCAgent, "cloned": agents.ClonedAgent}.get(name)
    extra = {"model": MODEL} if made else {}
    if made is agents.RoadMPCAgent:
        extra["cost"] = COST
    if made in (agents.MPCAgent, agents.RoadMPCAgent):
        options.setdefault("candidates", 4)  # keep the planning quick
    a = call(made or agents.AGENTS[name], **extra, **options)
    if a is None:
        return
    a.warmup = warmup
    for frame, speed in inputs:
        call(a.act, frame, speed, shape=(3,))
    action = call(a.act, CLIP[0][0], 30.0, raises=(), shape=(3,))
    assert action.dtype == np.float32 and np.isfinite(action).all()


DREAM = drivesim.DreamEnv(max_steps=3, render_mode="rgb_array")
DREAMS = drivesim.DreamVectorEnv(2, max_steps=3)
options_strategy = st.one_of(
    st.none(), st.just({}), st.fixed_dictionaries({"episode": counts}), st.fixed_dictionaries({"start": counts}),
    st.fixed_dictionaries({"frames": arrays(st.sampled_from([(1, *FRAME), (2, *FRAME), (0, *FRAME), (1, 2, *FRAME)]),
                                            [np.uint8, np.float32, np.float64])}),
    st.sampled_from([[], "episode", {"frames": []}, {"frames": CLIP[0][:2], "actions": np.zeros((3, 2))}]),
)
ResetNeeded = gymnasium.error.ResetNeeded


@given(ops=st.lists(st.one_of(st.tuples(st.just("reset"), seeds, options_strategy),
                              st.tuples(st.just("step"), arrays(items((A,), 3)) | numbers)), min_size=1, max_size=5))
def test_gymnasium(ops):
    """DreamEnv and DreamVectorEnv: resets with any seeds and options, steps with any actions;
    results in their spaces with finite rewards, then a seeded reset gives the same start."""
    for env, vector in ((DREAM, False), (DREAMS, True)):
        for op, *args in ops:
            if op == "reset":
                out = call(env.reset, seed=args[0], options=args[1], raises=(ValueError, TypeError))
                if out is not None:
                    assert out[0] in env.observation_space
            else:
                out = call(env.step, args[0], raises=(ValueError, TypeError, ResetNeeded))
                if out is not None:
                    obs, reward, terminated, truncated, info = out
                    assert obs in env.observation_space and finite(reward) and finite(info)
                    assert np.shape(reward) == ((2,) if vector else ())
        first, _ = env.reset(seed=11)
        again, _ = env.reset(seed=11)
        np.testing.assert_array_equal(first, again)
        assert call(env.step, env.action_space.sample(), raises=()) is not None
