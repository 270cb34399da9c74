//! The on/off times one step or period gets for a duty: SPEC §1.2's minimum-time rules.
//!
//! A pure function of the duty and the configuration, so the state machine, the status report
//! and the tests all agree on what a duty produces.

use super::config::{ChannelConfig, ShortPulse};
use super::Nanos;

/// Which rule shaped a plan, so the ROS side can say why the applied duty differs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Rule {
    /// The duty was reproduced as commanded.
    #[default]
    Exact,
    /// Period 0: no pulses, output held at 0 (000).
    NoPeriod,
    /// `suppress`: the pulse was shorter than the minimum on time; output 0 for the period (000).
    SuppressedPulse,
    /// `suppress`: the break was shorter than the minimum off time; output 1 for the period (000).
    SuppressedBreak,
    /// `stretch`: the pulse was raised to the minimum on time (002's bLmtSwiTi).
    StretchedPulse,
    /// `stretch`: the break was raised to the minimum off time.
    StretchedBreak,
    /// `band`: the duty lay in the lower edge band; constant 0 (004).
    BandLow,
    /// `band`: the duty lay in the upper edge band; constant 1 (004).
    BandHigh,
}

impl Rule {
    /// The rule's name as reported on `~/<ch>/status` and `/diagnostics`.
    pub const fn as_str(self) -> &'static str {
        match self {
            Rule::Exact => "exact",
            Rule::NoPeriod => "no_period",
            Rule::SuppressedPulse => "suppressed_pulse",
            Rule::SuppressedBreak => "suppressed_break",
            Rule::StretchedPulse => "stretched_pulse",
            Rule::StretchedBreak => "stretched_break",
            Rule::BandLow => "band_low",
            Rule::BandHigh => "band_high",
        }
    }
}

impl std::fmt::Display for Rule {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The times of one period for one duty.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Plan {
    /// The duty fraction the plan was made for, 0..=1.
    pub duty: f64,
    /// On time, ns.
    pub t_on: Nanos,
    /// Off time, ns; `t_on + t_off` is the period.
    pub t_off: Nanos,
    /// E1 (000): the commanded duty could not be reproduced because of a minimum time (or
    /// `max_on`).
    pub e1: bool,
    /// The minimum-time limit flag (002's bLmtSwiTi): a time was raised to its minimum (or
    /// `max_on`).
    pub limited: bool,
    /// The rule that shaped this plan.
    pub rule: Rule,
    /// The plan keeps the line high longer than `max_on_ms` (a constant 1, or an on time above
    /// it): the line guard will cut it, so E1 and the limit flag are set too.
    pub max_on: bool,
}

impl Plan {
    /// The duty actually delivered, `t_on / T` (0 with no period).
    pub fn applied_duty(&self) -> f64 {
        let period = self.t_on + self.t_off;
        if period == 0 {
            0.0
        } else {
            self.t_on as f64 / period as f64
        }
    }

    /// Makes the plan for duty fraction `duty` (0..=1) under `cfg`: the minimum-time rules,
    /// then whether the maximum on time will cut what they give.
    pub fn new(duty: f64, cfg: &ChannelConfig) -> Plan {
        let plan = Plan::shape(duty, cfg);
        // The on phase runs into the next period (a constant 1) or is longer than max_on by
        // itself: the line cannot deliver it. Even 100 % sets E1 here, unlike the minimum-time
        // rules: the output is not the constant 1 the command asks for.
        if cfg.max_on > 0 && plan.t_on > 0 && (plan.t_off == 0 || plan.t_on > cfg.max_on) {
            Plan {
                max_on: true,
                e1: true,
                limited: true,
                ..plan
            }
        } else {
            plan
        }
    }

    /// The minimum-time rules of SPEC §1.2 for duty fraction `duty` under `cfg`.
    fn shape(duty: f64, cfg: &ChannelConfig) -> Plan {
        let period = cfg.period;
        let base = Plan {
            duty,
            ..Plan::default()
        };
        if period == 0 {
            return Plan {
                rule: Rule::NoPeriod,
                ..base
            };
        }
        let constant = |on: bool, rule: Rule, e1: bool| Plan {
            t_on: if on { period } else { 0 },
            t_off: if on { 0 } else { period },
            e1,
            rule,
            ..base
        };
        // 002: the minimum switching time is deactivated for 0 % and 100 %.
        if duty <= 0.0 {
            return constant(false, Rule::Exact, false);
        }
        if duty >= 1.0 {
            return constant(true, Rule::Exact, false);
        }
        if cfg.short_pulse == ShortPulse::Band {
            // 004 with one rule for every row of its truth table and its worked example (edge
            // 0.5, input 0.5: 500 ms on, 500 ms off): below the edge FALSE, above 1 - edge
            // TRUE, PWM in between, both boundaries inclusive as the user wrote them.
            let e = cfg.edge_band;
            if definitely_less(duty, e) {
                return constant(false, Rule::BandLow, false);
            }
            if definitely_less(1.0 - e, duty) {
                return constant(true, Rule::BandHigh, false);
            }
        }
        // Round to the nearest ns; the whole period stays exactly `period`.
        let t_on = ((duty * period as f64).round() as Nanos).min(period);
        let t_off = period - t_on;
        // A time stretched to its minimum: `t_on` on, the rest of the period off, flagged. One
        // that leaves no valid break or pulse beside it (the minima together exceed the period)
        // takes the whole period.
        let stretched = |t_on: Nanos, rule: Rule| Plan {
            t_on,
            t_off: period - t_on,
            e1: true,
            limited: true,
            rule,
            ..base
        };
        if t_on < cfg.min_on {
            return match cfg.short_pulse {
                ShortPulse::Stretch if period - cfg.min_on.min(period) < cfg.min_off => {
                    stretched(period, Rule::StretchedPulse)
                }
                ShortPulse::Stretch => stretched(cfg.min_on, Rule::StretchedPulse),
                // `band` keeps suppress as its safety net inside the PWM range.
                ShortPulse::Suppress | ShortPulse::Band => {
                    constant(false, Rule::SuppressedPulse, true)
                }
            };
        }
        if t_off < cfg.min_off {
            return match cfg.short_pulse {
                // The pulse left beside a stretched break would be below min on: the duty is
                // high, so the break goes instead (as suppress would).
                ShortPulse::Stretch if period - cfg.min_off.min(period) < cfg.min_on => {
                    stretched(period, Rule::StretchedBreak)
                }
                ShortPulse::Stretch => stretched(period - cfg.min_off, Rule::StretchedBreak),
                ShortPulse::Suppress | ShortPulse::Band => {
                    constant(true, Rule::SuppressedBreak, true)
                }
            };
        }
        Plan {
            t_on,
            t_off,
            ..base
        }
    }
}

/// Relative tolerance under which two duty fractions count as equal: far below any duty a
/// period can resolve (1 ns of a 1 s period is 1e-9), far above the rounding of `pct / 100` or
/// `1 - edge` (a few 1e-16).
const DUTY_EPSILON: f64 = 1e-12;

/// `a < b` by more than float rounding: `0.67 < 1 - 0.33` is false here, as the user meant.
pub(crate) fn definitely_less(a: f64, b: f64) -> bool {
    a < b - DUTY_EPSILON
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::config::{ChannelParams, NS_PER_MS};

    fn cfg(period_ms: u64, min_on_ms: u64, sp: ShortPulse, edge: f64) -> ChannelConfig {
        ChannelParams {
            period_ms,
            min_on_ms,
            short_pulse: Some(sp),
            edge_band: edge,
            ..ChannelParams::default()
        }
        .validate()
        .unwrap()
    }

    const MS: Nanos = NS_PER_MS;

    #[test]
    fn on_time_proportional_period_unchanged_000() {
        let c = cfg(1000, 0, ShortPulse::Suppress, 0.0);
        let p = Plan::new(0.37, &c);
        assert_eq!((p.t_on, p.t_off, p.e1), (370 * MS, 630 * MS, false));
    }

    #[test]
    fn short_pulses_and_breaks_follow_the_policy_000_002() {
        // 1000 ms period, 100 ms minimum on and off time.
        for (sp, duty, want) in [
            // 000: "If the actual value specified via SV ... is shorter than the minimum on
            // duration, the output ... is accordingly 0"; E1 is set.
            (
                ShortPulse::Suppress,
                0.05,
                (0, 1000 * MS, true, false, Rule::SuppressedPulse),
            ),
            // 000: "If the off duration ... is less than the minimum off duration, Q1 or Q2 are
            // permanently on."
            (
                ShortPulse::Suppress,
                0.95,
                (1000 * MS, 0, true, false, Rule::SuppressedBreak),
            ),
            // 002: stretch raises the on time (or the off time) and sets the limit flag.
            (
                ShortPulse::Stretch,
                0.05,
                (100 * MS, 900 * MS, true, true, Rule::StretchedPulse),
            ),
            (
                ShortPulse::Stretch,
                0.95,
                (900 * MS, 100 * MS, true, true, Rule::StretchedBreak),
            ),
        ] {
            let p = Plan::new(duty, &cfg(1000, 100, sp, 0.0));
            assert_eq!(
                (p.t_on, p.t_off, p.e1, p.limited, p.rule),
                want,
                "{sp} {duty}"
            );
        }
    }

    #[test]
    fn zero_and_full_are_exact_and_never_flag_002() {
        for sp in [ShortPulse::Suppress, ShortPulse::Stretch, ShortPulse::Band] {
            let c = cfg(1000, 400, sp, 0.3);
            let p = Plan::new(0.0, &c);
            assert_eq!((p.t_on, p.e1, p.limited), (0, false, false), "{sp}");
            let p = Plan::new(1.0, &c);
            assert_eq!((p.t_off, p.e1, p.limited), (0, false, false), "{sp}");
        }
    }

    #[test]
    fn hardware_floor_applies_with_me_zero_000() {
        // 000: the shortest on duration of a transistor output is 0.1 ms.
        let c = cfg(1000, 0, ShortPulse::Suppress, 0.0);
        assert!(Plan::new(0.00005, &c).e1, "50 us < 100 us floor");
        assert!(
            !Plan::new(0.0001, &c).e1,
            "exactly the floor is reproducible"
        );
        assert!(Plan::new(0.99995, &c).e1, "50 us break < floor");
    }

    #[test]
    fn band_truth_table_below_half_004() {
        let c = cfg(1000, 0, ShortPulse::Band, 0.2);
        assert_eq!(Plan::new(0.19, &c).rule, Rule::BandLow);
        assert_eq!(Plan::new(0.19, &c).t_on, 0);
        assert_eq!(Plan::new(0.2, &c).t_on, 200 * MS, "d == e is PWM");
        assert_eq!(Plan::new(0.5, &c).t_on, 500 * MS);
        assert_eq!(Plan::new(0.8, &c).t_on, 800 * MS, "d == 1-e is PWM");
        assert_eq!(Plan::new(0.81, &c).rule, Rule::BandHigh);
        assert_eq!(Plan::new(0.81, &c).t_off, 0);
        assert!(
            !Plan::new(0.81, &c).e1,
            "the band is a policy, not a minimum time"
        );
    }

    #[test]
    fn band_truth_table_at_or_above_half_004() {
        // 004's rows for i_rEdge >= 0.5: below the edge FALSE, from it TRUE.
        let c = cfg(1000, 0, ShortPulse::Band, 0.7);
        assert_eq!(Plan::new(0.69, &c).t_on, 0);
        assert_eq!(Plan::new(0.7, &c).t_off, 0, "d >= e gives 1");
        let c = cfg(1000, 0, ShortPulse::Band, 0.5);
        assert_eq!(Plan::new(0.49, &c).t_on, 0);
        assert_eq!(Plan::new(0.51, &c).t_off, 0);
    }

    #[test]
    fn band_worked_example_edge_half_input_half_is_500_500_004() {
        // 004's example: TimeBase 1 s, i_rEdge 0.5, i_rIput 0.5 gives 500 ms TRUE and 500 ms
        // FALSE; d < e is FALSE, d > 1 - e is TRUE, neither holds, so PWM.
        let c = cfg(1000, 0, ShortPulse::Band, 0.5);
        let p = Plan::new(0.5, &c);
        assert_eq!((p.t_on, p.t_off, p.rule), (500 * MS, 500 * MS, Rule::Exact));
    }

    #[test]
    fn band_boundaries_are_exact_as_written_whatever_the_rounding_004() {
        // `pct / 100` and `1 - edge` round differently: 0.67 > 1 - 0.33 in binary floats. An
        // input exactly at either boundary is PWM, at every edge value.
        for pct in 1..=99u32 {
            for edge_pct in 0..=50u32 {
                let e = f64::from(edge_pct) / 100.0;
                let c = cfg(1000, 0, ShortPulse::Band, e);
                let d = f64::from(pct) / 100.0;
                let p = Plan::new(d, &c);
                let expect = if pct < edge_pct {
                    Rule::BandLow
                } else if pct > 100 - edge_pct {
                    Rule::BandHigh
                } else {
                    Rule::Exact
                };
                assert_eq!(p.rule, expect, "{pct} % at edge {e}");
            }
        }
        for (pct, e) in [
            (67.0, 0.33),
            (66.0, 0.34),
            (68.0, 0.32),
            (93.0, 0.07),
            (80.0, 0.2),
        ] {
            let c = cfg(1000, 0, ShortPulse::Band, e);
            assert_eq!(
                Plan::new(pct / 100.0, &c).rule,
                Rule::Exact,
                "{pct} % at {e}"
            );
        }
    }

    #[test]
    fn minima_beyond_the_period_give_0_or_1_with_e1_000_002() {
        // Relay PD 150 ms, ME 100 ms (min off = min on): no duty has both a valid pulse and a
        // valid break; suppress gives 0 or 1 for the period, with E1.
        let c = ChannelParams {
            period_ms: 150,
            min_on_ms: 100,
            output_kind: crate::core::OutputKind::Relay,
            ..ChannelParams::default()
        }
        .validate()
        .unwrap();
        for pct in 1..100u32 {
            let p = Plan::new(f64::from(pct) / 100.0, &c);
            assert!(p.t_on == 0 || p.t_off == 0, "{pct} %: {p:?}");
            assert!(p.e1 && !p.limited, "{pct} %");
        }
        // 002, nMinSwiTi = nPrd: every pulse is raised to the whole period, limit flag set.
        let c = ChannelParams {
            period_ms: 1000,
            min_on_ms: 1000,
            short_pulse: Some(ShortPulse::Stretch),
            min_off_ms: Some(0),
            ..ChannelParams::default()
        }
        .validate()
        .unwrap();
        let p = Plan::new(0.3, &c);
        assert_eq!(
            (p.t_on, p.t_off, p.e1, p.limited),
            (1000 * MS, 0, true, true)
        );
        // Stretch with both minima above half the period: still 0 or 1, never a short phase.
        let c = cfg(100, 60, ShortPulse::Stretch, 0.0);
        for pct in 1..100u32 {
            let p = Plan::new(f64::from(pct) / 100.0, &c);
            let ok = |t: Nanos, min: Nanos| t == 0 || t >= min;
            assert!(
                ok(p.t_on, c.min_on) && ok(p.t_off, c.min_off),
                "{pct} %: {p:?}"
            );
            assert!(p.limited, "{pct} %");
        }
    }

    #[test]
    fn max_on_flags_plans_that_keep_the_line_on_longer() {
        let c = ChannelParams {
            period_ms: 1000,
            max_on_ms: 600,
            ..ChannelParams::default()
        }
        .validate()
        .unwrap();
        let p = Plan::new(0.6, &c);
        assert!(!p.max_on && !p.e1, "600 ms fits: {p:?}");
        let p = Plan::new(0.61, &c);
        assert!(p.max_on && p.e1 && p.limited, "{p:?}");
        assert_eq!((p.t_on, p.rule), (610 * MS, Rule::Exact), "the times stay");
        // 100 % runs into the next period: cut, even at 100 %.
        assert!(Plan::new(1.0, &c).max_on && Plan::new(1.0, &c).e1);
        assert!(!Plan::new(0.0, &c).max_on);
    }

    #[test]
    fn period_zero_means_no_pulses_000() {
        let c = cfg(0, 0, ShortPulse::Suppress, 0.0);
        let p = Plan::new(0.5, &c);
        assert_eq!((p.t_on, p.t_off, p.rule), (0, 0, Rule::NoPeriod));
        assert_eq!(p.applied_duty(), 0.0);
    }
}
