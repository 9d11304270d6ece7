//! The SIMD dense kernels against the scalar reference, on awkward shapes.

mod common;

use common::{simd_levels, values, ACTS};
use drivesim_kernels::pack::dense_weights;
use drivesim_kernels::{
    dense, dense_add, dense_add_rows, dense_rows, f16, Activation, Isa, Matrix, MatrixData, OutputParts,
};

const ROWS: [usize; 10] = [1, 2, 3, 5, 7, 8, 9, 17, 33, 129];
const COLS: [usize; 14] = [1, 2, 3, 7, 8, 9, 15, 16, 17, 31, 33, 100, 1000, 2500];
const BATCHES: [usize; 6] = [1, 2, 3, 5, 16, 17];
const TOLERANCE: f32 = 1e-5;

/// max|got - want| / max(terms): the error relative to the largest sum of absolute terms.
/// Activations are 1-Lipschitz, so they do not enlarge the bound.
fn normwise_error(got: &[f32], want: &[f32], terms: &[f32]) -> f32 {
    assert!(got.iter().all(|v| v.is_finite()), "non-finite output");
    let scale = terms.iter().fold(1e-6f32, |m, &v| m.max(v));
    let diff = got.iter().zip(want).fold(0.0f32, |m, (g, w)| m.max((g - w).abs()));
    diff / scale
}

fn halves(v: &[f32]) -> Vec<f16> {
    v.iter().map(|&x| f16::from_f32(x)).collect()
}

#[test]
fn dense_matches_scalar() {
    let levels = simd_levels();
    let mut checked = 0;
    for &rows in &ROWS {
        for &cols in &COLS {
            let seed = (rows * 1000 + cols) as u64;
            let w32 = dense_weights(&values(seed, rows * cols, 1.0 / (cols as f32).sqrt()), rows, cols);
            let w16 = halves(&w32);
            let bias = values(seed + 1, rows, 0.5);
            let abs = |v: &[f32]| v.iter().map(|x| x.abs()).collect::<Vec<_>>();
            let (w32_abs, bias_abs) = (abs(&w32), abs(&bias));
            for &batch in &BATCHES {
                let x = values(seed + 2 + batch as u64, batch * cols, 2.0);
                // The size of the terms of each sum, |W| |x| + |b|: the scale of the rounding
                // error of any order of summation (a sum that cancels to nearly zero is exact
                // in no order, so its error relative to itself means nothing).
                let mut terms = vec![0.0; batch * rows];
                let w_abs = Matrix {
                    data: MatrixData::F32(&w32_abs),
                    rows,
                    cols,
                };
                dense(
                    Isa::SCALAR,
                    w_abs,
                    &bias_abs,
                    Activation::Identity,
                    &abs(&x),
                    &mut terms,
                );
                for data in [MatrixData::F32(&w32), MatrixData::F16(&w16)] {
                    let w = Matrix { data, rows, cols };
                    for act in ACTS {
                        let mut want = vec![0.0; batch * rows];
                        dense(Isa::SCALAR, w, &bias, act, &x, &mut want);
                        for &isa in &levels {
                            let mut got = vec![f32::NAN; batch * rows];
                            dense(isa, w, &bias, act, &x, &mut got);
                            let err = normwise_error(&got, &want, &terms);
                            assert!(
                                err <= TOLERANCE,
                                "{:?} rows {rows} cols {cols} batch {batch} {:?} {act:?}: error {err}",
                                isa.level(),
                                matches!(data, MatrixData::F16(_)).then_some("f16").unwrap_or("f32"),
                            );
                            checked += 1;
                        }
                    }
                }
            }
        }
    }
    eprintln!("{checked} SIMD dense cases checked");
}

#[test]
fn packed_matrix_computes_row_major_product() {
    // The scalar kernel on packed weights against the product written on the row-major
    // matrix, in the same order of summation: equal to the bit, so the layout is the one meant.
    for (rows, cols) in [(1, 1), (5, 3), (16, 7), (17, 33), (40, 9)] {
        let row_major = values((rows * 31 + cols) as u64, rows * cols, 0.5);
        let bias = values(3, rows, 0.5);
        let batch = 3;
        let x = values(4, batch * cols, 1.0);
        let mut want = Vec::new();
        for item in x.chunks_exact(cols) {
            for (row, b) in row_major.chunks_exact(cols).zip(&bias) {
                let dot: f32 = row.iter().zip(item).map(|(w, x)| w * x).sum();
                want.push(dot + b);
            }
        }
        let halved = halves(&row_major);
        let want16: Vec<f32> = x
            .chunks_exact(cols)
            .flat_map(|item| {
                halved
                    .chunks_exact(cols)
                    .zip(&bias)
                    .map(move |(row, b)| row.iter().zip(item).map(|(w, x)| w.to_f32() * x).sum::<f32>() + b)
            })
            .collect();
        let (p32, p16) = (
            dense_weights(&row_major, rows, cols),
            dense_weights(&halved, rows, cols),
        );
        for (data, want) in [(MatrixData::F32(&p32), &want), (MatrixData::F16(&p16), &want16)] {
            let mut got = vec![f32::NAN; batch * rows];
            dense(
                Isa::SCALAR,
                Matrix { data, rows, cols },
                &bias,
                Activation::Identity,
                &x,
                &mut got,
            );
            assert_eq!(&got, want, "rows {rows} cols {cols}");
        }
    }
}

#[test]
fn row_ranges_match_whole() {
    // Threads each take a range of rows of every item: together they write what one call does.
    let (rows, cols) = (37, 45);
    let w32 = dense_weights(&values(5, rows * cols, 0.2), rows, cols);
    let w16 = halves(&w32);
    let bias = values(6, rows, 0.5);
    for batch in [1, 2, 17] {
        let x = values(7, batch * cols, 1.0);
        for data in [MatrixData::F32(&w32), MatrixData::F16(&w16)] {
            let w = Matrix { data, rows, cols };
            for isa in Isa::supported() {
                let mut whole = vec![0.0; batch * rows];
                dense(isa, w, &bias, Activation::Tanh, &x, &mut whole);
                let mut parts = vec![f32::NAN; batch * rows];
                // Ranges start at panels, as threads' shares do: 0..16, 16..32 and 32..37.
                let ranges = OutputParts::new(&mut parts, rows, 3);
                while let Some(part) = ranges.take() {
                    dense_rows(isa, w, &bias, Activation::Tanh, &x, part);
                }
                assert_eq!(parts, whole, "{:?} batch {batch}", isa.level());
            }
        }
    }
}

/// Every output is summed in one order whatever the batch and the rows asked for: one item at
/// a time and any split of the rows into panels give the bits of the whole batch, on every
/// level (what makes a simulator bit-identical across thread counts and batches).
#[test]
fn dense_is_bit_identical_across_batches_and_row_splits() {
    let mut levels = simd_levels();
    levels.push(Isa::SCALAR);
    // Columns past the kernels' chunk of 1024, rows past a single input's spread tile, and a
    // batch whose inputs the kernels take in several groups (past 64 Ki floats).
    for (rows, cols, batch) in [
        (129, 2500, 5),
        (300, 1026, 5),
        (33, 3000, 5),
        (512, 4097, 5),
        (40, 1500, 101),
    ] {
        let w32 = dense_weights(&values(rows as u64, rows * cols, 0.05), rows, cols);
        let w16 = halves(&w32);
        let bias = values(7, rows, 0.5);
        let x = values(cols as u64, batch * cols, 1.0);
        for data in [MatrixData::F32(&w32), MatrixData::F16(&w16)] {
            let w = Matrix { data, rows, cols };
            for &isa in &levels {
                let mut whole = vec![0.0; batch * rows];
                dense(isa, w, &bias, Activation::Tanh, &x, &mut whole);
                for (n, item) in x.chunks_exact(cols).enumerate() {
                    let mut one = vec![0.0; rows];
                    dense(isa, w, &bias, Activation::Tanh, item, &mut one);
                    assert_eq!(one, whole[n * rows..][..rows], "{isa:?} {rows}x{cols}: item {n} alone");
                }
                for count in [2, 3, 7, 20] {
                    let mut split = vec![0.0; batch * rows];
                    let parts = OutputParts::new(&mut split, rows, count);
                    while let Some(part) = parts.take() {
                        dense_rows(isa, w, &bias, Activation::Tanh, &x, part);
                    }
                    assert_eq!(split, whole, "{isa:?} {rows}x{cols}: rows in {count} parts");
                }
            }
        }
    }
}

/// `dense_add` starts each item's sums from what its output holds: the bits of `dense` given
/// that as the bias, for a batch whose items start differently, whole or in row parts, at every
/// level (the scalar one included), past a chunk and a single input's spread tile.
#[test]
fn dense_add_is_dense_with_the_output_as_bias() {
    let mut levels = simd_levels();
    levels.push(Isa::SCALAR);
    for (rows, cols) in [(1, 1), (17, 2), (129, 33), (300, 1026), (33, 3000)] {
        let w32 = dense_weights(&values(rows as u64, rows * cols, 0.05), rows, cols);
        let w16 = halves(&w32);
        let batch = 5;
        let x = values(cols as u64, batch * cols, 1.0);
        let start = values(3, batch * rows, 0.5);
        for data in [MatrixData::F32(&w32), MatrixData::F16(&w16)] {
            let w = Matrix { data, rows, cols };
            for &isa in &levels {
                for act in [Activation::Tanh, Activation::Identity] {
                    let mut added = start.clone();
                    dense_add(isa, w, act, &x, &mut added);
                    for n in 0..batch {
                        let mut want = vec![0.0; rows];
                        let bias = &start[n * rows..][..rows];
                        dense(isa, w, bias, act, &x[n * cols..][..cols], &mut want);
                        assert_eq!(
                            added[n * rows..][..rows],
                            want,
                            "{isa:?} {rows}x{cols} {act:?}: item {n}"
                        );
                    }
                    let mut split = start.clone();
                    let parts = OutputParts::new(&mut split, rows, 3);
                    while let Some(part) = parts.take() {
                        dense_add_rows(isa, w, act, &x, part);
                    }
                    assert_eq!(split, added, "{isa:?} {rows}x{cols} {act:?}: rows in 3 parts");
                }
            }
        }
    }
}
