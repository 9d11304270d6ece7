//! Winograd convolutions, scalar and SIMD, against the direct scalar convolution (the oracle)
//! on awkward shapes: odd channel counts, odd grid sizes (tiles hanging over the edge), 1x1
//! grids, every activation, both kinds; each level with the weights its own weight transform
//! packed.

mod common;

use common::{levels, values, ACTS};
use drivesim_kernels::{
    pack, scalar, winograd_channels, winograd_conv, winograd_weights, Activation, ConvKind, ConvParams, ConvShape,
    OutputParts, Plane, Winograd,
};

/// The largest error of `got` against `want` with tiles of `tile` outputs per axis, relative
/// to the size of the terms each output sums (`sum |w| |x| + |b|`, bounded here by the largest
/// such sum over the layer).
fn check(
    kind: ConvKind,
    (h, w): (usize, usize),
    (ic, oc): (usize, usize),
    halo: (usize, usize),
    act: Activation,
    tile: usize,
) -> f32 {
    let k = 5;
    let seed = (h * 1000 + w * 100 + ic * 10 + oc) as u64;
    let ip = Plane::new(h, w, ic, kind.input_halo(k) + halo.0);
    let shape = ConvShape::new(kind, k, ip, oc, halo.1);
    let wino = Winograd::with_tile(shape, tile).expect("a Winograd shape");
    // F(4, k) has larger transform coefficients (up to 8 and 1/24) than F(2, k) (1 and 1/2).
    let tolerance = if tile == 2 { 2e-7 } else { 2e-6 };
    let mut input = vec![0.0; ip.len()];
    ip.write_interior(&mut input, &values(seed, ip.interior_len(), 1.0));
    let torch = values(seed + 1, ic * oc * k * k, 1.0);
    let bias = values(seed + 2, oc, 1.0);
    let (direct, folded) = pack::conv_weights(&shape, &torch, &bias, None);
    let direct_layer = ConvParams {
        shape,
        weights: &direct,
        bias: &folded,
        act,
    };
    let mut want = vec![0.0; shape.output.len()];
    scalar::conv(direct_layer, &input, &mut want);
    // The error scale: |input| and |w| are at most 1, so each output sums at most
    // 25 * ic products of size 1.
    let scale = (k * k * ic) as f32 + 1.0;
    // The packing of a loaded model (the scalar transform) and each level's own (a trainer's).
    let (scalar_packed, bias) = pack::winograd_weights(&wino, &torch, &bias, None);
    assert_eq!(bias, folded);
    let mut worst_all = 0.0f32;
    for isa in levels() {
        let mut packed = vec![f32::NAN; wino.packed_len()];
        winograd_weights(isa, &wino, &direct, &mut packed);
        // The vector levels transform in f32, the scalar level in f64 rounded once: the
        // transformed weights (at most 1 + 1 + 1 times the largest weight) differ by a few ulp.
        let name = isa.level().name();
        let apart = packed
            .iter()
            .zip(&scalar_packed)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(
            apart <= 1e-6,
            "{name} {kind:?} {ic}->{oc}, tile {tile}: transforms {apart} apart"
        );
        let layer = ConvParams {
            shape,
            weights: &packed,
            bias: &bias,
            act,
        };
        let mut v = vec![f32::NAN; wino.input_len()];
        let mut scratch = vec![f32::NAN; wino.scratch_len()];
        let mut got = vec![0.0; shape.output.len()];
        winograd_conv(isa, &wino, layer, &input, &mut v, &mut scratch, &mut got);
        let worst = got.iter().zip(&want).fold(0.0f32, |m, (g, w)| m.max((g - w).abs()));
        assert!(
            worst / scale <= tolerance,
            "{name} {kind:?} {h}x{w} {ic}->{oc} {act:?}, tile {tile}: error {worst} of {scale}"
        );
        // The border stays zero: `want` has a zero border, so `worst` covers it. Every interior
        // value is written, and channel ranges (as threads use them) give the same values:
        // rerun into an output whose interior is NaN.
        let op = shape.output;
        let mut nan_filled = vec![f32::NAN; shape.output.len()];
        nan_filled.copy_from_slice(&got);
        for y in 0..op.height {
            for x in 0..op.width {
                let at = op.index(y, x);
                nan_filled[at..at + op.channels].fill(f32::NAN);
            }
        }
        let parts = OutputParts::new(&mut nan_filled, oc, 2);
        while let Some(part) = parts.take() {
            winograd_channels(isa, &wino, layer, &v, &mut scratch, part);
        }
        assert!(
            nan_filled.iter().zip(&got).all(|(a, b)| a == b),
            "{name} {kind:?} {h}x{w} {ic}->{oc}, tile {tile}: channel ranges differ from one call, or a value was not written"
        );
        worst_all = worst_all.max(worst / scale);
    }
    worst_all
}

/// Checks `kind` with both tile sizes on every shape with every activation (output border
/// `halo`), and one shape with wider borders than the minimum; prints the largest errors.
fn check_all(kind: ConvKind, shapes: &[Shape], halo: usize) {
    for tile in [2, 4] {
        let mut worst = 0.0f32;
        for &(size, channels) in shapes {
            for act in ACTS {
                worst = worst.max(check(kind, size, channels, (0, halo), act, tile));
            }
        }
        let (size, channels) = shapes[1];
        worst = worst.max(check(kind, size, channels, (1, 0), Activation::Identity, tile));
        eprintln!("{kind:?}, tile {tile}: largest error {worst:.2e} of the terms' size");
    }
}

/// Input size and (input, output) channels.
type Shape = ((usize, usize), (usize, usize));

#[test]
fn down_matches_direct() {
    let shapes = [
        ((2, 2), (8, 5)),
        ((4, 6), (9, 17)),
        ((10, 14), (16, 16)),
        ((6, 20), (33, 47)),
        ((12, 4), (64, 40)),
        // More transformed input than weights (tiles before blocks), several tile groups.
        ((20, 40), (9, 20)),
        // Several groups of 4x4 tiles too.
        ((40, 56), (9, 20)),
    ];
    check_all(ConvKind::Down, &shapes, 2);
}

#[test]
fn up_matches_direct() {
    let shapes = [
        ((1, 1), (8, 5)),
        ((2, 3), (9, 17)),
        ((5, 7), (16, 16)),
        ((3, 10), (33, 47)),
        ((6, 2), (64, 40)),
        ((12, 14), (16, 17)),
        // Several groups of 4x4 tiles.
        ((24, 30), (9, 20)),
    ];
    check_all(ConvKind::Up, &shapes, 1);
}

#[test]
fn narrow_or_shallow_layers_stay_direct() {
    let plane = Plane::new(8, 8, 16, 2);
    assert!(Winograd::new(ConvShape::new(ConvKind::Down, 5, plane, 16, 0)).is_some());
    assert!(Winograd::new(ConvShape::new(ConvKind::Down, 5, plane, 3, 0)).is_none());
    assert!(Winograd::new(ConvShape::new(ConvKind::Down, 3, plane, 16, 0)).is_none());
    assert!(Winograd::new(ConvShape::new(ConvKind::Down, 5, Plane::new(8, 8, 3, 2), 16, 0)).is_none());
    assert!(Winograd::new(ConvShape::new(ConvKind::Down, 5, Plane::new(7, 8, 16, 2), 16, 0)).is_none());
    assert!(Winograd::with_tile(ConvShape::new(ConvKind::Down, 5, plane, 16, 0), 3).is_none());
}

/// Layers whose 2x2-tile transformed input would outweigh their weights get 4x4 tiles: the
/// comma config's second encoder and third generator layers; the others keep 2x2.
#[test]
fn large_images_with_few_channels_take_4x4_tiles() {
    let tile = |kind, (h, w), (ic, oc)| {
        let shape = ConvShape::new(kind, 5, Plane::new(h, w, ic, kind.input_halo(5)), oc, 0);
        Winograd::new(shape).expect("a Winograd shape").tile()
    };
    assert_eq!(tile(ConvKind::Down, (40, 80), (64, 128)), 4);
    assert_eq!(tile(ConvKind::Down, (20, 40), (128, 256)), 2);
    assert_eq!(tile(ConvKind::Down, (10, 20), (256, 512)), 2);
    assert_eq!(tile(ConvKind::Up, (5, 10), (512, 256)), 2);
    assert_eq!(tile(ConvKind::Up, (10, 20), (256, 128)), 2);
    assert_eq!(tile(ConvKind::Up, (20, 40), (128, 64)), 4);
}
