//! The parameters' values, typed, as generate_parameter_library generates them from its YAML:
//! one struct for the node ([`NodeValues`]), one a channel ([`ChannelValues`]) and one a valve
//! ([`ValveValues`]), a field a parameter, of the parameter's type. The store holds them; each
//! entry of the table names its field; names are spelled only at the ROS edge (the parameter
//! services, the parameter file, `/parameter_events`).
//!
//! What the node makes of them: the node-level settings, [`NodeSettings`], mapped by the
//! table's node entries as channel parameters map into the core's
//! [`ChannelParams`](crate::core::ChannelParams) and a valve's into its
//! [`ValveParams`](crate::core::ValveParams). Code reads these, never a parameter by name; a
//! live change is routed by comparing the settings before and after it.

use super::{ParamType, ParameterValue as V};
use crate::core::{Bank, Phase};
use std::path::PathBuf;

/// Every node-level parameter, typed (see the table in `table.rs` for units, ranges and
/// defaults).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct NodeSettings {
    /// `channels`: number of channels.
    pub channels: usize,
    /// `output`: `true` for the GPIO backend, `false` for the simulated sink.
    pub gpio: bool,
    /// `managed`: a managed (lifecycle) node.
    pub managed: bool,
    /// `trace`: trace files, in order.
    pub trace: Vec<PathBuf>,
    /// `trace_max_mb`: what the files of each trace may hold together, MB.
    pub trace_max_mb: u64,
    /// `status_rate_hz`: periodic status rate, Hz (0 = on change only).
    pub status_rate_hz: f64,
    /// `edge_log_rate`: edge lines per second and channel (0 = none).
    pub edge_log_rate: u32,
    /// `phase` and `max_simultaneous_on`: the node-level planner.
    pub bank: Bank,
    /// `command_hz_window`: window of the command-rate check, diagnostics runs.
    pub command_hz_window: usize,
    /// `command_hz_tolerance`: tolerance of the command-rate check, a fraction.
    pub command_hz_tolerance: f64,
    /// `split`: the split-range pairs, as written (parsed against the channels at start-up).
    pub split: String,
    /// `valve`: the three-point valves, as written (parsed against the channels at start-up).
    pub valve: String,
    /// `state_dir`: where the valves' state files live; empty for none.
    pub state_dir: String,
    /// `heartbeat_line`: the heartbeat line's offset, if there is one.
    pub heartbeat_line: Option<u32>,
    /// `heartbeat_chip`: the heartbeat line's chip.
    pub heartbeat_chip: PathBuf,
    /// `heartbeat_hz`: the heartbeat square wave's frequency, Hz.
    pub heartbeat_hz: f64,
    /// `estop_timeout_ms`: the heartbeat e-stop's timeout, ms (0 = off).
    pub estop_timeout_ms: u64,
    /// `rt_priority`: SCHED_FIFO priority of the output thread, if asked for.
    pub rt_priority: Option<i32>,
    /// `use_sim_time`: always false here.
    pub use_sim_time: bool,
    /// `heater_fault_latches_estop`: a heater fault of any channel latches the e-stop.
    pub heater_fault_latches_estop: bool,
}

impl NodeSettings {
    /// `phase` from its spelling (the table refused any other).
    pub(super) fn set_phase(&mut self, spelled: &str) {
        self.bank.phase = spelled.parse::<Phase>().unwrap_or_default();
    }
}

/// A field's Rust type as a parameter: its declared type and its value both ways. A field
/// holds exactly what the parameter holds (`i64`, `f64`, `bool`, `String`, as
/// generate_parameter_library's generated structs do), so a value read back is the value set.
pub trait Value: Sized + Default {
    /// The parameter's declared type.
    const TYPE: ParamType;
    /// The value in ROS form.
    fn to_value(&self) -> V;
    /// The field from a value of [`Value::TYPE`] (the store coerced it); any other reads as
    /// the type's default, which the store never lets happen.
    fn from_value(v: &V) -> Self;
}

/// [`Value`] for the four parameter types there are.
macro_rules! value {
    ($($t:ty => $ptype:ident, $variant:ident;)*) => {$(
        impl Value for $t {
            const TYPE: ParamType = ParamType::$ptype;
            fn to_value(&self) -> V {
                V::$variant(self.clone())
            }
            fn from_value(v: &V) -> Self {
                match v {
                    V::$variant(x) => x.clone(),
                    _ => Self::default(),
                }
            }
        }
    )*};
}

value! {
    i64 => Integer, Integer;
    f64 => Double, Double;
    bool => Bool, Boolean;
    String => String, String;
}

/// A struct of typed settings, one public field a parameter (`pwNN.<field>` for a channel,
/// `NAME.<field>` for a valve); the table's entry of each parameter names its field, and
/// [`Self::FIELDS`] lists them for the test that every field has its entry.
macro_rules! typed_settings {
    ($(#[$meta:meta])* $name:ident { $($field:ident: $ty:ty,)* }) => {
        $(#[$meta])*
        #[derive(Debug, Clone, PartialEq, Default)]
        pub struct $name {
            $(
                #[doc = concat!("`", stringify!($field), "` (see docs/parameters.md).")]
                pub $field: $ty,
            )*
        }

        impl $name {
            /// The fields, in the order written.
            #[cfg(test)]
            pub(super) const FIELDS: &'static [&'static str] = &[$(stringify!($field)),*];
        }
    };
}

typed_settings! {
    /// Every node-level parameter's value, typed. `Default` gives zero values: the declared
    /// defaults are the table's, set by the store.
    NodeValues {
        channels: i64,
        output: String,
        managed: bool,
        trace: String,
        trace_max_mb: i64,
        status_rate_hz: f64,
        edge_log_rate: i64,
        phase: String,
        max_simultaneous_on: i64,
        command_hz_window: i64,
        command_hz_tolerance: f64,
        split: String,
        valve: String,
        state_dir: String,
        heartbeat_line: i64,
        heartbeat_chip: String,
        heartbeat_hz: f64,
        estop_timeout_ms: i64,
        rt_priority: i64,
        heater_fault_latches_estop: bool,
        use_sim_time: bool,
    }
}

typed_settings! {
    /// Every parameter of one channel (`pwNN.*`), typed. `Default` gives zero values: the
    /// declared defaults are the table's, set by the store.
    ChannelValues {
        period_ms: i64,
        min_on_ms: i64,
        min_off_ms: i64,
        output_kind: String,
        profile: String,
        short_pulse: String,
        edge_band: f64,
        extend_max: f64,
        time_base_ms: f64,
        apply_at: String,
        on_disable: String,
        command_timeout_ms: i64,
        fault_duty_pct: f64,
        fault_hold_ms: i64,
        expected_command_hz_min: f64,
        expected_command_hz_max: f64,
        max_on_ms: i64,
        max_duty_pct: f64,
        min_duty_pct: f64,
        zero_means_zero: bool,
        duty_slew_pct_per_s: f64,
        duty_deadband_pct: f64,
        avg_duty_limit_pct: f64,
        avg_window_s: i64,
        feedback_topic: String,
        control: String,
        pid_sample_ms: i64,
        pid_kp: f64,
        pid_ki: f64,
        pid_kd: f64,
        pid_d_filter_s: f64,
        temp_min_c: f64,
        temp_max_c: f64,
        feedback_timeout_ms: i64,
        feedback_max_skew_ms: i64,
        setpoint_margin_c: f64,
        sensor_stuck_time_s: f64,
        sensor_stuck_band_c: f64,
        sensor_stuck_energy_s: f64,
        no_rise_time_s: f64,
        sensor_max_rate_c_per_s: f64,
        runaway_hysteresis_c: f64,
        runaway_max_error: f64,
        runaway_gain_time_s: f64,
        runaway_heating_gain_c: f64,
        stuck_on_rise_c: f64,
        stuck_on_time_s: f64,
        autotune_max_overshoot_c: f64,
        autotune_timeout_s: f64,
        autotune_extend_s: f64,
        autotune_margin_c: f64,
        model_gain_c_per_pct: f64,
        model_tau_s: f64,
        model_dead_time_s: f64,
        model_ambient_c: f64,
        model_sensor_tau_s: f64,
        feedforward_topic: String,
        feedforward_timeout_ms: i64,
        ambient_topic: String,
        ambient_timeout_ms: i64,
        setpoint_ramp_c_per_s: f64,
        model_tolerance_c: f64,
        model_time_s: f64,
        active_low: bool,
        enable: bool,
        duty: f64,
        gpio_chip: String,
        gpio_line: i64,
    }
}

typed_settings! {
    /// Every parameter of one valve (`NAME.*`), typed. `Default` gives zero values: the
    /// declared defaults are the table's, set by the store.
    ValveValues {
        travel_open_ms: i64,
        travel_close_ms: i64,
        deadband_pct: f64,
        min_pulse_ms: i64,
        reversal_pause_ms: i64,
        start_lag_ms: i64,
        backlash_pct: f64,
        end_overrun_pct: f64,
        reference_at_start: String,
        recalibrate_after_s: i64,
        exercise_every_h: i64,
        max_uncertainty_pct: f64,
        command_timeout_ms: i64,
        on_timeout: String,
        feedback_topic: String,
        feedback_tolerance_pct: f64,
        max_starts_per_h: i64,
        control: String,
        process_topic: String,
        process_type: String,
        loop_output: String,
        pid_kp: f64,
        pid_ki: f64,
        pid_kd: f64,
        pid_d_filter_s: f64,
        pid_reverse: bool,
        pid_sample_ms: i64,
        process_timeout_ms: i64,
        process_max_skew_ms: i64,
        safe_position_pct: f64,
        safe_after_ms: i64,
        open_limit_line: String,
        close_limit_line: String,
        limit_active_low: bool,
        limit_debounce_ms: i64,
    }
}
