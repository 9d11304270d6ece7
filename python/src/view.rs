//! `box_shrink`: an 8-bit image shrunk with Pillow's `Image.BOX` filter, byte for byte, for
//! CarRacing's view (`drivesim.carracing.observe`): the env's 1000x800 surface read in place
//! and shrunk 6.25x in about a tenth of a millisecond, where copying it to Pillow took 10-15.
//!
//! Pillow's resampling (`libImaging/Resample.c`), which this follows exactly: per output pixel
//! a window of input pixels whose centres fall in the box `((x) * scale, (x + 1) * scale]`,
//! each weighted `1 / count`; the weights in 22-bit fixed point (`PRECISION_BITS = 32 - 8 - 2`,
//! rounded half away from zero); a horizontal pass over every row, rounded to bytes, then a
//! vertical pass over its result, rounded again (`(sum + 2^21) >> 22`, clamped to 0..=255).

use crate::arrays::{array, value_error};
use crate::outputs::new_array;
use numpy::{PyArrayDyn, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;

const PRECISION_BITS: u32 = 32 - 8 - 2;
const MAX_SIDE: usize = 1 << 22;

/// One output pixel's window: `count` input pixels from `first`, each weighted `weight`.
/// (The box filter weighs every pixel of its window alike, so Pillow's sum of pixel times
/// weight is the window's sum times the weight, the same integer.)
struct Window {
    first: usize,
    count: usize,
    weight: i32,
}

/// Pillow's `precompute_coeffs` for the box filter, then `normalize_coeffs_8bpc`.
fn windows(in_size: usize, out_size: usize) -> Vec<Window> {
    let scale = in_size as f64 / out_size as f64;
    let filter_scale = scale.max(1.0);
    let support = 0.5 * filter_scale;
    (0..out_size)
        .map(|xx| {
            let centre = (xx as f64 + 0.5) * scale;
            // Pillow truncates towards zero (`(int)`); both values are >= -0.5 here.
            let xmin = ((centre - support + 0.5) as i64).max(0) as usize;
            let xmax = ((centre + support + 0.5) as i64).min(in_size as i64) as usize;
            let inside = |x: &usize| {
                let t = (*x as f64 - centre + 0.5) / filter_scale;
                t > -0.5 && t <= 0.5
            };
            // The box is an interval: its pixels are consecutive.
            let first = (xmin..xmax).find(inside).unwrap_or(xmin);
            let count = (first..xmax).take_while(inside).count();
            let weight = if count == 0 {
                0
            } else {
                (0.5 + f64::from(1u32 << PRECISION_BITS) / count as f64) as i32
            };
            Window { first, count, weight }
        })
        .collect()
}

/// Pillow's `clip8`: the fixed-point sum (started at a half) to a byte.
fn clip8(sum: i32) -> u8 {
    (sum >> PRECISION_BITS).clamp(0, 255) as u8
}

/// The sums over `pixels` (`channels` bytes each) of the channels `lanes`.
fn channel_sums(pixels: &[u8], channels: usize, lanes: &[usize; 4]) -> [i32; 4] {
    let count = pixels.len() / channels;
    if channels == 4 && count <= 257 {
        // Four bytes a pixel (a 32-bit surface): two 16-bit lanes to a u32 word, bytes 0 and 2
        // in one, 1 and 3 in the other; 257 pixels of 255 fit a lane.
        let (mut even, mut odd) = (0u32, 0u32);
        for pixel in pixels.chunks_exact(4) {
            let word = u32::from_le_bytes([pixel[0], pixel[1], pixel[2], pixel[3]]);
            even += word & 0x00FF_00FF;
            odd += (word >> 8) & 0x00FF_00FF;
        }
        let byte = [even & 0xFFFF, odd & 0xFFFF, even >> 16, odd >> 16];
        return lanes.map(|lane| byte[lane] as i32);
    }
    let mut sum = [0i32; 4];
    for pixel in pixels.chunks_exact(channels) {
        for (s, &lane) in sum.iter_mut().zip(lanes) {
            *s += i32::from(pixel[lane]);
        }
    }
    sum
}

/// `image` `[height, width, channels]` shrunk to `[out_height, out_width, picked.len()]`, the
/// channels `picked` (at most 4) in that order.
fn shrink(
    image: &[u8],
    (height, width, channels): (usize, usize, usize),
    (out_height, out_width): (usize, usize),
    picked: &[usize],
    out: &mut [u8],
) {
    let (across, down) = (windows(width, out_width), windows(height, out_height));
    let half = 1i32 << (PRECISION_BITS - 1);
    let n = picked.len();
    // Four sums always (the last channel repeated), so the inner loop has a fixed length the
    // compiler unrolls; only the first `n` are kept.
    let lanes: [usize; 4] = core::array::from_fn(|c| picked[c.min(n - 1)]);
    let mut rows = vec![0u8; height * out_width * n];
    for (row, done) in image
        .chunks_exact(width * channels)
        .zip(rows.chunks_exact_mut(out_width * n))
    {
        for (w, pixel_out) in across.iter().zip(done.chunks_exact_mut(n)) {
            let sum = channel_sums(
                &row[w.first * channels..(w.first + w.count) * channels],
                channels,
                &lanes,
            );
            for (o, &s) in pixel_out.iter_mut().zip(&sum) {
                *o = clip8(half + s * w.weight);
            }
        }
    }
    let line = out_width * n;
    let mut sum = vec![0i32; line];
    for (w, out_line) in down.iter().zip(out.chunks_exact_mut(line)) {
        sum.fill(0);
        for source in rows[w.first * line..(w.first + w.count) * line].chunks_exact(line) {
            for (s, &v) in sum.iter_mut().zip(source) {
                *s += i32::from(v);
            }
        }
        for (o, &s) in out_line.iter_mut().zip(&sum) {
            *o = clip8(half + s * w.weight);
        }
    }
}

/// `box_shrink(image, height, width, channels)`: ``image`` (uint8, C-ordered,
/// ``(H, W, C)``) shrunk to ``(height, width, len(channels))`` exactly as Pillow's
/// ``Image.resize((width, height), Image.BOX)`` shrinks it, keeping the channels ``channels``
/// (1 to 4 indices into C) in that order. ``ValueError`` for another dtype or layout, a size
/// larger than the image's or of zero, or channels out of range.
#[pyfunction]
pub fn box_shrink<'py>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    height: usize,
    width: usize,
    channels: Vec<usize>,
) -> PyResult<Bound<'py, PyArrayDyn<u8>>> {
    let image = array::<u8>(image, "image", "uint8")?;
    let &[h, w, c] = image.shape() else {
        return Err(value_error(format!(
            "image: expected (H, W, C), got shape {:?}",
            image.shape()
        )));
    };
    // A window's sum of 255s times its weight stays within i32 (as in Pillow) up to 2^22 pixels.
    if h.max(w) > MAX_SIDE {
        return Err(value_error(format!(
            "image: at most {MAX_SIDE} pixels a side, got ({h}, {w})"
        )));
    }
    if height == 0 || width == 0 || height > h || width > w {
        return Err(value_error(format!(
            "box_shrink: the size ({height}, {width}) must be positive and at most the image's ({h}, {w})"
        )));
    }
    if channels.is_empty() || channels.len() > 4 || channels.iter().any(|&k| k >= c) {
        return Err(value_error(format!(
            "channels: expected 1 to 4 indices below {c}, got {channels:?}"
        )));
    }
    let out = new_array::<u8>(py, &[height, width, channels.len()], "the shrunk image")?;
    // SAFETY: a new C-ordered array that no one else holds yet.
    let target = unsafe { out.as_slice_mut() }.map_err(|e| value_error(e.to_string()))?;
    let source = image.as_slice().map_err(|e| value_error(e.to_string()))?;
    py.detach(|| shrink(source, (h, w, c), (height, width), &channels, target));
    Ok(out)
}
