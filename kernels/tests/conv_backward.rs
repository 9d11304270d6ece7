//! The convolutions' backward passes on awkward shapes at every instruction-set level: the
//! data gradient (the forward kernel of the transposed shape, direct and Winograd) by the
//! adjoint identity `<conv(x), dy> = <x, conv_backward(dy)>`, the weight gradient against its
//! definition in f64 and by the identity `<dW, W> = <conv(x; W), dy>`, and bit-identical
//! results however threads split the channels.

mod common;

use common::{levels, Rng};
use drivesim_kernels::{
    conv, conv_grad_pixels, conv_weight_grad, conv_weight_grad_add_rows, conv_weight_grad_block_rows,
    conv_weight_grad_rows, conv_weight_grad_scratch_len, pack, winograd_conv, winograd_weights, Activation, ConvKind,
    ConvParams, ConvShape, Isa, Matrix, OutputParts, Plane, Winograd, GRAD_PIXELS,
};

/// `(kind, height, width, in channels, out channels)`: narrow and odd channel counts, planes of
/// more than one chunk of 128 output pixels, and shapes Winograd takes (8+ inputs, 5+ outputs).
const SHAPES: [(ConvKind, usize, usize, usize, usize); 9] = [
    (ConvKind::Down, 4, 6, 1, 1),
    (ConvKind::Down, 8, 10, 3, 5),
    (ConvKind::Down, 10, 34, 5, 17),
    (ConvKind::Down, 16, 32, 8, 16),
    (ConvKind::Down, 6, 8, 33, 40),
    (ConvKind::Up, 3, 5, 1, 3),
    (ConvKind::Up, 5, 9, 17, 3),
    (ConvKind::Up, 4, 8, 16, 8),
    (ConvKind::Up, 2, 3, 40, 33),
];
const K: usize = 5;

/// A batch of `items` planes with random interiors.
fn planes(rng: &mut Rng, plane: Plane, items: usize) -> Vec<f32> {
    let mut batch = vec![0.0; plane.len() * items];
    for item in batch.chunks_exact_mut(plane.len()) {
        plane.write_interior(item, &rng.fill(plane.interior_len(), 1.0));
    }
    batch
}

/// The layer of `(kind, h, w, ic, oc)`, its input with a border one wider than it needs and
/// its output with a border of 1.
fn layer(&(kind, h, w, ic, oc): &(ConvKind, usize, usize, usize, usize)) -> ConvShape {
    ConvShape::new(kind, K, Plane::new(h, w, ic, kind.input_halo(K) + 1), oc, 1)
}

/// `Σ a·b` over the interiors of `a` in `plane` and `b` in `b_plane` (the same image in a
/// border of its own), in f64, with the sum of the terms' magnitudes.
fn dot(plane: Plane, a: &[f32], b_plane: Plane, b: &[f32]) -> (f64, f64) {
    let (mut sum, mut terms) = (0.0, 0.0);
    for y in 0..plane.height {
        for x in 0..plane.width {
            let (at, bt) = (plane.index(y, x), b_plane.index(y, x));
            for c in 0..plane.channels {
                let p = a[at + c] as f64 * b[bt + c] as f64;
                sum += p;
                terms += p.abs();
            }
        }
    }
    (sum, terms)
}

/// The forward pass of `shape` with PyTorch weights `torch` and zero bias, direct or Winograd.
fn forward(isa: Isa, shape: ConvShape, torch: &[f32], winograd: bool, input: &[f32]) -> Vec<f32> {
    let mut out = vec![0.0; shape.output.len()];
    let zero = vec![0.0; shape.output.channels];
    let mut direct = vec![0.0; shape.packed_len()];
    pack::conv_weights_into(&shape, torch, &mut direct);
    let mut layer = ConvParams {
        shape,
        weights: &direct,
        bias: &zero,
        act: Activation::Identity,
    };
    match Winograd::new(shape).filter(|_| winograd) {
        None => conv(isa, layer, input, &mut out),
        Some(w) => {
            let mut packed = vec![0.0; w.packed_len()];
            winograd_weights(isa, &w, &direct, &mut packed);
            layer.weights = &packed;
            let (mut v, mut scratch) = (vec![0.0; w.input_len()], vec![0.0; w.scratch_len()]);
            winograd_conv(isa, &w, layer, input, &mut v, &mut scratch, &mut out);
        }
    }
    out
}

#[test]
fn data_gradient_is_the_adjoint_of_the_forward_pass() {
    let mut rng = Rng::new(11);
    let mut winograd_checked = 0;
    for isa in levels() {
        for dims in &SHAPES {
            let shape = layer(dims);
            let back = shape.transposed();
            let (twice, dims_of) = (back.transposed(), |p: Plane| (p.height, p.width, p.channels));
            assert_eq!(twice.kind, shape.kind, "transposing twice");
            assert_eq!(dims_of(twice.input), dims_of(shape.input));
            assert_eq!(dims_of(twice.output), dims_of(shape.output));
            let (ic, oc) = (dims.3, dims.4);
            let torch = rng.fill(ic * oc * K * K, 1.0);
            let x = planes(&mut rng, shape.input, 1);
            let dy = planes(&mut rng, back.input, 1);
            let y = forward(isa, shape, &torch, false, &x);
            for winograd in [false, true] {
                if winograd && Winograd::new(back).is_none() {
                    continue;
                }
                winograd_checked += winograd as usize;
                let dx = forward(isa, back, &torch, winograd, &dy);
                let (forward_dot, terms) = dot(shape.output, &y, back.input, &dy);
                let (adjoint_dot, _) = dot(shape.input, &x, shape.input, &dx);
                assert!(
                    (forward_dot - adjoint_dot).abs() <= 1e-5 * terms,
                    "{:?} {dims:?} winograd {winograd}: {forward_dot} vs {adjoint_dot}",
                    isa.level()
                );
                // The border of the gradient stays zero: the next layer reads it.
                let interior = dot(shape.input, &dx, shape.input, &dx).0;
                let all: f64 = dx.iter().map(|&v| v as f64 * v as f64).sum();
                assert_eq!(interior, all, "{dims:?}: border written");
            }
        }
    }
    assert!(winograd_checked > 0, "no shape took Winograd");
}

/// The weight gradient of `shape` from its definition in f64, PyTorch layout, and the sums of
/// the terms' magnitudes.
fn weight_grad_f64(shape: ConvShape, x: &[f32], dy: &[f32]) -> (Vec<f64>, Vec<f64>) {
    let (ip, op, k) = (shape.input, shape.output, shape.kernel);
    let (ic, oc) = (ip.channels, op.channels);
    // PyTorch's tensor: [out, in, k, k] for Down, [in, out, k, k] for Up.
    let index = |o: usize, i: usize, ky: usize, kx: usize| match shape.kind {
        ConvKind::Down => ((o * ic + i) * k + ky) * k + kx,
        ConvKind::Up => ((i * oc + o) * k + ky) * k + kx,
    };
    let (mut g, mut terms) = (vec![0.0; ic * oc * k * k], vec![0.0; ic * oc * k * k]);
    for (x, dy) in x.chunks_exact(ip.len()).zip(dy.chunks_exact(op.len())) {
        for oy in 0..op.height {
            for ox in 0..op.width {
                for ky in 0..k {
                    let Some(iy) = shape.kind.source(oy, ky, k / 2, ip.height) else {
                        continue;
                    };
                    for kx in 0..k {
                        let Some(ix) = shape.kind.source(ox, kx, k / 2, ip.width) else {
                            continue;
                        };
                        for o in 0..oc {
                            for i in 0..ic {
                                let p = dy[op.index(oy, ox) + o] as f64 * x[ip.index(iy, ix) + i] as f64;
                                g[index(o, i, ky, kx)] += p;
                                terms[index(o, i, ky, kx)] += p.abs();
                            }
                        }
                    }
                }
            }
        }
    }
    (g, terms)
}

/// The weight gradient of `shape` by the kernel, PyTorch layout: a strided layer's own, a
/// transposed layer's as its transposed shape's with input and output gradient swapped.
fn weight_grad(isa: Isa, shape: ConvShape, x: &[f32], dy: &[f32], items: usize) -> Vec<f32> {
    let (down, input, grad_of_output, input_plane, output_plane) = match shape.kind {
        ConvKind::Down => (shape, x, dy, shape.input, shape.output),
        ConvKind::Up => (shape.transposed(), dy, x, shape.output, shape.input),
    };
    // The kernel reads planes of the strided shape: copy the batches into them.
    let relayout = |batch: &[f32], from: Plane, to: Plane| {
        let mut out = vec![0.0; to.len() * items];
        for (src, dst) in batch.chunks_exact(from.len()).zip(out.chunks_exact_mut(to.len())) {
            for y in 0..from.height {
                for x in 0..from.width {
                    dst[to.index(y, x)..][..to.channels].copy_from_slice(&src[from.index(y, x)..][..from.channels]);
                }
            }
        }
        out
    };
    let input = relayout(input, input_plane, down.input);
    let grad_of_output = relayout(grad_of_output, output_plane, down.output);
    let rows = down.output.channels;
    let cols = K * K * down.input.channels;
    let mut packed = vec![f32::NAN; Matrix::packed_len(rows, cols)];
    let mut scratch = vec![0.0; conv_weight_grad_scratch_len(&down)];
    conv_weight_grad(isa, down, &input, &grad_of_output, &mut scratch, &mut packed);
    // Threads fill panels of rows: the same bits.
    if rows > 16 {
        let mut split = vec![f32::NAN; packed.len()];
        let parts = OutputParts::new(&mut split, rows, 2);
        while let Some(part) = parts.take() {
            conv_weight_grad_rows(isa, down, &input, &grad_of_output, &mut scratch, part);
        }
        assert!(split == packed, "{:?} {shape:?}: split rows differ", isa.level());
    }
    // Blocks of pixels, each into a gradient of its own, then added: one block is the whole
    // batch's bits; three blocks (on chunk boundaries, the last shorter) sum to the same values.
    let pixels = conv_grad_pixels(&down, items);
    let third = (pixels / 3).next_multiple_of(GRAD_PIXELS);
    for bounds in [
        vec![0, pixels],
        vec![0, third.min(pixels), (2 * third).min(pixels), pixels],
    ] {
        let (blocks, len) = (bounds.len() - 1, packed.len());
        let mut partials = vec![f32::NAN; blocks * len];
        let parts = OutputParts::grid(&mut partials, blocks, rows, 2);
        while let Some((b, part)) = parts.take_in_buffer() {
            let range = bounds[b]..bounds[b + 1];
            conv_weight_grad_block_rows(isa, down, &input, &grad_of_output, range, &mut scratch, part);
        }
        let mut sum = partials[..len].to_vec();
        for partial in partials.chunks_exact(len).skip(1) {
            sum.iter_mut().zip(partial).for_each(|(s, p)| *s += p);
        }
        let scale = packed.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        for (s, p) in sum.iter().zip(&packed) {
            match blocks {
                1 => assert_eq!(
                    s.to_bits(),
                    p.to_bits(),
                    "{:?} {shape:?}: one block differs",
                    isa.level()
                ),
                _ => assert!(
                    (s - p).abs() <= 1e-5 * scale,
                    "{:?} {shape:?}: blocks {s}, whole {p}",
                    isa.level()
                ),
            }
        }
    }
    // Adding to a gradient that holds the same values doubles it (to the rounding of sums of
    // terms up to the largest weight's size).
    let scale = packed.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let mut twice = packed.clone();
    let parts = OutputParts::new(&mut twice, rows, 2);
    while let Some(part) = parts.take() {
        conv_weight_grad_add_rows(isa, down, &input, &grad_of_output, &mut scratch, part);
    }
    for (t, p) in twice.iter().zip(&packed) {
        assert!(
            (t - 2.0 * p).abs() <= 1e-5 * scale,
            "{:?} {shape:?}: added {t}, once {p}",
            isa.level()
        );
    }
    let mut torch = vec![0.0; rows * cols];
    pack::conv_matrix_to_torch(&down, &packed, &mut torch);
    torch
}

#[test]
fn weight_gradient_matches_its_definition() {
    let mut rng = Rng::new(12);
    for isa in levels() {
        for dims in &SHAPES {
            for items in [0, 1, 3] {
                let shape = layer(dims);
                let x = planes(&mut rng, shape.input, items);
                let dy = planes(&mut rng, shape.output, items);
                let got = weight_grad(isa, shape, &x, &dy, items);
                let (want, terms) = weight_grad_f64(shape, &x, &dy);
                for (i, ((g, w), t)) in got.iter().zip(&want).zip(&terms).enumerate() {
                    assert!(
                        (*g as f64 - w).abs() <= 1e-5 * t + 1e-30,
                        "{:?} {dims:?} items {items} weight {i}: {g} vs {w}",
                        isa.level()
                    );
                }
            }
        }
    }
}

#[test]
fn weight_gradient_is_the_adjoint_of_the_weights() {
    // y is linear in W: <dW, W> = Σ over items of <conv(x; W, 0), dy>.
    let mut rng = Rng::new(13);
    for isa in levels() {
        for dims in &SHAPES {
            let (shape, items) = (layer(dims), 2);
            let torch = rng.fill(dims.3 * dims.4 * K * K, 1.0);
            let x = planes(&mut rng, shape.input, items);
            let dy = planes(&mut rng, shape.output, items);
            let (mut forward_dot, mut terms) = (0.0, 0.0);
            for (x, dy) in x
                .chunks_exact(shape.input.len())
                .zip(dy.chunks_exact(shape.output.len()))
            {
                let y = forward(isa, shape, &torch, false, x);
                let (d, t) = dot(shape.output, &y, shape.output, dy);
                forward_dot += d;
                terms += t;
            }
            let grad = weight_grad(isa, shape, &x, &dy, items);
            let adjoint: f64 = grad.iter().zip(&torch).map(|(&g, &w)| g as f64 * w as f64).sum();
            assert!(
                (forward_dot - adjoint).abs() <= 1e-5 * terms,
                "{:?} {dims:?}: {forward_dot} vs {adjoint}",
                isa.level()
            );
        }
    }
}

#[test]
fn weights_in_the_gradient_layout_pack_as_pytorch_weights_do() {
    let mut rng = Rng::new(13);
    for dims in &SHAPES {
        let shape = layer(dims);
        let (ic, oc) = (shape.input.channels, shape.output.channels);
        let torch = rng.fill(oc * ic * K * K, 1.0);
        let mut matrix = vec![0.0; pack::conv_matrix_len(&shape)];
        pack::conv_matrix_from_torch(&shape, &torch, &mut matrix);
        // The layer and its transposed shape (its data gradient) share one matrix.
        let mut from_transposed = vec![0.0; matrix.len()];
        pack::conv_matrix_from_torch(&shape.transposed(), &torch, &mut from_transposed);
        assert!(from_transposed == matrix, "{dims:?}");
        for s in [shape, shape.transposed()] {
            let (mut want, mut got) = (vec![0.0; s.packed_len()], vec![0.0; s.packed_len()]);
            pack::conv_weights_into(&s, &torch, &mut want);
            pack::conv_weights_from_matrix(&s, &matrix, &mut got);
            assert!(got == want, "{dims:?} {:?}", s.kind);
        }
        // The gradient's conversion reads the same layout back.
        let mut back = vec![0.0; torch.len()];
        pack::conv_matrix_to_torch(&shape.strided(), &matrix, &mut back);
        assert!(back == torch, "{dims:?}");
    }
}
