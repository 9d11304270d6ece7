//! numpy arrays in: each input checked for dtype, C order and shape with a `ValueError` that
//! names it, borrowed as a slice (no copy), and pinned for the call (see [`Borrowed`]); 8-bit
//! frames converted to the model's [-1, 1] floats. The arrays out are in `outputs`.

use crate::outputs::{grow, FrameType};
use crate::to_py;
use drivesim::{frames_from_rgb, Config, PixelLayout};
use numpy::npyffi::{self, NpyTypes, PY_ARRAY_API};
use numpy::{Element, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::exceptions::{PyOverflowError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyWeakrefReference;
use std::ops::Deref;

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

/// An input array borrowed for one call, safe against what another Python thread may do to
/// it while the call runs with the interpreter released:
///
/// - the numpy crate's borrow is of a private view made here (same memory, a new array object
///   no one else holds), so changing the caller's array's shape, strides or dtype in place
///   cannot change the borrow's key (which made its release panic, and the panic aborted);
/// - a weak reference to the array that owns the memory makes numpy refuse to reallocate it
///   (`resize(..., refcheck=False)` raises `ValueError` in that thread), so the slice stays
///   valid (issue 46: the resize freed the memory under the call, and the release aborted).
pub struct Borrowed<'py, T: Element> {
    // Declared first: the borrow is released before the pin goes.
    array: PyReadonlyArrayDyn<'py, T>,
    _pin: Bound<'py, PyWeakrefReference>,
}

impl<'py, T: Element> Deref for Borrowed<'py, T> {
    type Target = PyReadonlyArrayDyn<'py, T>;
    fn deref(&self) -> &Self::Target {
        &self.array
    }
}

/// The array at the end of `array`'s chain of bases: the one whose memory the others view.
fn owner<'py>(array: &Bound<'py, PyUntypedArray>) -> Bound<'py, PyAny> {
    let py = array.py();
    let mut current = array.as_array_ptr();
    loop {
        // SAFETY: `current` is a live array (the chain holds a reference to each base).
        let base = unsafe { (*npyffi::_PyArray_GET_ITEM_DATA(current)).base };
        // SAFETY: `base` is a live object or null.
        if base.is_null() || unsafe { npyffi::PyArray_Check(py, base) } == 0 {
            // SAFETY: a live array, borrowed from the chain.
            return unsafe { Bound::from_borrowed_ptr(py, current.cast()) };
        }
        current = base.cast();
    }
}

/// `obj` as a C-ordered array of `T`, borrowed and pinned ([`Borrowed`]).
pub fn array<'py, T: Element>(obj: &Bound<'py, PyAny>, what: &str, dtype: &str) -> PyResult<Borrowed<'py, T>> {
    let given = obj.cast::<PyArrayDyn<T>>().map_err(|_| {
        value_error(format!(
            "{what}: expected a numpy array of {dtype}, got {} (convert with np.asarray(x, dtype=np.{dtype}))",
            describe(obj)
        ))
    })?;
    if !given.is_c_contiguous() {
        return Err(value_error(format!(
            "{what}: expected a C-ordered (contiguous) array; use np.ascontiguousarray(x)"
        )));
    }
    let py = obj.py();
    let pin = PyWeakrefReference::new(&owner(given.as_untyped()))?;
    // SAFETY: a plain ndarray view of a live array, with its dtype (no Python code runs: the
    // base type has no `__array_finalize__`); the result is checked for null.
    let view = unsafe {
        let array_type = npyffi::get_type_object(py, NpyTypes::PyArray_Type);
        let view = PY_ARRAY_API.PyArray_View(py, given.as_array_ptr(), std::ptr::null_mut(), array_type);
        Bound::from_owned_ptr_or_err(py, view)?.cast_into_unchecked::<PyArrayDyn<T>>()
    };
    let array = view.try_readonly().map_err(|e| value_error(format!("{what}: {e}")))?;
    Ok(Borrowed { array, _pin: pin })
}

/// A float32 array whose shape is `lead` dimensions (any sizes, as many as `leads` allows)
/// followed by `tail`; returns the array and its leading dimensions.
pub fn f32_items<'py>(
    obj: &Bound<'py, PyAny>,
    what: &str,
    leads: &[usize],
    tail: &[usize],
) -> PyResult<(Borrowed<'py, f32>, Vec<usize>)> {
    let a = array::<f32>(obj, what, "float32")?;
    let lead = leading(a.shape(), what, leads, tail)?;
    Ok((a, lead))
}

/// Codes `(N, z_dim)` (named `what`) and hidden states `h` `(N, hidden_dim)`, or one of each,
/// checked to have the same leading dimensions, which are returned with them.
pub fn codes_and_states<'py>(
    c: &Config,
    z: &Bound<'py, PyAny>,
    what: &str,
    h: &Bound<'py, PyAny>,
) -> PyResult<(Borrowed<'py, f32>, Borrowed<'py, f32>, Vec<usize>)> {
    let (z, lead) = f32_items(z, what, &[0, 1], &[c.z_dim])?;
    let (h, h_lead) = f32_items(h, "h", &[0, 1], &[c.hidden_dim])?;
    if h_lead != lead {
        return Err(value_error(format!(
            "{what} and h must have the same leading dimensions: {lead:?} and {h_lead:?}"
        )));
    }
    Ok((z, h, lead))
}

/// A shape as Python writes it: `(3, 2)`, `(3,)`, `()`.
pub fn shape_str(shape: &[usize]) -> String {
    match shape {
        [one] => format!("({one},)"),
        dims => format!(
            "({})",
            dims.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")
        ),
    }
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
            "{what}: expected shape {}, got {}",
            forms.join(" or "),
            shape_str(shape)
        )));
    }
    let lead = shape[..shape.len() - tail.len()].to_vec();
    if lead.contains(&0) {
        return Err(value_error(format!("{what}: empty (shape {})", shape_str(shape))));
    }
    Ok(lead)
}

/// Frames given as `uint8` (0-255) or `float32` (in [-1, 1]), HWC.
pub enum Frames<'py> {
    U8(Borrowed<'py, u8>),
    F32(Borrowed<'py, f32>),
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
    /// `scratch` (grown to fit, or `MemoryError`: the one copy an 8-bit frame needs).
    pub fn floats<'a>(&'a self, config: &Config, scratch: &'a mut Vec<f32>) -> PyResult<&'a [f32]> {
        match self {
            Frames::F32(a) => Ok(a.as_slice().expect("checked C-ordered")),
            Frames::U8(a) => {
                let rgb = a.as_slice().expect("checked C-ordered");
                let out = grow(scratch, rgb.len())?;
                frames_from_rgb(rgb, PixelLayout::Hwc, config, out).map_err(to_py)?;
                Ok(out)
            }
        }
    }
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

/// A candidate rollout's checked arguments: `h`, `z` (each one for all candidates or one
/// each), the step-major actions `(T, N, action_dim)`, `T` and `N`.
#[allow(clippy::type_complexity)]
pub fn candidates<'py>(
    c: &drivesim::Config,
    h: &Bound<'py, PyAny>,
    actions: &Bound<'py, PyAny>,
    z: Option<&Bound<'py, PyAny>>,
) -> PyResult<(
    Borrowed<'py, f32>,
    Option<Borrowed<'py, f32>>,
    Borrowed<'py, f32>,
    usize,
    usize,
)> {
    let (actions, lead) = f32_items(actions, "actions", &[2], &[c.action_dim])?;
    let (steps, n) = (lead[0], lead[1]);
    let (h, h_lead) = f32_items(h, "h", &[0, 1], &[c.hidden_dim])?;
    one_or_each(&h, &h_lead, n, "h", c.hidden_dim)?;
    let z = z.map(|z| f32_items(z, "z", &[0, 1], &[c.z_dim])).transpose()?;
    if let Some((z, z_lead)) = &z {
        one_or_each(z, z_lead, n, "z", c.z_dim)?;
    }
    Ok((h, z.map(|z| z.0), actions, steps, n))
}

/// `h` or `z` of a candidate rollout: one `(dim,)` for all `n` candidates, or one each
/// `(n, dim)`; a ValueError with the shapes otherwise.
fn one_or_each(a: &Borrowed<'_, f32>, lead: &[usize], n: usize, what: &str, dim: usize) -> PyResult<()> {
    match lead {
        [] => Ok(()),
        [rows] if *rows == n => Ok(()),
        _ => Err(value_error(format!(
            "{what}: expected shape ({dim},) or ({n}, {dim}) for the {n} candidates of actions, got {}",
            shape_str(a.shape())
        ))),
    }
}

/// A checked array's values.
pub fn slice<'a>(a: &'a Borrowed<'_, f32>) -> &'a [f32] {
    a.as_slice().expect("checked C-ordered")
}

/// A temperature argument as the crate's f32: a number (TypeError otherwise) that is finite
/// and does not overflow f32 (ValueError otherwise; the crate rejects what is below 0).
pub fn temperature_f32(t: &Bound<'_, PyAny>) -> PyResult<f32> {
    let out_of_range = || value_error(format!("temperature is {t}: expected a finite number >= 0"));
    let value = t
        .extract::<f64>()
        .map_err(|e| match e.is_instance_of::<PyOverflowError>(t.py()) {
            true => out_of_range(), // an integer beyond any float
            false => e,
        })?;
    match value.is_finite() && value.abs() <= f32::MAX as f64 {
        true => Ok(value as f32),
        false => Err(out_of_range()),
    }
}

/// The frame type a `dtype` argument asks for (uint8 when None).
pub fn frame_type(py: Python<'_>, dtype: Option<&Bound<'_, PyAny>>) -> PyResult<FrameType> {
    dtype.map_or(Ok(FrameType::U8), |d| FrameType::parse(py, d))
}
