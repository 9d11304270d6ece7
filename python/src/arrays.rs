//! numpy arrays in and out: each input checked for dtype, C order and shape with a
//! `ValueError` that names it, borrowed as a slice (no copy); 8-bit frames converted to and
//! from the model's [-1, 1] floats.

use crate::to_py;
use drivesim::{frames_from_rgb, frames_to_rgb, Config, PixelLayout};
use numpy::{Element, PyArray, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

/// A `ValueError` with this message.
pub fn value_error(message: String) -> PyErr {
    PyValueError::new_err(message)
}

/// What `obj` is, for a message: `an array of float64` or `a list`.
fn describe(obj: &Bound<'_, PyAny>) -> String {
    match obj.cast::<numpy::PyUntypedArray>() {
        Ok(a) => format!("an array of {}", a.dtype()),
        Err(_) => format!("a {}", obj.get_type().name().map_or("value".into(), |n| n.to_string())),
    }
}

/// `obj` as a C-ordered array of `T`, borrowed.
pub fn array<'py, T: Element>(
    obj: &Bound<'py, PyAny>,
    what: &str,
    dtype: &str,
) -> PyResult<PyReadonlyArrayDyn<'py, T>> {
    let array = obj.cast::<PyArrayDyn<T>>().map_err(|_| {
        value_error(format!(
            "{what}: expected a numpy array of {dtype}, got {} (convert with np.asarray(x, dtype=np.{dtype}))",
            describe(obj)
        ))
    })?;
    let array = array.try_readonly().map_err(|e| value_error(format!("{what}: {e}")))?;
    if !array.is_c_contiguous() {
        return Err(value_error(format!(
            "{what}: expected a C-ordered (contiguous) array; use np.ascontiguousarray(x)"
        )));
    }
    Ok(array)
}

/// A float32 array whose shape is `lead` dimensions (any sizes, as many as `leads` allows)
/// followed by `tail`; returns the array and its leading dimensions.
pub fn f32_items<'py>(
    obj: &Bound<'py, PyAny>,
    what: &str,
    leads: &[usize],
    tail: &[usize],
) -> PyResult<(PyReadonlyArrayDyn<'py, f32>, Vec<usize>)> {
    let a = array::<f32>(obj, what, "float32")?;
    let lead = leading(a.shape(), what, leads, tail)?;
    Ok((a, lead))
}

/// The leading dimensions of `shape` when it ends in `tail` and has one of `leads` more.
pub fn leading(shape: &[usize], what: &str, leads: &[usize], tail: &[usize]) -> PyResult<Vec<usize>> {
    let ok = shape.len() >= tail.len()
        && shape[shape.len() - tail.len()..] == *tail
        && leads.contains(&(shape.len() - tail.len()));
    if !ok {
        let names = ["N", "T", "S"];
        let forms: Vec<String> = leads
            .iter()
            .map(|&n| {
                let dims: Vec<String> = names[..n]
                    .iter()
                    .rev()
                    .map(|s| s.to_string())
                    .chain(tail.iter().map(|d| d.to_string()))
                    .collect();
                format!("({})", dims.join(", "))
            })
            .collect();
        return Err(value_error(format!(
            "{what}: expected shape {}, got {shape:?}",
            forms.join(" or ")
        )));
    }
    let lead = shape[..shape.len() - tail.len()].to_vec();
    if lead.contains(&0) {
        return Err(value_error(format!("{what}: empty (shape {shape:?})")));
    }
    Ok(lead)
}

/// Frames given as `uint8` (0-255) or `float32` (in [-1, 1]), HWC.
pub enum Frames<'py> {
    U8(PyReadonlyArrayDyn<'py, u8>),
    F32(PyReadonlyArrayDyn<'py, f32>),
}

impl<'py> Frames<'py> {
    /// `obj` as frames of `config`'s shape with `leads` leading dimensions; returns them and
    /// the leading dimensions.
    pub fn new(obj: &Bound<'py, PyAny>, what: &str, config: &Config, leads: &[usize]) -> PyResult<(Self, Vec<usize>)> {
        let tail = [config.height, config.width, config.channels];
        let frames = if obj.cast::<PyArrayDyn<u8>>().is_ok() {
            Frames::U8(array::<u8>(obj, what, "uint8")?)
        } else if obj.cast::<PyArrayDyn<f32>>().is_ok() {
            Frames::F32(array::<f32>(obj, what, "float32")?)
        } else {
            return Err(value_error(format!(
                "{what}: expected a numpy array of uint8 (0-255) or float32 (in [-1, 1]), got {}",
                describe(obj)
            )));
        };
        let shape = match &frames {
            Frames::U8(a) => a.shape().to_vec(),
            Frames::F32(a) => a.shape().to_vec(),
        };
        let lead = leading(&shape, what, leads, &tail)?;
        Ok((frames, lead))
    }

    /// The frames as the model's floats: borrowed when given as float32, else converted into
    /// `scratch` (grown to fit: the one copy an 8-bit frame needs).
    pub fn floats<'a>(&'a self, config: &Config, scratch: &'a mut Vec<f32>) -> PyResult<&'a [f32]> {
        match self {
            Frames::F32(a) => Ok(a.as_slice().expect("checked C-ordered")),
            Frames::U8(a) => {
                let rgb = a.as_slice().expect("checked C-ordered");
                if scratch.len() < rgb.len() {
                    scratch.resize(rgb.len(), 0.0);
                }
                let out = &mut scratch[..rgb.len()];
                frames_from_rgb(rgb, PixelLayout::Hwc, config, out).map_err(to_py)?;
                Ok(out)
            }
        }
    }
}

/// Which frames a call returns: 8-bit (the default) or the model's floats.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum FrameType {
    U8,
    F32,
}

impl FrameType {
    /// From a `dtype` argument: anything `np.dtype` accepts that means uint8 or float32.
    pub fn parse(py: Python<'_>, dtype: &Bound<'_, PyAny>) -> PyResult<Self> {
        let name: String = py
            .import("numpy")?
            .getattr("dtype")?
            .call1((dtype,))
            .map_err(|_| value_error(format!("dtype: not a numpy dtype: {dtype}")))?
            .getattr("name")?
            .extract()?;
        match name.as_str() {
            "uint8" => Ok(FrameType::U8),
            "float32" => Ok(FrameType::F32),
            other => Err(value_error(format!("dtype: frames are uint8 or float32, not {other}"))),
        }
    }
}

/// A new C-ordered array of `shape`, zeroed.
pub fn new_array<'py, T: Element>(py: Python<'py>, shape: &[usize]) -> Bound<'py, PyArrayDyn<T>> {
    PyArray::zeros(py, shape.to_vec(), false)
}

/// Frames the crate writes, returned as the requested type in a new array of `shape`: `fill`
/// writes the model's floats straight into a float32 result, or into `scratch` (grown to fit)
/// for an 8-bit one, converted then. `fill` runs with the interpreter released.
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
            let out = new_array::<f32>(py, shape);
            // SAFETY: the array was just created here and no other reference to it exists.
            let floats = unsafe { out.as_slice_mut() }.expect("a new array is contiguous");
            py.detach(|| fill(floats)).map_err(to_py)?;
            Ok(out.into_any())
        }
        FrameType::U8 => {
            let out = new_array::<u8>(py, shape);
            // SAFETY: as above.
            let rgb = unsafe { out.as_slice_mut() }.expect("a new array is contiguous");
            if scratch.len() < rgb.len() {
                scratch.resize(rgb.len(), 0.0);
            }
            let floats = &mut scratch[..rgb.len()];
            py.detach(|| {
                fill(floats)?;
                frames_to_rgb(floats, PixelLayout::Hwc, config, rgb)
            })
            .map_err(to_py)?;
            Ok(out.into_any())
        }
    }
}

/// The codes `run` writes into a new array of `codes_shape`, and when `frames_shape` is given
/// the frames it writes too (as `frames_out` returns them): the codes alone, or
/// `(codes, frames)`. `run` runs with the interpreter released.
pub fn codes_and_frames<'py, F>(
    py: Python<'py>,
    kind: FrameType,
    config: &Config,
    codes_shape: &[usize],
    frames_shape: Option<&[usize]>,
    scratch: &mut Vec<f32>,
    run: F,
) -> PyResult<Bound<'py, PyAny>>
where
    F: FnOnce(&mut [f32], Option<&mut [f32]>) -> drivesim::Result<()> + Send,
{
    let codes = new_array::<f32>(py, codes_shape);
    // SAFETY: the array was just created here and no other reference to it exists.
    let codes_out = unsafe { codes.as_slice_mut() }.expect("a new array is contiguous");
    let Some(shape) = frames_shape else {
        py.detach(|| run(codes_out, None)).map_err(to_py)?;
        return Ok(codes.into_any());
    };
    let frames = frames_out(py, kind, config, shape, scratch, |f| run(codes_out, Some(f)))?;
    Ok((codes, frames).into_pyobject(py)?.into_any())
}

/// A copy of `data`, `rows` rows of equal length, as a new `(rows, len / rows)` array.
pub fn rows_copy<'py>(py: Python<'py>, data: &[f32], rows: usize) -> Bound<'py, PyArrayDyn<f32>> {
    let out = new_array::<f32>(py, &[rows, data.len() / rows]);
    // SAFETY: the array was just created here and no other reference to it exists.
    unsafe { out.as_slice_mut() }
        .expect("a new array is contiguous")
        .copy_from_slice(data);
    out
}
