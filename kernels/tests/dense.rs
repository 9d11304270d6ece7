//! The SIMD dense kernels and `rnn_step` against the scalar reference, on awkward shapes.

mod common;

use common::values;
use drivesim_kernels::pack::dense_weights;
use drivesim_kernels::{dense, dense_rows, f16, rnn_step, Activation, Isa, IsaLevel, Matrix, MatrixData, Rnn};

const ROWS: [usize; 10] = [1, 2, 3, 5, 7, 8, 9, 17, 33, 129];
const COLS: [usize; 14] = [1, 2, 3, 7, 8, 9, 15, 16, 17, 31, 33, 100, 1000, 2500];
const BATCHES: [usize; 6] = [1, 2, 3, 5, 16, 17];
const ACTS: [Activation; 4] = [
    Activation::Identity,
    Activation::Relu,
    Activation::LeakyRelu(0.2),
    Activation::Tanh,
];
const TOLERANCE: f32 = 1e-5;

/// The SIMD levels this CPU has; fails when `DRIVESIM_REQUIRE_ISA` names one it lacks.
fn simd_levels() -> Vec<Isa> {
    let supported: Vec<Isa> = Isa::supported().filter(|i| i.level() != IsaLevel::Scalar).collect();
    for level in IsaLevel::ALL {
        if !supported.iter().any(|i| i.level() == level) {
            eprintln!("skipping {}: not supported by this CPU", level.name());
        }
    }
    if let Ok(required) = std::env::var("DRIVESIM_REQUIRE_ISA") {
        let level = IsaLevel::from_name(&required).unwrap_or_else(|| panic!("unknown DRIVESIM_REQUIRE_ISA={required}"));
        assert!(
            level == IsaLevel::Scalar || supported.iter().any(|i| i.level() == level),
            "DRIVESIM_REQUIRE_ISA={required} but this CPU lacks it"
        );
    }
    supported
}

/// max|got - want| / max(terms): the error relative to the largest sum of absolute terms.
/// Activations are 1-Lipschitz, so they do not enlarge the bound.
fn normwise_error(got: &[f32], want: &[f32], terms: &[f32]) -> f32 {
    assert!(got.iter().all(|v| v.is_finite()), "non-finite output");
    let scale = terms.iter().fold(1e-6f32, |m, &v| m.max(v));
    let diff = got.iter().zip(want).fold(0.0f32, |m, (g, w)| m.max((g - w).abs()));
    diff / scale
}

/// max|got - want| / max(|want|_inf, 1e-6).
fn relative_error(got: &[f32], want: &[f32]) -> f32 {
    let scale = want.iter().fold(1e-6f32, |m, v| m.max(v.abs()));
    let diff = got.iter().zip(want).fold(0.0f32, |m, (g, w)| m.max((g - w).abs()));
    assert!(got.iter().all(|v| v.is_finite()), "non-finite output");
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

/// An RNN's weights, row-major: `[W | V | U]` (`hd x (hd + zd + ad)`), `b`, `A` and `a`.
struct RnnWeights {
    dims: (usize, usize, usize),
    wvu: Vec<f32>,
    b: Vec<f32>,
    big_a: Vec<f32>,
    small_a: Vec<f32>,
}

impl RnnWeights {
    fn random(hd: usize, zd: usize, ad: usize) -> Self {
        let cols = hd + zd + ad;
        let seed = (hd * 7 + zd) as u64;
        RnnWeights {
            dims: (hd, zd, ad),
            wvu: values(seed, hd * cols, 1.0 / (cols as f32).sqrt()),
            b: values(seed + 2, hd, 0.1),
            big_a: values(seed + 1, zd * hd, 1.0 / (hd as f32).sqrt()),
            small_a: values(seed + 3, zd, 0.1),
        }
    }

    /// `[W + V A | U]` and `b + V a`, the input of a step fed its own prediction, summed in f64.
    fn fed_back(&self) -> (Vec<f32>, Vec<f32>) {
        let (hd, zd, ad) = self.dims;
        let cols = hd + zd + ad;
        let mut input = Vec::with_capacity(hd * (hd + ad));
        let mut bias = Vec::with_capacity(hd);
        for (row, &b) in self.wvu.chunks_exact(cols).zip(&self.b) {
            let v = &row[hd..hd + zd];
            let v_times = |column: &dyn Fn(usize) -> f32| (0..zd).map(|k| v[k] as f64 * column(k) as f64).sum::<f64>();
            input.extend((0..hd).map(|j| (row[j] as f64 + v_times(&|k| self.big_a[k * hd + j])) as f32));
            input.extend_from_slice(&row[hd + zd..]);
            bias.push((b as f64 + v_times(&|k| self.small_a[k])) as f32);
        }
        (input, bias)
    }
}

/// Runs `rnn_step` on `isa`: from `z`, or fed back without it.
fn run_rnn(isa: Isa, rnn: &Rnn<'_>, h0: &[f32], z: Option<&[f32]>, action: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let batch = h0.len() / rnn.hidden();
    let mut concat = vec![0.0; batch * rnn.input.cols];
    let mut h = h0.to_vec();
    let mut z_next = vec![f32::NAN; batch * rnn.z_dim()];
    rnn_step(isa, rnn, &mut concat, &mut h, z, action, &mut z_next);
    (h, z_next)
}

#[test]
fn rnn_step_matches_scalar() {
    let levels = simd_levels();
    // (hidden, z, action): tiny, odd, and one that crosses the column panels.
    for (hd, zd, ad) in [
        (1, 1, 1),
        (3, 5, 2),
        (17, 9, 2),
        (33, 16, 3),
        (64, 32, 2),
        (40, 1000, 2),
    ] {
        let weights = RnnWeights::random(hd, zd, ad);
        let (fed_back, fed_back_bias) = weights.fed_back();
        // Both forms of the input, packed: from a given code, and fed back.
        let inputs = [
            (
                dense_weights(&weights.wvu, hd, hd + zd + ad),
                &weights.b,
                hd + zd + ad,
                true,
            ),
            (dense_weights(&fed_back, hd, hd + ad), &fed_back_bias, hd + ad, false),
        ];
        let a = dense_weights(&weights.big_a, zd, hd);
        let a16 = halves(&a);
        for batch in [1, 2, 5, 16, 17] {
            let h0 = values(7, batch * hd, 0.9);
            let z = values(8, batch * zd, 1.0);
            let action = values(9, batch * ad, 1.0);
            for &(ref input, input_bias, cols, from_code) in &inputs {
                let input16 = halves(input);
                for half in [false, true] {
                    let (input, output) = if half {
                        (MatrixData::F16(&input16), MatrixData::F16(&a16))
                    } else {
                        (MatrixData::F32(input), MatrixData::F32(&a))
                    };
                    let rnn = Rnn {
                        input: Matrix {
                            data: input,
                            rows: hd,
                            cols,
                        },
                        input_bias,
                        output: Matrix {
                            data: output,
                            rows: zd,
                            cols: hd,
                        },
                        output_bias: &weights.small_a,
                    };
                    let z = from_code.then_some(&z[..]);
                    let (want_h, want_z) = run_rnn(Isa::SCALAR, &rnn, &h0, z, &action);
                    for &isa in &levels {
                        let (h, z_next) = run_rnn(isa, &rnn, &h0, z, &action);
                        let (eh, ez) = (relative_error(&h, &want_h), relative_error(&z_next, &want_z));
                        assert!(
                            eh <= TOLERANCE && ez <= TOLERANCE,
                            "{:?} hd {hd} z {zd} a {ad} batch {batch} f16 {half} from code {from_code}: \
                             h error {eh}, z error {ez}",
                            isa.level()
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn fed_back_step_is_the_step_from_the_predicted_code() {
    for (hd, zd, ad) in [(1, 1, 1), (17, 9, 2), (40, 1000, 2), (64, 32, 3)] {
        let weights = RnnWeights::random(hd, zd, ad);
        let (fed_back, fed_back_bias) = weights.fed_back();
        let a = dense_weights(&weights.big_a, zd, hd);
        let matrix = |data, rows, cols| Matrix {
            data: MatrixData::F32(data),
            rows,
            cols,
        };
        let output = matrix(&a, zd, hd);
        let wvu = dense_weights(&weights.wvu, hd, hd + zd + ad);
        let from_code = Rnn {
            input: matrix(&wvu, hd, hd + zd + ad),
            input_bias: &weights.b,
            output,
            output_bias: &weights.small_a,
        };
        let fed_back = dense_weights(&fed_back, hd, hd + ad);
        let fed_back = Rnn {
            input: matrix(&fed_back, hd, hd + ad),
            input_bias: &fed_back_bias,
            ..from_code
        };
        for batch in [1, 3] {
            let h0 = values(10, batch * hd, 0.9);
            let action = values(11, batch * ad, 1.0);
            let mut predicted = vec![0.0; batch * zd];
            dense(
                Isa::SCALAR,
                output,
                &weights.small_a,
                Activation::Identity,
                &h0,
                &mut predicted,
            );
            let (want_h, want_z) = run_rnn(Isa::SCALAR, &from_code, &h0, Some(&predicted), &action);
            for isa in Isa::supported() {
                let (h, z) = run_rnn(isa, &fed_back, &h0, None, &action);
                let (eh, ez) = (relative_error(&h, &want_h), relative_error(&z, &want_z));
                assert!(
                    eh <= TOLERANCE && ez <= TOLERANCE,
                    "{:?} hd {hd} z {zd} a {ad} batch {batch}: h error {eh}, z error {ez}",
                    isa.level()
                );
            }
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
                // Ranges start at panels, as threads' shares do.
                for range in [0..16, 16..16, 16..32, 32..37] {
                    // SAFETY: `parts` holds every row of every item and is not shared.
                    unsafe { dense_rows(isa, w, &bias, Activation::Tanh, &x, parts.as_mut_ptr(), range) };
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
    // Columns past the kernels' chunk of 1024 and rows past a single input's spread tile.
    for (rows, cols) in [(129, 2500), (300, 1026), (33, 3000), (512, 4097)] {
        let w32 = dense_weights(&values(rows as u64, rows * cols, 0.05), rows, cols);
        let w16 = halves(&w32);
        let bias = values(7, rows, 0.5);
        let batch = 5;
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
                for split in [16, 48, 64, 272] {
                    let mut parts = vec![0.0; batch * rows];
                    for start in (0..rows).step_by(split) {
                        // SAFETY: `parts` holds the whole output; the ranges are disjoint and
                        // written one after another.
                        let end = (start + split).min(rows);
                        unsafe { dense_rows(isa, w, &bias, Activation::Tanh, &x, parts.as_mut_ptr(), start..end) };
                    }
                    assert_eq!(parts, whole, "{isa:?} {rows}x{cols}: rows in parts of {split}");
                }
            }
        }
    }
}
