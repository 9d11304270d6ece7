//! The backward kernels of training: the SIMD weight and data gradients and tanh backward
//! against the scalar reference on awkward shapes, the scalar gradients against f64, and the
//! adjoint identities that tie the gradients to the forward kernel.

mod common;

use common::{levels, simd_levels, values};
use drivesim_kernels::pack::dense_weights;
use drivesim_kernels::{
    activation_backward, adam, dense, dense_data_grad, dense_data_grad_cols, dense_weight_grad, dense_weight_grad_rows,
    scalar, Activation, AdamStep, Isa, Matrix, MatrixData, OutputParts,
};

const ROWS: [usize; 9] = [1, 3, 7, 16, 17, 33, 47, 64, 129];
const COLS: [usize; 10] = [1, 2, 3, 7, 8, 9, 17, 31, 100, 386];
/// Item counts around the kernels' chunk of 128 items.
const ITEMS: [usize; 7] = [0, 1, 2, 5, 127, 129, 300];

/// `G[r][c] = Σ_k dy[k][r] x[k][c]` in f64, row-major, with the sums of absolute terms.
fn weight_grad_f64(dy: &[f32], x: &[f32], rows: usize, cols: usize) -> (Vec<f64>, Vec<f64>) {
    let (mut g, mut terms) = (vec![0.0; rows * cols], vec![0.0; rows * cols]);
    for (dy, x) in dy.chunks_exact(rows).zip(x.chunks_exact(cols)) {
        for r in 0..rows {
            for c in 0..cols {
                let p = dy[r] as f64 * x[c] as f64;
                g[r * cols + c] += p;
                terms[r * cols + c] += p.abs();
            }
        }
    }
    (g, terms)
}

/// The packed gradient's value `(r, c)`, and zero padding checked.
fn unpack(packed: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    for r in rows..rows.next_multiple_of(16) {
        for c in 0..cols {
            assert_eq!(packed[Matrix::packed_index(r, c, cols)], 0.0, "padding row {r} col {c}");
        }
    }
    (0..rows * cols)
        .map(|i| packed[Matrix::packed_index(i / cols, i % cols, cols)])
        .collect()
}

#[test]
fn scalar_weight_grad_matches_f64() {
    for &rows in &ROWS {
        for &cols in &COLS {
            let items = 19;
            let dy = values((rows * 7 + cols) as u64, items * rows, 1.0);
            let x = values((rows + cols * 5) as u64, items * cols, 2.0);
            let mut packed = vec![f32::NAN; Matrix::packed_len(rows, cols)];
            scalar::dense_weight_grad(&dy, &x, rows, cols, &mut packed);
            let got = unpack(&packed, rows, cols);
            let (want, terms) = weight_grad_f64(&dy, &x, rows, cols);
            for ((g, w), t) in got.iter().zip(&want).zip(&terms) {
                // f32 summation of `items` terms: a few ulps of the terms' sum.
                assert!(
                    (*g as f64 - w).abs() <= 1e-6 * t.max(1e-30),
                    "{rows}x{cols}: {g} vs {w}"
                );
            }
        }
    }
}

#[test]
fn simd_weight_grad_matches_scalar() {
    let levels = simd_levels();
    let mut checked = 0;
    for &rows in &ROWS {
        for &cols in &COLS {
            for &items in &ITEMS {
                let dy = values((rows * 1000 + cols + items) as u64, items * rows, 1.0);
                let x = values((cols * 1000 + rows + items) as u64, items * cols, 2.0);
                let mut want = vec![f32::NAN; Matrix::packed_len(rows, cols)];
                scalar::dense_weight_grad(&dy, &x, rows, cols, &mut want);
                let (_, terms) = weight_grad_f64(&dy, &x, rows, cols);
                let scale = terms.iter().fold(1e-6f64, |m, &t| m.max(t));
                for &isa in &levels {
                    let mut got = vec![f32::NAN; want.len()];
                    dense_weight_grad(isa, &dy, &x, rows, cols, &mut got);
                    let got = unpack(&got, rows, cols);
                    let want = unpack(&want, rows, cols);
                    let err = got
                        .iter()
                        .zip(&want)
                        .fold(0.0f64, |m, (g, w)| m.max((g - w).abs() as f64))
                        / scale;
                    assert!(
                        err <= 1e-6,
                        "{:?} {rows}x{cols} items {items}: error {err}",
                        isa.level()
                    );
                    checked += 1;
                }
            }
        }
    }
    eprintln!("{checked} SIMD weight-gradient cases checked");
}

/// Threads split the gradient by panels of rows: any split gives the bits of the whole.
#[test]
fn weight_grad_is_bit_identical_across_row_splits() {
    let mut levels = simd_levels();
    levels.push(Isa::SCALAR);
    for (rows, cols, items) in [(129, 386, 300), (256, 129, 224), (33, 1026, 17)] {
        let dy = values(rows as u64, items * rows, 1.0);
        let x = values(cols as u64, items * cols, 1.0);
        for &isa in &levels {
            let mut whole = vec![0.0; Matrix::packed_len(rows, cols)];
            dense_weight_grad(isa, &dy, &x, rows, cols, &mut whole);
            for count in [2, 3, 7] {
                let mut split = vec![f32::NAN; whole.len()];
                let parts = OutputParts::new(&mut split, rows, count);
                while let Some(part) = parts.take() {
                    dense_weight_grad_rows(isa, &dy, &x, rows, cols, part);
                }
                assert_eq!(split, whole, "{isa:?} {rows}x{cols}: rows in {count} parts");
            }
        }
    }
}

/// `<dy, W x> = <dyᵀ x, W>`: the weight gradient is the adjoint of the forward product in `W`;
/// and `<dy, W x> = <dy W, x>`: so is the data gradient in `x`. Checked on every level, in f64
/// sums of the kernels' outputs.
#[test]
fn gradients_are_adjoint_to_the_forward_product() {
    let mut levels = simd_levels();
    levels.push(Isa::SCALAR);
    for (rows, cols, items) in [(37, 45, 9), (16, 1, 3), (1, 17, 130), (129, 386, 16)] {
        let w = dense_weights(&values(1, rows * cols, 0.3), rows, cols);
        let x = values(2, items * cols, 1.0);
        let dy = values(3, items * rows, 1.0);
        let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>();
        for &isa in &levels {
            let mut y = vec![0.0; items * rows];
            let matrix = Matrix {
                data: MatrixData::F32(&w),
                rows,
                cols,
            };
            dense(isa, matrix, &vec![0.0; rows], Activation::Identity, &x, &mut y);
            let mut dx = vec![0.0; items * cols];
            dense_data_grad(isa, &w, rows, cols, &dy, &mut dx);
            let mut g = vec![0.0; w.len()];
            dense_weight_grad(isa, &dy, &x, rows, cols, &mut g);
            let forward = dot(&dy, &y);
            let scale = (items * rows * cols) as f64 * 0.3;
            for (name, adjoint) in [("data", dot(&dx, &x)), ("weight", dot(&g, &w))] {
                assert!(
                    (forward - adjoint).abs() <= 1e-5 * scale,
                    "{:?} {rows}x{cols} items {items}: {name} {adjoint} vs {forward}",
                    isa.level()
                );
            }
        }
    }
}

/// `dx[k][c] = Σ_r W[r][c] dy[k][r]` in f64, with the sums of absolute terms.
fn data_grad_f64(w: &[f32], rows: usize, cols: usize, dy: &[f32]) -> (Vec<f64>, Vec<f64>) {
    let items = dy.len() / rows;
    let (mut dx, mut terms) = (vec![0.0; items * cols], vec![0.0; items * cols]);
    for (k, dy) in dy.chunks_exact(rows).enumerate() {
        for c in 0..cols {
            for (r, &d) in dy.iter().enumerate() {
                let p = w[Matrix::packed_index(r, c, cols)] as f64 * d as f64;
                dx[k * cols + c] += p;
                terms[k * cols + c] += p.abs();
            }
        }
    }
    (dx, terms)
}

/// Every level against f64 (the scalar reference too) on awkward shapes: rows that end inside
/// a panel, item counts around the SIMD blocks.
#[test]
fn data_grad_matches_f64() {
    let mut levels = simd_levels();
    levels.push(Isa::SCALAR);
    let mut checked = 0;
    for &rows in &ROWS {
        for &cols in &COLS {
            for items in [0, 1, 2, 5, 9, 17] {
                let w = dense_weights(&values((rows * 3 + cols) as u64, rows * cols, 1.0), rows, cols);
                let dy = values((rows + cols * 11 + items) as u64, items * rows, 1.0);
                let (want, terms) = data_grad_f64(&w, rows, cols, &dy);
                for &isa in &levels {
                    let mut got = vec![f32::NAN; items * cols];
                    dense_data_grad(isa, &w, rows, cols, &dy, &mut got);
                    for ((g, w), t) in got.iter().zip(&want).zip(&terms) {
                        assert!(
                            (*g as f64 - w).abs() <= 1e-6 * t.max(1e-30),
                            "{:?} {rows}x{cols} items {items}: {g} vs {w}",
                            isa.level()
                        );
                    }
                    checked += 1;
                }
            }
        }
    }
    eprintln!("{checked} data-gradient cases checked");
}

/// Threads split the data gradient by columns, and a trainer's batch varies: neither changes
/// a bit of any item's gradient.
#[test]
fn data_grad_is_bit_identical_across_column_splits_and_batches() {
    let mut levels = simd_levels();
    levels.push(Isa::SCALAR);
    for (rows, cols, items) in [(256, 129, 11), (33, 1026, 9), (12800 / 16, 40, 3)] {
        let w = dense_weights(&values(rows as u64, rows * cols, 1.0), rows, cols);
        let dy = values(cols as u64, items * rows, 1.0);
        for &isa in &levels {
            let mut whole = vec![0.0; items * cols];
            dense_data_grad(isa, &w, rows, cols, &dy, &mut whole);
            for count in [2, 3, 7] {
                let mut split = vec![f32::NAN; whole.len()];
                let parts = OutputParts::new(&mut split, cols, count);
                while let Some(part) = parts.take() {
                    dense_data_grad_cols(isa, &w, rows, cols, &dy, part);
                }
                assert_eq!(split, whole, "{isa:?} {rows}x{cols}: columns in {count} parts");
            }
            for (k, dy) in dy.chunks_exact(rows).enumerate() {
                let mut one = vec![f32::NAN; cols];
                dense_data_grad(isa, &w, rows, cols, dy, &mut one);
                assert_eq!(one, whole[k * cols..][..cols], "{isa:?} {rows}x{cols}: item {k} alone");
            }
        }
    }
}

#[test]
fn activation_backward_is_bit_identical_to_scalar() {
    let acts = [
        Activation::Identity,
        Activation::Relu,
        Activation::LeakyRelu(0.2),
        Activation::Tanh,
    ];
    for act in acts {
        for n in [0, 1, 7, 8, 15, 16, 17, 100] {
            // Outputs of the activation, zeros among them (ReLU's), and their gradients.
            let mut y: Vec<f32> = values(n as u64, n, 1.0).iter().map(|&x| act.apply(x)).collect();
            y.iter_mut().step_by(5).for_each(|y| *y = 0.0);
            let grad = values(n as u64 + 1, n, 3.0);
            let mut want = grad.clone();
            scalar::activation_backward(act, &y, &mut want);
            for (g, (w, &y)) in grad.iter().zip(want.iter().zip(&y)) {
                // The derivative from its definition, PyTorch's left slope at 0.
                let slope = match act {
                    Activation::Identity => 1.0,
                    Activation::Relu => (y > 0.0) as u8 as f32,
                    Activation::LeakyRelu(s) => {
                        if y > 0.0 {
                            1.0
                        } else {
                            s
                        }
                    }
                    Activation::Tanh => 1.0 - y * y,
                };
                assert_eq!(*w, g * slope, "{act:?}");
            }
            for isa in Isa::supported() {
                let mut got = grad.clone();
                activation_backward(isa, act, &y, &mut got);
                assert_eq!(got, want, "{:?} {act:?} n {n}", isa.level());
            }
        }
    }
}

/// Adam gives the same bits on every level, on lengths around every vector width, and follows
/// its definition (computed in f64) to f32 rounding.
#[test]
fn adam_is_the_same_on_every_level_and_follows_its_definition() {
    let step = AdamStep {
        beta1: 0.9,
        beta2: 0.999,
        eps: 1e-8,
        scale: 0.7,
        step_size: 1e-3 / (1.0 - 0.9f32.powi(3)),
        correction2_sqrt: (1.0 - 0.999f32.powi(3)).sqrt(),
    };
    for n in [0, 1, 3, 4, 7, 8, 15, 16, 17, 33, 100, 1001] {
        let (params, grads, m) = (values(1, n, 1.0), values(2, n, 1.0), values(3, n, 0.1));
        let v: Vec<f32> = values(4, n, 0.01).iter().map(|v| v.abs()).collect();
        let run = |isa: Isa| {
            let (mut p, mut m, mut v) = (params.clone(), m.clone(), v.clone());
            adam(isa, step, &mut p, &grads, &mut m, &mut v);
            (p, m, v)
        };
        let want = run(Isa::SCALAR);
        for isa in levels() {
            let bits = |x: &[f32]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            let got = run(isa);
            let name = isa.level().name();
            assert_eq!(bits(&got.0), bits(&want.0), "{name} {n}: parameters");
            assert_eq!(bits(&got.1), bits(&want.1), "{name} {n}: first moments");
            assert_eq!(bits(&got.2), bits(&want.2), "{name} {n}: second moments");
        }
        for i in 0..n {
            let g = grads[i] as f64 * step.scale as f64;
            let m1 = m[i] as f64 + (g - m[i] as f64) * (1.0 - step.beta1 as f64);
            let v1 = v[i] as f64 * step.beta2 as f64 + (1.0 - step.beta2 as f64) * g * g;
            let delta = step.step_size as f64 * m1 / (v1.sqrt() / step.correction2_sqrt as f64 + step.eps as f64);
            let p1 = params[i] as f64 - delta;
            assert!(
                (want.1[i] as f64 - m1).abs() <= 1e-6 * (m1.abs() + g.abs()),
                "{n} m {i}"
            );
            assert!((want.2[i] as f64 - v1).abs() <= 1e-6 * v1, "{n} v {i}");
            assert!(
                (want.0[i] as f64 - p1).abs() <= 1e-6 * (p1.abs() + delta.abs()),
                "{n} p {i}"
            );
        }
    }
}
