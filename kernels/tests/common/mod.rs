//! Helpers shared by the kernel tests (and, through `#[path]`, drivesim's tests and the
//! benchmarks): seeded values and the instruction-set levels to run.
#![allow(dead_code)] // each includer uses part of it

use drivesim_kernels::{Activation, Isa, IsaLevel};

/// A small xorshift generator of uniform floats in [-1, 1).
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Rng {
        Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }

    pub fn next(&mut self) -> f32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 40) as f32 / (1u64 << 23) as f32 - 1.0
    }

    /// `n` values in [-scale, scale).
    pub fn fill(&mut self, n: usize, scale: f32) -> Vec<f32> {
        (0..n).map(|_| self.next() * scale).collect()
    }
}

/// Deterministic values in [-scale, scale).
pub fn values(seed: u64, n: usize, scale: f32) -> Vec<f32> {
    Rng::new(seed).fill(n, scale)
}

/// Every activation the kernels fuse.
pub const ACTS: [Activation; 4] = [
    Activation::Identity,
    Activation::Relu,
    Activation::LeakyRelu(0.2),
    Activation::Tanh,
];

/// Every level this CPU supports, scalar included, saying which are skipped; fails when
/// `DRIVESIM_REQUIRE_ISA` names a level this CPU lacks (so CI cannot skip its best path).
pub fn levels() -> Vec<Isa> {
    for level in IsaLevel::ALL {
        if Isa::new(level).is_none() {
            eprintln!("skipping {}: CPU lacks it", level.name());
        }
    }
    if let Ok(required) = std::env::var("DRIVESIM_REQUIRE_ISA") {
        let level = IsaLevel::from_name(&required).unwrap_or_else(|| panic!("unknown DRIVESIM_REQUIRE_ISA={required}"));
        assert!(
            Isa::new(level).is_some(),
            "DRIVESIM_REQUIRE_ISA={required} but this CPU lacks it"
        );
    }
    Isa::supported().collect()
}

/// [`levels`] without scalar: the paths tested against it.
pub fn simd_levels() -> Vec<Isa> {
    levels()
        .into_iter()
        .filter(|isa| isa.level() != IsaLevel::Scalar)
        .collect()
}
