//! Speed of the dense kernel on the transition's shapes, f32, at batch 1 to 256, single-threaded:
//! the comma config's (z = hidden = 512: the state's part `[W | V]`, 512 x 1024, also the shape of
//! the training step's `[Aᵀ | Wᵀ]`, and `A` or the folded `W + V A`, 512 x 512) and the trained
//! default's (z = 128, hidden = 256: `[W | V | U]` 256 x 386 with its tanh, `[Aᵀ | Wᵀ]` 256 x 384,
//! `A` 128 x 256):
//! `cargo run --release -p drivesim-kernels --example dense_speed [-- --batch 1,16,64,256]`.
//! Prints GFLOP/s and the share of this core's FMA peak (measured here, 12 chains of FMAs).
//! Then the weight gradient of the same shapes over a transition training step's items (`--items
//! 3584`: 14 predictions of 256 windows), `dyᵀ x`, as the trainer computes it.
//! Set `DRIVESIM_ISA` to cap the level (scalar, neon, avx2, avx512). Times are this thread's
//! CPU time where the kernel gives it (see `conv_speed`).

#[path = "common/speed_clock.rs"]
mod speed_clock;

use drivesim_kernels::{dense, dense_weight_grad, pack, Activation, Isa, Matrix, MatrixData};
use speed_clock::{best_seconds, fma_peak_gflops};

/// The comma-separated positive numbers after `flag`, or `default` without the flag; a bad
/// value ends the program with a one-line error.
fn numbers(flag: &str, default: &[usize]) -> Vec<usize> {
    let Some(text) = std::env::args().skip_while(|a| a != flag).nth(1) else {
        return default.to_vec();
    };
    match text.split(',').map(str::parse).collect::<Result<Vec<usize>, _>>() {
        Ok(list) if !list.is_empty() && !list.contains(&0) => list,
        _ => {
            eprintln!("dense_speed: {flag} takes positive numbers separated by commas, not {text:?}");
            std::process::exit(1);
        }
    }
}

fn main() {
    let batches = numbers("--batch", &[1, 16, 64, 256]);
    let items = numbers("--items", &[3584])[0];
    let isa = Isa::best();
    let peak = fma_peak_gflops(isa);
    println!("level {}  FMA peak {peak:.1} GFLOP/s (one thread)", isa.level().name());
    for (name, rows, cols, act) in [
        ("comma [W|V], [Aᵀ|Wᵀ]", 512, 1024, Activation::Identity),
        ("comma A, W+VA", 512, 512, Activation::Identity),
        ("default [W|V|U]", 256, 386, Activation::Tanh),
        ("default [Aᵀ|Wᵀ]", 256, 384, Activation::Identity),
        ("default A", 128, 256, Activation::Identity),
    ] {
        let row_major: Vec<f32> = (0..rows * cols)
            .map(|i| ((i * 104729) % 97) as f32 / 970.0 - 0.05)
            .collect();
        let packed = pack::dense_weights(&row_major, rows, cols);
        let w = Matrix {
            data: MatrixData::F32(&packed),
            rows,
            cols,
        };
        let bias = vec![0.01; rows];
        for &batch in &batches {
            let x: Vec<f32> = (0..batch * cols)
                .map(|i| ((i * 7919) % 101) as f32 / 101.0 - 0.5)
                .collect();
            let mut y = vec![0.0; batch * rows];
            let seconds = best_seconds(|| dense(isa, w, &bias, act, &x, &mut y));
            let gflops = 2.0 * (rows * cols * batch) as f64 / seconds / 1e9;
            println!(
                "{name:22} {rows}x{cols} batch {batch:3}  {:8.4} ms  {gflops:6.1} GFLOP/s  {:5.1}% of peak",
                seconds * 1e3,
                100.0 * gflops / peak
            );
        }
    }
    for (name, rows, cols) in [
        ("comma grad [W|V|U]", 512, 1026),
        ("comma grad A", 512, 512),
        ("default grad [W|V|U]", 256, 386),
        ("default grad A", 128, 256),
    ] {
        let dy: Vec<f32> = (0..items * rows)
            .map(|i| ((i * 7919) % 101) as f32 / 101.0 - 0.5)
            .collect();
        let x: Vec<f32> = (0..items * cols)
            .map(|i| ((i * 104729) % 97) as f32 / 97.0 - 0.5)
            .collect();
        let mut grad = vec![0.0; Matrix::packed_len(rows, cols)];
        let seconds = best_seconds(|| dense_weight_grad(isa, &dy, &x, rows, cols, &mut grad));
        let gflops = 2.0 * (rows * cols * items) as f64 / seconds / 1e9;
        println!(
            "{name:22} {rows}x{cols} items {items}  {:8.4} ms  {gflops:6.1} GFLOP/s  {:5.1}% of peak",
            seconds * 1e3,
            100.0 * gflops / peak
        );
    }
}
