//! Shapes and operation counts shared by the criterion benches and `examples/bench_report.rs`
//! (included there with `#[path]`).
#![allow(dead_code)] // each includer uses part of it

#[path = "../../kernels/tests/common/mod.rs"]
mod values;

use drivesim::Config;
use drivesim_kernels::{ConvKind, ConvShape, Plane};
pub use values::values;

/// The comma config with `z_dim = hidden_dim = z`.
pub fn comma(z: usize) -> Config {
    Config {
        z_dim: z,
        hidden_dim: z,
        ..Config::COMMA
    }
}

/// The encoder's convolutions, built as the model builds them.
pub fn encoder_convs(c: &Config) -> Vec<ConvShape> {
    let halo = ConvKind::Down.input_halo(c.kernel);
    let mut input = Plane::new(c.height, c.width, c.channels, halo);
    (0..c.layers)
        .map(|i| {
            let last = i + 1 == c.layers;
            let shape = ConvShape::new(
                ConvKind::Down,
                c.kernel,
                input,
                c.base_channels << i,
                if last { 0 } else { halo },
            );
            input = shape.output;
            shape
        })
        .collect()
}

/// The generator's transposed convolutions, built as the model builds them.
pub fn generator_convs(c: &Config) -> Vec<ConvShape> {
    let halo = ConvKind::Up.input_halo(c.kernel);
    let (h, w) = c.top_size();
    let mut input = Plane::new(h, w, c.top_channels(), halo);
    (1..=c.layers)
        .map(|i| {
            let last = i == c.layers;
            let (oc, out_halo) = if last {
                (c.channels, 0)
            } else {
                (c.top_channels() >> i, halo)
            };
            let shape = ConvShape::new(ConvKind::Up, c.kernel, input, oc, out_halo);
            input = shape.output;
            shape
        })
        .collect()
}

/// Floating-point operations of a convolution counting every kernel tap (padding included):
/// `2 k^2 ic oc` per output pixel of a convolution, per input pixel of a transposed one (the
/// count PyTorch and ONNX profilers use). [`ConvShape::macs`] counts only in-image taps.
pub fn conv_flops(s: &ConvShape) -> u64 {
    let pixels = match s.kind {
        ConvKind::Down => s.output.height * s.output.width,
        ConvKind::Up => s.input.height * s.input.width,
    };
    (2 * pixels * s.kernel * s.kernel * s.input.channels * s.output.channels) as u64
}

/// Floating-point operations of `rows x cols` times one vector.
pub fn dense_flops(rows: usize, cols: usize) -> u64 {
    2 * (rows * cols) as u64
}

/// Per frame: the convolutions and the mean head.
pub fn encode_flops(c: &Config) -> u64 {
    encoder_convs(c).iter().map(conv_flops).sum::<u64>() + dense_flops(c.z_dim, c.flat_len())
}

/// Per frame: the dense layer and the transposed convolutions.
pub fn generate_flops(c: &Config) -> u64 {
    generator_convs(c).iter().map(conv_flops).sum::<u64>() + dense_flops(c.flat_len(), c.z_dim)
}

/// Per step: `[W|V|U] [h;z;c]` and `A h`.
pub fn transition_flops(c: &Config) -> u64 {
    dense_flops(c.hidden_dim, c.hidden_dim + c.z_dim + c.action_dim) + dense_flops(c.z_dim, c.hidden_dim)
}

/// FLOPs of one transition training step on one window of `window` codes: per prediction,
/// the forward products (`[W | V | U]` and `A`), the hidden state's data gradient
/// (`[Aᵀ | Wᵀ]`) and the weight gradients of both products, two FLOPs per multiply-add.
pub fn train_transition_flops(c: &Config, window: usize) -> u64 {
    let (h, z, a) = (c.hidden_dim as u64, c.z_dim as u64, c.action_dim as u64);
    let products = h * (h + z + a) + z * h;
    2 * (window as u64 - 1) * (2 * products + h * (z + h))
}

/// FLOPs of one VAE-GAN training step per frame of the batch (`drivesim::train`'s and
/// `weights/drivesim_reference/train.py`'s step), every convolution counted by [`conv_flops`] (direct-equivalent,
/// the discriminator has the encoder's shapes): forward, the encoder (once), the generator on
/// reconstructions and prior samples, the discriminator six times (real frames twice, the
/// two fakes twice); backward, the discriminator's loss (weights and data gradients but the
/// input's, on real frames and fakes), the encoder's feature error through the discriminator
/// from its third convolution and the generator's loss through all of it (data gradients, on
/// the fakes), the generator for the encoder (data, reconstructions) and for itself (weights
/// and data, both fakes), and the encoder (weights, and data gradients but the input's).
pub fn train_vae_gan_flops(c: &Config) -> u64 {
    let e: Vec<u64> = encoder_convs(c).iter().map(conv_flops).collect();
    let g: u64 = generator_convs(c).iter().map(conv_flops).sum();
    let (all, above_first) = (e.iter().sum::<u64>(), e[1..].iter().sum::<u64>());
    let (flat, z) = (c.flat_len(), c.z_dim);
    let (heads, fc, logit) = (dense_flops(2 * z, flat), dense_flops(flat, z), dense_flops(1, flat));
    let forward = (all + heads) + 2 * (g + fc) + 6 * (all + logit);
    let discriminator = 3 * (all + above_first + 2 * logit);
    let through_discriminator = 2 * (e[0] + e[1] + e[2]) + 2 * (all + logit);
    let generator = (g + fc) + 2 * (2 * g + fc);
    let encoder = all + above_first + 2 * heads;
    forward + discriminator + through_discriminator + generator + encoder
}
