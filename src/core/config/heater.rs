//! The heater settings of a channel: the loop's mode and gains, the temperature
//! limits and the checks' parameters, their ranges and validation. Off by default.

use super::{Nanos, OutOfRange, MAX_PERIOD_MS, MAX_TIMEOUT_MS, NS_PER_MS};

/// The gains of the loop.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gains {
    /// Proportional gain, % per °C.
    pub kp: f64,
    /// Integral gain, % per °C·s.
    pub ki: f64,
    /// Derivative gain, % per °C/s.
    pub kd: f64,
    /// Time constant of the derivative's first-order filter, s; 0 = unfiltered.
    pub d_filter_s: f64,
}

/// The parameters of `not_heating`, as Klipper's `verify_heater` names them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Runaway {
    /// `hysteresis`, °C: within this of the target the check rests.
    pub hysteresis_c: f64,
    /// `max_error`, °C·s summed over the 1 s ticks below the band.
    pub max_error: f64,
    /// `check_gain_time`, ns: an approach must gain `heating_gain_c` within it.
    pub gain_time: Nanos,
    /// `heating_gain`, °C.
    pub heating_gain_c: f64,
}

/// Who sets the duty of a channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Control {
    /// The duty commands (`~/<ch>/duty`, `~/<ch>/sv`, split range): today's behaviour.
    #[default]
    Open,
    /// The PID, from the feedback and `~/<ch>/setpoint`.
    Pid,
    /// Model-predictive control: the thermal model predicts the heater over its dead time and
    /// the duty brings the prediction to the setpoint (needs a model).
    Mpc,
}

impl Control {
    /// The parameter spelling: `open`, `pid` or `mpc`.
    pub const fn as_str(self) -> &'static str {
        match self {
            Control::Open => "open",
            Control::Pid => "pid",
            Control::Mpc => "mpc",
        }
    }

    /// Whether a loop sets the duty from the feedback and the setpoint (`pid` or `mpc`).
    pub const fn closed(self) -> bool {
        matches!(self, Control::Pid | Control::Mpc)
    }
}

super::named_enum!(
    Control,
    "open|pid|mpc",
    [Control::Open, Control::Pid, Control::Mpc]
);

/// Lowest temperature a limit may be set to, °C (absolute zero).
pub const MIN_TEMP_C: f64 = -273.15;
/// Highest temperature a limit may be set to, °C.
pub const MAX_TEMP_C: f64 = 3000.0;
/// Largest gain accepted for `pid_kp`, `pid_ki` and `pid_kd`.
pub const MAX_GAIN: f64 = 100_000.0;
/// Longest time accepted for the seconds parameters (derivative filter, `runaway_gain_time_s`,
/// `stuck_on_time_s`), s: a day.
pub const MAX_TIME_S: f64 = 86_400.0;
/// Largest temperature difference accepted (hysteresis, heating gain, stuck-on rise), °C.
pub const MAX_DELTA_C: f64 = 1000.0;
/// Largest `runaway_max_error` accepted, °C·s.
pub const MAX_RUNAWAY_ERROR: f64 = 1.0e7;
/// Shortest PID sample accepted, ms (0 means the channel's period).
pub const MIN_SAMPLE_MS: u64 = 10;
/// `feedback_timeout_ms`'s default, ms: Klipper's MCU switches a heater off 3 s after its host
/// stops refreshing it, and a sensor publishing at 1 Hz may lose two readings in a row
/// without tripping it.
pub const DEFAULT_FEEDBACK_TIMEOUT_MS: u64 = 3000;
/// Largest `feedback_max_skew_ms`, ms.
pub const MAX_SKEW_MS: u64 = 60_000;
/// Largest model gain accepted, °C per % of duty.
pub const MAX_MODEL_GAIN: f64 = 100.0;
/// Largest rate accepted for `sensor_max_rate_c_per_s`, °C/s.
pub const MAX_RATE_C_PER_S: f64 = 10_000.0;

/// The heater settings of one channel as a user states them. The defaults are
/// Klipper's for `runaway_*` and "off" for the rest.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeaterParams {
    /// A feedback topic is configured (`feedback_topic` not empty): readings arrive.
    pub feedback: bool,
    /// Who sets the duty.
    pub control: Control,
    /// PID sample, ms; 0 = the channel's period. 0, or 10..=3 600 000.
    pub pid_sample_ms: u64,
    /// % per °C.
    pub pid_kp: f64,
    /// % per °C·s.
    pub pid_ki: f64,
    /// % per °C/s.
    pub pid_kd: f64,
    /// The derivative's filter time constant, s; 0 = unfiltered.
    pub pid_d_filter_s: f64,
    /// Readings below this are `temperature_out_of_range`, °C.
    pub temp_min_c: f64,
    /// Readings above this are `temperature_out_of_range`, °C.
    pub temp_max_c: f64,
    /// `sensor_timeout`: no fresh reading for this long while enabled, ms; 0 = off (only
    /// under `open`).
    pub feedback_timeout_ms: u64,
    /// How far in the future a reading's `header.stamp` may lie against the node's clock
    /// (the two hosts' clock skew), ms. A stamp further ahead, or older than
    /// `feedback_timeout_ms` at its arrival, makes the reading stale. A zero stamp (an
    /// unstamped reading) counts from its arrival.
    pub feedback_max_skew_ms: u64,
    /// A setpoint must lie at least this far below `temp_max_c`, °C (Marlin's
    /// `HOTEND_OVERSHOOT`, 15).
    pub setpoint_margin_c: f64,
    /// `sensor_stuck`: the shortest time a reading must stand still to be stuck, s (at full
    /// power, the time); 0 = off.
    pub sensor_stuck_time_s: f64,
    /// `sensor_stuck`: a change of the reading by more than this counts as movement, °C (0:
    /// any change); `no_rise`: a rise of at most this is none.
    pub sensor_stuck_band_c: f64,
    /// `sensor_stuck`: how far the energy the heater gets may swing (stray from a steady
    /// power), in seconds of full power, while the reading stands still.
    pub sensor_stuck_energy_s: f64,
    /// `no_rise`: at full power (the loop or an autotune asking for it) for this long, the
    /// reading must rise, s; 0 = off.
    pub no_rise_time_s: f64,
    /// `sensor_jump`: a reading that moves faster than this against the one before (over at
    /// least a second), °C/s, is not a temperature; 0 = off.
    pub sensor_max_rate_c_per_s: f64,
    /// `not_heating`'s hysteresis, °C (Klipper 5).
    pub runaway_hysteresis_c: f64,
    /// `not_heating`'s max_error, °C·s (Klipper 120).
    pub runaway_max_error: f64,
    /// `not_heating`'s check_gain_time, s (Klipper 20).
    pub runaway_gain_time_s: f64,
    /// `not_heating`'s heating_gain, °C (Klipper 2).
    pub runaway_heating_gain_c: f64,
    /// `stuck_on`: a rise of more than this while the line was off, °C; 0 = off.
    pub stuck_on_rise_c: f64,
    /// `stuck_on`'s window, s.
    pub stuck_on_time_s: f64,
    /// An autotune aborts on a reading above its target plus this, °C (20).
    pub autotune_max_overshoot_c: f64,
    /// An autotune aborts when no relay cycle completes within this, s (1200).
    pub autotune_timeout_s: f64,
    /// Once an autotune's cycles agree with the model's dead time still uncertain, the relay
    /// may go on for at most this long, s, until the dead time is told within 10 %; 0 = the
    /// run ends at once (0).
    pub autotune_extend_s: f64,
    /// An autotune's target must lie at least this far below `temp_max_c`, °C (Marlin's
    /// M303: 15).
    pub autotune_margin_c: f64,
    /// The heater's thermal model (first order plus dead time); none when its gain is 0.
    pub model: ModelParams,
    /// `model_deviation`: a residual (reading less the model's prediction) beyond this, °C...
    pub model_tolerance_c: f64,
    /// ...lasting this long, s, latches the fault.
    pub model_time_s: f64,
    /// A feed-forward topic is configured (`feedforward_topic` not empty).
    pub feedforward: bool,
    /// A feed-forward older than this is stale and ignored, ms; 0 = never stale.
    pub feedforward_timeout_ms: u64,
    /// An ambient topic is configured (`ambient_topic` not empty).
    pub ambient: bool,
    /// An ambient reading older than this is stale and ignored, ms; 0 = never stale.
    pub ambient_timeout_ms: u64,
    /// The loop's target moves toward a new setpoint at this rate, °C/s; 0 = a step.
    pub setpoint_ramp_c_per_s: f64,
}

/// A heater's thermal model: first order plus dead time, driven by the line's real on time,
/// and a sensor that lags its block. With the line on a share `u` (%) of the time, after the
/// dead time: `dT/dt = (ambient + gain·u − T) / tau`, and the sensor reads `S` with
/// `dS/dt = (T − S) / sensor_tau` (`sensor_tau` 0: it reads `T`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ModelParams {
    /// Steady-state rise per % of duty, °C/%; 0 = no model.
    pub gain_c_per_pct: f64,
    /// Time constant, s.
    pub tau_s: f64,
    /// Dead time between the line and the sensor, s.
    pub dead_time_s: f64,
    /// Ambient, °C: the temperature at 0 %.
    pub ambient_c: f64,
    /// The sensor's time constant behind the block, s; 0 = the sensor reads the block.
    pub sensor_tau_s: f64,
}

impl ModelParams {
    /// Whether a model is set (its gain is above 0).
    pub fn is_set(&self) -> bool {
        self.gain_c_per_pct > 0.0
    }
}

impl Default for HeaterParams {
    fn default() -> Self {
        HeaterParams {
            feedback: false,
            control: Control::Open,
            pid_sample_ms: 0,
            pid_kp: 0.0,
            pid_ki: 0.0,
            pid_kd: 0.0,
            pid_d_filter_s: 0.0,
            temp_min_c: MIN_TEMP_C,
            temp_max_c: MAX_TEMP_C,
            feedback_timeout_ms: DEFAULT_FEEDBACK_TIMEOUT_MS,
            feedback_max_skew_ms: 1000,
            setpoint_margin_c: 15.0,
            sensor_stuck_time_s: DEFAULT_STUCK_TIME_S,
            sensor_stuck_band_c: 0.0,
            sensor_stuck_energy_s: DEFAULT_STUCK_ENERGY_S,
            no_rise_time_s: DEFAULT_NO_RISE_TIME_S,
            sensor_max_rate_c_per_s: DEFAULT_MAX_RATE_C_PER_S,
            runaway_hysteresis_c: 5.0,
            runaway_max_error: 120.0,
            runaway_gain_time_s: 20.0,
            runaway_heating_gain_c: 2.0,
            stuck_on_rise_c: DEFAULT_STUCK_ON_RISE_C,
            stuck_on_time_s: 30.0,
            autotune_max_overshoot_c: 20.0,
            autotune_timeout_s: 1200.0,
            autotune_extend_s: 0.0,
            autotune_margin_c: 15.0,
            model: ModelParams {
                gain_c_per_pct: 0.0,
                tau_s: 60.0,
                dead_time_s: 0.0,
                ambient_c: 20.0,
                sensor_tau_s: 0.0,
            },
            model_tolerance_c: DEFAULT_MODEL_TOLERANCE_C,
            model_time_s: DEFAULT_MODEL_TIME_S,
            feedforward: false,
            feedforward_timeout_ms: DEFAULT_FEEDFORWARD_TIMEOUT_MS,
            ambient: false,
            ambient_timeout_ms: DEFAULT_AMBIENT_TIMEOUT_MS,
            setpoint_ramp_c_per_s: 0.0,
        }
    }
}

/// `feedforward_timeout_ms`'s default, ms.
pub const DEFAULT_FEEDFORWARD_TIMEOUT_MS: u64 = 5000;
/// `ambient_timeout_ms`'s default, ms: a room sensor publishes every few seconds to a minute.
pub const DEFAULT_AMBIENT_TIMEOUT_MS: u64 = 120_000;
/// Largest feed-forward accepted, % of full power (either sign).
pub const MAX_FEEDFORWARD_PCT: f64 = 100.0;
/// Largest `setpoint_ramp_c_per_s`, °C/s.
pub const MAX_RAMP_C_PER_S: f64 = 1000.0;

/// `sensor_stuck_time_s`'s default, s.
pub const DEFAULT_STUCK_TIME_S: f64 = 6.0;
/// `stuck_on_rise_c`'s default, °C: above what a heater of the sizing range (rise at full
/// power up to 0.7 °C/s, dead time up to 3 s, noise up to ±0.2 °C) rises after its line goes
/// off, `r·L + 2n = 2.5 °C`, by half again and 1 °C.
pub const DEFAULT_STUCK_ON_RISE_C: f64 = 5.0;
/// `sensor_stuck_energy_s`'s default, seconds of full power.
pub const DEFAULT_STUCK_ENERGY_S: f64 = 1.5;
/// `no_rise_time_s`'s default, s.
pub const DEFAULT_NO_RISE_TIME_S: f64 = 10.0;
/// `sensor_max_rate_c_per_s`'s default, °C/s.
pub const DEFAULT_MAX_RATE_C_PER_S: f64 = 10.0;
/// `model_tolerance_c`'s default, °C.
pub const DEFAULT_MODEL_TOLERANCE_C: f64 = 10.0;
/// `model_time_s`'s default, s.
pub const DEFAULT_MODEL_TIME_S: f64 = 5.0;

/// Why heater settings are refused. The old settings stay in force.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum HeaterConfigError {
    /// A value outside its range, or not a number.
    #[error(transparent)]
    OutOfRange(#[from] OutOfRange),
    /// `temp_min_c` not below `temp_max_c`.
    #[error("temp_min_c {min_c} is not below temp_max_c {max_c}")]
    TempLimits {
        /// `temp_min_c`.
        min_c: f64,
        /// `temp_max_c`.
        max_c: f64,
    },
    /// A PID sample below the minimum (0 means the period).
    #[error("pid_sample_ms {value_ms} is outside 10..3600000 (0 = the channel's period)")]
    Sample {
        /// The refused value, ms.
        value_ms: u64,
    },
    /// `control` `pid` (or `mpc`) without feedback.
    #[error("control {0} needs a feedback_topic (set at start-up)")]
    PidWithoutFeedback(&'static str),
    /// `control` `pid` (or `mpc`) with `temp_max_c` left at its unset default.
    #[error(
        "control {0} needs temp_max_c: the highest temperature the heater may reach, below \
         {MAX_TEMP_C} °C (Klipper refuses a heater without max_temp)"
    )]
    PidWithoutTempMax(&'static str),
    /// `control` `pid` (or `mpc`) with `feedback_timeout_ms` 0.
    #[error(
        "control {0} needs feedback_timeout_ms above 0: the loop must not heat on a reading \
         that stopped coming (default {DEFAULT_FEEDBACK_TIMEOUT_MS} ms)"
    )]
    PidWithoutTimeout(&'static str),
    /// `control` `mpc` without a thermal model.
    #[error(
        "control mpc needs the heater's thermal model: model_gain_c_per_pct above 0 (run \
         ~/<ch>/autotune with apply, or set model_gain_c_per_pct, model_tau_s, \
         model_dead_time_s and model_ambient_c)"
    )]
    MpcWithoutModel,
    /// The setpoint margin leaves no setpoint between the limits.
    #[error(
        "setpoint_margin_c {margin_c} leaves no setpoint between temp_min_c {min_c} and \
         temp_max_c {max_c}"
    )]
    NoSetpointRoom {
        /// `setpoint_margin_c`.
        margin_c: f64,
        /// `temp_min_c`.
        min_c: f64,
        /// `temp_max_c`.
        max_c: f64,
    },
}

/// The channel's limits on an autotune run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AutotuneLimits {
    /// A reading above `target + max_overshoot_c` aborts, °C.
    pub max_overshoot_c: f64,
    /// No complete cycle within this aborts, ns.
    pub timeout: Nanos,
    /// How long the relay may go on after its cycles agree to tell the model's dead time,
    /// ns; 0 = not at all.
    pub extend: Nanos,
}

/// `sensor_stuck`'s settings, validated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StuckLimits {
    /// How long a still reading is believed while the power moves, ns; 0 = off.
    pub time: Nanos,
    /// A change above this is movement, °C.
    pub band_c: f64,
    /// The energy surplus that must move the reading, seconds of full power.
    pub energy_s: f64,
    /// `no_rise`'s time, ns; 0 = off.
    pub no_rise: Nanos,
    /// The duty the loop can reach at most (`max_duty_pct`), fraction: its full power. Set by
    /// the channel's validation.
    pub full: f64,
}

/// The validated heater settings the channel runs on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeaterConfig {
    /// The PID sample, ns; 0 = the channel's period.
    pub sample: Nanos,
    /// The gains.
    pub gains: Gains,
    /// `sensor_timeout`, ns; 0 = off.
    pub feedback_timeout: Nanos,
    /// How far in the future a stamp may lie, ns.
    pub max_skew: Nanos,
    /// `sensor_stuck`.
    pub stuck: StuckLimits,
    /// `model_deviation`'s time, ns.
    pub model_time: Nanos,
    /// `not_heating`.
    pub runaway: Runaway,
    /// `stuck_on`'s window, ns.
    pub stuck_window: Nanos,
    /// The autotune's limits.
    pub autotune: AutotuneLimits,
    /// A feed-forward or an ambient reading older than these is stale, ns; 0 = never.
    pub feedforward_timeout: Nanos,
    /// See `feedforward_timeout`.
    pub ambient_timeout: Nanos,
    /// The parameters this was made from.
    pub params: HeaterParams,
}

fn seconds(s: f64) -> Nanos {
    (s * 1e9).round() as Nanos
}

/// Longest model dead time accepted, s.
pub const MAX_MODEL_DEAD_TIME_S: f64 = 600.0;

impl HeaterParams {
    /// Whether `temp_max_c` was set: its default, [`MAX_TEMP_C`], means unset.
    pub fn temp_max_set(&self) -> bool {
        self.temp_max_c < MAX_TEMP_C
    }

    /// The highest setpoint accepted, °C: `temp_max_c − setpoint_margin_c` (`temp_max_c`
    /// while it is unset).
    pub fn setpoint_ceiling(&self) -> f64 {
        if self.temp_max_set() {
            self.temp_max_c - self.setpoint_margin_c
        } else {
            self.temp_max_c
        }
    }

    /// Checks every value against its range (NaN never passes) and makes the nanosecond
    /// configuration.
    pub fn validate(&self) -> Result<HeaterConfig, HeaterConfigError> {
        if self.pid_sample_ms != 0 && !(MIN_SAMPLE_MS..=MAX_PERIOD_MS).contains(&self.pid_sample_ms)
        {
            return Err(HeaterConfigError::Sample {
                value_ms: self.pid_sample_ms,
            });
        }
        OutOfRange::check("pid_kp", self.pid_kp, 0.0, MAX_GAIN)?;
        OutOfRange::check("pid_ki", self.pid_ki, 0.0, MAX_GAIN)?;
        OutOfRange::check("pid_kd", self.pid_kd, 0.0, MAX_GAIN)?;
        OutOfRange::check("pid_d_filter_s", self.pid_d_filter_s, 0.0, MAX_TIME_S)?;
        OutOfRange::check("temp_min_c", self.temp_min_c, MIN_TEMP_C, MAX_TEMP_C)?;
        OutOfRange::check("temp_max_c", self.temp_max_c, MIN_TEMP_C, MAX_TEMP_C)?;
        if self.temp_min_c >= self.temp_max_c {
            return Err(HeaterConfigError::TempLimits {
                min_c: self.temp_min_c,
                max_c: self.temp_max_c,
            });
        }
        OutOfRange::check(
            "feedback_timeout_ms",
            self.feedback_timeout_ms as f64,
            0.0,
            MAX_TIMEOUT_MS as f64,
        )?;
        OutOfRange::check(
            "feedback_max_skew_ms",
            self.feedback_max_skew_ms as f64,
            0.0,
            MAX_SKEW_MS as f64,
        )?;
        OutOfRange::check(
            "setpoint_margin_c",
            self.setpoint_margin_c,
            0.0,
            MAX_DELTA_C,
        )?;
        OutOfRange::check(
            "sensor_stuck_time_s",
            self.sensor_stuck_time_s,
            0.0,
            MAX_TIME_S,
        )?;
        OutOfRange::check(
            "sensor_stuck_band_c",
            self.sensor_stuck_band_c,
            0.0,
            MAX_DELTA_C,
        )?;
        OutOfRange::check(
            "sensor_stuck_energy_s",
            self.sensor_stuck_energy_s,
            0.1,
            MAX_TIME_S,
        )?;
        OutOfRange::check("no_rise_time_s", self.no_rise_time_s, 0.0, MAX_TIME_S)?;
        OutOfRange::check(
            "sensor_max_rate_c_per_s",
            self.sensor_max_rate_c_per_s,
            0.0,
            MAX_RATE_C_PER_S,
        )?;
        OutOfRange::check(
            "autotune_margin_c",
            self.autotune_margin_c,
            0.0,
            MAX_DELTA_C,
        )?;
        let m = &self.model;
        OutOfRange::check(
            "model_gain_c_per_pct",
            m.gain_c_per_pct,
            0.0,
            MAX_MODEL_GAIN,
        )?;
        OutOfRange::check("model_tau_s", m.tau_s, 0.1, MAX_TIME_S)?;
        OutOfRange::check(
            "model_dead_time_s",
            m.dead_time_s,
            0.0,
            MAX_MODEL_DEAD_TIME_S,
        )?;
        OutOfRange::check("model_ambient_c", m.ambient_c, MIN_TEMP_C, MAX_TEMP_C)?;
        OutOfRange::check(
            "model_sensor_tau_s",
            m.sensor_tau_s,
            0.0,
            MAX_MODEL_DEAD_TIME_S,
        )?;
        OutOfRange::check(
            "model_tolerance_c",
            self.model_tolerance_c,
            0.1,
            MAX_DELTA_C,
        )?;
        OutOfRange::check("model_time_s", self.model_time_s, 0.0, MAX_TIME_S)?;
        OutOfRange::check(
            "runaway_hysteresis_c",
            self.runaway_hysteresis_c,
            0.0,
            MAX_DELTA_C,
        )?;
        OutOfRange::check(
            "runaway_max_error",
            self.runaway_max_error,
            0.0,
            MAX_RUNAWAY_ERROR,
        )?;
        OutOfRange::check(
            "runaway_gain_time_s",
            self.runaway_gain_time_s,
            1.0,
            MAX_TIME_S,
        )?;
        // Klipper: heating_gain "above=0".
        OutOfRange::check(
            "runaway_heating_gain_c",
            self.runaway_heating_gain_c,
            0.001,
            MAX_DELTA_C,
        )?;
        OutOfRange::check("stuck_on_rise_c", self.stuck_on_rise_c, 0.0, MAX_DELTA_C)?;
        OutOfRange::check("stuck_on_time_s", self.stuck_on_time_s, 1.0, MAX_TIME_S)?;
        OutOfRange::check(
            "autotune_max_overshoot_c",
            self.autotune_max_overshoot_c,
            0.1,
            MAX_DELTA_C,
        )?;
        OutOfRange::check(
            "autotune_timeout_s",
            self.autotune_timeout_s,
            1.0,
            MAX_TIME_S,
        )?;
        OutOfRange::check("autotune_extend_s", self.autotune_extend_s, 0.0, MAX_TIME_S)?;
        OutOfRange::check(
            "feedforward_timeout_ms",
            self.feedforward_timeout_ms as f64,
            0.0,
            MAX_TIMEOUT_MS as f64,
        )?;
        OutOfRange::check(
            "ambient_timeout_ms",
            self.ambient_timeout_ms as f64,
            0.0,
            MAX_TIMEOUT_MS as f64,
        )?;
        OutOfRange::check(
            "setpoint_ramp_c_per_s",
            self.setpoint_ramp_c_per_s,
            0.0,
            MAX_RAMP_C_PER_S,
        )?;
        if self.control.closed() {
            let c = self.control.as_str();
            if !self.feedback {
                return Err(HeaterConfigError::PidWithoutFeedback(c));
            }
            if !self.temp_max_set() {
                return Err(HeaterConfigError::PidWithoutTempMax(c));
            }
            if self.feedback_timeout_ms == 0 {
                return Err(HeaterConfigError::PidWithoutTimeout(c));
            }
        }
        if self.control == Control::Mpc && !self.model.is_set() {
            return Err(HeaterConfigError::MpcWithoutModel);
        }
        if self.temp_max_set() && self.setpoint_ceiling() < self.temp_min_c {
            return Err(HeaterConfigError::NoSetpointRoom {
                margin_c: self.setpoint_margin_c,
                min_c: self.temp_min_c,
                max_c: self.temp_max_c,
            });
        }
        Ok(HeaterConfig {
            sample: self.pid_sample_ms * NS_PER_MS,
            gains: Gains {
                kp: self.pid_kp,
                ki: self.pid_ki,
                kd: self.pid_kd,
                d_filter_s: self.pid_d_filter_s,
            },
            feedback_timeout: self.feedback_timeout_ms * NS_PER_MS,
            max_skew: self.feedback_max_skew_ms * NS_PER_MS,
            stuck: StuckLimits {
                time: seconds(self.sensor_stuck_time_s),
                band_c: self.sensor_stuck_band_c,
                energy_s: self.sensor_stuck_energy_s,
                no_rise: seconds(self.no_rise_time_s),
                full: 1.0,
            },
            model_time: seconds(self.model_time_s),
            runaway: Runaway {
                hysteresis_c: self.runaway_hysteresis_c,
                max_error: self.runaway_max_error,
                gain_time: seconds(self.runaway_gain_time_s),
                heating_gain_c: self.runaway_heating_gain_c,
            },
            stuck_window: seconds(self.stuck_on_time_s),
            autotune: AutotuneLimits {
                max_overshoot_c: self.autotune_max_overshoot_c,
                timeout: seconds(self.autotune_timeout_s),
                extend: seconds(self.autotune_extend_s),
            },
            feedforward_timeout: self.feedforward_timeout_ms * NS_PER_MS,
            ambient_timeout: self.ambient_timeout_ms * NS_PER_MS,
            params: *self,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_klippers_and_the_checks_are_on() {
        let c = HeaterParams::default().validate().unwrap();
        assert_eq!(c.params.control, Control::Open);
        assert_eq!(c.runaway.hysteresis_c, 5.0);
        assert_eq!(c.runaway.max_error, 120.0);
        assert_eq!(c.runaway.gain_time, 20 * 1_000_000_000);
        assert_eq!(c.runaway.heating_gain_c, 2.0);
        assert_eq!(c.feedback_timeout, 3_000_000_000);
        assert_eq!(c.params.stuck_on_rise_c, DEFAULT_STUCK_ON_RISE_C);
        assert_eq!(c.stuck.time, 6_000_000_000);
        assert_eq!(c.stuck.no_rise, 10_000_000_000);
        assert!(!c.params.model.is_set());
        assert!(!c.params.temp_max_set());
    }

    #[test]
    fn pid_needs_its_maximum_and_a_feedback_timeout() {
        let pid = HeaterParams {
            feedback: true,
            control: Control::Pid,
            ..HeaterParams::default()
        };
        assert_eq!(
            pid.validate(),
            Err(HeaterConfigError::PidWithoutTempMax("pid"))
        );
        assert!(pid
            .validate()
            .unwrap_err()
            .to_string()
            .contains("control pid needs temp_max_c"));
        let with_max = HeaterParams {
            temp_max_c: 250.0,
            ..pid
        };
        assert!(with_max.validate().is_ok());
        assert_eq!(with_max.setpoint_ceiling(), 235.0);
        let no_timeout = HeaterParams {
            feedback_timeout_ms: 0,
            ..with_max
        };
        assert_eq!(
            no_timeout.validate(),
            Err(HeaterConfigError::PidWithoutTimeout("pid"))
        );
        // Open loop may switch the timeout off.
        let open = HeaterParams {
            control: Control::Open,
            ..no_timeout
        };
        assert!(open.validate().is_ok());
        // A margin that leaves no setpoint.
        let squeezed = HeaterParams {
            temp_min_c: 240.0,
            ..with_max
        };
        assert!(matches!(
            squeezed.validate(),
            Err(HeaterConfigError::NoSetpointRoom { .. })
        ));
    }

    #[test]
    fn bad_values_are_refused_with_a_reason() {
        let bad = |set: fn(&mut HeaterParams)| {
            let mut p = HeaterParams {
                feedback: true,
                ..HeaterParams::default()
            };
            set(&mut p);
            p.validate().unwrap_err().to_string()
        };
        assert_eq!(
            bad(|p| p.pid_kp = f64::NAN),
            "pid_kp NaN is outside 0..100000"
        );
        assert_eq!(bad(|p| p.pid_ki = -1.0), "pid_ki -1 is outside 0..100000");
        assert_eq!(
            bad(|p| {
                p.temp_min_c = 300.0;
                p.temp_max_c = 200.0;
            }),
            "temp_min_c 300 is not below temp_max_c 200"
        );
        assert_eq!(
            bad(|p| p.pid_sample_ms = 5),
            "pid_sample_ms 5 is outside 10..3600000 (0 = the channel's period)"
        );
        assert!(bad(|p| p.runaway_heating_gain_c = 0.0).starts_with("runaway_heating_gain_c 0"));
        assert!(bad(|p| p.stuck_on_time_s = f64::INFINITY).starts_with("stuck_on_time_s inf"));
        let no_feedback = HeaterParams {
            control: Control::Pid,
            ..HeaterParams::default()
        };
        assert_eq!(
            no_feedback.validate(),
            Err(HeaterConfigError::PidWithoutFeedback("pid"))
        );
    }

    #[test]
    fn mpc_needs_what_pid_needs_and_a_model() {
        let mpc = HeaterParams {
            feedback: true,
            control: Control::Mpc,
            temp_max_c: 250.0,
            ..HeaterParams::default()
        };
        let e = mpc.validate().unwrap_err();
        assert_eq!(e, HeaterConfigError::MpcWithoutModel);
        assert!(e
            .to_string()
            .starts_with("control mpc needs the heater's thermal model"));
        let with_model = HeaterParams {
            model: ModelParams {
                gain_c_per_pct: 1.2,
                ..mpc.model
            },
            ..mpc
        };
        assert!(with_model.validate().is_ok());
        let no_max = HeaterParams {
            temp_max_c: MAX_TEMP_C,
            ..with_model
        };
        assert_eq!(
            no_max.validate().unwrap_err().to_string().split(':').next(),
            Some("control mpc needs temp_max_c")
        );
        let ramp = HeaterParams {
            setpoint_ramp_c_per_s: -1.0,
            ..with_model
        };
        assert!(ramp
            .validate()
            .unwrap_err()
            .to_string()
            .starts_with("setpoint_ramp_c_per_s -1"));
    }
}
