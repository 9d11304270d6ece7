//! `Model`: loaded weights (the default model is built into the module), and recorded episodes.

use crate::to_py;
use drivesim::{Episodes, Model};
use numpy::{PyArray1, PyArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::path::PathBuf;
use std::sync::Arc;

/// The default model's weights, built in so that `Model.load()` needs no file.
static DEFAULT_WEIGHTS: &[u8] = include_bytes!("../../weights/default.safetensors");
/// The seed clip that `hallucinate` and the dream environments start from by default.
static SEED_CLIP: &[u8] = include_bytes!("../../weights/seed_clip.safetensors");
/// The driver learnt in the default model's dream (`weights/tool train driver`), built in so
/// that `Model.dreamt()` needs no file either.
static DREAMT_DRIVER: &[u8] = include_bytes!("../../weights/dreamt.safetensors");
/// The judge's sampler: a texture net learnt for the default's transition and the default's
/// read-out widened, whose futures rank drivers as the real track does (docs/judging.md), built
/// in for `Model.judge()`.
static JUDGE_SAMPLER: &[u8] = include_bytes!("../../weights/judge.safetensors");

/// The bytes of the weight file at `path`, or the built-in default's.
fn world_bytes(path: &Option<PathBuf>) -> drivesim::Result<std::borrow::Cow<'static, [u8]>> {
    Ok(match path {
        Some(path) => std::borrow::Cow::Owned(read(path)?),
        None => std::borrow::Cow::Borrowed(DEFAULT_WEIGHTS),
    })
}

fn read(path: &std::path::Path) -> drivesim::Result<Vec<u8>> {
    std::fs::read(path).map_err(|source| drivesim::Error::Io {
        path: path.display().to_string(),
        source,
    })
}

/// A loaded model: encoder, transition and generator weights, checked on load.
///
/// `Model.load()` gives the default model (trained on CarRacing, 80x160 frames); `Model.load(path)`
/// reads a weight file written by the crate's trainers or `weights/tool export`. One model can
/// serve many simulators: they share its weights.
#[pyclass(module = "drivesim", name = "Model", frozen)]
pub struct PyModel {
    pub(crate) inner: Arc<Model>,
}

#[pymethods]
impl PyModel {
    /// Loads a weight file (safetensors), or the built-in default model when `path` is None.
    ///
    /// Raises OSError when the file cannot be read and ValueError when it is not a valid weight
    /// file (the message says which tensor or field is wrong).
    ///
    /// `driver`: a driver file (`python -m drivesim driver` writes one) whose policy replaces the
    /// file's, its pace head left out; ValueError when the driver was learnt in another world.
    /// `sampler`: a sampler file (`python -m drivesim sampler` writes one) whose texture net
    /// draws the sampled futures in place of the file's (and whose read-out, where it has one,
    /// gives the mean dream); ValueError when it was learnt for
    /// another world, or when both are given (a driver learnt in one dream, judged in another).
    #[staticmethod]
    #[pyo3(signature = (path=None, driver=None, sampler=None))]
    fn load(
        py: Python<'_>,
        path: Option<PathBuf>,
        driver: Option<PathBuf>,
        sampler: Option<PathBuf>,
    ) -> PyResult<PyModel> {
        if driver.is_some() && sampler.is_some() {
            return Err(pyo3::exceptions::PyValueError::new_err(
                "Model.load: a driver file or a sampler file, not both (the driver was learnt in its world's own sampler)",
            ));
        }
        let model = py.detach(|| {
            let world = world_bytes(&path)?;
            match (driver, sampler) {
                (Some(driver), _) => Model::from_bytes_with_driver(&world, &read(&driver)?),
                (_, Some(sampler)) => Model::from_bytes_with_sampler(&world, &read(&sampler)?),
                _ => Model::from_bytes(&world),
            }
        });
        Ok(PyModel {
            inner: Arc::new(model.map_err(to_py)?),
        })
    }

    /// The world of `path` (None: the built-in default) dreamt through the judge's sampler
    /// (built in): the texture net whose sampled futures rank drivers as the real track does,
    /// learnt for the default's transition, and the default's read-out widened
    /// (`python -m drivesim widen`; ValueError for another world). What
    /// `python -m drivesim.carracing.rank --judge` dreams with.
    #[staticmethod]
    #[pyo3(signature = (path=None))]
    fn judge(py: Python<'_>, path: Option<PathBuf>) -> PyResult<PyModel> {
        let model = py.detach(|| Model::from_bytes_with_sampler(&world_bytes(&path)?, JUDGE_SAMPLER));
        Ok(PyModel {
            inner: Arc::new(model.map_err(to_py)?),
        })
    }

    /// The default model driven by the driver learnt in its dream (built in, as the default
    /// is): what `make_agent("dreamt")` drives.
    #[staticmethod]
    fn dreamt(py: Python<'_>) -> PyResult<PyModel> {
        let model = py.detach(|| Model::from_bytes_with_driver(DEFAULT_WEIGHTS, DREAMT_DRIVER));
        Ok(PyModel {
            inner: Arc::new(model.map_err(to_py)?),
        })
    }

    /// Reads a model from the bytes of a weight file.
    #[staticmethod]
    fn from_bytes(py: Python<'_>, data: &[u8]) -> PyResult<PyModel> {
        let model = py.detach(|| Model::from_bytes(data)).map_err(to_py)?;
        Ok(PyModel { inner: Arc::new(model) })
    }

    /// The architecture: a dict of `height`, `width`, `channels`, `base_channels`, `layers`,
    /// `kernel`, `z_dim`, `hidden_dim`, `action_dim`.
    #[getter]
    fn config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let c = self.inner.config();
        let d = PyDict::new(py);
        for (k, v) in [
            ("height", c.height),
            ("width", c.width),
            ("channels", c.channels),
            ("base_channels", c.base_channels),
            ("layers", c.layers),
            ("kernel", c.kernel),
            ("z_dim", c.z_dim),
            ("hidden_dim", c.hidden_dim),
            ("action_dim", c.action_dim),
        ] {
            d.set_item(k, v)?;
        }
        Ok(d)
    }

    /// `(height, width, channels)` of a frame.
    #[getter]
    fn frame_shape(&self) -> (usize, usize, usize) {
        let c = self.inner.config();
        (c.height, c.width, c.channels)
    }

    /// Values in a latent code.
    #[getter]
    fn z_dim(&self) -> usize {
        self.inner.config().z_dim
    }

    /// Values in the transition's hidden state.
    #[getter]
    fn hidden_dim(&self) -> usize {
        self.inner.config().hidden_dim
    }

    /// Values in an action: 2, (speed, steering).
    #[getter]
    fn action_dim(&self) -> usize {
        self.inner.config().action_dim
    }

    /// Frames per second the model was trained at (one transition step is `1 / frame_hz`
    /// seconds), or None when the file does not say.
    #[getter]
    fn frame_hz(&self) -> Option<f32> {
        self.inner.frame_hz()
    }

    /// Units of the hidden layer of the model's policy (the cloned driver that
    /// `Simulator.act` runs), or None where the weight file has none.
    #[getter]
    fn policy_width(&self) -> Option<usize> {
        self.inner.policy_width()
    }

    /// Units of the hidden layer of the reward head (`Simulator.reward`,
    /// `Simulator.rollout_candidates_scored`), or None where the weight file has none.
    #[getter]
    fn reward_width(&self) -> Option<usize> {
        self.inner.head_width(drivesim::HeadKind::Reward)
    }

    /// Units of the hidden layer of the value head (`Simulator.value`), or None.
    #[getter]
    fn value_width(&self) -> Option<usize> {
        self.inner.head_width(drivesim::HeadKind::Value)
    }

    /// Units of the hidden layer of the pace head (`Simulator.pace`), or None.
    #[getter]
    fn pace_width(&self) -> Option<usize> {
        self.inner.head_width(drivesim::HeadKind::Pace)
    }

    /// The discount per decision of the value head's returns (the file's `drivesim.discount`),
    /// or None when the file does not say.
    #[getter]
    fn discount(&self) -> Option<f32> {
        self.inner.discount()
    }

    /// Whether the transition can sample its codes, so that simulators can sample futures
    /// (`Simulator.set_sampling`): it predicts their spread (`transition.S`, `transition.s`)
    /// or it has the texture net (`texture_width`).
    #[getter]
    fn samples(&self) -> bool {
        self.inner.samples()
    }

    /// Units of the texture net's hidden layer (`transition.texture.*`, `train.py texture`), or
    /// None: a sampler trained adversarially so that sampled futures keep the road's kerbs and
    /// grass patches; where a file has it, sampling draws through it, not the spread head.
    #[getter]
    fn texture_width(&self) -> Option<usize> {
        self.inner.texture_width()
    }

    /// Whether sampled noise is correlated across the code's dimensions (`transition.L`, fitted
    /// by `train transition` from the one-step errors); otherwise each dimension draws alone.
    #[getter]
    fn samples_correlated(&self) -> bool {
        self.inner.samples_correlated()
    }

    /// What each action means and the range it was trained on (the file's `drivesim.actions`):
    /// a list of dicts with `name`, `unit`, `mean`, `std`, `min`, `max`, or None.
    #[getter]
    fn actions<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyList>>> {
        let Some(specs) = self.inner.actions() else {
            return Ok(None);
        };
        let list = PyList::empty(py);
        for s in specs {
            let d = PyDict::new(py);
            d.set_item("name", &s.name)?;
            d.set_item("unit", &s.unit)?;
            for (k, v) in [("mean", s.mean), ("std", s.std), ("min", s.min), ("max", s.max)] {
                d.set_item(k, v)?;
            }
            list.append(d)?;
        }
        Ok(Some(list))
    }

    fn __repr__(&self) -> String {
        let c = self.inner.config();
        format!(
            "Model(frame={}x{}x{}, base_channels={}, z_dim={}, hidden_dim={}, action_dim={})",
            c.height, c.width, c.channels, c.base_channels, c.z_dim, c.hidden_dim, c.action_dim
        )
    }
}

/// Recorded driving: a list of `(frames, actions)` per episode, frames `uint8` of shape
/// `(T, height, width, 3)` and actions `float32` of shape `(T, 2)` (speed, steering in effect at
/// each frame). Reads an episodes file (`.safetensors`, or gzipped `.safetensors.gz` as
/// `python -m drivesim record` writes them), or the built-in seed clip when `path` is None.
#[pyfunction]
#[pyo3(signature = (path=None))]
pub fn load_episodes<'py>(
    py: Python<'py>,
    path: Option<PathBuf>,
) -> PyResult<Vec<(Bound<'py, PyAny>, Bound<'py, PyAny>)>> {
    let episodes = py
        .detach(|| match path {
            Some(path) => Episodes::load(path),
            None => Episodes::from_bytes(SEED_CLIP),
        })
        .map_err(to_py)?;
    let (height, width) = episodes.frame_size();
    let mut out = Vec::with_capacity(episodes.len());
    for i in 0..episodes.len() {
        let e = episodes.episode(i).map_err(to_py)?;
        let frames = PyArray1::from_slice(py, e.frames).reshape([e.len(), height, width, Episodes::CHANNELS])?;
        let actions = PyArray1::from_slice(py, e.actions).reshape([e.len(), Episodes::ACTION_DIM])?;
        out.push((frames.into_any(), actions.into_any()));
    }
    Ok(out)
}

/// The fingerprint of the world a weight file holds (16 hexadecimal digits): what a driver
/// file names as the world it was learnt in (`weights/README.md`).
#[pyfunction]
pub fn world_fingerprint(py: Python<'_>, path: PathBuf) -> PyResult<String> {
    py.detach(|| drivesim::world_fingerprint(&read(&path)?)).map_err(to_py)
}

/// The bytes of the sampler file of a weight file's texture net for the world of `world` (a
/// weight file that is the same world but for its texture net and read-out): its
/// `transition.texture.*` tensors, its read-out where that is not the world's, and that world's
/// fingerprint (`weights/README.md`).
#[pyfunction]
pub fn sampler_file<'py>(py: Python<'py>, path: PathBuf, world: PathBuf) -> PyResult<Bound<'py, pyo3::types::PyBytes>> {
    let bytes = py
        .detach(|| drivesim::sampler_file(&read(&path)?, &read(&world)?))
        .map_err(to_py)?;
    Ok(pyo3::types::PyBytes::new(py, &bytes))
}

/// The bytes of the driver file of a weight file whose policy is a driver: its `policy.*`
/// tensors and its world's fingerprint (`weights/README.md`).
#[pyfunction]
pub fn driver_file<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, pyo3::types::PyBytes>> {
    let bytes = py.detach(|| drivesim::driver_file(&read(&path)?)).map_err(to_py)?;
    Ok(pyo3::types::PyBytes::new(py, &bytes))
}
