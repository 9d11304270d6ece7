//! The texture net (`transition.texture.*`, optional): a sampler of the next code that keeps
//! the road's texture. A transition predicts the mean of the next code, and a mean over where a
//! kerb or a grass patch may be a step later is a frame without them: they fade within a few
//! steps, and Gaussian noise around the mean (the spread head, [`crate::sampling`]) does not
//! bring them back. The texture net draws the offset from the mean itself, from noise of its
//! own and the hidden state the step left: `code = A h' + a + T([temperature * ε | h'])`, `T` a
//! two-layer tanh network of the heads' shape ([`crate::HeadKind`]; `ε` in the code's place,
//! `z_dim` standard normal draws of [`crate::sampling`]'s generator). It is trained
//! adversarially (`weights/drivesim_reference/train.py texture`): critics of its generated frames, of its codes
//! with the hidden state and of its fed-back codes judge it against the recorded drives, so that
//! its samples are frames a discriminator cannot tell from the road's (docs/history/next_second.md).
//!
//! A model with the texture net samples through it and not through the spread head; the mean
//! path (temperature 0) is the transition's, bit for bit.

use crate::heads::Head;
use crate::pool::Exec;
use crate::sampling::Sampling;
use crate::weights::TensorSource;
use crate::{Config, Result};

/// The prefix of the texture net's tensors: `hidden.weight` `[width, z_dim + hidden_dim]`,
/// `hidden.bias` `[width]`, `output.weight` `[z_dim, width]`, `output.bias` `[z_dim]`.
pub(crate) const TEXTURE: &str = "transition.texture.";

/// The texture net's two layers.
pub(crate) struct Texture {
    net: Head,
    z_dim: usize,
    hidden_dim: usize,
}

/// The texture net's scratch for a batch of `n` items, from the transition's planned buffers
/// (each at least as long as said).
pub(crate) struct TextureScratch<'a> {
    /// `[n, z_dim + hidden_dim]`: each item's `[temperature * ε | h']`.
    pub input: &'a mut [f32],
    /// `[n, width]`: the hidden layer's outputs (at most `hidden_dim` per item).
    pub hidden: &'a mut [f32],
    /// `[n, z_dim]`: the offsets from the means.
    pub offsets: &'a mut [f32],
}

impl Texture {
    /// The net under [`TEXTURE`] where the source has it (`None` where it has no tensor there);
    /// its width is its hidden bias's length, 1 to `hidden_dim`.
    pub fn load(config: &Config, src: &mut dyn TensorSource) -> Result<Option<Texture>> {
        let net = Head::load_at(config, src, TEXTURE, config.z_dim)?;
        Ok(net.map(|net| Texture {
            net,
            z_dim: config.z_dim,
            hidden_dim: config.hidden_dim,
        }))
    }

    /// Units of the hidden layer.
    pub fn width(&self) -> usize {
        self.net.width()
    }

    /// `codes += T([temperature * ε | h])` for rollout step `step`, items numbered from 0:
    /// `h` `[n, hidden_dim]`, `codes` `[n, z_dim]`, `ε` each item's own stream of `sampling`.
    /// The products run on the dense kernel, bit-identical for any threads or batch.
    pub fn sample(
        &self,
        exec: Exec<'_>,
        sampling: &Sampling,
        h: &[f32],
        step: u64,
        codes: &mut [f32],
        s: TextureScratch<'_>,
    ) {
        let (zd, hd) = (self.z_dim, self.hidden_dim);
        let n = codes.len() / zd;
        let (input, hidden, offsets) = (
            &mut s.input[..n * (zd + hd)],
            &mut s.hidden[..n * self.width()],
            &mut s.offsets[..n * zd],
        );
        // The noise goes where the input's codes go, then is scaled there; h beside it.
        sampling.draw_rows(input, zd, zd + hd, step);
        for (row, h) in input.chunks_exact_mut(zd + hd).zip(h.chunks_exact(hd)) {
            for value in &mut row[..zd] {
                *value *= sampling.temperature;
            }
            row[zd..].copy_from_slice(h);
        }
        self.net.run(exec, input, hidden, offsets);
        for (code, offset) in codes.iter_mut().zip(offsets.iter()) {
            *code += offset;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::weights::RandomSource;
    use crate::WeightDtype;
    use drivesim_kernels::Isa;

    fn tanh64(x: f64) -> f64 {
        1.0 - 2.0 / (drivesim_kernels::math::exp64(2.0 * x) + 1.0)
    }

    #[test]
    fn a_sample_is_the_mean_plus_the_net_of_the_scaled_noise_and_h() {
        let config = Config {
            z_dim: 6,
            hidden_dim: 9,
            ..Config::COMMA
        };
        let (zd, hd, width, n) = (6, 9, 5, 3);
        let mut src = RandomSource::new(4, WeightDtype::F32);
        let texture = Texture {
            net: Head::read_at(&config, &mut src, TEXTURE, zd, width).unwrap(),
            z_dim: zd,
            hidden_dim: hd,
        };
        // The same draw again, as f64 weights: hidden [width, zd + hd] and its bias, output [zd, width] and its bias.
        let mut again = RandomSource::new(4, WeightDtype::F32);
        let mut next = |len: usize, fan_in: usize| -> alloc::vec::Vec<f64> {
            let t = again.tensor("", &[len], crate::weights::Init::FanIn(fan_in)).unwrap();
            t.into_f32().iter().map(|&v| v as f64).collect()
        };
        let (w1, b1) = (next(width * (zd + hd), zd + hd), next(width, zd + hd));
        let (w2, b2) = (next(zd * width, width), next(zd, width));
        let sampling = Sampling {
            temperature: 0.7,
            seed: 11,
        };
        let h: alloc::vec::Vec<f32> = (0..n * hd).map(|i| ((i * 7 % 13) as f32 - 6.0) / 7.0).collect();
        let means: alloc::vec::Vec<f32> = (0..n * zd).map(|i| (i as f32 - 8.0) / 5.0).collect();
        let (mut input, mut hidden, mut offsets) = (
            alloc::vec![0.0; n * (zd + hd)],
            alloc::vec![0.0; n * hd],
            alloc::vec![0.0; n * zd],
        );
        let mut codes = means.clone();
        let exec = Exec {
            isa: Isa::best(),
            pool: None,
        };
        let scratch = TextureScratch {
            input: &mut input,
            hidden: &mut hidden,
            offsets: &mut offsets,
        };
        texture.sample(exec, &sampling, &h, 5, &mut codes, scratch);
        let mut noise = alloc::vec![0.0; n * zd];
        sampling.draw(&mut noise, zd, 5);
        for item in 0..n {
            let x: alloc::vec::Vec<f64> = (0..zd)
                .map(|d| 0.7f32 as f64 * noise[item * zd + d] as f64)
                .chain((0..hd).map(|d| h[item * hd + d] as f64))
                .collect();
            let units: alloc::vec::Vec<f64> = (0..width)
                .map(|u| tanh64(b1[u] + (0..zd + hd).map(|c| w1[u * (zd + hd) + c] * x[c]).sum::<f64>()))
                .collect();
            for d in 0..zd {
                let want =
                    means[item * zd + d] as f64 + b2[d] + (0..width).map(|u| w2[d * width + u] * units[u]).sum::<f64>();
                let got = codes[item * zd + d] as f64;
                assert!(
                    (got - want).abs() < 1e-5 * (1.0 + want.abs()),
                    "item {item} dim {d}: {got} against {want}"
                );
            }
        }
    }
}
