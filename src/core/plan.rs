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
    /// `extend`: the pulse was shorter than the minimum on time; the period grew so that it is
    /// exactly the minimum and the duty is kept (PLC PWM output modules' "extend cycle").
    ExtendedPulse,
    /// `extend`: the break was shorter than the minimum off time; the period grew so that it
    /// is exactly the minimum and the duty is kept.
    ExtendedBreak,
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
            Rule::ExtendedPulse => "extended_pulse",
            Rule::ExtendedBreak => "extended_break",
        }
    }

    /// Whether the period of the plan grew beyond the configured one (`extend`).
    pub const fn extended(self) -> bool {
        matches!(self, Rule::ExtendedPulse | Rule::ExtendedBreak)
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
    /// Off time, ns; `t_on + t_off` is the period (longer than the configured one when the
    /// rule is an extension).
    pub t_off: Nanos,
    /// E1 (000): the commanded duty could not be reproduced because of a minimum time (or
    /// `max_on`).
    pub e1: bool,
    /// The minimum-time limit flag (002's bLmtSwiTi): a time was raised to its minimum (or
    /// `max_on`), or a minimum time set the length of an extended period (the duty is kept,
    /// so E1 is not set, but the output's timing is not the configured one).
    pub limited: bool,
    /// The rule that shaped this plan.
    pub rule: Rule,
    /// The plan keeps the line high longer than `max_on_ms` (a constant 1, or an on time above
    /// it): the line guard will cut it, so E1 and the limit flag are set too.
    pub max_on: bool,
    /// With a time base: the rounding remainder this plan leaves for the next period, ticks,
    /// within ±½ (see [`Plan::carried`]); 0 without a time base, and for the plans that are
    /// not a rounded duty (0 %, 100 %, the band's constants, extended periods).
    pub carry: f64,
}

impl Plan {
    /// The duty actually delivered, `t_on / T` (0 with no period).
    pub fn applied_duty(&self) -> f64 {
        let period = self.period();
        if period == 0 {
            0.0
        } else {
            self.t_on as f64 / period as f64
        }
    }

    /// The period of the plan, `t_on + t_off`, ns: the configured one, or the extended one;
    /// 0 with no period.
    pub fn period(&self) -> Nanos {
        self.t_on + self.t_off
    }

    /// An extended plan laid on a grid of whole periods of `grid` ns (the stagger grid): its
    /// period grows to the next whole number of grid periods and its on time to the same
    /// duty of it, so the duty stays exact and the next period starts on the grid. Both times
    /// only grow, so the minima still hold. Other plans are returned as they are.
    /// With a time base of `tick` ns the on time is rounded to whole ticks (`grid` is a whole
    /// number of them).
    pub fn on_grid(self, grid: Nanos, tick: Nanos) -> Plan {
        let period = self.period();
        if !self.rule.extended() || grid == 0 || period.is_multiple_of(grid) {
            return self;
        }
        let whole = period.div_ceil(grid).saturating_mul(grid);
        let t_on = match tick {
            0 => (self.duty * whole as f64).round() as Nanos,
            tick => (self.duty * whole as f64 / tick as f64).round() as Nanos * tick,
        };
        let t_on = t_on.clamp(self.t_on, whole);
        let t_off = (whole - t_on).max(self.t_off.min(whole - t_on));
        Plan {
            t_on,
            t_off,
            ..self
        }
    }

    /// Makes the plan for duty fraction `duty` (0..=1) under `cfg`: the minimum-time rules,
    /// then whether the maximum on time will cut what they give. With a time base, the first
    /// period of a run (no rounding remainder carried in).
    pub fn new(duty: f64, cfg: &ChannelConfig) -> Plan {
        Plan::carried(duty, cfg, 0.0)
    }

    /// [`Plan::new`] for a period that takes in the rounding remainder `carry` (ticks) the
    /// period before left (its [`Plan::carry`]); without a time base `carry` is ignored.
    ///
    /// With a time base of `τ` ns and a period of `P` ticks, the on time is `n` ticks with
    /// `n = round(d × P + carry)`, and the plan carries `d × P + carry - n` on (error
    /// diffusion): over any run of periods of one command the on time delivered is within
    /// one tick of the command's, instead of the bias plain rounding would repeat every
    /// period. The minimum-time rules then act on the rounded on time exactly as on the
    /// ns-rounded one without a time base (E1, the limit flag). The carry is only the
    /// rounding remainder, taken before the rules: what a rule adds or removes (a suppressed
    /// pulse, a stretched one) is not carried, so the carry stays within ±½ tick and cannot
    /// build up behind a minimum.
    pub fn carried(duty: f64, cfg: &ChannelConfig, carry: f64) -> Plan {
        let plan = Plan::shape(duty, cfg, carry);
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
    fn shape(duty: f64, cfg: &ChannelConfig, carry: f64) -> Plan {
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
        // Round to the nearest ns (with a time base: to whole ticks, carrying the remainder);
        // the whole period stays exactly `period`.
        let (t_on, carry) = match cfg.tick {
            0 => (((duty * period as f64).round() as Nanos).min(period), 0.0),
            tick => {
                let ticks = (period / tick) as f64;
                let ideal = duty * ticks + carry.clamp(-0.5, 0.5);
                let n = ideal.round().clamp(0.0, ticks);
                ((n as Nanos) * tick, ideal - n)
            }
        };
        let base = Plan { carry, ..base };
        let t_off = period - t_on;
        if cfg.short_pulse == ShortPulse::Extend && (t_on < cfg.min_on || t_off < cfg.min_off) {
            if let Some(plan) = extended(duty, cfg) {
                return Plan { duty, ..plan };
            }
        }
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
                // `band` keeps suppress as its safety net inside the PWM range; `extend` falls
                // back to it beyond `extend_max`.
                ShortPulse::Suppress | ShortPulse::Band | ShortPulse::Extend => Plan {
                    carry,
                    ..constant(false, Rule::SuppressedPulse, true)
                },
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
                ShortPulse::Suppress | ShortPulse::Band | ShortPulse::Extend => Plan {
                    carry,
                    ..constant(true, Rule::SuppressedBreak, true)
                },
            };
        }
        Plan {
            t_on,
            t_off,
            ..base
        }
    }
}

/// `extend` for duty fraction `duty` (strictly between 0 and 1) whose pulse or break is below
/// its minimum at the configured period: the period `T' = max(min_on / d, min_off / (1 - d))`,
/// in which the phase whose minimum sets it is exactly that minimum and the other is the rest
/// of `T'` rounded to the nearest ns (never below its own minimum), so `t_on / T'` is `d` within
/// half a ns of `T'`. `None` when `T'` exceeds `extend_max` times the configured period.
///
/// E1 stays clear, as the duty is delivered; the limit flag is set, as a minimum time set the
/// length of the period.
fn extended(duty: f64, cfg: &ChannelConfig) -> Option<Plan> {
    let (min_on, min_off) = (cfg.min_on as f64, cfg.min_off as f64);
    // The factor needs no resolving: it is read as the user gave it.
    let limit = (cfg.params.extend_max * cfg.period as f64).floor();
    // min_on / d >= min_off / (1 - d), without dividing.
    let pulse_sets_it = min_on * (1.0 - duty) >= min_off * duty;
    let ideal = if pulse_sets_it {
        min_on / duty
    } else {
        min_off / (1.0 - duty)
    };
    // Also refuses a duty so close to 0 or 1 that `ideal` is not finite.
    if ideal.is_nan() || ideal > limit + 1.0 {
        return None;
    }
    // With a time base the rest is rounded to whole ticks too (the minima already are); the
    // duty is then kept to within half a tick of `T'`, with no carry.
    let whole = |ns: f64| match cfg.tick {
        0 => ns.round() as Nanos,
        tick => (ns / tick as f64).round() as Nanos * tick,
    };
    let (t_on, t_off, rule) = if pulse_sets_it {
        let rest = whole(min_on * (1.0 - duty) / duty);
        (cfg.min_on, rest.max(cfg.min_off), Rule::ExtendedPulse)
    } else {
        let rest = whole(min_off * duty / (1.0 - duty));
        (rest.max(cfg.min_on), cfg.min_off, Rule::ExtendedBreak)
    };
    ((t_on + t_off) as f64 <= limit).then_some(Plan {
        t_on,
        t_off,
        limited: true,
        rule,
        ..Plan::default()
    })
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
        for sp in [
            ShortPulse::Suppress,
            ShortPulse::Stretch,
            ShortPulse::Band,
            ShortPulse::Extend,
        ] {
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

    /// `extend` with `extend_max` and both minima as given.
    fn extend(period_ms: u64, min_on_ms: u64, min_off_ms: u64, extend_max: f64) -> ChannelConfig {
        ChannelParams {
            period_ms,
            min_on_ms,
            min_off_ms: Some(min_off_ms),
            short_pulse: Some(ShortPulse::Extend),
            extend_max,
            ..ChannelParams::default()
        }
        .validate()
        .unwrap()
    }

    #[test]
    fn extend_grows_the_period_so_the_short_phase_is_exactly_its_minimum() {
        // 1000 ms period, 100 ms minimum on and off time: T' = min_on / d or min_off / (1 - d).
        let c = extend(1000, 100, 100, 10.0);
        for (duty, want) in [
            (0.05, (100 * MS, 1900 * MS, Rule::ExtendedPulse)),
            (0.95, (1900 * MS, 100 * MS, Rule::ExtendedBreak)),
            (0.02, (100 * MS, 4900 * MS, Rule::ExtendedPulse)),
            // Long enough at the configured period: unchanged.
            (0.1, (100 * MS, 900 * MS, Rule::Exact)),
            (0.5, (500 * MS, 500 * MS, Rule::Exact)),
        ] {
            let p = Plan::new(duty, &c);
            assert_eq!((p.t_on, p.t_off, p.rule), want, "{duty}");
            // The duty is kept: no E1; an extension sets the limit flag.
            assert!(!p.e1, "{duty}");
            assert_eq!(p.limited, p.rule.extended(), "{duty}");
            assert!((p.applied_duty() - duty).abs() < 1e-12, "{duty}: {p:?}");
        }
    }

    #[test]
    fn extend_keeps_the_duty_to_half_a_ns_of_the_period() {
        // 7 % of T' = 100 ms / 0.07 = 1428.571 428 57 ms: the break is rounded to the ns, the
        // pulse is exactly the minimum.
        let c = extend(1000, 100, 100, 10.0);
        let p = Plan::new(0.07, &c);
        assert_eq!((p.t_on, p.t_off), (100 * MS, 1_328_571_429));
        let error = (p.t_on as f64 - 0.07 * p.period() as f64).abs();
        assert!(error <= 0.5, "{error} ns");
        // And the mirror for a short break.
        let p = Plan::new(0.93, &c);
        assert_eq!((p.t_on, p.t_off), (1_328_571_429, 100 * MS));
        assert!((p.t_on as f64 - 0.93 * p.period() as f64).abs() <= 0.5);
    }

    #[test]
    fn extend_takes_the_longer_period_when_both_minima_matter() {
        // The numbers of 000's relay table: PD 150 ms, ME 100 ms = min off. No duty fits both
        // minima in one period; extended, every duty has both: the minimum that needs the
        // longer period is exactly met, the other phase is at least its own minimum.
        let c = extend(150, 100, 100, 10.0);
        for (pct, want) in [
            (50, (100, 100, Rule::ExtendedPulse)),
            (40, (100, 150, Rule::ExtendedPulse)),
            (60, (150, 100, Rule::ExtendedBreak)),
            (20, (100, 400, Rule::ExtendedPulse)),
        ] {
            let p = Plan::new(f64::from(pct) / 100.0, &c);
            assert_eq!(
                (p.t_on, p.t_off, p.rule),
                (want.0 * MS, want.1 * MS, want.2)
            );
        }
        // Unequal minima: at 30 % the pulse is 45 ms, short of 50 ms, and the break 105 ms,
        // short of 200 ms; min_off / 0.7 = 285.7 ms beats min_on / 0.3 = 166.7 ms.
        let c = extend(150, 50, 200, 10.0);
        let p = Plan::new(0.3, &c);
        assert_eq!((p.t_on, p.t_off), (85_714_286, 200 * MS));
        assert_eq!(p.rule, Rule::ExtendedBreak);
        for pct in 1..100u32 {
            let d = f64::from(pct) / 100.0;
            let p = Plan::new(d, &c);
            if p.rule.extended() {
                assert!(p.t_on >= c.min_on && p.t_off >= c.min_off, "{pct} %: {p:?}");
                assert!(p.period() >= c.period, "{pct} %: {p:?}");
                assert!(
                    (p.t_on as f64 - d * p.period() as f64).abs() <= 0.5,
                    "{pct} %"
                );
            }
        }
    }

    #[test]
    fn extend_stops_at_extend_max_then_suppresses_with_e1() {
        // 1 % of 1 s with a 100 ms minimum needs exactly 10 s: allowed at 10 x, not at 9.99 x.
        let p = Plan::new(0.01, &extend(1000, 100, 100, 10.0));
        assert_eq!(
            (p.t_on, p.t_off, p.rule),
            (100 * MS, 9900 * MS, Rule::ExtendedPulse)
        );
        let p = Plan::new(0.01, &extend(1000, 100, 100, 9.99));
        assert_eq!((p.t_on, p.t_off), (0, 1000 * MS));
        assert_eq!(
            (p.rule, p.e1, p.limited),
            (Rule::SuppressedPulse, true, false)
        );
        let p = Plan::new(0.99, &extend(1000, 100, 100, 9.99));
        assert_eq!(
            (p.t_on, p.t_off, p.rule),
            (1000 * MS, 0, Rule::SuppressedBreak)
        );
        // 1 x: no extension possible, exactly suppress.
        let ext = extend(1000, 100, 100, 1.0);
        let sup = cfg(1000, 100, ShortPulse::Suppress, 0.0);
        for pct in 0..=100u32 {
            let d = f64::from(pct) / 100.0;
            let (a, b) = (Plan::new(d, &ext), Plan::new(d, &sup));
            assert_eq!(
                (a.t_on, a.t_off, a.e1, a.rule),
                (b.t_on, b.t_off, b.e1, b.rule)
            );
        }
        // A duty too small for any finite period.
        let p = Plan::new(1e-300, &extend(1000, 100, 100, 100.0));
        assert_eq!(p.rule, Rule::SuppressedPulse);
    }

    #[test]
    fn extend_holds_a_minimum_longer_than_the_period() {
        // Under extend a minimum above the period is kept as given: the period grows to it.
        let c = extend(1000, 3000, 3000, 10.0);
        assert_eq!((c.min_on, c.min_off), (3000 * MS, 3000 * MS));
        let p = Plan::new(0.5, &c);
        assert_eq!(
            (p.t_on, p.t_off, p.rule),
            (3000 * MS, 3000 * MS, Rule::ExtendedPulse)
        );
        // 20 % needs 15 s: beyond 10 x, suppressed.
        assert_eq!(Plan::new(0.2, &c).rule, Rule::SuppressedPulse);
    }

    #[test]
    fn max_on_still_flags_an_extended_pulse_longer_than_itself() {
        let c = ChannelParams {
            period_ms: 150,
            min_on_ms: 100,
            max_on_ms: 120,
            output_kind: crate::core::OutputKind::Relay,
            short_pulse: Some(ShortPulse::Extend),
            ..ChannelParams::default()
        }
        .validate()
        .unwrap();
        let p = Plan::new(0.6, &c);
        assert_eq!((p.t_on, p.rule), (150 * MS, Rule::ExtendedBreak));
        assert!(p.max_on && p.e1 && p.limited, "{p:?}");
    }

    #[test]
    fn period_zero_means_no_pulses_000() {
        let c = cfg(0, 0, ShortPulse::Suppress, 0.0);
        let p = Plan::new(0.5, &c);
        assert_eq!((p.t_on, p.t_off, p.rule), (0, 0, Rule::NoPeriod));
        assert_eq!(p.applied_duty(), 0.0);
    }
}
