//! `Environment`: N dreamed drives that a controller steps, on numpy arrays.

use crate::arrays::{f32_items, frame_type, shape_str, slice, temperature_f32, value_error, Frames};
use crate::model::PyModel;
use crate::outputs::{codes_and_frames, frames_out, rows_copy};
use crate::{count, size, to_py};
use drivesim::{Environment, Model};
use numpy::{PyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use std::sync::{Arc, Mutex, MutexGuard};

struct State {
    env: Environment<Arc<Model>>,
    scratch: Vec<f32>,
}

/// `drives` dreamed drives stepping together in one batch: reset from real frames (or codes),
/// then each `step` applies one action per drive and moves every drive to its next predicted
/// code. `candidates` is the most action sequences one `rollout_candidates` call takes.
/// `drives`, `candidates` and `threads` are integers >= 1 (threads at most 1024): ValueError
/// otherwise, MemoryError when the plan cannot be allocated. Before a successful reset,
/// `step`, `frames`, `codes`, `hidden` and `rollout_candidates` raise ValueError.
///
/// >>> import numpy as np, drivesim
/// >>> env = drivesim.Environment(drivesim.Model.load(), drives=2)
/// >>> frames, actions = drivesim.load_episodes()[0]  # the built-in seed clip
/// >>> seeds = np.stack([frames[:5], frames[:5]], axis=1)  # (S, drives, 80, 160, 3)
/// >>> env.reset(seeds, np.stack([actions[:4], actions[:4]], axis=1))
/// >>> env.step(np.array([[30.0, -0.2], [30.0, 0.2]], np.float32))
/// >>> env.frames().shape
/// (2, 80, 160, 3)
#[pyclass(module = "drivesim", name = "Environment")]
pub struct PyEnvironment {
    state: Mutex<State>,
    drives: usize,
}

fn lock(state: &Mutex<State>) -> PyResult<MutexGuard<'_, State>> {
    crate::lock(state, "environment")
}

#[pymethods]
impl PyEnvironment {
    #[new]
    #[pyo3(
        signature = (model, drives=None, candidates=None, threads=None),
        text_signature = "(model, drives=1, candidates=64, threads=1)"
    )]
    fn new(
        py: Python<'_>,
        model: &PyModel,
        drives: Option<&Bound<'_, PyAny>>,
        candidates: Option<&Bound<'_, PyAny>>,
        threads: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let drives = drives.map_or(Ok(1), |d| size(d, "drives", 1))?;
        let candidates = candidates.map_or(Ok(64), |c| size(c, "candidates", 1))?;
        let threads = threads.map_or(Ok(1), |t| size(t, "threads", 1))?;
        let model = Arc::clone(&model.inner);
        let env = py
            .detach(|| Environment::new(model, drives, candidates)?.with_threads(threads))
            .map_err(to_py)?;
        Ok(PyEnvironment {
            state: Mutex::new(State {
                env,
                scratch: Vec::new(),
            }),
            drives,
        })
    }

    /// How many drives step together.
    #[getter]
    fn drives(&self) -> usize {
        self.drives
    }

    /// Starts every drive from real frames: `frames` `(S, drives, height, width, 3)`, uint8 or
    /// float32, seed by seed, and `actions` `(S - 1, drives, 2)` the actions between them.
    fn reset(&self, py: Python<'_>, frames: &Bound<'_, PyAny>, actions: &Bound<'_, PyAny>) -> PyResult<()> {
        let mut guard = lock(&self.state)?;
        let State { env, scratch } = &mut *guard;
        let c = *env.simulator().config();
        let (frames, lead) = Frames::new(frames, "frames", &c, &[2])?;
        self.check_drives("frames", lead[1])?;
        let actions = self.actions_between(&c, actions, lead[0])?;
        let floats = frames.floats(&c, scratch)?;
        py.detach(|| env.reset_from_frames(floats, &actions)).map_err(to_py)
    }

    /// Starts every drive from codes: `codes` `(S, drives, z_dim)` and `actions`
    /// `(S - 1, drives, 2)`.
    fn reset_from_codes(&self, py: Python<'_>, codes: &Bound<'_, PyAny>, actions: &Bound<'_, PyAny>) -> PyResult<()> {
        let mut guard = lock(&self.state)?;
        let env = &mut guard.env;
        let c = *env.simulator().config();
        let (codes, lead) = f32_items(codes, "codes", &[2], &[c.z_dim])?;
        self.check_drives("codes", lead[1])?;
        let actions = self.actions_between(&c, actions, lead[0])?;
        let codes = slice(&codes);
        py.detach(|| env.reset_from_codes(codes, &actions)).map_err(to_py)
    }

    /// Samples every later step and rollout (`Simulator.set_sampling`): a step's noise is that
    /// of the steps since the last reset and the drive, so a reset and the same actions give
    /// the same drive again. Temperature 0 (the default): the mean. ValueError for a
    /// temperature below 0, or above 0 where the model cannot sample (`Model.samples`).
    fn set_sampling(&self, temperature: &Bound<'_, PyAny>, seed: &Bound<'_, PyAny>) -> PyResult<()> {
        let (temperature, seed) = (temperature_f32(temperature)?, count(seed, "seed", 0, u64::MAX)?);
        lock(&self.state)?.env.set_sampling(temperature, seed).map_err(to_py)
    }

    /// One step of every drive: `actions` `(drives, 2)`, (speed, steering) each.
    fn step(&self, py: Python<'_>, actions: &Bound<'_, PyAny>) -> PyResult<()> {
        let mut guard = lock(&self.state)?;
        let env = &mut guard.env;
        let c = *env.simulator().config();
        let (actions, lead) = f32_items(actions, "actions", &[1], &[c.action_dim])?;
        self.check_drives("actions", lead[0])?;
        let actions = slice(&actions);
        py.detach(|| env.step(actions)).map_err(to_py)
    }

    /// Each drive's current code, `(drives, z_dim)` (a copy); ValueError before a reset.
    #[getter]
    fn codes<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let guard = seeded(lock(&self.state)?)?;
        rows_copy(py, guard.env.codes(), self.drives, "the codes")
    }

    /// Each drive's hidden state, `(drives, hidden_dim)` (a copy); ValueError before a reset.
    #[getter]
    fn hidden<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let guard = seeded(lock(&self.state)?)?;
        rows_copy(py, guard.env.hidden(), self.drives, "the hidden states")
    }

    /// Each drive's current frame, generated: `(drives, height, width, 3)`, uint8 (the
    /// default) or float32 (`dtype=np.float32`).
    #[pyo3(signature = (dtype=None))]
    fn frames<'py>(&self, py: Python<'py>, dtype: Option<&Bound<'py, PyAny>>) -> PyResult<Bound<'py, PyAny>> {
        let kind = frame_type(py, dtype)?;
        let mut guard = lock(&self.state)?;
        let State { env, scratch } = &mut *guard;
        let c = *env.simulator().config();
        let shape = [self.drives, c.height, c.width, c.channels];
        frames_out(py, kind, &c, &shape, scratch, |f| env.frames(f))
    }

    /// Rolls out `N` candidate action sequences from drive `drive`'s state: `actions`
    /// `(T, N, 2)`; returns the codes `(T, N, z_dim)`, or with `frames=True` `(codes, frames)`.
    #[pyo3(signature = (drive, actions, frames=false, dtype=None))]
    fn rollout_candidates<'py>(
        &self,
        py: Python<'py>,
        drive: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        frames: bool,
        dtype: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let drive = size(drive, "drive", 0)?;
        let kind = frame_type(py, dtype)?;
        let mut guard = lock(&self.state)?;
        let State { env, scratch } = &mut *guard;
        let c = *env.simulator().config();
        let (actions, lead) = f32_items(actions, "actions", &[2], &[c.action_dim])?;
        let (steps, n) = (lead[0], lead[1]);
        let actions = slice(&actions);
        codes_and_frames(py, kind, &c, &[steps, n], frames, scratch, |codes, f| {
            env.rollout_candidates(drive, n, actions, codes, f)
        })
    }
}

/// The state when a reset gave the drives one, else the crate's `NotSeeded` (ValueError).
fn seeded(guard: MutexGuard<'_, State>) -> PyResult<MutexGuard<'_, State>> {
    match guard.env.is_seeded() {
        true => Ok(guard),
        false => Err(to_py(drivesim::Error::NotSeeded)),
    }
}

impl PyEnvironment {
    fn check_drives(&self, what: &str, found: usize) -> PyResult<()> {
        match found == self.drives {
            true => Ok(()),
            false => Err(value_error(format!(
                "{what}: expected {} drives, got {found}",
                self.drives
            ))),
        }
    }

    /// The actions between `seeds` seeds, `(seeds - 1, drives, action_dim)`, as a flat slice
    /// (a copy: they are few).
    fn actions_between(&self, c: &drivesim::Config, actions: &Bound<'_, PyAny>, seeds: usize) -> PyResult<Vec<f32>> {
        let a = if seeds == 1 {
            // One seed: no action between; accept an empty array of any leading shape.
            return Ok(Vec::new());
        } else {
            f32_items(actions, "actions", &[2], &[c.action_dim])?
        };
        if a.1 != [seeds - 1, self.drives] {
            return Err(value_error(format!(
                "actions: expected shape ({}, {}, {}) for {seeds} seeds, got {}",
                seeds - 1,
                self.drives,
                c.action_dim,
                shape_str(a.0.shape())
            )));
        }
        Ok(slice(&a.0).to_vec())
    }
}
