//! Sizing advice: settings the vendor documents recommend against, though the channel runs them
//! as set. Reported on `/diagnostics` as a WARN naming the rule and the figures; nothing here
//! changes the timing.

use super::{ChannelConfig, Profile};
use std::fmt;

/// A vendor recommendation a channel's settings do not follow.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Sizing {
    /// 003: "CYCLE_P ≤ PER_TM/50" — the time base (the pulse generator's sampling time) is
    /// above a fiftieth of the period.
    CycleAboveFiftieth {
        /// `time_base_ms`.
        time_base_ms: f64,
        /// `period_ms`.
        period_ms: u64,
    },
    /// 003: "Recommended are values P_B_TM ≤ 0.1 × PER_TM" — the minimum on time is above a
    /// tenth of the period.
    MinPulseAboveTenth {
        /// `min_on_ms`.
        min_on_ms: u64,
        /// `period_ms`.
        period_ms: u64,
    },
    /// 001: "The resolution is defined by the relationship between: sampling period / task
    /// period. A minimum of 10 is recommended."
    ResolutionBelowTen {
        /// `period_ms`.
        period_ms: u64,
        /// `time_base_ms`.
        time_base_ms: f64,
    },
}

impl fmt::Display for Sizing {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Sizing::CycleAboveFiftieth {
                time_base_ms,
                period_ms,
            } => write!(
                f,
                "003 recommends CYCLE_P <= PER_TM/50: time_base_ms {time_base_ms} is above \
                 period_ms {period_ms} / 50 = {} ms",
                period_ms as f64 / 50.0
            ),
            Sizing::MinPulseAboveTenth {
                min_on_ms,
                period_ms,
            } => write!(
                f,
                "003 recommends P_B_TM <= 0.1 x PER_TM: min_on_ms {min_on_ms} is above 0.1 x \
                 period_ms {period_ms} = {} ms",
                period_ms as f64 / 10.0
            ),
            Sizing::ResolutionBelowTen {
                period_ms,
                time_base_ms,
            } => write!(
                f,
                "001 recommends a resolution (period / task period) of at least 10: period_ms \
                 {period_ms} / time_base_ms {time_base_ms} = {:.2}",
                period_ms as f64 / time_base_ms
            ),
        }
    }
}

impl ChannelConfig {
    /// The first vendor recommendation these settings do not follow, for the profile's
    /// vendor: under `tcont_cp` 003's CYCLE_P ≤ PER_TM/50 (with a time base) and P_B_TM ≤
    /// 0.1 × PER_TM; under `schneider_pwm` 001's period / task period ≥ 10 (with a time
    /// base). None with no period.
    pub fn sizing(&self) -> Option<Sizing> {
        let p = &self.params;
        if p.period_ms == 0 {
            return None;
        }
        let period = p.period_ms as f64;
        match p.profile {
            Profile::TcontCp if p.time_base_ms > 0.0 && p.time_base_ms * 50.0 > period => {
                Some(Sizing::CycleAboveFiftieth {
                    time_base_ms: p.time_base_ms,
                    period_ms: p.period_ms,
                })
            }
            Profile::TcontCp if p.min_on_ms as f64 * 10.0 > period => {
                Some(Sizing::MinPulseAboveTenth {
                    min_on_ms: p.min_on_ms,
                    period_ms: p.period_ms,
                })
            }
            Profile::SchneiderPwm if p.time_base_ms > 0.0 && period < 10.0 * p.time_base_ms => {
                Some(Sizing::ResolutionBelowTen {
                    period_ms: p.period_ms,
                    time_base_ms: p.time_base_ms,
                })
            }
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::ChannelParams;

    fn sizing(
        profile: Profile,
        period_ms: u64,
        time_base_ms: f64,
        min_on_ms: u64,
    ) -> Option<Sizing> {
        ChannelParams {
            profile,
            period_ms,
            time_base_ms,
            min_on_ms,
            ..ChannelParams::default()
        }
        .validate()
        .unwrap()
        .sizing()
    }

    #[test]
    fn tcont_cp_cycle_p_at_most_a_fiftieth_and_p_b_tm_a_tenth_003() {
        // 003's example: CYCLE_P 100 ms; PER_TM 10 s is 100 of them.
        assert_eq!(sizing(Profile::TcontCp, 10_000, 100.0, 0), None);
        assert_eq!(
            sizing(Profile::TcontCp, 5000, 100.0, 500),
            None,
            "exactly the limits"
        );
        let s = sizing(Profile::TcontCp, 4000, 100.0, 0).unwrap();
        assert_eq!(
            s.to_string(),
            "003 recommends CYCLE_P <= PER_TM/50: time_base_ms 100 is above period_ms 4000 / \
             50 = 80 ms"
        );
        let s = sizing(Profile::TcontCp, 1000, 0.0, 150).unwrap();
        assert_eq!(
            s,
            Sizing::MinPulseAboveTenth {
                min_on_ms: 150,
                period_ms: 1000
            }
        );
        assert!(s.to_string().contains("P_B_TM <= 0.1 x PER_TM"), "{s}");
        // Another profile: no advice from 003.
        assert_eq!(sizing(Profile::PicoGfx, 1000, 100.0, 150), None);
        assert_eq!(sizing(Profile::TcontCp, 0, 100.0, 150), None);
    }

    #[test]
    fn schneider_pwm_resolution_at_least_ten_001() {
        // 001's example: a 2 s sampling period with a task period of at most 200 ms.
        assert_eq!(sizing(Profile::SchneiderPwm, 2000, 200.0, 0), None);
        let s = sizing(Profile::SchneiderPwm, 2000, 250.0, 0).unwrap();
        assert_eq!(
            s.to_string(),
            "001 recommends a resolution (period / task period) of at least 10: period_ms 2000 \
             / time_base_ms 250 = 8.00"
        );
        assert_eq!(
            sizing(Profile::SchneiderPwm, 2000, 0.0, 0),
            None,
            "no time base"
        );
    }
}
