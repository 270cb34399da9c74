//! Numbers with a fixed count of decimals for `/diagnostics` texts, written the way `{:.N}`
//! writes them, with integer arithmetic.
//!
//! `format!("{:.3}", x)` runs the standard library's exact float formatting, whose fallback
//! (Dragon4, with 1280-bit integers) takes over for many ordinary values: one such number
//! costs thousands of instructions, and `/diagnostics` writes about two dozen of them a
//! second. [`Fixed`] writes the same characters — the decimal nearest to the binary value,
//! ties to even, the sign of a negative value (or of -0.0) kept — from the value's mantissa and
//! exponent with 128-bit integers, and hands the rare value out of that range (beyond about
//! 2^75, NaN, the infinities) to the standard formatting.

use std::fmt;

/// The most decimals [`Fixed`] writes itself; more go to the standard formatting.
const MAX_DECIMALS: u8 = 9;

/// `value` with `decimals` digits after the point, exactly as `format!("{:.decimals$}", value)`
/// writes it (width and alignment of the `{}` it is written with apply, as for a string).
#[derive(Debug, Clone, Copy)]
pub struct Fixed(pub f64, pub u8);

impl Fixed {
    /// The digits of |value| × 10^decimals rounded to the nearest integer (ties to even),
    /// or `None` when that does not fit the integer arithmetic.
    fn scaled(self) -> Option<u128> {
        let Fixed(v, decimals) = self;
        if !v.is_finite() || decimals > MAX_DECIMALS {
            return None;
        }
        let bits = v.to_bits();
        let exp_bits = ((bits >> 52) & 0x7ff) as i32;
        let frac = u128::from(bits & ((1 << 52) - 1));
        // |v| = m × 2^e exactly.
        let (m, e) = if exp_bits == 0 {
            (frac, -1074)
        } else {
            (frac | (1 << 52), exp_bits - 1075)
        };
        // m < 2^53 and 10^9 < 2^30: the product fits in 83 bits.
        let digits = m * 10u128.pow(u32::from(decimals));
        if e >= 0 {
            // Exact; fits while the shift keeps it below 2^128.
            return (e <= 44).then(|| digits << e);
        }
        let shift = e.unsigned_abs();
        if shift >= 128 {
            // Below 2^83 / 2^128: less than half a unit of the last digit, and not a tie.
            return Some(0);
        }
        let q = digits >> shift;
        let rest = digits & ((1u128 << shift) - 1);
        let half = 1u128 << (shift - 1);
        Some(if rest > half || (rest == half && q & 1 == 1) {
            q + 1
        } else {
            q
        })
    }
}

impl fmt::Display for Fixed {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let Some(q) = self.scaled() else {
            let s = format!("{:.*}", usize::from(self.1), self.0);
            return f.pad(&s);
        };
        // Sign, at most 39 integer digits, the point and 9 decimals.
        let mut buf = [0u8; 64];
        let mut at = buf.len();
        let unit = 10u128.pow(u32::from(self.1));
        let (mut int, mut dec) = (q / unit, q % unit);
        for _ in 0..self.1 {
            at -= 1;
            buf[at] = b'0' + (dec % 10) as u8;
            dec /= 10;
        }
        if self.1 > 0 {
            at -= 1;
            buf[at] = b'.';
        }
        loop {
            at -= 1;
            buf[at] = b'0' + (int % 10) as u8;
            int /= 10;
            if int == 0 {
                break;
            }
        }
        if self.0.is_sign_negative() {
            at -= 1;
            buf[at] = b'-';
        }
        // Only ASCII digits, '.' and '-' were written.
        f.pad(std::str::from_utf8(&buf[at..]).unwrap_or("?"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn same(v: f64, n: u8) {
        assert_eq!(
            Fixed(v, n).to_string(),
            format!("{:.*}", usize::from(n), v),
            "{v:e} with {n} decimals"
        );
    }

    #[test]
    fn writes_what_the_standard_formatting_writes() {
        let values = [
            0.0,
            -0.0,
            0.25,
            0.35,
            2.5,
            3.5,
            -2.5,
            0.125,
            0.375,
            0.0005,
            1.0005,
            -0.0001,
            37.0,
            99.999_999_5,
            999.9995,
            1e15,
            1.5e22,
            3.777e22,
            1e23,
            1e300,
            -1e300,
            5e-324,
            f64::MIN_POSITIVE,
            f64::MAX,
            f64::MIN,
            f64::EPSILON,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            1000.0 / 3.0,
            370.000_000_000_1,
            (1u64 << 53) as f64,
            ((1u64 << 53) - 1) as f64 / 1024.0,
        ];
        for v in values {
            for n in 0..=12 {
                same(v, n);
            }
        }
        assert_eq!(format!("[{:>8}]", Fixed(1.25, 1)), "[     1.2]");
    }

    #[test]
    fn every_tie_goes_to_the_even_digit() {
        // k/2^j are exact in binary; with j decimals (or fewer) many are exact ties.
        for j in 1..=10u32 {
            for k in -2000i64..=2000 {
                let v = k as f64 / f64::from(1u32 << j);
                for n in 0..=j.min(9) as u8 {
                    same(v, n);
                }
            }
        }
    }

    proptest! {
        #[test]
        fn any_bits_any_decimals(bits in any::<u64>(), n in 0u8..=10) {
            same(f64::from_bits(bits), n);
        }

        #[test]
        fn ordinary_values(v in -1e7f64..1e7, n in 0u8..=6) {
            same(v, n);
        }
    }
}
