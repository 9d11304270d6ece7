//! numpy arrays out: every result is a new C-ordered array, allocated fallibly before the
//! simulator is touched (a size that overflows or that the allocator refuses is `MemoryError`,
//! never a panic), then filled with the interpreter released; 8-bit frames converted from the
//! model's [-1, 1] floats.

use crate::to_py;
use drivesim::{frames_to_rgb, Config, PixelLayout};
use numpy::npyffi::{npy_intp, PY_ARRAY_API};
use numpy::{Element, PyArrayDescrMethods, PyArrayDyn, PyArrayMethods};
use pyo3::exceptions::PyMemoryError;
use pyo3::prelude::*;

/// A `MemoryError` for `what`, `bytes` (None: more than the address space) in all.
fn memory_error(what: &str, bytes: Option<usize>) -> PyErr {
    PyMemoryError::new_err(match bytes {
        Some(b) => format!(
            "cannot allocate {what}: {b} bytes ({:.1} GiB)",
            b as f64 / (1u64 << 30) as f64
        ),
        None => format!("cannot allocate {what}: its size overflows the address space"),
    })
}

/// A new zeroed C-ordered array of `shape` (the result `what`, for a message), or
/// `MemoryError` when its size overflows or numpy cannot allocate it.
pub fn new_array<'py, T: Element>(py: Python<'py>, shape: &[usize], what: &str) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    let bytes = shape
        .iter()
        .try_fold(std::mem::size_of::<T>(), |n, &d| n.checked_mul(d))
        .filter(|&b| b <= isize::MAX as usize);
    if bytes.is_none() {
        return Err(memory_error(what, None));
    }
    // Every dimension fits npy_intp: their product in bytes does.
    let mut dims: Vec<npy_intp> = shape.iter().map(|&d| d as npy_intp).collect();
    // SAFETY: `dims` holds `shape.len()` dimensions; PyArray_Zeros steals the dtype reference
    // and returns a new reference, or null with numpy's MemoryError set.
    unsafe {
        let ptr = PY_ARRAY_API.PyArray_Zeros(
            py,
            dims.len() as std::os::raw::c_int,
            dims.as_mut_ptr(),
            T::get_dtype(py).into_dtype_ptr(),
            0,
        );
        match Bound::from_owned_ptr_or_err(py, ptr) {
            Ok(array) => Ok(array.cast_into_unchecked()),
            Err(_) => Err(memory_error(what, bytes)),
        }
    }
}

/// `scratch` grown to at least `len` floats (or `MemoryError`), its first `len`.
pub fn grow(scratch: &mut Vec<f32>, len: usize) -> PyResult<&mut [f32]> {
    if scratch.len() < len {
        let more = len - scratch.len();
        scratch
            .try_reserve_exact(more)
            .map_err(|_| memory_error("the frames' scratch", len.checked_mul(4)))?;
        scratch.resize(len, 0.0);
    }
    Ok(&mut scratch[..len])
}

/// Frames the crate writes, returned as the requested type in a new array of `shape`: `fill`
/// writes the model's floats straight into a float32 result, or into `scratch` (grown to fit)
/// for an 8-bit one, converted then. Everything is allocated before `fill` runs, with the
/// interpreter released.
pub fn frames_out<'py, F>(
    py: Python<'py>,
    kind: FrameType,
    config: &Config,
    shape: &[usize],
    scratch: &mut Vec<f32>,
    fill: F,
) -> PyResult<Bound<'py, PyAny>>
where
    F: FnOnce(&mut [f32]) -> drivesim::Result<()> + Send,
{
    match kind {
        FrameType::F32 => {
            let out = new_array::<f32>(py, shape, "the frames")?;
            // SAFETY: the array was just created here and no other reference to it exists.
            let floats = unsafe { out.as_slice_mut() }.expect("a new array is contiguous");
            py.detach(|| fill(floats)).map_err(to_py)?;
            Ok(out.into_any())
        }
        FrameType::U8 => {
            let out = new_array::<u8>(py, shape, "the frames")?;
            // SAFETY: as above.
            let rgb = unsafe { out.as_slice_mut() }.expect("a new array is contiguous");
            let floats = grow(scratch, rgb.len())?;
            py.detach(|| {
                fill(floats)?;
                frames_to_rgb(floats, PixelLayout::Hwc, config, rgb)
            })
            .map_err(to_py)?;
            Ok(out.into_any())
        }
    }
}

/// The codes `run` writes into a new array `(*lead, z_dim)`, and with `frames` the frames it
/// writes too, `(*lead, height, width, channels)` (as `frames_out` returns them): the codes
/// alone, or `(codes, frames)`. `run` runs with the interpreter released, after every allocation.
pub fn codes_and_frames<'py, F>(
    py: Python<'py>,
    kind: FrameType,
    config: &Config,
    lead: &[usize],
    frames: bool,
    scratch: &mut Vec<f32>,
    run: F,
) -> PyResult<Bound<'py, PyAny>>
where
    F: FnOnce(&mut [f32], Option<&mut [f32]>) -> drivesim::Result<()> + Send,
{
    let with = |tail: &[usize]| [lead, tail].concat();
    let codes = new_array::<f32>(py, &with(&[config.z_dim]), "the codes")?;
    // SAFETY: the array was just created here and no other reference to it exists.
    let codes_out = unsafe { codes.as_slice_mut() }.expect("a new array is contiguous");
    if !frames {
        py.detach(|| run(codes_out, None)).map_err(to_py)?;
        return Ok(codes.into_any());
    }
    let shape = with(&[config.height, config.width, config.channels]);
    let frames = frames_out(py, kind, config, &shape, scratch, |f| run(codes_out, Some(f)))?;
    Ok((codes, frames).into_pyobject(py)?.into_any())
}

/// A copy of `data`, `rows` rows of equal length, as a new `(rows, len / rows)` array.
pub fn rows_copy<'py>(py: Python<'py>, data: &[f32], rows: usize, what: &str) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    let out = new_array::<f32>(py, &[rows, data.len() / rows], what)?;
    // SAFETY: the array was just created here and no other reference to it exists.
    unsafe { out.as_slice_mut() }
        .expect("a new array is contiguous")
        .copy_from_slice(data);
    Ok(out)
}

/// Which frames a call returns: 8-bit (the default) or the model's floats.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum FrameType {
    U8,
    F32,
}
