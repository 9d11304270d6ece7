//! The 8-bit image helpers: exact round trips in both layouts, the layouts themselves, batches,
//! clamping, and typed errors.

use drivesim::{frames_from_rgb, frames_to_rgb, Config, Error, PixelLayout};

const CONFIG: Config = Config {
    height: 16,
    width: 32,
    ..Config::COMMA
};

fn image(count: usize) -> Vec<u8> {
    (0..count * CONFIG.frame_len()).map(|i| (i * 37 % 256) as u8).collect()
}

#[test]
fn every_byte_round_trips_in_both_layouts_and_batches() {
    for layout in [PixelLayout::Hwc, PixelLayout::Chw] {
        for count in [1, 3] {
            let rgb = image(count);
            let mut frames = vec![0.0; rgb.len()];
            frames_from_rgb(&rgb, layout, &CONFIG, &mut frames).unwrap();
            assert!(frames.iter().all(|v| (-1.0..=1.0).contains(v)));
            let mut back = vec![0u8; rgb.len()];
            frames_to_rgb(&frames, layout, &CONFIG, &mut back).unwrap();
            assert_eq!(back, rgb, "{layout:?} x{count}");
        }
    }
}

#[test]
fn chw_is_planar_and_hwc_interleaved() {
    let (h, w, c) = (CONFIG.height, CONFIG.width, CONFIG.channels);
    let planar = image(1);
    let mut from_chw = vec![0.0; planar.len()];
    frames_from_rgb(&planar, PixelLayout::Chw, &CONFIG, &mut from_chw).unwrap();
    // The same picture written pixel-interleaved by hand.
    let mut interleaved = vec![0u8; planar.len()];
    for ch in 0..c {
        for p in 0..h * w {
            interleaved[p * c + ch] = planar[ch * h * w + p];
        }
    }
    let mut from_hwc = vec![0.0; planar.len()];
    frames_from_rgb(&interleaved, PixelLayout::Hwc, &CONFIG, &mut from_hwc).unwrap();
    assert_eq!(from_chw, from_hwc);
    assert_eq!(from_hwc[0], interleaved[0] as f32 / 127.5 - 1.0);
}

#[test]
fn out_of_range_values_clamp_and_bad_buffers_are_errors() {
    let n = CONFIG.frame_len();
    let mut frames = vec![0.0f32; n];
    frames[0] = 7.0;
    frames[1] = -3.0;
    frames[2] = 0.999;
    let mut rgb = vec![0u8; n];
    frames_to_rgb(&frames, PixelLayout::Hwc, &CONFIG, &mut rgb).unwrap();
    assert_eq!(&rgb[..4], &[255, 0, 255, 128]);
    frames[5] = f32::NAN;
    assert!(matches!(
        frames_to_rgb(&frames, PixelLayout::Hwc, &CONFIG, &mut rgb),
        Err(Error::NonFinite { index: 5, .. })
    ));
    assert!(matches!(
        frames_to_rgb(&frames[1..], PixelLayout::Hwc, &CONFIG, &mut rgb[1..]),
        Err(Error::NotWholeItems { .. })
    ));
    assert!(matches!(
        frames_from_rgb(&rgb, PixelLayout::Chw, &CONFIG, &mut frames[1..]),
        Err(Error::BufferLength { .. })
    ));
    assert!(matches!(
        frames_from_rgb(&[], PixelLayout::Chw, &CONFIG, &mut []),
        Err(Error::NotWholeItems { .. })
    ));
}
