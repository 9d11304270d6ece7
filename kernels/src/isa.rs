//! Which instruction set the kernels use, detected once and cached.

use core::sync::atomic::{AtomicU8, Ordering};

/// Instruction-set levels, ordered by vector width. A CPU has the levels of its architecture:
/// on x86-64 each is a superset of the one before.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum IsaLevel {
    /// Portable Rust: the reference every other level is tested against.
    Scalar,
    /// aarch64 NEON (128-bit vectors), with its half-precision conversions.
    Neon,
    /// x86-64 AVX2 + FMA + F16C (256-bit vectors).
    Avx2,
    /// x86-64 AVX-512F (512-bit vectors), on top of everything in `Avx2`.
    Avx512,
}

impl IsaLevel {
    /// Every level, lowest first.
    pub const ALL: [IsaLevel; 4] = [IsaLevel::Scalar, IsaLevel::Neon, IsaLevel::Avx2, IsaLevel::Avx512];

    /// The level's name, as `DRIVESIM_ISA` takes it.
    pub const fn name(self) -> &'static str {
        match self {
            IsaLevel::Scalar => "scalar",
            IsaLevel::Neon => "neon",
            IsaLevel::Avx2 => "avx2",
            IsaLevel::Avx512 => "avx512",
        }
    }

    /// f32 lanes of this level's vectors.
    pub const fn lanes(self) -> usize {
        match self {
            IsaLevel::Scalar => 1,
            IsaLevel::Neon => 4,
            IsaLevel::Avx2 => 8,
            IsaLevel::Avx512 => 16,
        }
    }

    /// Parses a name as written by [`IsaLevel::name`].
    pub fn from_name(name: &str) -> Option<IsaLevel> {
        IsaLevel::ALL
            .into_iter()
            .find(|l| l.name().eq_ignore_ascii_case(name.trim()))
    }

    fn cpu_has(self) -> bool {
        match self {
            IsaLevel::Scalar => true,
            // Every aarch64 target that has it enables it at build time (it is baseline on
            // aarch64 Linux, macOS and Windows).
            #[cfg(target_arch = "aarch64")]
            IsaLevel::Neon => cfg!(target_feature = "neon"),
            #[cfg(all(target_arch = "x86_64", feature = "std"))]
            IsaLevel::Avx2 => {
                std::arch::is_x86_feature_detected!("avx2")
                    && std::arch::is_x86_feature_detected!("fma")
                    && std::arch::is_x86_feature_detected!("f16c")
            }
            #[cfg(all(target_arch = "x86_64", feature = "std"))]
            IsaLevel::Avx512 => IsaLevel::Avx2.cpu_has() && std::arch::is_x86_feature_detected!("avx512f"),
            // Without std there is no run-time detection: trust what the build targets.
            #[cfg(all(target_arch = "x86_64", not(feature = "std")))]
            IsaLevel::Avx2 => cfg!(all(
                target_feature = "avx2",
                target_feature = "fma",
                target_feature = "f16c"
            )),
            #[cfg(all(target_arch = "x86_64", not(feature = "std")))]
            IsaLevel::Avx512 => IsaLevel::Avx2.cpu_has() && cfg!(target_feature = "avx512f"),
            _ => false,
        }
    }
}

/// Proof that this CPU supports an [`IsaLevel`]: the only way to make one is through a check,
/// so the kernels may call `#[target_feature]` code for it without further tests.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Isa(IsaLevel);

/// 0 until [`Isa::best`] ran, then `level + 1`.
static BEST: AtomicU8 = AtomicU8::new(0);

impl Isa {
    /// The portable reference kernels, available everywhere.
    pub const SCALAR: Isa = Isa(IsaLevel::Scalar);

    /// `level` if this CPU supports it.
    pub fn new(level: IsaLevel) -> Option<Isa> {
        level.cpu_has().then_some(Isa(level))
    }

    /// The level this proves.
    pub const fn level(self) -> IsaLevel {
        self.0
    }

    /// Every level this CPU supports, lowest first (ignores `DRIVESIM_ISA`).
    pub fn supported() -> impl Iterator<Item = Isa> {
        IsaLevel::ALL.into_iter().filter_map(Isa::new)
    }

    /// The highest supported level, capped by the environment variable `DRIVESIM_ISA`
    /// (`scalar`, `neon`, `avx2` or `avx512`: levels up to that one in [`IsaLevel`]'s order)
    /// when std is available. Detected once, then cached.
    pub fn best() -> Isa {
        let cached = BEST.load(Ordering::Relaxed);
        if cached != 0 {
            return Isa(IsaLevel::ALL[cached as usize - 1]);
        }
        let cap = env_cap().unwrap_or(IsaLevel::Avx512);
        let best = Isa::supported()
            .filter(|isa| isa.0 <= cap)
            .last()
            .unwrap_or(Isa::SCALAR);
        BEST.store(best.0 as u8 + 1, Ordering::Relaxed);
        best
    }
}

#[cfg(feature = "std")]
fn env_cap() -> Option<IsaLevel> {
    IsaLevel::from_name(&std::env::var("DRIVESIM_ISA").ok()?)
}

#[cfg(not(feature = "std"))]
fn env_cap() -> Option<IsaLevel> {
    None
}
