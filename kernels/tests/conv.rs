//! The SIMD convolution kernels against the scalar reference, on awkward shapes, at every
//! instruction-set level this CPU supports.

mod common;

use common::{simd_levels, Rng, ACTS};
use drivesim_kernels::{
    conv, conv_channels, pack, scalar, Activation, ConvKind, ConvParams, ConvShape, Isa, IsaLevel, OutputParts, Plane,
};

/// Runs one shape at every level and compares with the scalar kernel; `extra_halo` widens both
/// borders beyond the minimum.
#[allow(clippy::too_many_arguments)]
fn check(
    rng: &mut Rng,
    levels: &[Isa],
    kind: ConvKind,
    k: usize,
    size: (usize, usize),
    channels: (usize, usize),
    extra_halo: usize,
    act: Activation,
) {
    check_with_gain(rng, levels, kind, k, size, channels, extra_halo, act, 1.0)
}

/// [`check`] with the weights scaled by `gain`.
#[allow(clippy::too_many_arguments)]
fn check_with_gain(
    rng: &mut Rng,
    levels: &[Isa],
    kind: ConvKind,
    k: usize,
    (h, w): (usize, usize),
    (ic, oc): (usize, usize),
    extra_halo: usize,
    act: Activation,
    gain: f32,
) {
    let ip = Plane::new(h, w, ic, kind.input_halo(k) + extra_halo);
    let shape = ConvShape::new(kind, k, ip, oc, extra_halo);
    let mut input = vec![0.0; ip.len()];
    ip.write_interior(&mut input, &rng.fill(ip.interior_len(), 1.0));
    // Random PyTorch-layout weights times `gain`, packed as the model packs them.
    let torch: Vec<f32> = rng.fill(ic * oc * k * k, 1.0).iter().map(|w| w * gain).collect();
    let (weights, bias) = pack::conv_weights(&shape, &torch, &rng.fill(oc, 1.0), None);
    let mut want = vec![0.0; shape.output.len()];
    let layer = ConvParams {
        shape,
        weights: &weights,
        bias: &bias,
        act,
    };
    scalar::conv(layer, &input, &mut want);
    let scale = want.iter().fold(1e-6f32, |m, v| m.max(v.abs()));
    for &isa in levels {
        let mut got = vec![0.0; shape.output.len()];
        conv(isa, layer, &input, &mut got);
        let worst = got.iter().zip(&want).fold(0.0f32, |m, (g, w)| m.max((g - w).abs()));
        assert!(
            worst / scale <= 1e-5,
            "{} {kind:?} k{k} {h}x{w} {ic}->{oc} halo+{extra_halo} {act:?}: error {worst} of {scale}",
            isa.level().name()
        );
        // Threads compute blocks of output channels with `conv_channels`: the same values.
        if oc > 32 {
            let mut split = vec![0.0; shape.output.len()];
            let parts = OutputParts::new(&mut split, oc, 2);
            while let Some(part) = parts.take() {
                conv_channels(isa, layer, &input, part);
            }
            assert!(
                split == got,
                "{} {kind:?} {ic}->{oc}: split channels differ",
                isa.level().name()
            );
        }
        // The border must stay zero (and the scalar kernel leaves it zero too, so got == want
        // there is already checked; make it explicit).
        let op = shape.output;
        for y in 0..op.height + 2 * op.halo {
            for x in 0..op.width + 2 * op.halo {
                let interior =
                    (op.halo..op.halo + op.height).contains(&y) && (op.halo..op.halo + op.width).contains(&x);
                if !interior {
                    let at = y * op.row_stride() + x * op.channels;
                    assert!(
                        got[at..at + op.channels].iter().all(|&v| v == 0.0),
                        "{} {kind:?} k{k} {h}x{w} {ic}->{oc}: border pixel ({y}, {x}) written",
                        isa.level().name()
                    );
                }
            }
        }
    }
}

const CHANNELS: [usize; 10] = [1, 2, 3, 5, 7, 8, 9, 16, 17, 33];

#[test]
fn channel_counts_match_scalar() {
    let levels = simd_levels();
    let mut rng = Rng::new(1);
    for kind in [ConvKind::Down, ConvKind::Up] {
        let size = match kind {
            ConvKind::Down => (7, 10),
            ConvKind::Up => (3, 5),
        };
        for &ic in &CHANNELS {
            for &oc in &CHANNELS {
                let act = ACTS[(ic + oc) % ACTS.len()];
                check(&mut rng, &levels, kind, 5, size, (ic, oc), 0, act);
            }
        }
    }
}

#[test]
fn sizes_match_scalar() {
    let levels = simd_levels();
    let mut rng = Rng::new(2);
    let sizes = [1, 2, 3, 5, 7, 10, 13];
    for kind in [ConvKind::Down, ConvKind::Up] {
        for k in [5, 3, 1, 7] {
            for &h in &sizes {
                for &w in &sizes {
                    if kind == ConvKind::Down && (h < 2 || w < 2) {
                        continue; // no output pixel
                    }
                    let (ic, oc) = [(3, 17), (8, 9), (5, 33), (16, 3)][(h + w + k) % 4];
                    let act = ACTS[(h * 7 + w + k) % ACTS.len()];
                    check(&mut rng, &levels, kind, k, (h, w), (ic, oc), (h + w) % 2, act);
                }
            }
        }
    }
}

#[test]
fn every_activation_and_wide_rows() {
    let levels = simd_levels();
    let mut rng = Rng::new(3);
    for act in ACTS {
        // Rows longer than a tile, both channel-block widths, and a 1x1 output.
        check(&mut rng, &levels, ConvKind::Down, 5, (6, 58), (4, 40), 0, act);
        check(&mut rng, &levels, ConvKind::Up, 5, (3, 29), (9, 20), 1, act);
        check(&mut rng, &levels, ConvKind::Down, 5, (2, 2), (7, 33), 0, act);
        check(&mut rng, &levels, ConvKind::Up, 3, (1, 1), (7, 5), 0, act);
        // Large pre-activations exercise the exp branch and the clamp of tanh.
        check(&mut rng, &levels, ConvKind::Down, 3, (4, 30), (64, 3), 0, act);
        // Few output channels with input channels a multiple of the lanes take the path that
        // vectorises over input channels (the generator's last layer is 64 -> 3).
        check(&mut rng, &levels, ConvKind::Up, 5, (5, 13), (64, 3), 0, act);
        check(&mut rng, &levels, ConvKind::Up, 5, (3, 7), (32, 4), 1, act);
        check(&mut rng, &levels, ConvKind::Down, 5, (6, 14), (16, 1), 0, act);
        check(&mut rng, &levels, ConvKind::Up, 3, (2, 9), (48, 2), 0, act);
    }
}

#[test]
fn large_panels_take_several_passes() {
    let levels = simd_levels();
    let mut rng = Rng::new(4);
    for act in ACTS {
        // Panels of weights over 256 KiB are summed a few kernel rows at a time (see
        // `x86_64::conv`): uneven windows, rows with no taps in a window, partial sums.
        // Weights scaled by 1/sqrt(fan-in), as trained ones are: with thousands of terms of
        // order 1 the sums would saturate tanh, and their rounding would exceed the tolerance.
        let cases = [
            (ConvKind::Down, 5, (5, 9), (200, 40), 0),
            (ConvKind::Up, 5, (3, 5), (180, 20), 1),
            (ConvKind::Down, 3, (4, 6), (480, 17), 0),
            (ConvKind::Up, 5, (2, 3), (520, 36), 0),
        ];
        for (kind, k, size, (ic, oc), halo) in cases {
            let gain = 1.0 / ((ic * k * k) as f32).sqrt();
            check_with_gain(&mut rng, &levels, kind, k, size, (ic, oc), halo, act, gain);
        }
    }
}

/// `DRIVESIM_REQUIRE_ISA=avx2` (or `avx512`, `neon`) makes CI fail when the CPU cannot run that
/// level, so a green run proves the SIMD path was tested rather than skipped.
#[test]
fn required_isa_is_present() {
    let Ok(name) = std::env::var("DRIVESIM_REQUIRE_ISA") else {
        return;
    };
    let level = IsaLevel::from_name(&name).unwrap_or_else(|| panic!("DRIVESIM_REQUIRE_ISA={name}: unknown level"));
    assert!(
        Isa::new(level).is_some(),
        "DRIVESIM_REQUIRE_ISA={name} but this CPU lacks {}",
        level.name()
    );
}
