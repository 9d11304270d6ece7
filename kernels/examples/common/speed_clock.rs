//! The examples' clock: this thread's CPU time, the best of a few calibrated runs, and the
//! FMA peak they compare against.

// Each example uses a part of it.
#![allow(dead_code)]

use drivesim_kernels::Isa;
use std::time::Instant;

/// Nanoseconds this thread has run on a CPU, or wall time when the kernel does not say.
/// `DRIVESIM_SPEED_CLOCK=wall` measures wall time (on an idle machine, where the scheduler's
/// clock may be coarse).
pub fn now_ns(start: Instant) -> u64 {
    let wall = std::env::var("DRIVESIM_SPEED_CLOCK").is_ok_and(|v| v == "wall");
    (!wall)
        .then(|| std::fs::read_to_string("/proc/thread-self/schedstat").ok())
        .flatten()
        .and_then(|s| s.split_whitespace().next()?.parse().ok())
        .unwrap_or_else(|| start.elapsed().as_nanos() as u64)
}

/// Seconds per call of `f`: repetitions calibrated to about 250 ms (the clock may tick
/// coarsely), then the best of 3 such runs.
pub fn best_seconds(mut f: impl FnMut()) -> f64 {
    let epoch = Instant::now();
    let mut reps = 1;
    loop {
        let t = now_ns(epoch);
        (0..reps).for_each(|_| f());
        if now_ns(epoch) - t > 250_000_000 {
            break;
        }
        reps *= 2;
    }
    (0..3)
        .map(|_| {
            let t = now_ns(epoch);
            (0..reps).for_each(|_| f());
            (now_ns(epoch) - t) as f64 * 1e-9 / reps as f64
        })
        .fold(f64::INFINITY, f64::min)
}

/// One thread's FMA peak in GFLOP/s at `isa`'s vector width: 12 independent chains of FMAs
/// (enough to cover 2 ports by up to 6 cycles of latency). NaN where there is no x86 vector unit.
pub fn fma_peak_gflops(isa: Isa) -> f64 {
    #[cfg(target_arch = "x86_64")]
    {
        use drivesim_kernels::IsaLevel;
        use std::arch::x86_64::*;
        /// 12 chains of FMAs of one width, `iters` rounds.
        macro_rules! chains {
            ($name:ident, $features:literal, $set1:ident, $fma:ident, $add:ident, $first:ident) => {
                #[target_feature(enable = $features)]
                fn $name(iters: u64) -> f32 {
                    let (a, b) = ($set1(0.999_999), $set1(1e-7));
                    let mut acc = [$set1(1.0); 12];
                    for _ in 0..std::hint::black_box(iters) {
                        acc.iter_mut().for_each(|v| *v = $fma(*v, a, b));
                    }
                    $first(acc.iter().fold($set1(0.0), |s, &v| $add(s, v)))
                }
            };
        }
        chains!(
            chains256,
            "avx2,fma",
            _mm256_set1_ps,
            _mm256_fmadd_ps,
            _mm256_add_ps,
            _mm256_cvtss_f32
        );
        chains!(
            chains512,
            "avx512f",
            _mm512_set1_ps,
            _mm512_fmadd_ps,
            _mm512_add_ps,
            _mm512_cvtss_f32
        );
        let iters = 2_000_000u64;
        let (lanes, seconds) = match isa.level() {
            // SAFETY: `isa` proves the features.
            IsaLevel::Avx512 => (
                16,
                best_seconds(|| _ = std::hint::black_box(unsafe { chains512(iters) })),
            ),
            IsaLevel::Avx2 => (
                8,
                best_seconds(|| _ = std::hint::black_box(unsafe { chains256(iters) })),
            ),
            _ => return f64::NAN,
        };
        (iters * 12 * 2 * lanes) as f64 / seconds / 1e9
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = isa;
        f64::NAN
    }
}
