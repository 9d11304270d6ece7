//! The `drivesim._drivesim` extension module: the crate's `Model`, `Simulator` and
//! `Environment` on numpy arrays. The Python package (`python/drivesim/`) re-exports them and
//! adds the gymnasium environments and the agents.
//!
//! Every call checks its arrays (dtype, shape, C order) before it touches the crate, computes
//! with the interpreter released (`Python::detach`), and turns the crate's `Error` into
//! `ValueError`, `OSError` or `MemoryError` with the crate's message: nothing panics through.

mod arrays;
mod environment;
mod model;
mod outputs;
mod simulator;
mod view;

use pyo3::exceptions::{
    PyFileNotFoundError, PyMemoryError, PyOSError, PyOverflowError, PyPermissionError, PyRuntimeError, PyTypeError,
    PyValueError,
};
use pyo3::prelude::*;

/// The crate's error as the Python exception a caller expects: files are `OSError` (its
/// subclasses where the cause says which), a plan too large `MemoryError`, threads the system
/// would not start `RuntimeError`, and everything about the values given `ValueError`.
pub(crate) fn to_py(e: drivesim::Error) -> PyErr {
    let mut message = e.to_string();
    let mut source = std::error::Error::source(&e);
    while let Some(s) = source {
        message = format!("{message}: {s}");
        source = s.source();
    }
    match &e {
        drivesim::Error::Io { source, .. } => match source.kind() {
            std::io::ErrorKind::NotFound => PyFileNotFoundError::new_err(message),
            std::io::ErrorKind::PermissionDenied => PyPermissionError::new_err(message),
            _ => PyOSError::new_err(message),
        },
        drivesim::Error::OutOfMemory { .. } => PyMemoryError::new_err(message),
        drivesim::Error::Threads { .. } => PyRuntimeError::new_err(message),
        _ => PyValueError::new_err(message),
    }
}

/// A count argument (`batch`, `threads`, `drives`, a seed, an index): an integer (anything
/// with `__index__`, e.g. `np.int64`) from `min` to `max`, else `TypeError` (not an integer) or
/// `ValueError` (out of range), naming `what`.
pub(crate) fn count(obj: &Bound<'_, PyAny>, what: &str, min: u64, max: u64) -> PyResult<u64> {
    let out_of_range = || PyValueError::new_err(format!("{what}: expected an integer from {min} to {max}, got {obj}"));
    match obj.extract::<u64>() {
        Ok(v) if (min..=max).contains(&v) => Ok(v),
        Ok(_) => Err(out_of_range()),
        // Below 0 or beyond 2**64 - 1.
        Err(e) if e.is_instance_of::<PyOverflowError>(obj.py()) => Err(out_of_range()),
        Err(_) => Err(PyTypeError::new_err(format!(
            "{what}: expected an integer, got {}",
            obj.get_type().name().map_or("a value".into(), |n| n.to_string())
        ))),
    }
}

/// A count argument that fits `usize` ([`count`]), at least `min`.
pub(crate) fn size(obj: &Bound<'_, PyAny>, what: &str, min: usize) -> PyResult<usize> {
    Ok(count(obj, what, min as u64, usize::MAX as u64)? as usize)
}

/// Locks a simulator or an environment (`what`) for one call. A second thread's call on the
/// same object is an error (each thread should have its own) rather than a wait: waiting for
/// the lock while holding the interpreter could deadlock against the call that holds it.
pub(crate) fn lock<'a, T>(state: &'a std::sync::Mutex<T>, what: &str) -> PyResult<std::sync::MutexGuard<'a, T>> {
    state.try_lock().map_err(|e| match e {
        std::sync::TryLockError::WouldBlock => PyRuntimeError::new_err(format!(
            "this {what} is in use by another thread: give each thread its own"
        )),
        std::sync::TryLockError::Poisoned(_) => {
            PyRuntimeError::new_err(format!("this {what} failed in another thread"))
        }
    })
}

#[pymodule]
fn _drivesim(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<model::PyModel>()?;
    m.add_class::<simulator::PySimulator>()?;
    m.add_class::<environment::PyEnvironment>()?;
    m.add_function(wrap_pyfunction!(model::load_episodes, m)?)?;
    m.add_function(wrap_pyfunction!(model::world_fingerprint, m)?)?;
    m.add_function(wrap_pyfunction!(model::driver_file, m)?)?;
    m.add_function(wrap_pyfunction!(model::sampler_file, m)?)?;
    m.add_function(wrap_pyfunction!(view::box_shrink, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
