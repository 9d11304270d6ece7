//! 8-bit images to and from the model's frames (`f32`, HWC, in [-1, 1]): what every caller
//! with a camera or a PNG would otherwise write, once, with the same scaling as the training
//! data (`v / 127.5 - 1`).

use crate::error::{expect_finite, expect_len};
use crate::{Config, Error, Result};

/// How the channels of an 8-bit image are laid out.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PixelLayout {
    /// `[height][width][channel]`, pixel-interleaved (PNG, most cameras; the model's frames).
    Hwc,
    /// `[channel][height][width]`, planar (PyTorch tensors).
    Chw,
}

/// The index in a `layout` image of channel `c` of pixel `pixel` (row-major), of `pixels`.
fn index(layout: PixelLayout, pixel: usize, c: usize, pixels: usize, channels: usize) -> usize {
    match layout {
        PixelLayout::Hwc => pixel * channels + c,
        PixelLayout::Chw => c * pixels + pixel,
    }
}

/// The number of whole frames of `config` in `len` values, or [`Error::NotWholeItems`].
fn frames_in(buffer: &'static str, len: usize, config: &Config) -> Result<usize> {
    let item_len = config.frame_len();
    if len == 0 || !len.is_multiple_of(item_len) {
        return Err(Error::NotWholeItems {
            buffer,
            item_len,
            found: len,
        });
    }
    Ok(len / item_len)
}

/// Frames for the model from 8-bit images (one or more, back to back) laid out as `layout`:
/// each value `v / 127.5 - 1`, written HWC into `frames` (as long as `rgb`).
///
/// ```
/// use drivesim::{frames_from_rgb, frames_to_rgb, Config, PixelLayout};
///
/// let config = Config { height: 16, width: 32, ..Config::COMMA };
/// let rgb: Vec<u8> = (0..config.frame_len()).map(|i| (i % 256) as u8).collect();
/// let mut frame = vec![0.0; config.frame_len()];
/// frames_from_rgb(&rgb, PixelLayout::Hwc, &config, &mut frame)?;
/// assert_eq!((frame[0], frame[255]), (-1.0, 1.0));
/// let mut back = vec![0u8; rgb.len()];
/// frames_to_rgb(&frame, PixelLayout::Hwc, &config, &mut back)?;
/// assert_eq!(back, rgb);
/// # Ok::<(), drivesim::Error>(())
/// ```
pub fn frames_from_rgb(rgb: &[u8], layout: PixelLayout, config: &Config, frames: &mut [f32]) -> Result<()> {
    let count = frames_in("rgb", rgb.len(), config)?;
    expect_len("frames", frames, rgb.len())?;
    let (channels, pixels) = (config.channels, config.height * config.width);
    for n in 0..count {
        let (image, frame) = (&rgb[n * config.frame_len()..], &mut frames[n * config.frame_len()..]);
        for pixel in 0..pixels {
            for c in 0..channels {
                frame[pixel * channels + c] = image[index(layout, pixel, c, pixels, channels)] as f32 / 127.5 - 1.0;
            }
        }
    }
    Ok(())
}

/// 8-bit images laid out as `layout` from the model's frames (HWC, one or more): each value
/// clamped to [-1, 1] and rounded, `round((v + 1) * 127.5)`, the inverse of
/// [`frames_from_rgb`] on its values. Frames must be finite.
pub fn frames_to_rgb(frames: &[f32], layout: PixelLayout, config: &Config, rgb: &mut [u8]) -> Result<()> {
    let count = frames_in("frames", frames.len(), config)?;
    expect_len("rgb", rgb, frames.len())?;
    expect_finite("frames", frames)?;
    let (channels, pixels) = (config.channels, config.height * config.width);
    for n in 0..count {
        let (frame, image) = (&frames[n * config.frame_len()..], &mut rgb[n * config.frame_len()..]);
        for pixel in 0..pixels {
            for c in 0..channels {
                let v = (frame[pixel * channels + c].clamp(-1.0, 1.0) + 1.0) * 127.5;
                // +0.5 and truncation: round half up without std's `round`.
                image[index(layout, pixel, c, pixels, channels)] = (v + 0.5) as u8;
            }
        }
    }
    Ok(())
}
