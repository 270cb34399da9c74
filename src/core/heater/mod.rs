//! The heater loop of a channel: temperature feedback, a PID to a setpoint, and the
//! heater checks that latch a fault and switch the line off. Pure: the channel drives it in
//! virtual time (`Channel::feedback`, `Channel::set_setpoint`, its deadlines), and only the
//! channel knows when its line was really on, which `stuck_on` needs.
//!
//! A channel without feedback runs open loop as before. Under `pid` every check that needs no
//! model is on by default (`sensor_timeout`, `sensor_stuck`, `sensor_jump`, the range,
//! `not_heating`), and `pid` refuses to start without `temp_max_c`.
//!
//! - [`pid`]: the loop.
//! - [`mpc`]: model-predictive control, on the thermal model.
//! - [`fit`]: the model fitted to an autotune's record.
//! - [`checks`]: `not_heating` (Klipper's `verify_heater`), `stuck_on`, `sensor_stuck`,
//!   `sensor_jump`.
//! - [`model`]: the thermal model behind `model_deviation`.
//! - [`autotune`]: the relay autotune, which also identifies the model.
//! - [`plant`]: a first-order-plus-dead-time heater, for the tests and the simulated heater.

pub mod autotune;
pub mod checks;
pub mod fit;
pub mod model;
pub mod mpc;
pub mod pid;
pub mod plant;

pub use super::config::heater::{
    Control, Gains, HeaterConfig, HeaterConfigError, HeaterParams, ModelParams, Runaway,
    StuckLimits, DEFAULT_AMBIENT_TIMEOUT_MS, DEFAULT_FEEDBACK_TIMEOUT_MS,
    DEFAULT_FEEDFORWARD_TIMEOUT_MS, DEFAULT_MAX_RATE_C_PER_S, DEFAULT_MODEL_TIME_S,
    DEFAULT_MODEL_TOLERANCE_C, DEFAULT_NO_RISE_TIME_S, DEFAULT_STUCK_ENERGY_S,
    DEFAULT_STUCK_ON_RISE_C, DEFAULT_STUCK_TIME_S, MAX_DELTA_C, MAX_FEEDFORWARD_PCT, MAX_GAIN,
    MAX_MODEL_DEAD_TIME_S, MAX_MODEL_GAIN, MAX_RAMP_C_PER_S, MAX_RATE_C_PER_S, MAX_RUNAWAY_ERROR,
    MAX_SKEW_MS, MAX_TEMP_C, MAX_TIME_S, MIN_SAMPLE_MS, MIN_TEMP_C,
};
use super::Nanos;
pub use checks::{Delivered, Flat, Jump, Leap, NoRise, NotHeating, Rise, Still, Stuck, StuckOn};
pub use model::{Model, Prediction};
pub use mpc::{Mpc, MpcTerms};
pub use pid::{Pid, Terms};
pub use plant::{Plant, PlantFault, PlantParams};
use std::fmt;

/// How often `not_heating` ticks (Klipper's `verify_heater` runs every second).
pub const CHECK_TICK: Nanos = 1_000_000_000;

/// A latched heater fault: which check, with its figures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HeaterFault {
    /// A reading outside `temp_min_c..=temp_max_c`, NaN or infinite.
    OutOfRange {
        /// The reading, °C.
        celsius: f64,
        /// `temp_min_c`.
        min_c: f64,
        /// `temp_max_c`.
        max_c: f64,
    },
    /// No reading for `feedback_timeout_ms` while enabled.
    SensorTimeout {
        /// Time since the last reading (or since start-up), ms.
        silent_ms: u64,
        /// `feedback_timeout_ms`.
        timeout_ms: u64,
    },
    /// Klipper's "not heating at expected rate".
    NotHeating {
        /// The reading, °C.
        celsius: f64,
        /// The setpoint, °C.
        target_c: f64,
        /// The summed error, °C·s.
        error: f64,
        /// `runaway_max_error`.
        max_error: f64,
    },
    /// The temperature rose while the line was held off (a welded SSR or relay).
    StuckOn {
        /// The rise within the window, °C.
        rise_c: f64,
        /// `stuck_on_rise_c`.
        limit_c: f64,
        /// `stuck_on_time_s`.
        window_s: f64,
    },
    /// The reading stood still while the heater got an energy that must have moved it (or
    /// stayed at full power): a frozen sensor.
    SensorStuck {
        /// The reading, °C.
        celsius: f64,
        /// How long it stood still, s.
        still_s: f64,
        /// How far the energy the heater got swung meanwhile, seconds of full power.
        swing_s: f64,
        /// `sensor_stuck_energy_s`.
        limit_s: f64,
        /// The heater was at full power all the while.
        full: bool,
    },
    /// The heater was at full power (the loop asking for more) and the reading did not rise.
    NoRise {
        /// The mean reading at the start, °C.
        start_c: f64,
        /// The mean reading now, °C.
        now_c: f64,
        /// How long at full power, s.
        full_s: f64,
    },
    /// The reading moved faster than a heater can.
    SensorJump {
        /// The change, °C.
        change_c: f64,
        /// Within this time, s.
        within_s: f64,
        /// `sensor_max_rate_c_per_s`.
        max_rate: f64,
    },
    /// The reading left the thermal model's prediction by more than the tolerance for the
    /// check's time.
    ModelDeviation {
        /// The reading, °C.
        celsius: f64,
        /// The model's prediction, °C.
        predicted_c: f64,
        /// `model_tolerance_c`.
        tolerance_c: f64,
        /// `model_time_s`.
        time_s: f64,
    },
}

impl HeaterFault {
    /// The check's name, as on `/diagnostics`: `temperature_out_of_range`, `sensor_timeout`,
    /// `not_heating`, `stuck_on`, `sensor_stuck`, `no_rise`, `sensor_jump`, `model_deviation`.
    pub fn check(&self) -> &'static str {
        match self {
            HeaterFault::OutOfRange { .. } => "temperature_out_of_range",
            HeaterFault::SensorTimeout { .. } => "sensor_timeout",
            HeaterFault::NotHeating { .. } => "not_heating",
            HeaterFault::StuckOn { .. } => "stuck_on",
            HeaterFault::SensorStuck { .. } => "sensor_stuck",
            HeaterFault::NoRise { .. } => "no_rise",
            HeaterFault::SensorJump { .. } => "sensor_jump",
            HeaterFault::ModelDeviation { .. } => "model_deviation",
        }
    }
}

impl fmt::Display for HeaterFault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            HeaterFault::OutOfRange {
                celsius,
                min_c,
                max_c,
            } => write!(
                f,
                "temperature_out_of_range: reading {celsius} °C outside {min_c}..{max_c} °C"
            ),
            HeaterFault::SensorTimeout {
                silent_ms,
                timeout_ms,
            } => write!(
                f,
                "sensor_timeout: no fresh reading for {silent_ms} ms (feedback_timeout_ms \
                 {timeout_ms})"
            ),
            HeaterFault::SensorStuck {
                celsius,
                still_s,
                swing_s,
                limit_s,
                full,
            } => {
                if full {
                    write!(
                        f,
                        "sensor_stuck: reading {celsius:.2} °C still for {still_s:.1} s with \
                         the heater at full power"
                    )
                } else {
                    write!(
                        f,
                        "sensor_stuck: reading {celsius:.2} °C still for {still_s:.1} s while \
                         the heater's energy swung by {swing_s:.1} s of full power \
                         (sensor_stuck_energy_s {limit_s})"
                    )
                }
            }
            HeaterFault::NoRise {
                start_c,
                now_c,
                full_s,
            } => write!(
                f,
                "no_rise: at full power for {full_s} s the reading went from {start_c:.2} °C \
                 to {now_c:.2} °C: the sensor does not see the heater, or the heater does \
                 not heat"
            ),
            HeaterFault::SensorJump {
                change_c,
                within_s,
                max_rate,
            } => write!(
                f,
                "sensor_jump: reading moved {change_c:+.2} °C within {within_s:.2} s \
                 (sensor_max_rate_c_per_s {max_rate}, over at least 1 s)"
            ),
            HeaterFault::ModelDeviation {
                celsius,
                predicted_c,
                tolerance_c,
                time_s,
            } => write!(
                f,
                "model_deviation: reading {celsius:.2} °C, model {predicted_c:.2} °C: off by \
                 {:+.2} °C, beyond model_tolerance_c {tolerance_c} for model_time_s {time_s} s",
                celsius - predicted_c
            ),
            HeaterFault::NotHeating {
                celsius,
                target_c,
                error,
                max_error,
            } => write!(
                f,
                "not_heating: {celsius:.2} °C for setpoint {target_c:.2} °C, error {error:.1} \
                 °C·s reached runaway_max_error {max_error}"
            ),
            HeaterFault::StuckOn {
                rise_c,
                limit_c,
                window_s,
            } => write!(
                f,
                "stuck_on: rose {rise_c:.2} °C within {window_s} s with the line off \
                 (stuck_on_rise_c {limit_c})"
            ),
        }
    }
}

/// Why a heater input was refused; what was in force stays.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum Refusal {
    /// A duty command while `control` is `pid`.
    #[error("duty command refused: control is pid (send a setpoint, or set control open)")]
    DutyUnderPid,
    /// A duty command while `control` is `mpc`.
    #[error("duty command refused: control is mpc (send a setpoint, or set control open)")]
    DutyUnderMpc,
    /// A feed-forward that is not a number within ±100 % of full power.
    #[error("feedforward {0} refused: not a number within -100..100 % of full power")]
    Feedforward(f64),
    /// An ambient reading that is not a temperature below `temp_max_c`.
    #[error("ambient {value} °C refused: not a temperature within {min_c}..{max_c} °C")]
    Ambient {
        /// The reading.
        value: f64,
        /// The lowest accepted, °C.
        min_c: f64,
        /// `temp_max_c`.
        max_c: f64,
    },
    /// A setpoint while `control` is `open`.
    #[error("setpoint refused: control is open (set control pid or mpc)")]
    SetpointUnderOpen,
    /// A duty command or a setpoint while an autotune runs.
    #[error("refused: an autotune is running on this channel (cancel it first)")]
    Autotuning,
    /// A setpoint that is NaN or infinite.
    #[error("setpoint {0} refused: not a finite number")]
    SetpointNotFinite(f64),
    /// A setpoint outside the temperature limits: below `temp_min_c` or above
    /// `temp_max_c − setpoint_margin_c`.
    #[error(
        "setpoint {value} °C refused: outside temp_min_c..temp_max_c − setpoint_margin_c \
         ({min_c}..{max_c} °C)"
    )]
    SetpointOutOfRange {
        /// The setpoint.
        value: f64,
        /// `temp_min_c`.
        min_c: f64,
        /// `temp_max_c − setpoint_margin_c`.
        max_c: f64,
    },
}

/// Why `reset_fault` was refused.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum ResetRefusal {
    /// No heater fault is latched.
    #[error("no heater fault is latched")]
    NoFault,
    /// The condition of the latched fault lasts.
    #[error("the condition lasts: {0}")]
    Lasts(HeaterFault),
}

/// What the channel reports of its heater loop.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct HeaterStatus {
    /// Feedback is configured.
    pub feedback: bool,
    /// `control` is `pid`.
    pub pid: bool,
    /// `control` in force.
    pub control: Control,
    /// The loop's target now: the setpoint, or on its way there at `setpoint_ramp_c_per_s`,
    /// °C.
    pub target: Option<f64>,
    /// Under `mpc`: the loop's terms at its last sample.
    pub mpc: Option<MpcTerms>,
    /// The thermal model in force.
    pub model_params: Option<ModelParams>,
    /// The feed-forward in force, % of full power (0 while none is fresh), and whether a
    /// configured one is stale (none yet, or the last older than `feedforward_timeout_ms`).
    pub feedforward_pct: f64,
    /// See `feedforward_pct`.
    pub feedforward_stale: bool,
    /// The ambient in force (the ambient topic's, else the model's), °C, and whether a
    /// configured ambient topic is stale.
    pub ambient_c: Option<f64>,
    /// See `ambient_c`.
    pub ambient_stale: bool,
    /// The last reading, °C, and when it arrived (monotonic ns).
    pub reading: Option<(f64, Nanos)>,
    /// The setpoint in force, °C.
    pub setpoint: Option<f64>,
    /// The PID's terms at its last sample.
    pub terms: Terms,
    /// The latched fault.
    pub fault: Option<HeaterFault>,
    /// The condition of the latched fault still holds (a reset would be refused).
    pub fault_lasts: bool,
    /// `not_heating`'s summed error, °C·s.
    pub runaway_error: f64,
    /// The thermal model's prediction and residual at the last fresh reading.
    pub model: Option<Prediction>,
    /// Readings refused as stale by their stamp, and the age of the last one, ns (negative:
    /// stamped in the future).
    pub stale: (u64, i64),
    /// The latest reading was refused as stale.
    pub stale_now: bool,
    /// The setpoint in force was lowered to fit a lowered `temp_max_c`: from, °C.
    pub setpoint_lowered_from: Option<f64>,
    /// TCONT_CP's sizing rules (003) the settings break under `pid`.
    pub sizing: [Option<Sizing>; 3],
}

/// A rule of TCONT_CP's sizing (003) that the settings break while `pid` is in force.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Sizing {
    /// `period_ms` above TI/5, TI = kp/ki (003: "PER_TM <= TI/5").
    PeriodAboveTi5 {
        /// The period, ms.
        period_ms: f64,
        /// TI, s.
        ti_s: f64,
    },
    /// A minimum time above a tenth of the period (003: "P_B_TM <= 0.1 * PER_TM").
    MinTimeAboveTenth {
        /// `min_on_ms` or `min_off_ms`.
        which: &'static str,
        /// Its value, ms.
        value_ms: f64,
        /// The period, ms.
        period_ms: f64,
    },
}

impl fmt::Display for Sizing {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Sizing::PeriodAboveTi5 { period_ms, ti_s } => write!(
                f,
                "sizing rule period_ms <= TI/5 broken (003): period_ms {period_ms} > TI/5 = {} ms \
                 (TI = pid_kp/pid_ki = {ti_s:.3} s)",
                ti_s * 1000.0 / 5.0
            ),
            Sizing::MinTimeAboveTenth {
                which,
                value_ms,
                period_ms,
            } => write!(
                f,
                "sizing rule minimum time <= 0.1 x period broken (003): {which} {value_ms} > \
                 {} ms",
                period_ms / 10.0
            ),
        }
    }
}

/// TCONT_CP's sizing rules (003) for a channel under `pid`: period `period_ms`, the minima
/// `min_on_ms` and `min_off_ms` as configured (0 = the hardware floor, which is not counted).
pub fn sizing(
    heater: &HeaterParams,
    period_ms: f64,
    min_on_ms: f64,
    min_off_ms: f64,
) -> impl Iterator<Item = Sizing> {
    let pid = heater.control == Control::Pid && period_ms > 0.0;
    let ti_s = (heater.pid_ki > 0.0).then(|| heater.pid_kp / heater.pid_ki);
    let ti = ti_s
        .filter(|ti| pid && period_ms > ti * 1000.0 / 5.0)
        .map(|ti_s| Sizing::PeriodAboveTi5 { period_ms, ti_s });
    let minima = [("min_on_ms", min_on_ms), ("min_off_ms", min_off_ms)]
        .into_iter()
        .filter(move |(_, v)| pid && *v > 0.1 * period_ms)
        .map(move |(which, value_ms)| Sizing::MinTimeAboveTenth {
            which,
            value_ms,
            period_ms,
        });
    ti.into_iter().chain(minima)
}

/// The heater state a channel keeps (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Heat {
    pub(crate) pid: Pid,
    pub(crate) not_heating: NotHeating,
    pub(crate) stuck: StuckOn,
    /// The last reading, °C, and when it arrived.
    pub(crate) reading: Option<(f64, Nanos)>,
    /// The setpoint in force and when it arrived.
    pub(crate) setpoint: Option<(f64, Nanos)>,
    /// Since when readings are expected (creation, or the last reconfiguration of feedback).
    pub(crate) expected_since: Nanos,
    /// The next PID sample, the last one, and the next `not_heating` tick.
    pub(crate) next_sample: Option<Nanos>,
    pub(crate) last_sample: Option<Nanos>,
    pub(crate) next_tick: Option<Nanos>,
    /// The latched fault.
    pub(crate) fault: Option<HeaterFault>,
    /// The rise `stuck_on` saw at the last reading.
    pub(crate) rise: Rise,
    /// The autotune run, with its ticket.
    pub(crate) autotune: Option<(u32, autotune::Autotune)>,
    /// The line's on time over its finished high phases, ns (the running one is added from
    /// the line's state): what the heater really got.
    pub(crate) on_closed: Nanos,
    /// Up to when the on time is counted in `on_closed`.
    pub(crate) on_counted_to: Nanos,
    /// The line's cumulative on time at past readings.
    pub(crate) delivered: Delivered,
    /// `sensor_stuck` and `sensor_jump`.
    pub(crate) still: Stuck,
    pub(crate) leap: Leap,
    /// `no_rise`.
    pub(crate) flat: NoRise,
    /// The thermal model, when one is set, and what it said at the last fresh reading.
    pub(crate) model: Option<Model>,
    pub(crate) prediction: Option<Prediction>,
    /// Since when the residual lies beyond the tolerance.
    pub(crate) deviating_since: Option<Nanos>,
    /// The arrival of the reading the last PID sample used (the derivative moves only on a
    /// new one).
    pub(crate) sampled_reading_at: Option<Nanos>,
    /// Stale readings refused, and the age of the last one, ns; the latest was one.
    pub(crate) stale: (u64, i64),
    pub(crate) stale_now: bool,
    /// The setpoint was lowered to fit a lowered `temp_max_c`: from, °C.
    pub(crate) lowered_from: Option<f64>,
    /// The last reading that jumped.
    pub(crate) last_jump_at: Option<Nanos>,
    /// The model-predictive loop's estimate, run whenever a model is set (so a switch to
    /// `mpc` finds it warm), and the output its next sample starts from (bumpless).
    pub(crate) mpc: Option<Mpc>,
    pub(crate) mpc_start: Option<f64>,
    /// The last feed-forward (%) and ambient (°C) received, with their instants (the
    /// ambient's from its stamp).
    pub(crate) ff_in: Option<(f64, Nanos)>,
    pub(crate) ambient_in: Option<(f64, Nanos)>,
    /// The feed-forward in force (0 while stale), and whether each configured input is stale.
    pub(crate) ff_used: f64,
    pub(crate) ff_stale: bool,
    pub(crate) ambient_stale: bool,
    /// Where the setpoint ramp stood, °C, and when.
    pub(crate) ramp: Option<(f64, Nanos)>,
}

/// The first of `len` snapshots whose time (`time_of(k)`, ns, rising with `k`) is at or after
/// `t`, by bisection; `len` when none is.
pub(crate) fn first_at_or_after(len: usize, time_of: impl Fn(usize) -> Nanos, t: Nanos) -> usize {
    let (mut lo, mut hi) = (0, len);
    while lo < hi {
        let mid = (lo + hi) / 2;
        if time_of(mid) < t {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    lo
}

/// How far back the delivered-duty history reaches, ns: `sensor_stuck`'s time and window.
pub(crate) fn delivered_span(cfg: &HeaterConfig, window: Nanos) -> Nanos {
    cfg.stuck
        .time
        .saturating_mul(2)
        .saturating_add(window.saturating_mul(2))
}

impl Heat {
    pub(crate) fn new(cfg: &HeaterConfig, window: Nanos, now: Nanos) -> Heat {
        Heat {
            pid: Pid::new(cfg.gains),
            not_heating: NotHeating::default(),
            stuck: StuckOn::default(),
            reading: None,
            setpoint: None,
            expected_since: now,
            next_sample: None,
            last_sample: None,
            next_tick: cfg
                .params
                .feedback
                .then_some(now.saturating_add(CHECK_TICK)),
            fault: None,
            rise: Rise {
                rise_c: 0.0,
                off_whole_window: false,
            },
            autotune: None,
            on_closed: 0,
            on_counted_to: 0,
            delivered: Delivered::new(delivered_span(cfg, window)),
            still: Stuck::default(),
            leap: Leap::default(),
            flat: NoRise::new(cfg.stuck.no_rise),
            model: cfg
                .params
                .model
                .is_set()
                .then(|| Model::new(cfg.params.model)),
            prediction: None,
            deviating_since: None,
            sampled_reading_at: None,
            stale: (0, 0),
            stale_now: false,
            lowered_from: None,
            last_jump_at: None,
            mpc: cfg
                .params
                .model
                .is_set()
                .then(|| Mpc::new(cfg.params.model)),
            mpc_start: None,
            ff_in: None,
            ambient_in: None,
            ff_used: 0.0,
            ff_stale: cfg.params.feedforward,
            ambient_stale: cfg.params.ambient,
            ramp: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tcont_cp_sizing_rules_003() {
        let p = HeaterParams {
            feedback: true,
            control: Control::Pid,
            pid_kp: 10.0,
            pid_ki: 1.0,
            ..HeaterParams::default()
        };
        // TI = 10 s: the period may be up to 2 s.
        assert_eq!(sizing(&p, 2000.0, 0.0, 0.0).count(), 0);
        let w: Vec<_> = sizing(&p, 2500.0, 300.0, 0.0).collect();
        assert_eq!(w.len(), 2, "{w:?}");
        assert!(w[0].to_string().contains("period_ms <= TI/5"));
        assert!(w[1].to_string().contains("min_on_ms 300 > 250 ms"));
        // Open loop: no rule applies.
        let open = HeaterParams {
            control: Control::Open,
            ..p
        };
        assert_eq!(sizing(&open, 2500.0, 300.0, 0.0).count(), 0);
    }
}
