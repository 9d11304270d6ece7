//! Speed of the convolution kernels on the comma.ai model's layers (80x160x3 frames), one image
//! per call, single-threaded: `cargo run --release -p drivesim-kernels --example conv_speed`.
//! Set `DRIVESIM_ISA` to cap the level (scalar, neon, avx2, avx512).
//!
//! Times are this thread's CPU time (from `/proc/thread-self/schedstat` where it exists, else
//! wall time), so that other processes sharing the cores do not inflate them.

#[path = "common/speed_clock.rs"]
mod speed_clock;

use drivesim_kernels::{conv, Activation, ConvKind, ConvParams, ConvShape, Isa, Plane};
use speed_clock::best_seconds;

fn main() {
    let isa = Isa::best();
    let leaky = Activation::LeakyRelu(0.2);
    let layers = [
        ("enc conv0 3->64", ConvKind::Down, (80, 160, 3), 64, leaky),
        ("enc conv1 64->128", ConvKind::Down, (40, 80, 64), 128, leaky),
        ("enc conv2 128->256", ConvKind::Down, (20, 40, 128), 256, leaky),
        ("enc conv3 256->512", ConvKind::Down, (10, 20, 256), 512, leaky),
        (
            "gen deconv0 512->256",
            ConvKind::Up,
            (5, 10, 512),
            256,
            Activation::Relu,
        ),
        (
            "gen deconv1 256->128",
            ConvKind::Up,
            (10, 20, 256),
            128,
            Activation::Relu,
        ),
        ("gen deconv2 128->64", ConvKind::Up, (20, 40, 128), 64, Activation::Relu),
        ("gen deconv3 64->3", ConvKind::Up, (40, 80, 64), 3, Activation::Tanh),
    ];
    println!("level {}", isa.level().name());
    let mut totals = [(0.0f64, 0.0f64); 2];
    for (name, kind, (h, w, c), oc, act) in layers {
        let input_plane = Plane::new(h, w, c, kind.input_halo(5));
        let shape = ConvShape::new(kind, 5, input_plane, oc, 2);
        let input: Vec<f32> = (0..input_plane.len())
            .map(|i| ((i * 7919) % 101) as f32 / 101.0 - 0.5)
            .collect();
        // `DRIVESIM_SPEED_ALIGN=64` places the weights on a 64-byte boundary (else where the
        // allocator puts them).
        let align = std::env::var("DRIVESIM_SPEED_ALIGN")
            .ok()
            .and_then(|v| v.parse::<usize>().ok());
        let mut store: Vec<f32> = vec![0.0; shape.packed_len() + 16];
        let skip = align.map_or(0, |a| store.as_ptr().align_offset(a));
        let weights = &mut store[skip..skip + shape.packed_len()];
        for (i, w) in weights.iter_mut().enumerate() {
            *w = ((i * 104729) % 97) as f32 / 970.0 - 0.05;
        }
        let weights = &*weights;
        let bias = vec![0.01; oc];
        let mut output = vec![0.0; shape.output.len()];
        let layer = ConvParams {
            shape,
            weights,
            bias: &bias,
            act,
        };
        let flops = 2.0 * shape.macs() as f64;
        let best = best_seconds(|| conv(isa, layer, &input, &mut output));
        let net = (kind == ConvKind::Up) as usize;
        totals[net].0 += best;
        totals[net].1 += flops;
        println!(
            "{name:24} {:7.3} ms  {:6.1} MFLOP  {:6.1} GFLOP/s",
            best * 1e3,
            flops / 1e6,
            flops / best / 1e9
        );
    }
    for (net, (t, f)) in ["encoder convs", "generator convs"].iter().zip(totals) {
        println!(
            "{net:24} {:7.3} ms  {:6.1} MFLOP  {:6.1} GFLOP/s",
            t * 1e3,
            f / 1e6,
            f / t / 1e9
        );
    }
}
