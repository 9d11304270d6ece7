//! `Simulator`: encode, generate, transition steps and rollouts on numpy arrays.

use crate::arrays::{candidates, codes_and_states, f32_items, frame_type, slice, temperature_f32, value_error, Frames};
use crate::model::PyModel;
use crate::outputs::{codes_and_frames, frames_out, new_array};
use crate::{count, size, to_py};
use drivesim::{HeadKind, Model, Simulator};
use numpy::{PyArrayDyn, PyArrayMethods};
use pyo3::prelude::*;
use std::sync::{Arc, Mutex, MutexGuard};

/// A transition step's result: the next codes and the next hidden states.
type Step<'py> = (Bound<'py, PyArrayDyn<f32>>, Bound<'py, PyArrayDyn<f32>>);
/// A scored candidate rollout's result: codes, rewards and values.
type Scored<'py> = (
    Bound<'py, PyArrayDyn<f32>>,
    Bound<'py, PyArrayDyn<f32>>,
    Bound<'py, PyArrayDyn<f32>>,
);

/// A simulator and the scratch its 8-bit frames convert through.
pub struct State {
    pub sim: Simulator<Arc<Model>>,
    pub scratch: Vec<f32>,
}

fn lock(state: &Mutex<State>) -> PyResult<MutexGuard<'_, State>> {
    crate::lock(state, "simulator")
}

/// Runs the model: encodes frames, steps the transition, generates frames, rolls out dreams.
///
/// `Simulator(model, batch=1, threads=1)` plans and allocates every buffer once, for up to
/// `batch` frames or codes per call (an integer >= 1; ValueError otherwise, MemoryError when
/// the plan cannot be allocated); `threads` (1 to 1024; ValueError otherwise, RuntimeError
/// when the system will not start them) share each network's layers. Frames are numpy
/// arrays of shape `(N, height, width, 3)` (or one frame, `(height, width, 3)`), `uint8`
/// (0-255) or `float32` (in [-1, 1]); codes, hidden states and actions are `float32`, one row
/// per item. Results are new arrays; the interpreter is released while the crate computes.
/// Results are bit-identical whatever the thread count or batch.
///
/// >>> import numpy as np, drivesim
/// >>> model = drivesim.Model.load()
/// >>> sim = drivesim.Simulator(model)
/// >>> z = sim.encode(np.zeros((80, 160, 3), np.uint8))
/// >>> z_next, h = sim.transition(z, np.zeros(model.hidden_dim, np.float32), np.array([30.0, 0.0], np.float32))
/// >>> sim.generate(z_next).shape
/// (80, 160, 3)
#[pyclass(module = "drivesim", name = "Simulator")]
pub struct PySimulator {
    state: Mutex<State>,
}

impl PySimulator {
    fn config(&self) -> PyResult<drivesim::Config> {
        Ok(*lock(&self.state)?.sim.config())
    }
}

/// A result's shape: the input's leading dimensions (none for a single item), then the item's.
fn shape_of(lead: &[usize], tail: &[usize]) -> Vec<usize> {
    lead.iter().chain(tail).copied().collect()
}

#[pymethods]
impl PySimulator {
    #[new]
    #[pyo3(signature = (model, batch=None, threads=None), text_signature = "(model, batch=1, threads=1)")]
    fn new(
        py: Python<'_>,
        model: &PyModel,
        batch: Option<&Bound<'_, PyAny>>,
        threads: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let batch = batch.map_or(Ok(1), |b| size(b, "batch", 1))?;
        let threads = threads.map_or(Ok(1), |t| size(t, "threads", 1))?;
        let model = Arc::clone(&model.inner);
        let sim = py
            .detach(|| Simulator::with_batch(model, batch)?.with_threads(threads))
            .map_err(to_py)?;
        Ok(PySimulator {
            state: Mutex::new(State {
                sim,
                scratch: Vec::new(),
            }),
        })
    }

    /// The most frames or codes one call takes.
    #[getter]
    fn batch(&self) -> PyResult<usize> {
        Ok(lock(&self.state)?.sim.max_batch())
    }

    /// Threads that share each call, the caller's included.
    #[getter]
    fn threads(&self) -> PyResult<usize> {
        Ok(lock(&self.state)?.sim.threads())
    }

    /// The instruction set the kernels run on (`"avx512"`, `"avx2"`, `"neon"` or `"scalar"`).
    #[getter]
    fn isa(&self) -> PyResult<String> {
        Ok(lock(&self.state)?.sim.isa().level().name().to_string())
    }

    /// Bytes of the buffers planned and allocated at construction (weights not included).
    #[getter]
    fn buffer_bytes(&self) -> PyResult<usize> {
        Ok(lock(&self.state)?.sim.buffer_bytes())
    }

    /// Encodes frames to latent codes (the VAE mean): `(N, height, width, 3)` uint8 or float32
    /// frames give `(N, z_dim)` float32 codes; one frame `(height, width, 3)` gives `(z_dim,)`.
    fn encode<'py>(&self, py: Python<'py>, frames: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let mut guard = lock(&self.state)?;
        let State { sim, scratch } = &mut *guard;
        let c = *sim.config();
        let (frames, lead) = Frames::new(frames, "frames", &c, &[0, 1])?;
        let out = new_array::<f32>(py, &shape_of(&lead, &[c.z_dim]), "the codes")?;
        let floats = frames.floats(&c, scratch)?;
        // SAFETY: the array was just created here and no other reference to it exists.
        let z = unsafe { out.as_slice_mut() }.expect("a new array is contiguous");
        py.detach(|| sim.encode(floats, z)).map_err(to_py)?;
        Ok(out)
    }

    /// Generates frames from codes: `(N, z_dim)` codes give `(N, height, width, 3)` frames,
    /// `(z_dim,)` one frame; `dtype` uint8 (the default, 0-255) or float32 (in [-1, 1]).
    #[pyo3(signature = (z, dtype=None))]
    fn generate<'py>(
        &self,
        py: Python<'py>,
        z: &Bound<'py, PyAny>,
        dtype: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let kind = frame_type(py, dtype)?;
        let mut guard = lock(&self.state)?;
        let State { sim, scratch } = &mut *guard;
        let c = *sim.config();
        let (z, lead) = f32_items(z, "z", &[0, 1], &[c.z_dim])?;
        let z = slice(&z);
        let shape = shape_of(&lead, &[c.height, c.width, c.channels]);
        frames_out(py, kind, &c, &shape, scratch, |frames| sim.generate(z, frames))
    }

    /// One transition step from given codes: `z` `(N, z_dim)`, the hidden states `h`
    /// `(N, hidden_dim)` and actions `(N, 2)` (speed, steering), or one of each without the
    /// leading N. Returns `(z_next, h_next)`, new arrays; `h` is not changed.
    fn transition<'py>(
        &self,
        py: Python<'py>,
        z: &Bound<'py, PyAny>,
        h: &Bound<'py, PyAny>,
        action: &Bound<'py, PyAny>,
    ) -> PyResult<Step<'py>> {
        let c = self.config()?;
        let (z, lead) = f32_items(z, "z", &[0, 1], &[c.z_dim])?;
        let z = slice(&z);
        self.step(py, Some(z), &lead, h, action)
    }

    /// One transition step from the code `h` itself predicts (as after a rollout's or another
    /// step's prediction): the step a dream takes from its own last frame. Returns
    /// `(z_next, h_next)`; `h` is not changed.
    fn transition_fed_back<'py>(
        &self,
        py: Python<'py>,
        h: &Bound<'py, PyAny>,
        action: &Bound<'py, PyAny>,
    ) -> PyResult<Step<'py>> {
        let c = self.config()?;
        let lead = f32_items(h, "h", &[0, 1], &[c.hidden_dim])?.1;
        self.step(py, None, &lead, h, action)
    }

    /// Samples the futures of every later rollout (`rollout`, `rollout_from_codes`,
    /// `rollout_candidates`) of a model whose transition predicts its spread (`Model.samples`):
    /// each predicted code becomes `mean + temperature * sigma * noise`, the noise drawn from
    /// `seed`, the step and the item alone (the same seed, the same dream, whatever the
    /// threads or batch). Temperature 0 is the mean, as without. ValueError for a temperature
    /// below 0, or above 0 where the model cannot sample.
    fn set_sampling(&self, temperature: &Bound<'_, PyAny>, seed: &Bound<'_, PyAny>) -> PyResult<()> {
        let (temperature, seed) = (temperature_f32(temperature)?, count(seed, "seed", 0, u64::MAX)?);
        lock(&self.state)?.sim.set_sampling(temperature, seed).map_err(to_py)
    }

    /// The sampling's `(temperature, seed)`; temperature 0: off.
    #[getter]
    fn sampling(&self) -> PyResult<(f32, u64)> {
        Ok(lock(&self.state)?.sim.sampling())
    }

    /// For a controller stepping the transition itself, what the rollouts do after each step: the
    /// mean codes `codes` `(N, z_dim)` a step predicted, with the hidden states `h` it left, sampled
    /// as rollout step `step` (items from 0). A new array; with sampling off, the codes as given.
    fn sample<'py>(
        &self,
        py: Python<'py>,
        h: &Bound<'py, PyAny>,
        step: &Bound<'py, PyAny>,
        codes: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let step = count(step, "step", 0, u64::MAX)?;
        let z_dim = self.config()?.z_dim;
        self.on_states(
            py,
            (codes, "codes"),
            h,
            (z_dim, "the codes"),
            |sim, codes, h, sampled| {
                sampled.copy_from_slice(codes);
                sim.sample(h, step, sampled)
            },
        )
    }

    /// The cloned driver's actions (the model's policy; `Model.policy_width` is None without
    /// one, and then this raises ValueError): `z` `(N, z_dim)`, the codes of the frames seen
    /// now, and `h` `(N, hidden_dim)`, the transition's hidden states after the drive's earlier
    /// codes and actions (zeros at its first frame, then each `transition`'s `h_next`), give
    /// `(N, 2)` float32 actions, the speed to drive at and the steering, within the model's
    /// trained ranges; one of each without the leading N gives `(2,)`.
    fn act<'py>(
        &self,
        py: Python<'py>,
        z: &Bound<'py, PyAny>,
        h: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        self.head(py, HeadKind::Policy, z, h)
    }

    /// The reward head on states a decision led to (`Model.reward_width` is None without one,
    /// and then this raises ValueError): `z` `(N, z_dim)`, the code after the step, and `h`
    /// `(N, hidden_dim)`, the hidden state the step left, give `(N, 2)` float32: the env's
    /// reward expected for the decision and the chance that the car is off the road (in
    /// [0, 1]); one of each without the leading N gives `(2,)`.
    fn reward<'py>(
        &self,
        py: Python<'py>,
        z: &Bound<'py, PyAny>,
        h: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        self.head(py, HeadKind::Reward, z, h)
    }

    /// The value head (`Model.value_width`; ValueError without one): the discounted return
    /// (discount `Model.discount` per decision) from each state `z` `(N, z_dim)`, `h`
    /// `(N, hidden_dim)`, as `(N, 1)` float32; one state without the leading N gives `(1,)`.
    fn value<'py>(
        &self,
        py: Python<'py>,
        z: &Bound<'py, PyAny>,
        h: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        self.head(py, HeadKind::Value, z, h)
    }

    /// The pace head (`Model.pace_width`; ValueError without one): the racing speed from the
    /// states `act` reads, `(N, 1)` float32 (speed units, at least 0), or `(1,)` for one state.
    fn pace<'py>(
        &self,
        py: Python<'py>,
        z: &Bound<'py, PyAny>,
        h: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        self.head(py, HeadKind::Pace, z, h)
    }

    /// A dream from seed frames: `seed_frames` `(S, height, width, 3)` and `actions`
    /// `(S - 1 + T, 2)` (the actions between the seeds, then one per predicted step) give the
    /// `T` predicted codes `(T, z_dim)`; with `frames=True`, also the generated frames
    /// `(T, height, width, 3)` as `(codes, frames)`.
    #[pyo3(signature = (seed_frames, actions, frames=false, dtype=None))]
    fn rollout<'py>(
        &self,
        py: Python<'py>,
        seed_frames: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        frames: bool,
        dtype: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let kind = frame_type(py, dtype)?;
        let mut guard = lock(&self.state)?;
        let State { sim, scratch } = &mut *guard;
        let c = *sim.config();
        let (seeds, lead) = Frames::new(seed_frames, "seed_frames", &c, &[1])?;
        let (actions, steps) = f32_items(actions, "actions", &[1], &[c.action_dim])?;
        let steps = steps[0].checked_sub(lead[0] - 1).filter(|&t| t > 0).ok_or_else(|| {
            value_error(format!(
                "actions: {} seed frames need {} actions between them and at least one more to predict, got {}",
                lead[0],
                lead[0] - 1,
                steps[0]
            ))
        })?;
        let mut seed_scratch = Vec::new();
        let seeds = seeds.floats(&c, &mut seed_scratch)?;
        let actions = slice(&actions);
        codes_and_frames(py, kind, &c, &[steps], frames, scratch, |codes, f| {
            sim.rollout(seeds, actions, codes, f)
        })
    }

    /// Rolls out `N` candidate action sequences at once from one state: the planner's building
    /// block. `h` is the hidden state `(hidden_dim,)` shared by every candidate, or `(N,
    /// hidden_dim)`; `actions` `(T, N, 2)` step-major; `z`, the current code `(z_dim,)` or
    /// `(N, z_dim)`, or None to start from the code `h` predicts. Returns the codes
    /// `(T, N, z_dim)`, or with `frames=True` `(codes, frames)` with frames `(T, N, height,
    /// width, 3)`. Each candidate gets the bits a rollout of its own would.
    #[pyo3(signature = (h, actions, z=None, frames=false, dtype=None))]
    fn rollout_candidates<'py>(
        &self,
        py: Python<'py>,
        h: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        z: Option<&Bound<'py, PyAny>>,
        frames: bool,
        dtype: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let kind = frame_type(py, dtype)?;
        let mut guard = lock(&self.state)?;
        let State { sim, scratch } = &mut *guard;
        let c = *sim.config();
        let (h, z, actions, steps, n) = candidates(&c, h, actions, z)?;
        let (h, z, actions) = (slice(&h), z.as_ref().map(slice), slice(&actions));
        codes_and_frames(py, kind, &c, &[steps, n], frames, scratch, |codes, f| {
            sim.rollout_candidates(h, z, n, actions, codes, f)
        })
    }

    /// `rollout_candidates` (codes only) with the reward and value heads read after every step
    /// in the same batch: the planner's scores. Returns `(codes, rewards, values)`: codes
    /// `(T, N, z_dim)`, rewards `(T, N, 2)` (each step's reward and off-road chance, as
    /// `reward` reads the state the step reached) and values `(T, N)` (`value` of that state).
    /// ValueError for a model without both heads.
    #[pyo3(signature = (h, actions, z=None))]
    fn rollout_candidates_scored<'py>(
        &self,
        py: Python<'py>,
        h: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        z: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Scored<'py>> {
        let mut guard = lock(&self.state)?;
        let sim = &mut guard.sim;
        let c = *sim.config();
        let (h, z, actions, steps, n) = candidates(&c, h, actions, z)?;
        let codes = new_array::<f32>(py, &[steps, n, c.z_dim], "the codes")?;
        let rewards = new_array::<f32>(py, &[steps, n, 2], "the rewards")?;
        let values = new_array::<f32>(py, &[steps, n], "the values")?;
        // SAFETY: the arrays were just created here and no other reference to them exists.
        let outs = unsafe { (codes.as_slice_mut(), rewards.as_slice_mut(), values.as_slice_mut()) };
        let (codes_out, rewards_out, values_out) = (outs.0.expect("new"), outs.1.expect("new"), outs.2.expect("new"));
        let (h, z, actions) = (slice(&h), z.as_ref().map(slice), slice(&actions));
        py.detach(|| sim.rollout_candidates_scored(h, z, n, actions, codes_out, rewards_out, values_out))
            .map_err(to_py)?;
        Ok((codes, rewards, values))
    }

    fn __repr__(&self) -> PyResult<String> {
        let guard = lock(&self.state)?;
        let c = guard.sim.config();
        Ok(format!(
            "Simulator(frame={}x{}, z_dim={}, batch={}, threads={}, isa={})",
            c.height,
            c.width,
            c.z_dim,
            guard.sim.max_batch(),
            guard.sim.threads(),
            guard.sim.isa().level().name()
        ))
    }
}

impl PySimulator {
    /// A head's outputs for states `z`, `h` (one, or `(N, ...)` each).
    fn head<'py>(
        &self,
        py: Python<'py>,
        kind: HeadKind,
        z: &Bound<'py, PyAny>,
        h: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let outputs = kind.outputs(&self.config()?);
        self.on_states(py, (z, "z"), h, (outputs, "the outputs"), |sim, z, h, out| match kind {
            HeadKind::Policy => sim.act(z, h, out),
            HeadKind::Reward => sim.reward(z, h, out),
            HeadKind::Value => sim.value(z, h, out),
            HeadKind::Pace => sim.pace(z, h, out),
        })
    }

    /// `run(sim, z, h, out)` on states (codes `z` and hidden states `h`, one of each or `(N,
    /// ...)` each) into a new array of `width` values per state, the GIL released.
    fn on_states<'py>(
        &self,
        py: Python<'py>,
        (z, what): (&Bound<'py, PyAny>, &str),
        h: &Bound<'py, PyAny>,
        (width, name): (usize, &str),
        run: impl FnOnce(&mut Simulator<Arc<Model>>, &[f32], &[f32], &mut [f32]) -> drivesim::Result<()> + Send,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let mut guard = lock(&self.state)?;
        let sim = &mut guard.sim;
        let (z, h, lead) = codes_and_states(sim.config(), z, what, h)?;
        let out = new_array::<f32>(py, &shape_of(&lead, &[width]), name)?;
        // SAFETY: the array was just created here and no other reference to it exists.
        let values = unsafe { out.as_slice_mut() }.expect("new");
        let (z, h) = (slice(&z), slice(&h));
        py.detach(|| run(sim, z, h, values)).map_err(to_py)?;
        Ok(out)
    }

    /// A transition step from `z` (or from `h`'s own prediction when None).
    fn step<'py>(
        &self,
        py: Python<'py>,
        z: Option<&[f32]>,
        lead: &[usize],
        h: &Bound<'py, PyAny>,
        action: &Bound<'py, PyAny>,
    ) -> PyResult<Step<'py>> {
        let mut guard = lock(&self.state)?;
        let sim = &mut guard.sim;
        let c = *sim.config();
        let (h, h_lead) = f32_items(h, "h", &[0, 1], &[c.hidden_dim])?;
        let (action, a_lead) = f32_items(action, "action", &[0, 1], &[c.action_dim])?;
        if h_lead != lead || a_lead != lead {
            return Err(value_error(format!(
                "z, h and action must have the same leading dimensions: {lead:?}, {h_lead:?} and {a_lead:?}"
            )));
        }
        let h_next = new_array::<f32>(py, &shape_of(lead, &[c.hidden_dim]), "the hidden states")?;
        let z_next = new_array::<f32>(py, &shape_of(lead, &[c.z_dim]), "the codes")?;
        // SAFETY: both arrays were just created here and no other reference to them exists.
        let (h_out, z_out) = unsafe { (h_next.as_slice_mut(), z_next.as_slice_mut()) };
        let (h_out, z_out) = (h_out.expect("new"), z_out.expect("new"));
        h_out.copy_from_slice(slice(&h));
        let action = slice(&action);
        py.detach(|| match z {
            Some(z) => sim.transition(z, h_out, action, z_out),
            None => sim.transition_fed_back(h_out, action, z_out),
        })
        .map_err(to_py)?;
        Ok((z_next, h_next))
    }
}
