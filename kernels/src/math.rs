//! Elementary functions without libm, written so that the SIMD kernels can evaluate the very
//! same formulas lane by lane (and so agree with the scalar path to a few ulp).

/// Below this |x|, tanh is evaluated by its odd Taylor series; above, through exp.
/// At 0.0625 the series' first dropped term is ~3e-13 relative, and the exp form's
/// cancellation costs at most ~1e-6 relative.
pub const TANH_SERIES_LIMIT: f32 = 0.0625;
/// 1 - 2/(e^20 + 1) rounds to 1.0 in f32, so larger inputs are clamped to 10 (keeps exp finite).
pub const TANH_CLAMP: f32 = 10.0;

/// Coefficients of the odd series tanh(x) = x (1 + c1 x^2 + c2 x^4 + c3 x^6).
pub const TANH_SERIES: [f32; 3] = [-1.0 / 3.0, 2.0 / 15.0, -17.0 / 315.0];

/// Hyperbolic tangent, accurate to about 1e-6 relative over all finite inputs.
#[inline]
pub fn tanh(x: f32) -> f32 {
    let a = x.abs().min(TANH_CLAMP);
    let t = if a < TANH_SERIES_LIMIT {
        let a2 = a * a;
        a * (1.0 + a2 * (TANH_SERIES[0] + a2 * (TANH_SERIES[1] + a2 * TANH_SERIES[2])))
    } else {
        1.0 - 2.0 / (exp(2.0 * a) + 1.0)
    };
    if x < 0.0 {
        -t
    } else {
        t
    }
}

/// ln 2 split in a part exact in f32 and a remainder, for exact range reduction.
pub const LN2_HI: f32 = 0.693_145_75;
/// ln 2 minus [`LN2_HI`].
pub const LN2_LO: f32 = 1.428_606_8e-6;
/// Taylor coefficients 1/k! for k = 2..=6 of exp(r) on |r| <= ln2/2 (error < 2e-7 relative).
pub const EXP_POLY: [f32; 5] = [1.0 / 2.0, 1.0 / 6.0, 1.0 / 24.0, 1.0 / 120.0, 1.0 / 720.0];

/// e^x for 0 <= x <= 2 * TANH_CLAMP: x = n ln2 + r, e^x = 2^n e^r.
#[inline]
pub fn exp(x: f32) -> f32 {
    let n = (x * core::f32::consts::LOG2_E + 0.5) as i32 as f32; // x >= 0: truncation rounds
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let p = 1.0
        + r * (1.0 + r * (EXP_POLY[0] + r * (EXP_POLY[1] + r * (EXP_POLY[2] + r * (EXP_POLY[3] + r * EXP_POLY[4])))));
    p * f32::from_bits(((n as i32 + 127) as u32) << 23)
}

/// Square root by Newton's method in f64 (core has no sqrt without std); used only at load.
pub fn sqrt(x: f64) -> f64 {
    if x <= 0.0 || x.is_nan() || x.is_infinite() {
        return if x == 0.0 || x.is_infinite() { x } else { f64::NAN };
    }
    // Start from halving the exponent, then Newton doubles the correct bits each step.
    let mut y = f64::from_bits((x.to_bits() >> 1) + (1023u64 << 51));
    for _ in 0..6 {
        y = 0.5 * (y + x / y);
    }
    y
}

/// `x^n` by repeated squaring (core has no `powi` without std).
pub fn powi(x: f64, mut n: u32) -> f64 {
    let (mut result, mut square) = (1.0, x);
    while n > 0 {
        if n & 1 == 1 {
            result *= square;
        }
        square *= square;
        n >>= 1;
    }
    result
}

/// Cosine of `x` in `[0, π]` by its Taylor series (core has no `cos` without std): to about
/// 1e-15 there, for learning-rate schedules.
pub fn cos(x: f64) -> f64 {
    let (x2, mut term, mut sum) = (x * x, 1.0, 1.0);
    for k in 1..30 {
        term *= -x2 / ((2 * k - 1) * (2 * k)) as f64;
        sum += term;
    }
    sum
}

/// e^x in f64 for the losses of training (core has no `exp` without std): `x = n ln2 + r`
/// with `|r| <= ln2 / 2`, Taylor series of e^r to 1e-16; 0 below -745, infinity above 709.
pub fn exp64(x: f64) -> f64 {
    if x.is_nan() {
        return x;
    }
    if x > 709.0 {
        return f64::INFINITY;
    }
    if x < -745.0 {
        return 0.0;
    }
    let n = (x * core::f64::consts::LOG2_E + if x < 0.0 { -0.5 } else { 0.5 }) as i64;
    // ln2 in two parts (fdlibm's): n · LN2_HI is exact, so r keeps its bits for large n.
    const LN2_HI: f64 = 6.931_471_803_691_238e-1;
    const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
    let r = (x - n as f64 * LN2_HI) - n as f64 * LN2_LO;
    let (mut term, mut sum) = (1.0, 1.0);
    for k in 1..18 {
        term *= r / k as f64;
        sum += term;
    }
    // 2^n in two factors: n alone may leave the exponent range near the ends.
    let half = n / 2;
    sum * pow2(half) * pow2(n - half)
}

/// 2^n for -1022 <= n <= 1023.
fn pow2(n: i64) -> f64 {
    f64::from_bits(((n + 1023) as u64) << 52)
}

/// The natural logarithm in f64 for x > 0 (core has none without std): `x = m 2^e` with
/// `m` in [1, 2), `ln m = 2 atanh((m - 1) / (m + 1))` by its series (the ratio is at most 1/3).
pub fn ln64(x: f64) -> f64 {
    if x.is_nan() || x < 0.0 {
        return f64::NAN;
    }
    if x == 0.0 {
        return f64::NEG_INFINITY;
    }
    if x.is_infinite() {
        return x;
    }
    // Subnormals: scale into the normal range first.
    let (x, shift) = if x < f64::MIN_POSITIVE {
        (x * pow2(54), -54)
    } else {
        (x, 0)
    };
    let bits = x.to_bits();
    let e = ((bits >> 52) & 0x7ff) as i64 - 1023 + shift;
    let m = f64::from_bits((bits & ((1u64 << 52) - 1)) | (1023u64 << 52));
    let s = (m - 1.0) / (m + 1.0);
    let (s2, mut power, mut sum) = (s * s, s, 0.0);
    for k in 0..30 {
        sum += power / (2 * k + 1) as f64;
        power *= s2;
    }
    2.0 * sum + e as f64 * core::f64::consts::LN_2
}

#[cfg(all(test, feature = "std"))]
mod tests {
    use super::*;

    #[test]
    fn tanh_matches_std_everywhere() {
        let mut worst = 0.0f64;
        let mut x = -30.0f32;
        while x <= 30.0 {
            let want = (x as f64).tanh();
            let err = ((tanh(x) as f64) - want).abs() / want.abs().max(1e-30);
            worst = worst.max(if x == 0.0 { 0.0 } else { err });
            x += 1.0 / 4096.0;
        }
        assert!(worst < 2e-6, "worst relative error {worst}");
        assert_eq!(tanh(0.0), 0.0);
        assert_eq!(tanh(100.0), 1.0);
        assert_eq!(tanh(-100.0), -1.0);
        assert!(tanh(1e-30) == 1e-30);
    }

    #[test]
    fn exp_matches_std() {
        let mut x = 0.0f32;
        while x <= 18.0 {
            let want = (x as f64).exp();
            assert!(((exp(x) as f64) - want).abs() / want < 5e-7, "exp({x})");
            x += 1.0 / 1024.0;
        }
    }

    #[test]
    fn powi_and_cos_match_std() {
        for n in [0, 1, 2, 3, 10, 1000, 14000] {
            let want = 0.999f64.powi(n as i32);
            // Squaring doubles the relative error each time: about n ulps at worst.
            assert!((powi(0.999, n) - want).abs() <= 1e-11 * want, "0.999^{n}");
        }
        for i in 0..=1000 {
            let x = core::f64::consts::PI * i as f64 / 1000.0;
            assert!((cos(x) - x.cos()).abs() <= 1e-14, "cos({x})");
        }
    }

    #[test]
    fn exp64_and_ln64_match_std() {
        // Normal results (subnormal ones keep fewer bits, in std too).
        let mut x = -708.0f64;
        while x <= 709.0 {
            let want = x.exp();
            assert!(
                (exp64(x) - want).abs() <= 1e-15 * want,
                "exp64({x}): {} vs {want}",
                exp64(x)
            );
            x += 0.173;
        }
        for &x in &[1e-310f64, 1e-300, 1e-5, 0.3, 1.0, 1.5, 2.0, 7.25, 1e10, 1.7e308] {
            let want = x.ln();
            assert!((ln64(x) - want).abs() <= 1e-15 * want.abs().max(1.0), "ln64({x})");
        }
        assert_eq!(ln64(1.0), 0.0);
        assert!(ln64(-1.0).is_nan() && exp64(f64::NAN).is_nan());
        assert!(exp64(-740.0) < 1e-320 && exp64(-746.0) == 0.0 && exp64(710.0).is_infinite());
    }

    #[test]
    fn sqrt_matches_std() {
        for &x in &[1e-12, 1e-5, 0.5, 1.0, 2.0, 1.00001, 3.7e8] {
            assert!((sqrt(x) - x.sqrt()).abs() <= 1e-15 * x.sqrt(), "sqrt({x})");
        }
        assert_eq!(sqrt(0.0), 0.0);
        assert!(sqrt(-1.0).is_nan());
    }
}
