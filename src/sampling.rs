//! Sampled futures: a transition with a spread head (`transition.S`, `transition.s`: the log
//! standard deviation of each dimension of the next code, `S h' + s`) predicts a Gaussian per
//! dimension around its mean `A h' + a`. A simulator with sampling on
//! ([`crate::Simulator::set_sampling`]) draws each predicted code as
//! `mean + temperature * exp(S h' + s) * noise`, the noise standard normal from a counter-based
//! generator: each value depends only on the seed, the step, the item and the dimension, so the
//! samples are the same bits whatever the thread count, the batch or what ran before. A model
//! with `transition.L` correlates the noise across dimensions: `L ε` for the standard normal
//! `ε`, `L` the Cholesky factor of the correlation of the one-step errors scaled by the spread
//! (fitted by [`crate::train::fit_noise_factor`]), so each dimension's spread stays the head's.

use drivesim_kernels::math;

/// A simulator's sampling: the temperature (0: the mean, bit for bit) and the seed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Sampling {
    pub temperature: f32,
    pub seed: u64,
}

impl Sampling {
    pub const OFF: Sampling = Sampling {
        temperature: 0.0,
        seed: 0,
    };

    pub fn is_on(&self) -> bool {
        self.temperature > 0.0
    }

    /// Fills `noise` (`[item][z]`, items numbered from 0) with the standard normal draws of
    /// rollout step `step`: each value from the seed, the step, the item and the dimension.
    pub fn draw(&self, noise: &mut [f32], z: usize, step: u64) {
        self.draw_rows(noise, z, z, step);
    }

    /// [`Sampling::draw`] into the first `z` values of each row of `stride` values of `rows`
    /// (the others left as they are): the same draws, where another input sits beside them.
    pub fn draw_rows(&self, rows: &mut [f32], z: usize, stride: usize, step: u64) {
        for (n, item) in rows.chunks_exact_mut(stride).enumerate() {
            let key = stream_key(self.seed, step, n as u64);
            for (d, value) in item[..z].iter_mut().enumerate() {
                *value = standard_normal(key, d as u64);
            }
        }
    }

    /// `code += temperature * exp(log_sigma) * noise`, value by value.
    pub fn add_spread(&self, codes: &mut [f32], log_sigma: &[f32], noise: &[f32]) {
        for ((code, &log_sigma), &noise) in codes.iter_mut().zip(log_sigma).zip(noise) {
            *code += self.temperature * sigma(log_sigma) * noise;
        }
    }
}

/// `exp(log_sigma)`, `log_sigma` clamped to [-20, 20] (the kernels' exp covers [0, 20]).
pub(crate) fn sigma(log_sigma: f32) -> f32 {
    let x = log_sigma.clamp(-20.0, 20.0);
    if x >= 0.0 {
        math::exp(x)
    } else {
        1.0 / math::exp(-x)
    }
}

/// SplitMix64's finaliser: a bijection of u64 whose every output bit depends on every input bit.
fn mix(mut x: u64) -> u64 {
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

const GOLDEN: u64 = 0x9E37_79B9_7F4A_7C15;

/// The key of one (seed, step, item) stream: its dimensions are SplitMix64's outputs from it.
fn stream_key(seed: u64, step: u64, item: u64) -> u64 {
    mix(mix(seed ^ GOLDEN) ^ mix(step.wrapping_add(GOLDEN)) ^ mix(item.wrapping_mul(GOLDEN) ^ 0xD1B5_4A32_D192_ED03))
}

/// The standard normal value of dimension `dim` of the stream `key`: a uniform in (0, 1) from
/// 53 bits, through the normal's inverse distribution function.
fn standard_normal(key: u64, dim: u64) -> f32 {
    let bits = mix(key.wrapping_add(dim.wrapping_add(1).wrapping_mul(GOLDEN)));
    let uniform = ((bits >> 11) as f64 + 0.5) * (1.0 / (1u64 << 53) as f64);
    inverse_normal(uniform) as f32
}

/// Φ⁻¹(p) for p in (0, 1) by Acklam's rational approximation (relative error below 1.2e-9): a
/// rational function in the centre, of `sqrt(-2 ln p)` in the tails (one draw in 20).
fn inverse_normal(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969_683_028_665_376e1,
        2.209_460_984_245_205e2,
        -2.759_285_104_469_687e2,
        1.383_577_518_672_69e2,
        -3.066_479_806_614_716e1,
        2.506_628_277_459_239,
    ];
    const B: [f64; 5] = [
        -5.447_609_879_822_406e1,
        1.615_858_368_580_409e2,
        -1.556_989_798_598_866e2,
        6.680_131_188_771_972e1,
        -1.328_068_155_288_572e1,
    ];
    const C: [f64; 6] = [
        -7.784_894_002_430_293e-3,
        -3.223_964_580_411_365e-1,
        -2.400_758_277_161_838,
        -2.549_732_539_343_734,
        4.374_664_141_464_968,
        2.938_163_982_698_783,
    ];
    const D: [f64; 4] = [
        7.784_695_709_041_462e-3,
        3.224_671_290_700_398e-1,
        2.445_134_137_142_996,
        3.754_408_661_907_416,
    ];
    const LOW: f64 = 0.02425;
    let tail = |q: f64| {
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    if p < LOW {
        tail(math::sqrt(-2.0 * math::ln64(p)))
    } else if p > 1.0 - LOW {
        -tail(math::sqrt(-2.0 * math::ln64(1.0 - p)))
    } else {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_normal_matches_known_quantiles() {
        // Φ⁻¹ at a few probabilities (to 1e-9: Acklam's accuracy; the tail through ln64 and sqrt).
        for (p, x) in [
            (0.5, 0.0),
            (0.975, 1.959_963_984_540_054),
            (0.841_344_746_068_543, 1.0),
            (0.01, -2.326_347_874_040_841),
            (1e-9, -5.997_807_015_007_686),
        ] {
            assert!(
                (inverse_normal(p) - x).abs() < 1e-8,
                "{p}: {} against {x}",
                inverse_normal(p)
            );
        }
    }

    #[test]
    fn draws_look_standard_normal_and_independent() {
        let (n, key) = (200_000u64, stream_key(7, 3, 11));
        let draws: alloc::vec::Vec<f64> = (0..n).map(|d| standard_normal(key, d) as f64).collect();
        let mean = draws.iter().sum::<f64>() / n as f64;
        let var = draws.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n as f64;
        let lag = draws.windows(2).map(|w| (w[0] - mean) * (w[1] - mean)).sum::<f64>() / n as f64;
        let beyond_2 = draws.iter().filter(|x| x.abs() > 2.0).count() as f64 / n as f64;
        assert!(
            mean.abs() < 0.01 && (var - 1.0).abs() < 0.01 && lag.abs() < 0.01,
            "{mean} {var} {lag}"
        );
        assert!((beyond_2 - 0.0455).abs() < 0.002, "{beyond_2}");
        // Neighbouring streams are unrelated: another step, item or seed.
        for other in [stream_key(7, 4, 11), stream_key(7, 3, 12), stream_key(8, 3, 11)] {
            let cross = (0..n)
                .map(|d| standard_normal(key, d) as f64 * standard_normal(other, d) as f64)
                .sum::<f64>();
            assert!((cross / n as f64).abs() < 0.01);
        }
    }
}
