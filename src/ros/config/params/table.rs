//! The one table of the node's parameters. Every node, channel and valve parameter is declared
//! here once: the typed field that holds its value (in [`NodeValues`], [`ChannelValues`] or
//! [`ValveValues`], as generate_parameter_library's YAML names a field of its generated
//! struct; the parameter's name and type are the field's), default, range, whether it is
//! read-only, its description with units, what its special values mean, its accepted
//! spellings, and — for a channel parameter — how it maps into the core's [`ChannelParams`]
//! and from the `pwm_actuator_msgs/ChannelParams` message. The parameter services'
//! declarations and descriptors, the validation messages, the message mapping and the
//! parameter page `docs/parameters.md` (generated, compared by a test) all derive from it.
//!
//! Defaults and limits of the channel settings come from the core (`ChannelParams::default()`,
//! `MAX_PERIOD_MS`, `MAX_TIMEOUT_MS`), so none is written twice.

use super::settings::{ChannelValues, NodeSettings, NodeValues, Value, ValveValues};
use super::{ParamType, Range, DEFAULT_CHANNELS, MAX_CHANNELS, MAX_STATUS_RATE_HZ};
use super::{ParameterValue as V, MIN_STATUS_RATE_HZ};
use super::{DEFAULT_COMMAND_HZ_TOLERANCE, DEFAULT_COMMAND_HZ_WINDOW};
use super::{MAX_COMMAND_HZ_WINDOW, MAX_EXPECTED_COMMAND_HZ};
use super::{MAX_HEARTBEAT_HZ, MIN_HEARTBEAT_HZ};
use crate::core::config::{
    ShortStr, UnknownName, MAX_AVG_WINDOW_S, MAX_EXTEND_FACTOR, MAX_ON_MS, MAX_PERIOD_MS,
    MAX_SLEW_PCT_PER_S, MAX_TIMEOUT_MS,
};
use crate::core::heater::{
    Control, HeaterParams, MAX_DELTA_C, MAX_GAIN, MAX_MODEL_DEAD_TIME_S, MAX_MODEL_GAIN,
    MAX_RAMP_C_PER_S, MAX_RATE_C_PER_S, MAX_RUNAWAY_ERROR, MAX_SKEW_MS, MAX_TEMP_C, MAX_TIME_S,
    MIN_TEMP_C,
};
use crate::core::valve::control::{
    MAX_D_FILTER_S, MAX_LOOP_GAIN, MAX_LOOP_SAMPLE_MS, MAX_PROCESS_SKEW_MS, MAX_PROCESS_TIMEOUT_MS,
    MIN_LOOP_SAMPLE_MS,
};
use crate::core::valve::{
    Control as ValveControl, ControlParams, LoopOutput, OnTimeout, ReferenceAtStart, ValveParams,
    MAX_BACKLASH_PCT, MAX_COMMAND_TIMEOUT_MS, MAX_DEADBAND_PCT, MAX_END_OVERRUN_PCT,
    MAX_EXERCISE_EVERY_H, MAX_FEEDBACK_TOLERANCE_PCT, MAX_RECALIBRATE_AFTER_S,
    MAX_REVERSAL_PAUSE_MS, MAX_STARTS_PER_H, MAX_TRAVEL_MS, MIN_REVERSAL_PAUSE_MS, MIN_TRAVEL_MS,
};
use crate::core::{ApplyAt, ChannelParams, OnDisable, OutputKind, Phase, Profile, ShortPulse};
use crate::output::gpio::parse_line_addr;
use crate::output::gpio_input::MAX_DEBOUNCE_MS;
use crate::output::trace_files::{DEFAULT_TRACE_MAX_MB, MAX_TRACE_MAX_MB, MIN_TRACE_MAX_MB};
use crate::ros::interface::msg;
use std::str::FromStr;

/// Who decides about a value's range.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Checked {
    /// The advertised range is checked here.
    Range,
    /// 0, or a value in `min..=` the advertised maximum (a rate: 0 is "off").
    OffOr(f64),
    /// The core's validation gives the verdict (its messages are more precise); only values
    /// the core cannot represent (negative times) are refused here.
    Core,
}

/// Writes a parameter's value into the core's settings; an unknown spelling is refused.
pub(super) type ToCore = fn(&mut ChannelParams, &V) -> Result<(), UnknownName>;

/// Reads a parameter's value from the `ChannelParams` message.
pub(super) type FromMsg = fn(&msg::ChannelParams) -> V;

/// Accepts or refuses a string parameter's spelling.
pub(super) type Choices = fn(&str) -> Result<(), UnknownName>;

/// A parameter's typed field in the settings of type `S`: its name, its declared type (the
/// field's), and how its value is read and written.
pub(super) struct Field<S> {
    pub name: &'static str,
    pub ptype: ParamType,
    pub get: fn(&S) -> V,
    pub set: fn(&mut S, &V),
}

impl<S> Clone for Field<S> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<S> Copy for Field<S> {}

impl<S> std::fmt::Debug for Field<S> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name)
    }
}

/// Where a parameter's value lives: the field of the node's, a channel's or a valve's
/// settings.
#[derive(Debug, Clone, Copy)]
pub(super) enum Access {
    /// A field of [`NodeValues`].
    Node(Field<NodeValues>),
    /// A field of each channel's [`ChannelValues`].
    Channel(Field<ChannelValues>),
    /// A field of each valve's [`ValveValues`].
    Valve(Field<ValveValues>),
}

impl Access {
    fn name(self) -> &'static str {
        match self {
            Access::Node(f) => f.name,
            Access::Channel(f) => f.name,
            Access::Valve(f) => f.name,
        }
    }

    fn ptype(self) -> ParamType {
        match self {
            Access::Node(f) => f.ptype,
            Access::Channel(f) => f.ptype,
            Access::Valve(f) => f.ptype,
        }
    }
}

/// The declared type of a field, from its Rust type.
pub(super) fn type_of<S, T: Value>(_: fn(&S) -> &T) -> ParamType {
    T::TYPE
}

/// The [`Access`] of field `$field` of the node's (`node`), a channel's (`channel`) or a
/// valve's (`valve`) settings: the parameter's name is the field's, its type the field's.
macro_rules! field {
    (node, $field:ident) => {
        Access::Node(field!(@ NodeValues, $field))
    };
    (channel, $field:ident) => {
        Access::Channel(field!(@ ChannelValues, $field))
    };
    (valve, $field:ident) => {
        Access::Valve(field!(@ ValveValues, $field))
    };
    (@ $settings:ty, $field:ident) => {
        Field::<$settings> {
            name: stringify!($field),
            ptype: type_of(|s: &$settings| &s.$field),
            get: |s| Value::to_value(&s.$field),
            set: |s, v| s.$field = Value::from_value(v),
        }
    };
}

/// One parameter (for a channel parameter, without its `pwNN.` prefix).
pub(super) struct Decl {
    pub suffix: &'static str,
    pub ptype: ParamType,
    /// The typed field that holds its value.
    pub access: Access,
    pub default: fn() -> V,
    /// What it is, with its unit.
    pub description: &'static str,
    /// Rules the range cannot express (sent as `additional_constraints`).
    pub constraints: &'static str,
    /// `Some(why)`: set only at start-up.
    pub read_only: Option<&'static str>,
    pub range: Range,
    pub checked: Checked,
    /// What special values mean, for refusal messages (` (-1 = ...)`), or empty.
    pub note: &'static str,
    /// The accepted spellings of a string parameter.
    pub choices: Option<Choices>,
    /// Channel parameters of the core's settings: how the value maps into them.
    pub core: Option<ToCore>,
    /// Channel parameters exposed on `~/<ch>/params`: the message field of the same name.
    pub msg: Option<FromMsg>,
    /// Node parameters: how the value maps into the [`NodeSettings`].
    pub node: Option<ToNode>,
}

/// Maps a node parameter's (checked) value into the node's settings.
pub(super) type ToNode = fn(&mut NodeSettings, &V);

/// Why a start-up-only parameter cannot change while running.
const START_UP: &str = "it is read at start-up only; restart the node to change it";

impl Decl {
    fn new(access: Access, default: fn() -> V) -> Decl {
        Decl {
            suffix: access.name(),
            ptype: access.ptype(),
            access,
            default,
            description: "",
            constraints: "",
            read_only: None,
            range: Range::Unbounded,
            checked: Checked::Range,
            note: "",
            choices: None,
            core: None,
            msg: None,
            node: None,
        }
    }
}

/// Accepts the spellings of `T` (an empty string too when `empty` means "as the profile says").
fn spelled<T: FromStr<Err = UnknownName>>(s: &str, empty: bool) -> Result<(), UnknownName> {
    if empty && s.is_empty() {
        Ok(())
    } else {
        s.parse::<T>().map(drop)
    }
}

fn text(v: &V) -> &str {
    match v {
        V::String(s) => s,
        _ => "",
    }
}

fn int(v: &V) -> i64 {
    match v {
        V::Integer(i) => *i,
        _ => 0,
    }
}

/// A time in ms; negative values were refused by the range checks, `max(0)` guards the cast.
fn ms(v: &V) -> u64 {
    count(int(v))
}

/// An optional policy: empty means "as the profile says".
fn policy<T: FromStr<Err = UnknownName>>(v: &V) -> Result<Option<T>, UnknownName> {
    match text(v) {
        "" => Ok(None),
        s => s.parse().map(Some),
    }
}

fn boolean(v: &V) -> bool {
    matches!(v, V::Boolean(true))
}

fn double(v: &V) -> f64 {
    match v {
        V::Double(x) => *x,
        _ => 0.0,
    }
}

fn core_defaults() -> ChannelParams {
    ChannelParams::default()
}

fn heater_defaults() -> HeaterParams {
    HeaterParams::default()
}

fn valve_defaults() -> ValveParams {
    ValveParams::default()
}

/// Default debounce of the end switch lines, ms: longer than the bounce of common snap-action
/// switches (1..5 ms), short beside any travel time.
pub const DEFAULT_LIMIT_DEBOUNCE_MS: u64 = 5;

/// Accepts an empty limit line or `[CHIP:]OFFSET`.
fn limit_line_spelling(s: &str) -> Result<(), UnknownName> {
    match s.trim() {
        "" => Ok(()),
        t if parse_line_addr(t).is_some() => Ok(()),
        t => Err(UnknownName {
            value: ShortStr::new(t),
            accepted: "empty or [CHIP:]OFFSET (e.g. 5, gpiochip1:5)",
        }),
    }
}

/// Accepts the spellings of a valve's `process_type`.
fn process_type_spelling(s: &str) -> Result<(), UnknownName> {
    match s {
        "temperature" | "float64" => Ok(()),
        _ => Err(UnknownName {
            value: ShortStr::new(s),
            accepted: "temperature|float64",
        }),
    }
}

/// Why a valve's end switch settings, feedback, backlash and reference at start cannot change
/// while running.
const VALVE_START_UP: &str = "the end switch lines and the feedback are requested, and the \
                              reference at start runs, at start-up; restart the node";

/// Why a valve's process value topic and type cannot change while running.
const VALVE_PROCESS: &str =
    "the process value topic and its type are fixed at start-up; restart the node";

/// Why a valve's travel times cannot change while running.
const VALVE_TRAVEL: &str = "the position estimate and the moves under way count in the travel \
                            times; restart the node (it references the valve) to change them";

/// The parameters of each valve `NAME` (declared as `NAME.<suffix>` for every valve of the
/// `valve` parameter). The motion settings change while running (checked whole, as a
/// channel's); the travel times, the end switches and the reference at start are read at
/// start-up. The vendor practice behind each is in docs/valve.md.
pub(super) fn valve_decls() -> Vec<Decl> {
    let travel = Range::Integer(MIN_TRAVEL_MS as i64, MAX_TRAVEL_MS as i64);
    vec![
        Decl {
            description: "Travel time from fully closed to fully open, ms (Siemens PID_3Step \
                          TransitTime, OSCAT ACTUATOR_3P T_RUN).",
            range: travel,
            read_only: Some(VALVE_TRAVEL),
            ..Decl::new(field!(valve, travel_open_ms), || {
                V::Integer(valve_defaults().travel_open_ms as i64)
            })
        },
        Decl {
            description: "Travel time from fully open to fully closed, ms (Beckhoff \
                          FB_BA_Anlg3Pnt keeps the two apart).",
            range: travel,
            read_only: Some(VALVE_TRAVEL),
            ..Decl::new(field!(valve, travel_close_ms), || {
                V::Integer(valve_defaults().travel_close_ms as i64)
            })
        },
        Decl {
            description: "Dead band, percent of the stroke: no move while target and estimate \
                          differ by less than this either way (a half width: Beckhoff's fHys is \
                          the full width, fHys/2 either way, so deadband_pct = fHys/2).",
            range: Range::Double(0.0, MAX_DEADBAND_PCT),
            ..Decl::new(field!(valve, deadband_pct), || {
                V::Double(valve_defaults().deadband_pct)
            })
        },
        Decl {
            description: "Minimum pulse, ms: a shorter move is accumulated until it reaches \
                          this, a started move lasts at least this (Schneider SERVO).",
            constraints: "at most the shorter travel time",
            range: Range::Integer(0, MAX_TRAVEL_MS as i64),
            checked: Checked::Core,
            ..Decl::new(field!(valve, min_pulse_ms), || {
                V::Integer(valve_defaults().min_pulse_ms as i64)
            })
        },
        Decl {
            description: "Reversal pause, ms: both lines are low at least this long, counted \
                          from the real fall (and from start-up), before a line rises. At \
                          least 20: a relay releases in up to 10 ms and a triac conducts to the \
                          next current zero (up to 10 ms at 50 Hz).",
            range: Range::Integer(MIN_REVERSAL_PAUSE_MS as i64, MAX_REVERSAL_PAUSE_MS as i64),
            checked: Checked::Core,
            ..Decl::new(field!(valve, reversal_pause_ms), || {
                V::Integer(valve_defaults().reversal_pause_ms as i64)
            })
        },
        Decl {
            description: "Start lag, ms: from a line's rise until the motor moves the valve. \
                          Every drive lasts this much longer than its displacement needs, and \
                          the estimate counts only the drive after it; its tolerance (half of \
                          it plus 20 ms) goes into the uncertainty.",
            constraints: "at most 10 % of the shorter travel time",
            range: Range::Integer(0, MAX_TRAVEL_MS as i64 / 10),
            checked: Checked::Core,
            ..Decl::new(field!(valve, start_lag_ms), || {
                V::Integer(valve_defaults().start_lag_ms as i64)
            })
        },
        Decl {
            description: "Backlash, percent of the stroke: the play between motor and stem; \
                          after a reversal the motor turns this far before the valve follows. \
                          It goes into the uncertainty, and the estimate sits in the middle of \
                          the play.",
            range: Range::Double(0.0, MAX_BACKLASH_PCT),
            read_only: Some(VALVE_START_UP),
            ..Decl::new(field!(valve, backlash_pct), || {
                V::Double(valve_defaults().backlash_pct)
            })
        },
        Decl {
            description: "Overrun at an end, percent of the travel time: a move to 0 % or \
                          100 % drives past the end from the farthest position the \
                          uncertainty allows (at the slowest travel time), and then this much \
                          longer (OSCAT ACTUATOR_3P); 150 % of the travel time at most.",
            range: Range::Double(0.0, MAX_END_OVERRUN_PCT),
            ..Decl::new(field!(valve, end_overrun_pct), || {
                V::Double(valve_defaults().end_overrun_pct)
            })
        },
        Decl {
            description: "How the valve finds its position at start: close (drive closed for \
                          150 % of the travel time and take 0 %, Siemens PID_3Step's virtual \
                          actuator limit), open (the same towards open), skip_if_restored (no \
                          stroke when the state file gave the position, close otherwise), none \
                          (the restored position, or unreferenced until an end is reached).",
            choices: Some(|s| spelled::<ReferenceAtStart>(s, false)),
            read_only: Some(VALVE_START_UP),
            ..Decl::new(field!(valve, reference_at_start), || {
                V::String(valve_defaults().reference_at_start.as_str().to_string())
            })
        },
        Decl {
            description: "Recalibration: once this much run time has accumulated since the \
                          last reference, or the uncertainty passed half of \
                          max_uncertainty_pct, the next command within 5 % of an end goes to \
                          that end first, s (OSCAT T_CAL). A move that would take the \
                          uncertainty past max_uncertainty_pct goes through the nearer end \
                          whatever the target. 0: by the uncertainty only.",
            range: Range::Integer(0, MAX_RECALIBRATE_AFTER_S as i64),
            ..Decl::new(field!(valve, recalibrate_after_s), || {
                V::Integer(valve_defaults().recalibrate_after_s as i64)
            })
        },
        Decl {
            description: "Exercise stroke: a valve idle this long closes fully, opens fully and \
                          returns, one valve at a time, h (OSCAT T_DIAG, ACTUATOR_2P \
                          self-activation). 0: never.",
            range: Range::Integer(0, MAX_EXERCISE_EVERY_H as i64),
            ..Decl::new(field!(valve, exercise_every_h), || {
                V::Integer(valve_defaults().exercise_every_h as i64)
            })
        },
        Decl {
            description: "Diagnostics warn above this uncertainty of the position estimate, \
                          percent (the travel 10 % off, the start lag off by its tolerance and \
                          the backlash, over every drive since the last reference); a move that \
                          would pass it recalibrates first.",
            range: Range::Double(0.0, 100.0),
            ..Decl::new(field!(valve, max_uncertainty_pct), || {
                V::Double(valve_defaults().max_uncertainty_pct)
            })
        },
        Decl {
            description: "Command timeout, ms: no position command for this long triggers \
                          on_timeout. 0: off.",
            range: Range::Integer(0, MAX_COMMAND_TIMEOUT_MS as i64),
            ..Decl::new(field!(valve, command_timeout_ms), || {
                V::Integer(valve_defaults().command_timeout_ms as i64)
            })
        },
        Decl {
            description: "What a command timeout does: stop (where it is), close or open.",
            choices: Some(|s| spelled::<OnTimeout>(s, false)),
            ..Decl::new(field!(valve, on_timeout), || {
                V::String(valve_defaults().on_timeout.as_str().to_string())
            })
        },
        Decl {
            description: "Position feedback topic (std_msgs/Float64, percent, 0 = closed: a \
                          potentiometer or 0-10 V input read by another node, PID_3Step's \
                          Feedback_PER). With it the estimate is corrected at rest, a drive that \
                          does not move it is motor_stalled, and the travel times are measured. \
                          Empty: none.",
            read_only: Some(VALVE_START_UP),
            ..Decl::new(field!(valve, feedback_topic), || {
                V::String(std::string::String::new())
            })
        },
        Decl {
            description: "Accuracy of the position feedback, percent of the stroke: at rest the \
                          position lies within this of the feedback.",
            range: Range::Double(0.0, MAX_FEEDBACK_TOLERANCE_PCT),
            ..Decl::new(field!(valve, feedback_tolerance_pct), || {
                V::Double(valve_defaults().feedback_tolerance_pct)
            })
        },
        Decl {
            description: "The motor's budget of starts per hour (the actuator's duty class, IEC \
                          60034-1 S4; modulating actuators are commonly rated 1200). Tracking \
                          starts are paced by it: while it runs low the dead band in force \
                          widens, so small corrections wait and add up (Schneider SERVO), and no \
                          hour holds more starts. The reference, the exercise stroke and the \
                          command timeout's end move are never held back, only counted. 0: no \
                          budget.",
            range: Range::Integer(0, MAX_STARTS_PER_H as i64),
            ..Decl::new(field!(valve, max_starts_per_h), || {
                V::Integer(valve_defaults().max_starts_per_h as i64)
            })
        },
        Decl {
            description: "Who sets the valve's target: position (the position commands on \
                          ~/valve/NAME/position) or pid (the valve's own loop, Siemens \
                          PID_3Step: from the process value on process_topic to the setpoint \
                          on ~/valve/NAME/setpoint).",
            constraints: "pid needs a process_topic and pid_kp or pid_ki above 0",
            choices: Some(|s| spelled::<ValveControl>(s, false)),
            ..Decl::new(field!(valve, control), || {
                V::String(valve_defaults().control.control.as_str().to_string())
            })
        },
        Decl {
            description: "The loop's process value topic: sensor_msgs/Temperature (°C) or \
                          std_msgs/Float64 (a pressure or a flow in its unit), as process_type \
                          says. Empty: none (control pid is refused).",
            read_only: Some(VALVE_PROCESS),
            ..Decl::new(field!(valve, process_topic), || {
                V::String(std::string::String::new())
            })
        },
        Decl {
            description: "The message type of process_topic: temperature (sensor_msgs/\
                          Temperature, whose stamp gives the reading's age) or float64 \
                          (std_msgs/Float64, aged from its arrival).",
            constraints: "temperature|float64",
            choices: Some(process_type_spelling),
            read_only: Some(VALVE_PROCESS),
            ..Decl::new(field!(valve, process_type), || {
                V::String("temperature".into())
            })
        },
        Decl {
            description: "What the loop's output drives: position (the valve's target; the \
                          estimate must be good), step (step pulses, PID_3Step without position \
                          feedback) or auto (position with a feedback_topic, step without).",
            choices: Some(|s| spelled::<LoopOutput>(s, false)),
            ..Decl::new(field!(valve, loop_output), || {
                V::String(valve_defaults().control.output.as_str().to_string())
            })
        },
        Decl {
            description: "The loop's proportional gain, % of the stroke per unit of the process \
                          value.",
            range: Range::Double(0.0, MAX_LOOP_GAIN),
            ..Decl::new(field!(valve, pid_kp), || {
                V::Double(valve_defaults().control.pid_kp)
            })
        },
        Decl {
            description: "The loop's integral gain, % per unit·s.",
            range: Range::Double(0.0, MAX_LOOP_GAIN),
            ..Decl::new(field!(valve, pid_ki), || {
                V::Double(valve_defaults().control.pid_ki)
            })
        },
        Decl {
            description: "The loop's derivative gain, % per unit/s, on the measurement.",
            range: Range::Double(0.0, MAX_LOOP_GAIN),
            ..Decl::new(field!(valve, pid_kd), || {
                V::Double(valve_defaults().control.pid_kd)
            })
        },
        Decl {
            description: "The derivative's first-order filter, s. 0: unfiltered.",
            range: Range::Double(0.0, MAX_D_FILTER_S),
            ..Decl::new(field!(valve, pid_d_filter_s), || {
                V::Double(valve_defaults().control.pid_d_filter_s)
            })
        },
        Decl {
            description: "Reverse acting: opening the valve lowers the process value (a \
                          cooling valve).",
            ..Decl::new(field!(valve, pid_reverse), || {
                V::Boolean(valve_defaults().control.pid_reverse)
            })
        },
        Decl {
            description: "The loop's sample, ms.",
            range: Range::Integer(MIN_LOOP_SAMPLE_MS as i64, MAX_LOOP_SAMPLE_MS as i64),
            ..Decl::new(field!(valve, pid_sample_ms), || {
                V::Integer(valve_defaults().control.pid_sample_ms as i64)
            })
        },
        Decl {
            description: "The process value's freshness, ms: a reading older than this on \
                          arrival is stale and used by nothing; with no fresh reading for this \
                          long the loop stops and the valve holds where it is (WARN).",
            range: Range::Integer(1, MAX_PROCESS_TIMEOUT_MS as i64),
            ..Decl::new(field!(valve, process_timeout_ms), || {
                V::Integer(valve_defaults().control.process_timeout_ms as i64)
            })
        },
        Decl {
            description: "How far a reading's stamp may lie ahead of this node's clock, ms; \
                          beyond it the reading is stale.",
            range: Range::Integer(0, MAX_PROCESS_SKEW_MS as i64),
            ..Decl::new(field!(valve, process_max_skew_ms), || {
                V::Integer(valve_defaults().control.process_max_skew_ms as i64)
            })
        },
        Decl {
            description: "Where the valve goes, percent, once the loop has held for \
                          safe_after_ms without a fresh process value. Negative: nowhere (it \
                          holds).",
            range: Range::Double(-1.0, 100.0),
            ..Decl::new(field!(valve, safe_position_pct), || {
                V::Double(valve_defaults().control.safe_position_pct)
            })
        },
        Decl {
            description: "How long the loop holds before the valve goes to safe_position_pct, \
                          ms.",
            range: Range::Integer(0, MAX_PROCESS_TIMEOUT_MS as i64),
            ..Decl::new(field!(valve, safe_after_ms), || {
                V::Integer(valve_defaults().control.safe_after_ms as i64)
            })
        },
        Decl {
            description: "End switch at the open end: a GPIO input line [CHIP:]OFFSET (a bare \
                          offset, quoted to stay a string, is on /dev/gpiochip0), read with \
                          edge events. Active, it \
                          stops the opening drive at once and sets the position to 100 %. \
                          Empty: none.",
            constraints: "output gpio only; not an output line of the node, not another \
                          switch's line",
            choices: Some(limit_line_spelling),
            read_only: Some(VALVE_START_UP),
            ..Decl::new(field!(valve, open_limit_line), || {
                V::String(std::string::String::new())
            })
        },
        Decl {
            description: "End switch at the closed end, as open_limit_line: active, it stops \
                          the closing drive at once and sets the position to 0 % (referenced).",
            constraints: "output gpio only; not an output line of the node, not another \
                          switch's line",
            choices: Some(limit_line_spelling),
            read_only: Some(VALVE_START_UP),
            ..Decl::new(field!(valve, close_limit_line), || {
                V::String(std::string::String::new())
            })
        },
        Decl {
            description: "Both end switches are active with their line electrically low \
                          (normally closed contacts to ground with a pull-up).",
            read_only: Some(VALVE_START_UP),
            ..Decl::new(field!(valve, limit_active_low), || V::Boolean(false))
        },
        Decl {
            description: "Debounce period of the end switch lines, ms (the kernel's: the chip's \
                          own, or the GPIO character device's in software); a change is \
                          reported once the line has been stable this long. 0: none.",
            range: Range::Integer(0, MAX_DEBOUNCE_MS as i64),
            read_only: Some(VALVE_START_UP),
            ..Decl::new(field!(valve, limit_debounce_ms), || {
                V::Integer(DEFAULT_LIMIT_DEBOUNCE_MS as i64)
            })
        },
    ]
}

/// A valve's settings from its parameters' values; an unknown spelling falls back to the
/// default (the store refused it already).
pub(super) fn valve_params(v: &ValveValues) -> ValveParams {
    let d = valve_defaults();
    ValveParams {
        travel_open_ms: count(v.travel_open_ms),
        travel_close_ms: count(v.travel_close_ms),
        deadband_pct: v.deadband_pct,
        min_pulse_ms: count(v.min_pulse_ms),
        reversal_pause_ms: count(v.reversal_pause_ms),
        start_lag_ms: count(v.start_lag_ms),
        backlash_pct: v.backlash_pct,
        end_overrun_pct: v.end_overrun_pct,
        reference_at_start: v.reference_at_start.parse().unwrap_or(d.reference_at_start),
        recalibrate_after_s: count(v.recalibrate_after_s),
        exercise_every_h: count(v.exercise_every_h),
        max_uncertainty_pct: v.max_uncertainty_pct,
        command_timeout_ms: count(v.command_timeout_ms),
        on_timeout: v.on_timeout.parse().unwrap_or(d.on_timeout),
        feedback_tolerance_pct: v.feedback_tolerance_pct,
        max_starts_per_h: count(v.max_starts_per_h),
        control: ControlParams {
            control: v.control.parse().unwrap_or(d.control.control),
            process: !v.process_topic.trim().is_empty(),
            output: v.loop_output.parse().unwrap_or(d.control.output),
            pid_kp: v.pid_kp,
            pid_ki: v.pid_ki,
            pid_kd: v.pid_kd,
            pid_d_filter_s: v.pid_d_filter_s,
            pid_reverse: v.pid_reverse,
            pid_sample_ms: count(v.pid_sample_ms),
            process_timeout_ms: count(v.process_timeout_ms),
            process_max_skew_ms: count(v.process_max_skew_ms),
            safe_position_pct: v.safe_position_pct,
            safe_after_ms: count(v.safe_after_ms),
        },
    }
}

/// A count or a time in ms; negative values were refused by the range checks, `max(0)` guards
/// the cast.
pub(super) fn count(i: i64) -> u64 {
    i.max(0) as u64
}

/// The node's settings from its parameters' values, each mapped by its entry in the table.
pub(super) fn node_settings(values: &NodeValues) -> NodeSettings {
    let mut n = NodeSettings::default();
    for d in node_decls() {
        if let (Some(to_node), Access::Node(f)) = (d.node, d.access) {
            to_node(&mut n, &(f.get)(values));
        }
    }
    n
}

/// A channel's settings as the core's [`ChannelParams`], each value mapped by its entry in
/// the table; `Err` names the parameter whose spelling the core does not know.
pub(super) fn channel_params(
    values: &ChannelValues,
) -> Result<ChannelParams, (&'static str, UnknownName)> {
    let mut params = ChannelParams::default();
    for d in channel_decls() {
        if let (Some(to_core), Access::Channel(f)) = (d.core, d.access) {
            to_core(&mut params, &(f.get)(values)).map_err(|e| (d.suffix, e))?;
        }
    }
    Ok(params)
}

/// The node-level parameters.
pub(super) fn node_decls() -> Vec<Decl> {
    vec![
        Decl {
            description: "Number of PWM channels, named pw01, pw02, ...",
            read_only: Some(START_UP),
            range: Range::Integer(1, MAX_CHANNELS as i64),
            node: Some(|n, v| n.channels = int(v).max(0) as usize),
            ..Decl::new(field!(node, channels), || {
                V::Integer(DEFAULT_CHANNELS as i64)
            })
        },
        Decl {
            description: "Output backend: sim (simulated sink, optional trace) or gpio (Linux \
                          GPIO character device, one line per channel).",
            constraints: "sim|gpio",
            read_only: Some(START_UP),
            choices: Some(|s| match s {
                "sim" | "gpio" => Ok(()),
                _ => Err(UnknownName {
                    value: ShortStr::new(s),
                    accepted: "sim|gpio",
                }),
            }),
            node: Some(|n, v| n.gpio = text(v) == "gpio"),
            ..Decl::new(field!(node, output), || V::String("sim".into()))
        },
        Decl {
            description: "A managed (lifecycle) node: the lines are requested on configure, \
                          follow their channels only while ACTIVE, and are released on cleanup \
                          and shutdown; ~/change_state and the other lifecycle services.",
            constraints: "start-up only (--managed)",
            read_only: Some(START_UP),
            node: Some(|n, v| n.managed = boolean(v)),
            ..Decl::new(field!(node, managed), || V::Boolean(false))
        },
        Decl {
            description: "Trace file(s), comma-separated: .vcd and .csv hold what is written \
                          to the lines (any output); .mcap holds every edge, status and \
                          /diagnostics message as ROS 2 messages. Empty: no trace.",
            constraints: "start-up only",
            read_only: Some(START_UP),
            node: Some(|n, v| {
                n.trace = text(v)
                    .split(',')
                    .map(str::trim)
                    .filter(|s| !s.is_empty())
                    .map(std::path::PathBuf::from)
                    .collect()
            }),
            ..Decl::new(
                field!(node, trace),
                || V::String(std::string::String::new()),
            )
        },
        Decl {
            description: "What the files of each trace may hold together, MB (10^6 bytes): \
                          at a quarter of it the file written is closed, the older ones move \
                          one number up (run.csv becomes run.1.csv, ...) and the oldest of \
                          four is deleted and counted on /diagnostics. Pipes and devices are \
                          not limited.",
            constraints: "start-up only",
            read_only: Some(START_UP),
            range: Range::Integer(MIN_TRACE_MAX_MB as i64, MAX_TRACE_MAX_MB as i64),
            node: Some(|n, v| n.trace_max_mb = int(v).max(0) as u64),
            ..Decl::new(field!(node, trace_max_mb), || {
                V::Integer(DEFAULT_TRACE_MAX_MB as i64)
            })
        },
        Decl {
            description: "Rate of the periodic ~/<ch>/status messages, Hz (they are also sent \
                          on every change: each edge, command and parameter; 1 Hz keeps \
                          002's whole-second countdowns current). 0: on change only.",
            constraints: "0, or 0.01..1000",
            range: Range::Double(0.0, MAX_STATUS_RATE_HZ),
            checked: Checked::OffOr(MIN_STATUS_RATE_HZ),
            note: " (0 = on change only)",
            node: Some(|n, v| n.status_rate_hz = double(v)),
            ..Decl::new(field!(node, status_rate_hz), || V::Double(1.0))
        },
        Decl {
            description: "Console lines per second and channel showing edges (info level, \
                          also on /rosout); edges beyond are summarised once a second. 0: no \
                          edge lines, the default, so that an always-on node's log and \
                          /rosout carry events rather than every pulse (`--demo` sets 10; \
                          the edges are on ~/<ch>/edges and in the traces either way).",
            range: Range::Integer(0, 1000),
            node: Some(|n, v| n.edge_log_rate = int(v).clamp(0, 1000) as u32),
            ..Decl::new(field!(node, edge_log_rate), || V::Integer(0))
        },
        Decl {
            description: "How the channels' periods lie against each other. sync: each \
                          channel's periods start at its enable. stagger: channels of equal \
                          period share a grid of whole periods and lay their on phases end to \
                          end in channel order; no two lines of equal period are ever on \
                          together (a pulse that would be waits, or is skipped with E1), and \
                          with the duties summing to at most 100 % none has to.",
            constraints: "sync|stagger; takes effect at each channel's next period start (a \
                          channel joining the grid waits, off, for its next instant)",
            choices: Some(|s| spelled::<Phase>(s, false)),
            node: Some(|n, v| n.set_phase(text(v))),
            ..Decl::new(field!(node, phase), || {
                V::String(Phase::Sync.as_str().into())
            })
        },
        Decl {
            description: "At most this many lines on at once, over all channels: an on phase \
                          without a free slot waits, off, with its whole length and within \
                          its period (the break after it shrinks), and is skipped and reported \
                          (E1) when it can no longer fit. Never shortens a pulse or break below \
                          its minimum. 0: no limit.",
            constraints: "a lowered limit takes effect at once: the latest-started pulses \
                          end as soon as their minimum on time allows (E1)",
            range: Range::Integer(0, MAX_CHANNELS as i64),
            note: " (0 = no limit)",
            node: Some(|n, v| n.bank.max_on = int(v).max(0) as usize),
            ..Decl::new(field!(node, max_simultaneous_on), || V::Integer(0))
        },
        Decl {
            description: "Window of the command-rate check on /diagnostics (`<node>: <ch> \
                          command frequency`), in diagnostics runs, one a second: the rate is \
                          the commands of the last this-many seconds over their duration \
                          (diagnostic_updater's FrequencyStatus window_size).",
            constraints: "a change starts a new, empty window",
            range: Range::Integer(1, MAX_COMMAND_HZ_WINDOW as i64),
            node: Some(|n, v| n.command_hz_window = int(v).max(1) as usize),
            ..Decl::new(field!(node, command_hz_window), || {
                V::Integer(DEFAULT_COMMAND_HZ_WINDOW as i64)
            })
        },
        Decl {
            description: "Tolerance of the command-rate check, a fraction: rates from \
                          expected_command_hz_min * (1 - tolerance) to expected_command_hz_max \
                          * (1 + tolerance) are met (diagnostic_updater's FrequencyStatus \
                          tolerance).",
            range: Range::Double(0.0, 1.0),
            node: Some(|n, v| n.command_hz_tolerance = double(v)),
            ..Decl::new(field!(node, command_hz_tolerance), || {
                V::Double(DEFAULT_COMMAND_HZ_TOLERANCE)
            })
        },
        Decl {
            description: "Split-range pairs (001), comma-separated NAME:HOT:COLD[:DEADBAND_PCT]: \
                          ~/split/NAME/command (std_msgs/Float64, -100..100 %) drives HOT when \
                          positive and COLD when negative; the two lines are never high \
                          together. Empty: none.",
            constraints: "each channel in one pair at most",
            read_only: Some(START_UP),
            node: Some(|n, v| n.split = text(v).to_string()),
            ..Decl::new(
                field!(node, split),
                || V::String(std::string::String::new()),
            )
        },
        Decl {
            description: "Three-point valves, comma-separated NAME:OPEN:CLOSE: channel OPEN \
                          drives the actuator open, CLOSE drives it closed, never both; \
                          ~/valve/NAME/position (std_msgs/Float64, 0..100 %, 0 = closed) sets \
                          the target; the valve's settings are the parameters NAME.* below. \
                          Empty: none.",
            constraints: "each channel in one valve or split pair at most; NAME not a channel's",
            read_only: Some(START_UP),
            node: Some(|n, v| n.valve = text(v).to_string()),
            ..Decl::new(
                field!(node, valve),
                || V::String(std::string::String::new()),
            )
        },
        Decl {
            description: "Directory of the valves' state files (NAME.state): each valve's \
                          position and its bounds, written atomically at every stop and once a \
                          second while it moves, read at start-up (see reference_at_start). \
                          Empty: none, the position is lost at every restart.",
            constraints: "start-up only; an existing, writable directory",
            read_only: Some(START_UP),
            node: Some(|n, v| n.state_dir = text(v).to_string()),
            ..Decl::new(field!(node, state_dir), || {
                V::String(std::string::String::new())
            })
        },
        Decl {
            description: "Heartbeat line: offset on heartbeat_chip (with output sim, a simulated \
                          line named heartbeat). The output thread toggles it at heartbeat_hz \
                          while it runs and stops on an output fault, a stop or a hang (the line \
                          then rests inactive, or where it was on a kill), for an external \
                          charge pump or watchdog relay that cuts actuator power when the \
                          toggling stops. -1: none.",
            constraints: "start-up only; driven inactive by safe-off too",
            read_only: Some(START_UP),
            range: Range::Integer(-1, u32::MAX as i64),
            node: Some(|n, v| n.heartbeat_line = u32::try_from(int(v)).ok()),
            ..Decl::new(field!(node, heartbeat_line), || V::Integer(-1))
        },
        Decl {
            description: "Chip of the heartbeat line (output gpio).",
            constraints: "start-up only",
            read_only: Some(START_UP),
            node: Some(|n, v| n.heartbeat_chip = text(v).into()),
            ..Decl::new(field!(node, heartbeat_chip), || {
                V::String("/dev/gpiochip0".into())
            })
        },
        Decl {
            description: "Frequency of the heartbeat line's square wave, Hz (two toggles per \
                          period).",
            read_only: Some(START_UP),
            range: Range::Double(MIN_HEARTBEAT_HZ, MAX_HEARTBEAT_HZ),
            node: Some(|n, v| n.heartbeat_hz = double(v)),
            ..Decl::new(field!(node, heartbeat_hz), || V::Double(10.0))
        },
        Decl {
            description: "Heartbeat e-stop, ms: when no false arrives on ~/estop within this \
                          time (from start-up, then from the last false) the e-stop latches, \
                          as for a wireless stop whose silence must stop the machine. 0: off.",
            constraints: "start-up only",
            read_only: Some(START_UP),
            range: Range::Integer(0, MAX_TIMEOUT_MS as i64),
            node: Some(|n, v| n.estop_timeout_ms = ms(v)),
            ..Decl::new(field!(node, estop_timeout_ms), || V::Integer(0))
        },
        Decl {
            description: "SCHED_FIFO priority of the output thread (with mlockall). 0: normal \
                          scheduling.",
            constraints: "needs CAP_SYS_NICE or an rtprio limit; refused cleanly otherwise",
            read_only: Some(START_UP),
            range: Range::Integer(0, 99),
            node: Some(|n, v| {
                n.rt_priority = Some(int(v)).filter(|p| *p > 0).map(|p| p.min(99) as i32)
            }),
            ..Decl::new(field!(node, rt_priority), || V::Integer(0))
        },
        Decl {
            description: "A heater fault of any channel (any check: \
                          temperature_out_of_range, sensor_timeout, sensor_stuck, no_rise, \
                          sensor_jump, not_heating, stuck_on, model_deviation) also latches the \
                          e-stop of every channel; ~/reset_estop releases it.",
            constraints: "start-up only",
            read_only: Some(START_UP),
            node: Some(|n, v| n.heater_fault_latches_estop = boolean(v)),
            ..Decl::new(field!(node, heater_fault_latches_estop), || {
                V::Boolean(false)
            })
        },
        Decl {
            description: "Standard ROS parameter; always false here.",
            constraints: "only false: pulses are timed on CLOCK_MONOTONIC",
            node: Some(|n, v| n.use_sim_time = boolean(v)),
            ..Decl::new(field!(node, use_sim_time), || V::Boolean(false))
        },
    ]
}

/// The parameters of each channel, `pwNN.<suffix>`.
pub(super) fn channel_decls() -> Vec<Decl> {
    vec![
        Decl {
            description: "Period T, ms. 0: no pulses, output held off (000).",
            constraints: "0, or >= 5 (transistor) / >= 100 (relay); takes effect at the next \
                          period boundary",
            range: Range::Integer(0, MAX_PERIOD_MS as i64),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.period_ms = ms(v);
                Ok(())
            }),
            msg: Some(|m| V::Integer(m.period_ms)),
            ..Decl::new(field!(channel, period_ms), || {
                V::Integer(core_defaults().period_ms as i64)
            })
        },
        Decl {
            description: "Minimum on time, ms (ME / T_MINI / nMinSwiTi / P_B_TM). 0: the \
                          hardware floor (0.1 ms transistor, 50 ms relay).",
            constraints: "relay: 0 or >= 50; above period_ms acts as period_ms (every duty \
                          but 0 and 100 % then gives 0 or 1 with E1), except with short_pulse \
                          extend; above one hour refused, except under twincat_ba (002: \
                          limited to the period whatever its size)",
            range: Range::Integer(0, MAX_PERIOD_MS as i64),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.min_on_ms = ms(v);
                Ok(())
            }),
            msg: Some(|m| V::Integer(m.min_on_ms)),
            ..Decl::new(field!(channel, min_on_ms), || {
                V::Integer(core_defaults().min_on_ms as i64)
            })
        },
        Decl {
            description: "Minimum off time, ms. -1: as the profile says (= min_on_ms, except \
                          twincat_ba and schneider_pwm: the hardware floor).",
            constraints: "relay: 0 or >= 50; above period_ms acts as period_ms, except with \
                          short_pulse extend",
            range: Range::Integer(-1, MAX_PERIOD_MS as i64),
            note: " (-1 = as the profile says)",
            core: Some(|c, v| {
                c.min_off_ms = u64::try_from(int(v)).ok();
                Ok(())
            }),
            msg: Some(|m| V::Integer(m.min_off_ms)),
            ..Decl::new(field!(channel, min_off_ms), || {
                V::Integer(core_defaults().min_off_ms.map_or(-1, |v| v as i64))
            })
        },
        Decl {
            description: "Limits of 000's table: transistor (period >= 5 ms, floor 0.1 ms) or \
                          relay (period >= 100 ms, min times >= 50 ms).",
            constraints: "transistor|relay",
            choices: Some(|s| spelled::<OutputKind>(s, false)),
            core: Some(|c, v| {
                c.output_kind = text(v).parse()?;
                Ok(())
            }),
            msg: Some(|m| V::String(m.output_kind.clone())),
            ..Decl::new(field!(channel, output_kind), || {
                V::String(core_defaults().output_kind.as_str().into())
            })
        },
        Decl {
            description: "Policy set of a vendor block: pico_gfx (000), schneider_pwm (001), \
                          twincat_ba (002), tcont_cp (003), frequency_output (004).",
            constraints: "pico_gfx|twincat_ba|tcont_cp|schneider_pwm|frequency_output",
            choices: Some(|s| spelled::<Profile>(s, false)),
            core: Some(|c, v| {
                c.profile = text(v).parse()?;
                Ok(())
            }),
            msg: Some(|m| V::String(m.profile.clone())),
            ..Decl::new(field!(channel, profile), || {
                V::String(core_defaults().profile.as_str().into())
            })
        },
        Decl {
            description: "Pulses or breaks below their minimum: suppress, stretch, band or \
                          extend (the period grows so the pulse or break is exactly its \
                          minimum and the duty is kept, up to extend_max). Empty: as the \
                          profile says.",
            constraints: "suppress|stretch|band|extend or empty",
            choices: Some(|s| spelled::<ShortPulse>(s, true)),
            core: Some(|c, v| {
                c.short_pulse = policy(v)?;
                Ok(())
            }),
            msg: Some(|m| V::String(m.short_pulse.clone())),
            ..Decl::new(field!(channel, short_pulse), || {
                V::String(std::string::String::new())
            })
        },
        Decl {
            description: "Frequency_Output edge i_rEdge (004), fraction 0..1, used by \
                          short_pulse band.",
            range: Range::Double(0.0, 1.0),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.edge_band = double(v);
                Ok(())
            }),
            msg: Some(|m| V::Double(m.edge_band)),
            ..Decl::new(field!(channel, edge_band), || {
                V::Double(core_defaults().edge_band)
            })
        },
        Decl {
            description: "Longest period short_pulse extend may grow to, a factor of \
                          period_ms: a pulse or break that would need a longer one is \
                          suppressed, with E1. 1: no extension.",
            constraints: "takes effect at the next period boundary",
            range: Range::Double(1.0, MAX_EXTEND_FACTOR),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.extend_max = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, extend_max), || {
                V::Double(core_defaults().extend_max)
            })
        },
        Decl {
            description: "Time base (tick), ms: every pulse and break is a whole number of \
                          ticks and every edge lies on the tick grid (003's CYCLE_P, 001's \
                          task period, a zero-cross SSR's half cycle: 10 for 50 Hz, 8.3333 \
                          for 60 Hz). Rounded to the ns; the period to whole ticks, the \
                          minima up, max_on_ms down. 0: off.",
            constraints: "0, or 0.1..period_ms; takes effect at the next period boundary",
            range: Range::Double(0.0, MAX_PERIOD_MS as f64),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.time_base_ms = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, time_base_ms), || {
                V::Double(core_defaults().time_base_ms)
            })
        },
        Decl {
            description: "When a new duty takes effect: next_period, next_step or immediate. \
                          Empty: as the profile says.",
            constraints: "next_period|next_step|immediate or empty",
            choices: Some(|s| spelled::<ApplyAt>(s, true)),
            core: Some(|c, v| {
                c.apply_at = policy(v)?;
                Ok(())
            }),
            msg: Some(|m| V::String(m.apply_at.clone())),
            ..Decl::new(field!(channel, apply_at), || {
                V::String(std::string::String::new())
            })
        },
        Decl {
            description: "Output on disable: off or hold. Empty: as the profile says.",
            constraints: "off|hold or empty",
            choices: Some(|s| spelled::<OnDisable>(s, true)),
            core: Some(|c, v| {
                c.on_disable = policy(v)?;
                Ok(())
            }),
            msg: Some(|m| V::String(m.on_disable.clone())),
            ..Decl::new(field!(channel, on_disable), || {
                V::String(std::string::String::new())
            })
        },
        Decl {
            description: "Watchdog, ms: no duty command for this long forces the output off \
                          until the next one. 0: off.",
            range: Range::Integer(0, MAX_TIMEOUT_MS as i64),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.command_timeout_ms = ms(v);
                Ok(())
            }),
            msg: Some(|m| V::Integer(m.command_timeout_ms)),
            ..Decl::new(field!(channel, command_timeout_ms), || {
                V::Integer(core_defaults().command_timeout_ms as i64)
            })
        },
        Decl {
            description: "Fault value, percent 0..100: the duty the channel runs at when the \
                          watchdog trips, through the same minimum-time rules (frost \
                          protection, a safe valve position). 0: off at once.",
            constraints: "in force at once",
            range: Range::Double(0.0, 100.0),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.fault_duty_pct = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, fault_duty_pct), || {
                V::Double(core_defaults().fault_duty_pct)
            })
        },
        Decl {
            description: "How long the fault value runs before the output goes off, ms. 0: \
                          until the next command.",
            constraints: "in force at once",
            range: Range::Integer(0, MAX_TIMEOUT_MS as i64),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.fault_hold_ms = ms(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, fault_hold_ms), || {
                V::Integer(core_defaults().fault_hold_ms as i64)
            })
        },
        Decl {
            description: "Lowest expected rate of duty commands (~/<ch>/duty, ~/<ch>/sv, a \
                          split-range command), Hz. Below it, less command_hz_tolerance, the \
                          channel's `command frequency` status on /diagnostics is WARN \
                          (Frequency too low.), and ERROR (No events recorded.) when none came \
                          within command_hz_window. 0: no lower bound; with \
                          expected_command_hz_max also 0 the rate is shown, not checked.",
            constraints: "0, or up to expected_command_hz_max when that is set; reporting \
                          only: commands are never refused for their rate",
            range: Range::Double(0.0, MAX_EXPECTED_COMMAND_HZ),
            note: " (0 = no lower bound)",
            ..Decl::new(field!(channel, expected_command_hz_min), || V::Double(0.0))
        },
        Decl {
            description: "Highest expected rate of duty commands, Hz. Above it, plus \
                          command_hz_tolerance, the channel's `command frequency` status on \
                          /diagnostics is WARN (Frequency too high.). 0: no upper bound.",
            constraints: "0, or at least expected_command_hz_min; reporting only",
            range: Range::Double(0.0, MAX_EXPECTED_COMMAND_HZ),
            note: " (0 = no upper bound)",
            ..Decl::new(field!(channel, expected_command_hz_max), || V::Double(0.0))
        },
        Decl {
            description: "Maximum continuous on time of the line, ms: a line high this long \
                          goes off for at least its minimum off time, then follows its \
                          schedule again, with E1 and the limit flag (a guard against a \
                          controller stuck at 100 %). 0: off.",
            constraints: "0, or at least the minimum on time in force; takes effect at the \
                          next period boundary",
            range: Range::Integer(0, MAX_ON_MS as i64),
            checked: Checked::Core,
            note: " (0 = off)",
            core: Some(|c, v| {
                c.max_on_ms = ms(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, max_on_ms), || {
                V::Integer(core_defaults().max_on_ms as i64)
            })
        },
        Decl {
            description: "Highest duty applied, percent 0..100: a command above it is limited \
                          to it, after clamping and before the minimum-time rules; it limits \
                          the fault value too (a heater's maximum power). 100: off.",
            constraints: "at least min_duty_pct; takes effect at the next period boundary",
            range: Range::Double(0.0, 100.0),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.max_duty_pct = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, max_duty_pct), || {
                V::Double(core_defaults().max_duty_pct)
            })
        },
        Decl {
            description: "Lowest duty applied, percent 0..100: a command below it is raised \
                          to it, 0 % included unless zero_means_zero. 0: off.",
            constraints: "at most max_duty_pct; takes effect at the next period boundary",
            range: Range::Double(0.0, 100.0),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.min_duty_pct = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, min_duty_pct), || {
                V::Double(core_defaults().min_duty_pct)
            })
        },
        Decl {
            description: "A duty command of 0 % stays 0 %, whatever min_duty_pct.",
            constraints: "takes effect at the next period boundary",
            core: Some(|c, v| {
                c.zero_means_zero = matches!(v, V::Boolean(true));
                Ok(())
            }),
            ..Decl::new(field!(channel, zero_means_zero), || {
                V::Boolean(core_defaults().zero_means_zero)
            })
        },
        Decl {
            description: "Slew limit, percent per second: the duty applied moves toward the \
                          command at most this fast, both ways, from 0 at each enable (soft \
                          start); safety offs still act at once. 0: off.",
            constraints: "takes effect at the next period boundary",
            range: Range::Double(0.0, MAX_SLEW_PCT_PER_S),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.duty_slew_pct_per_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, duty_slew_pct_per_s), || {
                V::Double(core_defaults().duty_slew_pct_per_s)
            })
        },
        Decl {
            description: "Dead band, percent 0..100: a duty command whose duty (after the \
                          power limits) differs from the one in force by less is ignored \
                          (relay wear); it still feeds the watchdog. 0 %, min_duty_pct and \
                          max_duty_pct always pass. 0: off.",
            constraints: "takes effect at the next period boundary",
            range: Range::Double(0.0, 100.0),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.duty_deadband_pct = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, duty_deadband_pct), || {
                V::Double(core_defaults().duty_deadband_pct)
            })
        },
        Decl {
            description: "Rolling-average cap, percent 0..100: over every window of \
                          avg_window_s the line is on for at most this share of the window \
                          (an energy budget); a period whose on time would exceed what is left \
                          is shortened or planned off. It limits the duty applied, the fault \
                          value included. 100: off.",
            constraints: "takes effect at the next period boundary",
            range: Range::Double(0.0, 100.0),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.avg_duty_limit_pct = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, avg_duty_limit_pct), || {
                V::Double(core_defaults().avg_duty_limit_pct)
            })
        },
        Decl {
            description: "The window of the rolling-average cap, s.",
            constraints: "takes effect at the next period boundary",
            range: Range::Integer(1, MAX_AVG_WINDOW_S as i64),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.avg_window_s = int(v).max(0) as u64;
                Ok(())
            }),
            ..Decl::new(field!(channel, avg_window_s), || {
                V::Integer(core_defaults().avg_window_s as i64)
            })
        },
        Decl {
            description: "Temperature feedback: a sensor_msgs/Temperature topic (°C), \
                          subscribed best effort so best-effort and reliable publishers both \
                          match. Its last reading and age go to ~/<ch>/status and \
                          /diagnostics. Empty: none.",
            constraints: "start-up only; needed by control pid and the heater checks",
            read_only: Some(START_UP),
            core: Some(|c, v| {
                c.heater.feedback = !text(v).is_empty();
                Ok(())
            }),
            ..Decl::new(field!(channel, feedback_topic), || {
                V::String(std::string::String::new())
            })
        },
        Decl {
            description: "Who sets the duty: open (duty commands, as without a heater loop), \
                          pid (the PID, from the feedback and ~/<ch>/setpoint) or mpc \
                          (model-predictive control on the thermal model model_*: the model \
                          predicts the heater over its dead time and the duty brings the \
                          prediction to the setpoint, plus the loss to the ambient and the \
                          feed-forward; no gains). Under pid and mpc a duty command is \
                          refused, and command_timeout_ms watches the setpoint and the \
                          feedback; under open a setpoint is refused.",
            constraints: "open|pid|mpc; pid and mpc need feedback_topic, mpc a model \
                          (model_gain_c_per_pct above 0); a switch is bumpless",
            choices: Some(|s| spelled::<Control>(s, false)),
            core: Some(|c, v| {
                c.heater.control = text(v).parse()?;
                Ok(())
            }),
            ..Decl::new(field!(channel, control), || {
                V::String(heater_defaults().control.as_str().into())
            })
        },
        Decl {
            description: "PID sample, ms: the loop computes the duty this often from the \
                          latest reading. 0: the channel's period.",
            constraints: "0, or 10..3600000; in force at once",
            range: Range::Integer(0, MAX_PERIOD_MS as i64),
            checked: Checked::Core,
            note: " (0 = the channel's period)",
            core: Some(|c, v| {
                c.heater.pid_sample_ms = ms(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, pid_sample_ms), || V::Integer(0))
        },
        Decl {
            description: "Proportional gain, % per °C.",
            constraints: "a gain change is bumpless",
            range: Range::Double(0.0, MAX_GAIN),
            core: Some(|c, v| {
                c.heater.pid_kp = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, pid_kp), || V::Double(0.0))
        },
        Decl {
            description: "Integral gain, % per °C·s (TI = pid_kp / pid_ki). The integral \
                          stops while the duty is held at a limit (anti-windup).",
            constraints: "a gain change is bumpless",
            range: Range::Double(0.0, MAX_GAIN),
            core: Some(|c, v| {
                c.heater.pid_ki = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, pid_ki), || V::Double(0.0))
        },
        Decl {
            description: "Derivative gain, % per °C/s, on the measurement (no kick on a \
                          setpoint step).",
            constraints: "a gain change is bumpless",
            range: Range::Double(0.0, MAX_GAIN),
            core: Some(|c, v| {
                c.heater.pid_kd = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, pid_kd), || V::Double(0.0))
        },
        Decl {
            description: "Time constant of the derivative's first-order filter, s. 0: none.",
            range: Range::Double(0.0, MAX_TIME_S),
            core: Some(|c, v| {
                c.heater.pid_d_filter_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, pid_d_filter_s), || V::Double(0.0))
        },
        Decl {
            description: "Lowest valid reading, °C: below it (and NaN or ±inf) the heater \
                          fault temperature_out_of_range latches. Also the lowest setpoint.",
            constraints: "below temp_max_c",
            range: Range::Double(MIN_TEMP_C, MAX_TEMP_C),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.heater.temp_min_c = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, temp_min_c), || {
                V::Double(heater_defaults().temp_min_c)
            })
        },
        Decl {
            description: "Highest valid reading, °C: above it the heater fault \
                          temperature_out_of_range latches. A setpoint must lie \
                          setpoint_margin_c below it, an autotune's target autotune_margin_c. \
                          The default, 3000, means unset: control pid refuses to run without \
                          it (Klipper's max_temp, which a heater needs). Lowering it below the \
                          setpoint in force lowers the setpoint with it.",
            constraints: "above temp_min_c; required by control pid",
            range: Range::Double(MIN_TEMP_C, MAX_TEMP_C),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.heater.temp_max_c = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, temp_max_c), || {
                V::Double(heater_defaults().temp_max_c)
            })
        },
        Decl {
            description: "sensor_timeout: no fresh reading for this long while the channel is \
                          enabled latches the heater fault, ms. The loop, not_heating and the \
                          autotune act on fresh readings only. 3000 (Klipper's MCU stops a \
                          heater 3 s after its host falls silent; a 1 Hz sensor may lose two \
                          readings in a row). 0 (off) only under control open; an autotune \
                          then holds its readings to 3000 all the same.",
            constraints: "above 0 under control pid",
            range: Range::Integer(0, MAX_TIMEOUT_MS as i64),
            checked: Checked::Core,
            note: " (0 = off, under open only)",
            core: Some(|c, v| {
                c.heater.feedback_timeout_ms = ms(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, feedback_timeout_ms), || {
                V::Integer(heater_defaults().feedback_timeout_ms as i64)
            })
        },
        Decl {
            description: "How far in the future a reading's header.stamp may lie against this \
                          node's clock, ms (the clock skew between the sensor's host and this \
                          one). A stamp further ahead, or older than feedback_timeout_ms when \
                          the reading arrives, makes the reading stale: counted on \
                          ~/<ch>/status and /diagnostics, used by nothing. A zero stamp \
                          (unstamped) counts from its arrival.",
            range: Range::Integer(0, MAX_SKEW_MS as i64),
            core: Some(|c, v| {
                c.heater.feedback_max_skew_ms = ms(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, feedback_max_skew_ms), || {
                V::Integer(heater_defaults().feedback_max_skew_ms as i64)
            })
        },
        Decl {
            description: "A setpoint must lie at least this far below temp_max_c, °C (Marlin's \
                          HOTEND_OVERSHOOT): the loop's overshoot stays below the maximum.",
            range: Range::Double(0.0, MAX_DELTA_C),
            checked: Checked::Core,
            core: Some(|c, v| {
                c.heater.setpoint_margin_c = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, setpoint_margin_c), || {
                V::Double(heater_defaults().setpoint_margin_c)
            })
        },
        Decl {
            description: "sensor_stuck: a reading that stands still (within \
                          sensor_stuck_band_c) for at least this long, s, while the energy \
                          the heater gets swings by sensor_stuck_energy_s, or while it is at \
                          full power, latches the heater fault. At least twice the heater's \
                          dead time. 0: off.",
            range: Range::Double(0.0, MAX_TIME_S),
            note: " (0 = off)",
            core: Some(|c, v| {
                c.heater.sensor_stuck_time_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, sensor_stuck_time_s), || {
                V::Double(heater_defaults().sensor_stuck_time_s)
            })
        },
        Decl {
            description: "sensor_stuck: a change of the reading by more than this is movement, \
                          °C (0: any change); no_rise: a rise of at most this (and the \
                          readings' own scatter) is none.",
            range: Range::Double(0.0, MAX_DELTA_C),
            core: Some(|c, v| {
                c.heater.sensor_stuck_band_c = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, sensor_stuck_band_c), || {
                V::Double(heater_defaults().sensor_stuck_band_c)
            })
        },
        Decl {
            description: "sensor_stuck: how far the energy the heater gets may swing (stray \
                          from a steady power) while the reading stands still, in seconds of \
                          full power. A heater that rises at r °C/s at full power moves by at \
                          least r times this.",
            range: Range::Double(0.1, MAX_TIME_S),
            core: Some(|c, v| {
                c.heater.sensor_stuck_energy_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, sensor_stuck_energy_s), || {
                V::Double(heater_defaults().sensor_stuck_energy_s)
            })
        },
        Decl {
            description: "no_rise: with the loop (or an autotune) at full power for this long, \
                          s, the reading must rise, or the heater fault latches (the sensor \
                          does not see the heater, or the heater does not heat). At least \
                          twice the heater's dead time. 0: off.",
            range: Range::Double(0.0, MAX_TIME_S),
            note: " (0 = off)",
            core: Some(|c, v| {
                c.heater.no_rise_time_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, no_rise_time_s), || {
                V::Double(heater_defaults().no_rise_time_s)
            })
        },
        Decl {
            description: "sensor_jump: a reading that moves by more than this many °C per \
                          second against the one before it (over at least a second) latches \
                          the heater fault: no heater's block moves that fast; a shorted or \
                          broken sensor does. Above the heater's fastest rise. 0: off.",
            range: Range::Double(0.0, MAX_RATE_C_PER_S),
            note: " (0 = off)",
            core: Some(|c, v| {
                c.heater.sensor_max_rate_c_per_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, sensor_max_rate_c_per_s), || {
                V::Double(heater_defaults().sensor_max_rate_c_per_s)
            })
        },
        Decl {
            description: "not_heating (Klipper's verify_heater hysteresis), °C: within this of \
                          the setpoint the check rests.",
            range: Range::Double(0.0, MAX_DELTA_C),
            core: Some(|c, v| {
                c.heater.runaway_hysteresis_c = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, runaway_hysteresis_c), || {
                V::Double(heater_defaults().runaway_hysteresis_c)
            })
        },
        Decl {
            description: "not_heating (verify_heater max_error), °C·s: the error summed once a \
                          second below setpoint − hysteresis at which the fault latches.",
            range: Range::Double(0.0, MAX_RUNAWAY_ERROR),
            core: Some(|c, v| {
                c.heater.runaway_max_error = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, runaway_max_error), || {
                V::Double(heater_defaults().runaway_max_error)
            })
        },
        Decl {
            description: "not_heating (verify_heater check_gain_time), s: after a new \
                          setpoint, the temperature must gain runaway_heating_gain_c within \
                          this, again and again, until within the hysteresis.",
            range: Range::Double(1.0, MAX_TIME_S),
            core: Some(|c, v| {
                c.heater.runaway_gain_time_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, runaway_gain_time_s), || {
                V::Double(heater_defaults().runaway_gain_time_s)
            })
        },
        Decl {
            description: "not_heating (verify_heater heating_gain), °C.",
            range: Range::Double(0.001, MAX_DELTA_C),
            core: Some(|c, v| {
                c.heater.runaway_heating_gain_c = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, runaway_heating_gain_c), || {
                V::Double(heater_defaults().runaway_heating_gain_c)
            })
        },
        Decl {
            description: "stuck_on: a rise of more than this, °C, within stuck_on_time_s while \
                          the line has been held off the whole time (a welded SSR or relay) \
                          latches the heater fault. 0: off.",
            constraints: "above the rise a healthy heater makes after switching off \
                          (docs/heater.md)",
            range: Range::Double(0.0, MAX_DELTA_C),
            note: " (0 = off)",
            core: Some(|c, v| {
                c.heater.stuck_on_rise_c = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, stuck_on_rise_c), || {
                V::Double(heater_defaults().stuck_on_rise_c)
            })
        },
        Decl {
            description: "stuck_on's window, s.",
            range: Range::Double(1.0, MAX_TIME_S),
            core: Some(|c, v| {
                c.heater.stuck_on_time_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, stuck_on_time_s), || {
                V::Double(heater_defaults().stuck_on_time_s)
            })
        },
        Decl {
            description: "An autotune (~/<ch>/autotune) aborts on a reading above its target \
                          plus this, °C.",
            range: Range::Double(0.1, MAX_DELTA_C),
            core: Some(|c, v| {
                c.heater.autotune_max_overshoot_c = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, autotune_max_overshoot_c), || {
                V::Double(heater_defaults().autotune_max_overshoot_c)
            })
        },
        Decl {
            description:
                "An autotune aborts when no relay cycle completes within this of the run's \
                          start or of the last cycle's end, s (the approach and the first cycle \
                          share the first window).",
            range: Range::Double(1.0, MAX_TIME_S),
            core: Some(|c, v| {
                c.heater.autotune_timeout_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, autotune_timeout_s), || {
                V::Double(heater_defaults().autotune_timeout_s)
            })
        },
        Decl {
            description: "Once an autotune's cycles agree but the model's dead time is \
                          uncertain (its standard error above 4 % of it: the sensor's noise \
                          hides it behind the sensor's lag), the relay may go on for at most \
                          this long, s, until the dead time is told within 10 %; the run then \
                          gives the model, and says when the bound ended it uncertain. 0: the \
                          run ends as soon as its cycles agree. A slow, noisy heater can need \
                          40 minutes (docs/autotune.md).",
            range: Range::Double(0.0, MAX_TIME_S),
            note: " (0 = off)",
            core: Some(|c, v| {
                c.heater.autotune_extend_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, autotune_extend_s), || {
                V::Double(heater_defaults().autotune_extend_s)
            })
        },
        Decl {
            description: "An autotune's target must lie at least this far below temp_max_c, °C \
                          (Marlin's M303: 15): the relay overshoots its target.",
            range: Range::Double(0.0, MAX_DELTA_C),
            core: Some(|c, v| {
                c.heater.autotune_margin_c = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, autotune_margin_c), || {
                V::Double(heater_defaults().autotune_margin_c)
            })
        },
        Decl {
            description: "The heater's thermal model (first order plus dead time, run on the \
                          line's real on time): its steady-state rise per % of duty, °C/%. \
                          0: no model. An autotune run identifies the model and applies it \
                          with the gains.",
            range: Range::Double(0.0, MAX_MODEL_GAIN),
            note: " (0 = no model)",
            core: Some(|c, v| {
                c.heater.model.gain_c_per_pct = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, model_gain_c_per_pct), || {
                V::Double(heater_defaults().model.gain_c_per_pct)
            })
        },
        Decl {
            description: "The thermal model's time constant, s.",
            range: Range::Double(0.1, MAX_TIME_S),
            core: Some(|c, v| {
                c.heater.model.tau_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, model_tau_s), || {
                V::Double(heater_defaults().model.tau_s)
            })
        },
        Decl {
            description: "The thermal model's dead time between the line and the sensor, s.",
            range: Range::Double(0.0, MAX_MODEL_DEAD_TIME_S),
            core: Some(|c, v| {
                c.heater.model.dead_time_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, model_dead_time_s), || {
                V::Double(heater_defaults().model.dead_time_s)
            })
        },
        Decl {
            description: "The thermal model's ambient: the temperature at 0 %, °C.",
            range: Range::Double(MIN_TEMP_C, MAX_TEMP_C),
            core: Some(|c, v| {
                c.heater.model.ambient_c = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, model_ambient_c), || {
                V::Double(heater_defaults().model.ambient_c)
            })
        },
        Decl {
            description: "The thermal model's sensor: its time constant behind the block, s \
                          (a probe in a bore, a thermistor on a bed lags what it measures). 0: \
                          the sensor reads the block.",
            range: Range::Double(0.0, MAX_MODEL_DEAD_TIME_S),
            core: Some(|c, v| {
                c.heater.model.sensor_tau_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, model_sensor_tau_s), || {
                V::Double(heater_defaults().model.sensor_tau_s)
            })
        },
        Decl {
            description: "Feed-forward: a std_msgs/Float64 topic carrying a known disturbance \
                          in % of the heater's full power it costs (a part-cooling fan's duty \
                          through a gain, filament flow). Used by mpc, added to pid's output. \
                          Values beyond ±100 % are refused; one older than \
                          feedforward_timeout_ms is stale, ignored, and /diagnostics warns. \
                          Empty: none.",
            constraints: "start-up only",
            read_only: Some(START_UP),
            core: Some(|c, v| {
                c.heater.feedforward = !text(v).trim().is_empty();
                Ok(())
            }),
            ..Decl::new(field!(channel, feedforward_topic), || {
                V::String(std::string::String::new())
            })
        },
        Decl {
            description: "A feed-forward older than this is stale and ignored, ms (a stale \
                          value is handed to the loop's own estimate, so the duty does not \
                          jump). 0: never stale.",
            range: Range::Integer(0, MAX_TIMEOUT_MS as i64),
            core: Some(|c, v| {
                c.heater.feedforward_timeout_ms = ms(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, feedforward_timeout_ms), || {
                V::Integer(heater_defaults().feedforward_timeout_ms as i64)
            })
        },
        Decl {
            description: "Ambient temperature: a sensor_msgs/Temperature topic (°C), the \
                          ambient the model's loss is computed against instead of \
                          model_ambient_c. Readings outside temp_min_c..temp_max_c are \
                          refused; one older than ambient_timeout_ms is stale, the model's \
                          ambient is used, and /diagnostics warns. Empty: none.",
            constraints: "start-up only",
            read_only: Some(START_UP),
            core: Some(|c, v| {
                c.heater.ambient = !text(v).trim().is_empty();
                Ok(())
            }),
            ..Decl::new(field!(channel, ambient_topic), || {
                V::String(std::string::String::new())
            })
        },
        Decl {
            description: "An ambient reading older than this is stale and ignored, ms. 0: \
                          never stale.",
            range: Range::Integer(0, MAX_TIMEOUT_MS as i64),
            core: Some(|c, v| {
                c.heater.ambient_timeout_ms = ms(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, ambient_timeout_ms), || {
                V::Integer(heater_defaults().ambient_timeout_ms as i64)
            })
        },
        Decl {
            description: "Setpoint ramp, °C/s: under pid and mpc the loop's target moves \
                          toward a new setpoint at this rate, from where it stood (from the \
                          reading at the first setpoint, an enable or a reset); not_heating \
                          watches the ramped target. /diagnostics shows it as target_c. 0: a \
                          step.",
            range: Range::Double(0.0, MAX_RAMP_C_PER_S),
            core: Some(|c, v| {
                c.heater.setpoint_ramp_c_per_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, setpoint_ramp_c_per_s), || V::Double(0.0))
        },
        Decl {
            description: "model_deviation: a residual (the reading less the model's \
                          prediction, its slow offset taken out) beyond this, °C, for \
                          model_time_s latches the heater fault. Above what unannounced \
                          disturbances shift it by.",
            range: Range::Double(0.1, MAX_DELTA_C),
            core: Some(|c, v| {
                c.heater.model_tolerance_c = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, model_tolerance_c), || {
                V::Double(heater_defaults().model_tolerance_c)
            })
        },
        Decl {
            description: "model_deviation's time, s.",
            range: Range::Double(0.0, MAX_TIME_S),
            core: Some(|c, v| {
                c.heater.model_time_s = double(v);
                Ok(())
            }),
            ..Decl::new(field!(channel, model_time_s), || {
                V::Double(heater_defaults().model_time_s)
            })
        },
        Decl {
            description: "Invert the electrical level of the output line.",
            constraints: "start-up only",
            read_only: Some(
                "changing the polarity of a live line could glitch it; restart the node",
            ),
            msg: Some(|m| V::Boolean(m.active_low)),
            ..Decl::new(field!(channel, active_low), || V::Boolean(false))
        },
        Decl {
            description: "Enable the channel at start-up. While running, use ~/<ch>/enable.",
            constraints: "start-up only",
            read_only: Some("it is the start-up value; while running, publish on ~/<ch>/enable"),
            ..Decl::new(field!(channel, enable), || V::Boolean(false))
        },
        Decl {
            description: "Duty at start-up, percent 0..100. While running, use ~/<ch>/duty or \
                          ~/<ch>/sv.",
            constraints: "start-up only",
            read_only: Some("it is the start-up value; while running, publish on ~/<ch>/duty"),
            range: Range::Double(0.0, 100.0),
            ..Decl::new(field!(channel, duty), || V::Double(0.0))
        },
        Decl {
            description: "GPIO character device of the channel's line (output gpio).",
            read_only: Some(START_UP),
            ..Decl::new(field!(channel, gpio_chip), || {
                V::String("/dev/gpiochip0".into())
            })
        },
        Decl {
            description: "Line offset on gpio_chip (output gpio). -1: unset.",
            constraints: "required with output gpio; no line may serve two channels",
            read_only: Some(START_UP),
            range: Range::Integer(-1, u32::MAX as i64),
            note: " (-1 = unset)",
            ..Decl::new(field!(channel, gpio_line), || V::Integer(-1))
        },
    ]
}

/// The fields of `pwm_actuator_msgs/ChannelParams` that map onto channel parameters, in table
/// order, comma-separated.
pub fn msg_fields() -> String {
    channel_decls()
        .iter()
        .filter(|d| d.msg.is_some())
        .map(|d| d.suffix)
        .collect::<Vec<_>>()
        .join(", ")
}
