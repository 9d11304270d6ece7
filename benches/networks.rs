//! Criterion benchmarks of the comma config: whole networks (encode, generate, one transition
//! step, also on 2 threads) and their layers, at z = hidden = 512 and 2048, batch 1 and 16 (the
//! transition's products also at a planner's 64 and 256), f32 and f16 weights. Throughput is in
//! floating-point operations (see `common::conv_flops`), so criterion's "elem/s" is FLOP/s; the
//! share of the FMA peak per shape: `cargo run --release -p drivesim-kernels --example dense_speed`.
//!
//! `cargo bench --bench networks [-- FILTER]`; `DRIVESIM_ISA=avx2|scalar` caps the kernels.

mod common;

use common::*;
use criterion::{criterion_group, criterion_main, BenchmarkGroup, Criterion, Throughput};
use drivesim::{Config, Model, Simulator, WeightDtype};
use drivesim_kernels::{
    conv, conv_patch_len, conv_weight_grad, conv_weight_grad_scratch_len, dense, dense_data_grad, f16, pack,
    winograd_conv, winograd_weights, Activation, ConvKind, ConvParams, ConvShape, Isa, Matrix, MatrixData, Winograd,
};
use std::hint::black_box;
use std::time::Duration;

const SEED: u64 = 2016;
const BATCHES: [usize; 2] = [1, 16];
/// A planner's batches of candidates.
const PLANNER_BATCHES: [usize; 4] = [1, 16, 64, 256];

fn group<'a>(c: &'a mut Criterion, name: &str) -> BenchmarkGroup<'a, criterion::measurement::WallTime> {
    let mut g = c.benchmark_group(name);
    g.sample_size(10)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(2));
    g
}

/// Encode, generate and one transition step through the public API.
fn networks(c: &mut Criterion) {
    let mut g = group(c, "network");
    for z in [512, 2048] {
        let cfg = comma(z);
        let dtypes = [WeightDtype::F32, WeightDtype::F16];
        for dtype in dtypes {
            let model = Model::random(&cfg, SEED, dtype).expect("valid config");
            let tag = format!("z{z}_{}", if dtype == WeightDtype::F16 { "f16" } else { "f32" });
            for batch in BATCHES {
                let mut sim = Simulator::with_batch(&model, batch).expect("simulator planned");
                let frames = values(1, batch * cfg.frame_len(), 1.0);
                let codes = values(2, batch * z, 1.0);
                let actions = values(3, batch * cfg.action_dim, 1.0);
                let mut out_frames = vec![0.0; batch * cfg.frame_len()];
                let mut out_codes = vec![0.0; batch * z];
                let mut h = vec![0.0; batch * z];
                // The convolutional networks have no f16 path: time them once, in f32.
                if dtype == WeightDtype::F32 {
                    g.throughput(Throughput::Elements(batch as u64 * encode_flops(&cfg)));
                    g.bench_function(format!("encode/{tag}/batch{batch}"), |b| {
                        b.iter(|| sim.encode(black_box(&frames), &mut out_codes).unwrap())
                    });
                    g.throughput(Throughput::Elements(batch as u64 * generate_flops(&cfg)));
                    g.bench_function(format!("generate/{tag}/batch{batch}"), |b| {
                        b.iter(|| sim.generate(black_box(&codes), &mut out_frames).unwrap())
                    });
                }
                // The step is the one part short enough for the threads' hand-off to matter.
                let mut sim2 = Simulator::with_batch(&model, batch)
                    .and_then(|sim| sim.with_threads(2))
                    .expect("simulator planned and threads started");
                for (sim, threads) in [(&mut sim, ""), (&mut sim2, "/threads2")] {
                    g.throughput(Throughput::Elements(batch as u64 * transition_flops(&cfg)));
                    g.bench_function(format!("transition/{tag}/batch{batch}{threads}"), |b| {
                        b.iter(|| {
                            h.fill(0.0);
                            sim.transition(black_box(&codes), &mut h, &actions, &mut out_codes)
                                .unwrap()
                        })
                    });
                    // Fed the previous prediction, as in a rollout after its seeds: for f32
                    // weights, the folded step.
                    g.bench_function(format!("transition_fed_back/{tag}/batch{batch}{threads}"), |b| {
                        b.iter(|| {
                            sim.transition_fed_back(&mut h, black_box(&actions), &mut out_codes)
                                .unwrap()
                        })
                    });
                }
            }
        }
    }
    g.finish();
}

/// Every convolution of the encoder and generator, one image, through the kernels crate.
fn conv_layers(c: &mut Criterion) {
    let isa = Isa::best();
    let cfg = comma(512);
    let mut g = group(c, "conv");
    let layers = encoder_convs(&cfg)
        .into_iter()
        .enumerate()
        .map(|(i, s)| (format!("encoder.conv{i}"), s, Activation::LeakyRelu(0.2)))
        .chain(generator_convs(&cfg).into_iter().enumerate().map(|(i, s)| {
            let act = if i + 1 == cfg.layers {
                Activation::Tanh
            } else {
                Activation::Relu
            };
            (format!("generator.deconv{}", i + 1), s, act)
        }));
    for (name, shape, act) in layers {
        let ConvShape { input, output, .. } = shape;
        let mut x = vec![0.0; input.len()];
        input.write_interior(&mut x, &values(4, input.interior_len(), 1.0));
        let w = values(5, shape.packed_len(), 0.05);
        let bias = values(6, output.channels, 0.1);
        let mut y = vec![0.0; output.len()];
        g.throughput(Throughput::Elements(conv_flops(&shape)));
        let layer = ConvParams {
            shape,
            weights: &w,
            bias: &bias,
            act,
        };
        g.bench_function(name.as_str(), |b| b.iter(|| conv(isa, layer, black_box(&x), &mut y)));
        // The same layer by Winograd, as the networks run it where it applies. Throughput still
        // counts the direct convolution's FLOPs, so the two compare as rates of the same work.
        if let Some(wino) = Winograd::new(shape) {
            let u = values(5, wino.packed_len(), 0.05);
            let mut v = vec![0.0; wino.input_len()];
            let mut scratch = vec![0.0; wino.scratch_len()];
            let layer = ConvParams { weights: &u, ..layer };
            g.bench_function(format!("{name}.winograd"), |b| {
                b.iter(|| winograd_conv(isa, &wino, layer, black_box(&x), &mut v, &mut scratch, &mut y))
            });
        }
    }
    g.finish();
}

/// The backward kernels of training on the default model's layers (80x160, b = 32): each
/// layer's data gradient (the forward kernel of its transposed shape, direct and Winograd) on
/// one image, and its weight gradient (`conv_weight_grad`, the dense weight gradient over
/// patches) over a batch of 8; and the dense layers' data gradients. Throughput counts the
/// layer's forward FLOPs per image, the same work (`cargo bench --bench networks -- backward`).
fn conv_backward(c: &mut Criterion) {
    let isa = Isa::best();
    let cfg = Config {
        base_channels: 32,
        ..comma(128)
    };
    let mut g = group(c, "backward");
    let layers = encoder_convs(&cfg)
        .into_iter()
        .enumerate()
        .map(|(i, s)| (format!("encoder.conv{i}"), s))
        .chain(
            generator_convs(&cfg)
                .into_iter()
                .enumerate()
                .map(|(i, s)| (format!("generator.deconv{}", i + 1), s)),
        );
    for (name, shape) in layers {
        g.throughput(Throughput::Elements(conv_flops(&shape)));
        let back = shape.transposed();
        let torch = values(
            5,
            shape.input.channels * shape.output.channels * shape.kernel.pow(2),
            0.05,
        );
        let mut direct = vec![0.0; back.packed_len()];
        pack::conv_weights_into(&back, &torch, &mut direct);
        let zero = vec![0.0; back.output.channels];
        let mut dy = vec![0.0; back.input.len()];
        back.input
            .write_interior(&mut dy, &values(4, back.input.interior_len(), 1.0));
        let mut dx = vec![0.0; back.output.len()];
        let layer = ConvParams {
            shape: back,
            weights: &direct,
            bias: &zero,
            act: Activation::Identity,
        };
        g.bench_function(format!("{name}.data"), |b| {
            b.iter(|| conv(isa, layer, black_box(&dy), &mut dx))
        });
        if let Some(wino) = Winograd::new(back) {
            let mut u = vec![0.0; wino.packed_len()];
            winograd_weights(isa, &wino, &direct, &mut u);
            // A trainer transforms every layer's weights after each update, in both forms.
            g.bench_function(format!("{name}.data.winograd_weights"), |b| {
                b.iter(|| winograd_weights(isa, &wino, black_box(&direct), &mut u))
            });
            let (mut v, mut scratch) = (vec![0.0; wino.input_len()], vec![0.0; wino.scratch_len()]);
            let layer = ConvParams { weights: &u, ..layer };
            g.bench_function(format!("{name}.data.winograd"), |b| {
                b.iter(|| winograd_conv(isa, &wino, layer, black_box(&dy), &mut v, &mut scratch, &mut dx))
            });
        }
        // The weight gradient of a strided layer, or of a transposed one's transposed shape
        // with input and output gradient swapped.
        let items = 8;
        let down = if shape.kind == ConvKind::Down { shape } else { back };
        let mut input = vec![0.0; items * down.input.len()];
        let mut grad_out = vec![0.0; items * down.output.len()];
        for (n, item) in input.chunks_exact_mut(down.input.len()).enumerate() {
            down.input
                .write_interior(item, &values(7 + n as u64, down.input.interior_len(), 1.0));
        }
        for (n, item) in grad_out.chunks_exact_mut(down.output.len()).enumerate() {
            down.output
                .write_interior(item, &values(20 + n as u64, down.output.interior_len(), 1.0));
        }
        let mut scratch = vec![0.0; conv_weight_grad_scratch_len(&down)];
        let mut grad = vec![0.0; Matrix::packed_len(down.output.channels, conv_patch_len(&down))];
        g.throughput(Throughput::Elements(items as u64 * conv_flops(&shape)));
        g.bench_function(format!("{name}.weights/batch{items}"), |b| {
            b.iter(|| conv_weight_grad(isa, down, black_box(&input), &grad_out, &mut scratch, &mut grad))
        });
    }
    // The dense layers' data gradients (`dense_data_grad`, read from the forward packing) over
    // a batch of 8: the encoder's two heads and the generator's first layer.
    let flat = cfg.flat_len();
    for (name, rows, cols) in [
        ("encoder.heads", 2 * cfg.z_dim, flat),
        ("generator.fc", flat, cfg.z_dim),
    ] {
        let items = 8;
        let w = pack::dense_weights(&values(7, rows * cols, 1.0 / (cols as f32).sqrt()), rows, cols);
        let dy = values(8, items * rows, 1.0);
        let mut dx = vec![0.0; items * cols];
        g.throughput(Throughput::Elements(items as u64 * dense_flops(rows, cols)));
        g.bench_function(format!("{name}.data/batch{items}"), |b| {
            b.iter(|| dense_data_grad(isa, &w, rows, cols, black_box(&dy), &mut dx))
        });
    }
    g.finish();
}

/// The dense layers of both sizes through the kernels crate; f16 weights for z = 2048.
fn dense_layers(c: &mut Criterion) {
    let isa = Isa::best();
    let mut g = group(c, "dense");
    for z in [512, 2048] {
        let cfg = comma(z);
        let flat = cfg.flat_len();
        // The transition's products: its state's part from a code (`[W | V]`) and fed back
        // (`W + V A`, the same shape as `A`), at a planner's batches too.
        let layers = [
            ("encoder.mean", z, flat, Activation::Identity, &BATCHES[..]),
            ("generator.fc", flat, z, Activation::Relu, &BATCHES[..]),
            ("transition.WV", z, 2 * z, Activation::Identity, &PLANNER_BATCHES[..]),
            ("transition.A", z, z, Activation::Identity, &PLANNER_BATCHES[..]),
        ];
        for (name, rows, cols, act, batches) in layers {
            let w32 = pack::dense_weights(&values(7, rows * cols, 1.0 / (cols as f32).sqrt()), rows, cols);
            let w16: Vec<f16> = w32.iter().map(|&v| f16::from_f32(v)).collect();
            let bias = values(8, rows, 0.1);
            let halves: &[bool] = if z == 2048 { &[false, true] } else { &[false] };
            for &half in halves {
                let data = if half {
                    MatrixData::F16(&w16)
                } else {
                    MatrixData::F32(&w32)
                };
                let m = Matrix { data, rows, cols };
                for &batch in batches {
                    let x = values(9, batch * cols, 1.0);
                    let mut y = vec![0.0; batch * rows];
                    let dtype = if half { "f16" } else { "f32" };
                    g.throughput(Throughput::Elements(batch as u64 * dense_flops(rows, cols)));
                    g.bench_function(format!("{name}/{rows}x{cols}/{dtype}/batch{batch}"), |b| {
                        b.iter(|| dense(isa, m, &bias, act, black_box(&x), &mut y))
                    });
                }
            }
        }
    }
    g.finish();
}

criterion_group!(benches, dense_layers, networks, conv_layers, conv_backward);
criterion_main!(benches);
