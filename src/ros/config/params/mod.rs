//! The node's ROS parameters: their declarations (type, default, description, range), the one
//! store every door writes through (command line, parameter files, the parameter services, the
//! `~/<ch>/params` topic), and the checks a change must pass before it is applied.
//!
//! A change is checked whole, on a copy of the store's typed settings ([`ChannelValues`], ...):
//! every value is coerced to its declared type, range-checked, and written to its field; then
//! every channel it touches is mapped once into a [`ChannelParams`](crate::core::ChannelParams)
//! and validated by the core
//! ([`ChannelParams::validate`](crate::core::ChannelParams::validate)), every valve it touches
//! as a `ValveParams` (its `validate`), so cross-parameter rules (`min_on_ms <= period_ms`, the
//! minima fitting the period, a valve's minimum pulse within its travel times) hold whatever
//! order the values arrive in. A refused change leaves the store untouched and says why. Nothing here talks to ROS or to the output thread.
//!
//! Type coercion, the same through every door: an integer parameter accepts a double that is a
//! whole number (`500.0` becomes `500`), a double parameter accepts an integer (`1` becomes
//! `1.0`); both are lossless and reported as notes. Anything else of the wrong type is refused.

mod reference;
mod settings;
mod startup;
mod store;
mod table;

pub use reference::{reference_markdown, REFERENCE_COMMAND, REFERENCE_PATH};
pub use settings::{ChannelValues, NodeSettings, NodeValues, Value, ValveValues};
pub use startup::{start_up, ChannelStart, StartUp, StartValue, StartupConfig};
pub use store::{items_from_msg, Accepted, ParamStore, Stage};
pub use table::msg_fields;

use super::logging::{escape_controls, shown};
use crate::core::config::UnknownName;
use crate::core::valve::ValveConfigError;
use crate::core::ConfigError;
use ros2_client::parameters::raw;
use ros2_client::ParameterValue;
use table::Checked;

/// Default `command_hz_window`: diagnostics runs (one a second) in the window, as
/// diagnostic_updater's `FrequencyStatusParam` (`window_size = 5`).
pub const DEFAULT_COMMAND_HZ_WINDOW: usize = 5;

/// Largest `command_hz_window`, runs (10 minutes at one a second).
pub const MAX_COMMAND_HZ_WINDOW: usize = 600;

/// Default `command_hz_tolerance`, a fraction, as diagnostic_updater's `FrequencyStatusParam`.
pub const DEFAULT_COMMAND_HZ_TOLERANCE: f64 = 0.1;

/// Highest `expected_command_hz_min` / `_max`, Hz.
pub const MAX_EXPECTED_COMMAND_HZ: f64 = 10_000.0;

/// Most channels a node may have (names stay two digits: `pw01`..`pw99`).
pub const MAX_CHANNELS: usize = 99;

/// Slowest periodic status rate, Hz (one message every 100 s); 0 means on change only.
pub const MIN_STATUS_RATE_HZ: f64 = 0.01;

/// Fastest periodic status rate, Hz.
pub const MAX_STATUS_RATE_HZ: f64 = 1000.0;

/// Lowest `heartbeat_hz`, Hz (a toggle every second).
pub const MIN_HEARTBEAT_HZ: f64 = 0.5;

/// Highest `heartbeat_hz`, Hz (a toggle every 2 ms).
pub const MAX_HEARTBEAT_HZ: f64 = 250.0;

/// Channels when nothing says otherwise (000: PW01, PW02).
pub const DEFAULT_CHANNELS: usize = 2;

/// The name of channel `index` (0 = `pw01`).
pub fn channel_name(index: usize) -> String {
    format!("pw{:02}", index + 1)
}

/// The declared type of a parameter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ParamType {
    /// `bool`.
    Bool,
    /// `integer` (i64).
    Integer,
    /// `double` (f64).
    Double,
    /// `string`.
    String,
}

impl ParamType {
    /// The `rcl_interfaces/ParameterType` code.
    pub fn raw(self) -> u8 {
        match self {
            ParamType::Bool => raw::ParameterType::BOOL,
            ParamType::Integer => raw::ParameterType::INTEGER,
            ParamType::Double => raw::ParameterType::DOUBLE,
            ParamType::String => raw::ParameterType::STRING,
        }
    }

    fn article(self) -> &'static str {
        match self {
            ParamType::Bool => "a bool",
            ParamType::Integer => "an integer",
            ParamType::Double => "a double",
            ParamType::String => "a string",
        }
    }
}

/// The advertised range of a numeric parameter (inclusive).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Range {
    /// No range.
    Unbounded,
    /// Integer range.
    Integer(i64, i64),
    /// Floating-point range.
    Double(f64, f64),
}

/// A declared parameter (`rcl_interfaces/ParameterDescriptor` plus the default).
#[derive(Debug, Clone)]
pub struct Descriptor {
    /// Full name, e.g. `pw01.period_ms`.
    pub name: String,
    /// Declared type.
    pub ptype: ParamType,
    /// Value when nothing sets it.
    pub default: ParameterValue,
    /// What it is, with its unit.
    pub description: String,
    /// Rules the range cannot express.
    pub constraints: String,
    /// Set only at start-up; a live change to another value is refused with `why_read_only`.
    pub read_only: bool,
    /// Why it is read-only.
    pub why_read_only: &'static str,
    /// Advertised range.
    pub range: Range,
    /// What special values mean, for refusal messages (` (-1 = ...)`), or empty.
    pub note: &'static str,
    checked: Checked,
    choices: Option<table::Choices>,
    /// The typed field that holds the value.
    access: table::Access,
    /// Which channel's or valve's settings hold it (0 for a node parameter).
    at: usize,
}

impl Descriptor {
    /// The wire form served by `describe_parameters`.
    pub fn to_raw(&self) -> raw::ParameterDescriptor {
        let (integer_range, floating_point_range) = match self.range {
            Range::Unbounded => (vec![], vec![]),
            Range::Integer(from_value, to_value) => (
                vec![raw::IntegerRange {
                    from_value,
                    to_value,
                    step: 0,
                }],
                vec![],
            ),
            Range::Double(from_value, to_value) => (
                vec![],
                vec![raw::FloatingPointRange {
                    from_value,
                    to_value,
                    step: 0.0,
                }],
            ),
        };
        raw::ParameterDescriptor {
            name: self.name.clone(),
            r#type: self.ptype.raw(),
            description: self.description.clone(),
            additional_constraints: self.constraints.clone(),
            read_only: self.read_only,
            dynamic_typing: false,
            floating_point_range,
            integer_range,
        }
    }
}

/// Why a parameter change was refused. The text is the reason given to ROS clients.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ParamError {
    /// No such parameter.
    #[error("parameter `{name}` is not declared{hint}")]
    Undeclared {
        /// The name asked for, as [`shown`] echoes input (escaped, bounded).
        name: String,
        /// A hint (e.g. the channel count), starting with a separator, or empty.
        hint: String,
    },
    /// A start-up-only parameter asked to change while running.
    #[error("parameter `{name}` is read-only while the node runs: {why}")]
    ReadOnly {
        /// The parameter.
        name: String,
        /// Why.
        why: &'static str,
    },
    /// A value of the wrong type that cannot be converted without loss.
    #[error("parameter `{name}` is {expected}; got {got}")]
    WrongType {
        /// The parameter.
        name: String,
        /// The declared type, with its article.
        expected: &'static str,
        /// The value given, described.
        got: String,
    },
    /// A double given for an integer parameter that is not a whole number.
    #[error("parameter `{name}` is an integer; {value} is not a whole number")]
    NotWhole {
        /// The parameter.
        name: String,
        /// The value given.
        value: f64,
    },
    /// A number outside the advertised range.
    #[error("parameter `{name}`: {value} is outside {from}..{to}{note}")]
    OutOfRange {
        /// The parameter.
        name: String,
        /// The value given.
        value: String,
        /// Lower bound.
        from: String,
        /// Upper bound.
        to: String,
        /// What the special values mean, starting with a separator, or empty.
        note: &'static str,
    },
    /// A string that names none of the accepted choices.
    // The core keeps 32 bytes of the value as given; escaped here like all echoed input.
    #[error("parameter `{name}`: {}", escape_controls(&.source.to_string()))]
    BadChoice {
        /// The parameter.
        name: String,
        /// The core's message with the accepted spellings.
        #[source]
        source: UnknownName,
    },
    /// The channel's settings together are refused by the core.
    #[error("{channel}: {source}")]
    Channel {
        /// Channel name, e.g. `pw01`.
        channel: String,
        /// The core's verdict.
        #[source]
        source: ConfigError,
    },
    /// A valve's settings together are refused by the core.
    #[error("valve {valve}: {source}")]
    Valve {
        /// The valve's name.
        valve: String,
        /// The core's verdict.
        #[source]
        source: ValveConfigError,
    },
    /// `use_sim_time` set to true.
    #[error(
        "use_sim_time cannot be true: pulses are timed on CLOCK_MONOTONIC and messages are \
         stamped with the system clock"
    )]
    SimTime,
    /// A ChannelParams message whose `set` is empty.
    #[error("{channel}/params: `set` is empty; name the fields to apply, e.g. [\"period_ms\"]")]
    EmptySet {
        /// Channel name.
        channel: String,
    },
    /// A ChannelParams message naming a field it does not have.
    #[error("{channel}/params: `{field}` in `set` is not a ChannelParams field ({fields})")]
    UnknownField {
        /// Channel name.
        channel: String,
        /// The name given, as [`shown`] echoes input (escaped, bounded).
        field: String,
        /// The fields there are.
        fields: String,
    },
    /// An expected command rate whose minimum is above its maximum.
    #[error(
        "{channel}: expected_command_hz_min {min} is above expected_command_hz_max {max}; set \
         the maximum to 0 (no upper bound) or at least the minimum"
    )]
    RateBounds {
        /// Channel name.
        channel: String,
        /// `expected_command_hz_min`, Hz.
        min: f64,
        /// `expected_command_hz_max`, Hz.
        max: f64,
    },
    /// Output `gpio` without a line for a channel.
    #[error(
        "output gpio needs a line for every channel: set {channel}.gpio_line (and \
         {channel}.gpio_chip unless it is /dev/gpiochip0)"
    )]
    MissingLine {
        /// Channel name.
        channel: String,
    },
}

fn describe_value(v: &ParameterValue) -> String {
    match v {
        ParameterValue::NotSet => "no value (NOT_SET)".into(),
        ParameterValue::Boolean(b) => format!("the bool {b}"),
        ParameterValue::Integer(i) => format!("the integer {i}"),
        ParameterValue::Double(d) => format!("the double {d}"),
        ParameterValue::String(s) => format!("the string \"{}\"", shown(s)),
        ParameterValue::ByteArray(_) => "a byte array".into(),
        ParameterValue::BooleanArray(_) => "a bool array".into(),
        ParameterValue::IntegerArray(_) => "an integer array".into(),
        ParameterValue::DoubleArray(_) => "a double array".into(),
        ParameterValue::StringArray(_) => "a string array".into(),
    }
}

/// Shows a value the way `ros2 param get` would.
pub fn show_value(v: &ParameterValue) -> String {
    match v {
        ParameterValue::NotSet => "NOT_SET".into(),
        ParameterValue::Boolean(b) => b.to_string(),
        ParameterValue::Integer(i) => i.to_string(),
        ParameterValue::Double(d) => format!("{d:?}"),
        ParameterValue::String(s) => format!("{s:?}"),
        other => format!("{other:?}"),
    }
}

/// Largest integer every f64 holds exactly.
const EXACT_F64_INT: f64 = 9_007_199_254_740_992.0;

/// Converts `value` to the declared type of `d` when that loses nothing. Returns the value and
/// a note when it was converted.
pub fn coerce(
    d: &Descriptor,
    value: &ParameterValue,
) -> Result<(ParameterValue, Option<String>), ParamError> {
    let wrong = || ParamError::WrongType {
        name: d.name.clone(),
        expected: d.ptype.article(),
        got: describe_value(value),
    };
    match (d.ptype, value) {
        (ParamType::Bool, ParameterValue::Boolean(_))
        | (ParamType::Integer, ParameterValue::Integer(_))
        | (ParamType::Double, ParameterValue::Double(_))
        | (ParamType::String, ParameterValue::String(_)) => Ok((value.clone(), None)),
        (ParamType::Integer, ParameterValue::Double(x)) => {
            if x.is_finite() && x.fract() == 0.0 && x.abs() <= EXACT_F64_INT {
                let i = *x as i64;
                Ok((
                    ParameterValue::Integer(i),
                    Some(format!("{}: double {x:?} taken as integer {i}", d.name)),
                ))
            } else if x.is_finite() {
                Err(ParamError::NotWhole {
                    name: d.name.clone(),
                    value: *x,
                })
            } else {
                Err(wrong())
            }
        }
        (ParamType::Double, ParameterValue::Integer(i)) if (*i as f64).abs() <= EXACT_F64_INT => {
            let x = *i as f64;
            Ok((
                ParameterValue::Double(x),
                Some(format!("{}: integer {i} taken as double {x:?}", d.name)),
            ))
        }
        _ => Err(wrong()),
    }
}

/// Checks the advertised range (for parameters whose range is checked here).
fn check_range(d: &Descriptor, v: &ParameterValue) -> Result<(), ParamError> {
    let out = |value: String, from: String, to: String| ParamError::OutOfRange {
        name: d.name.clone(),
        value,
        from,
        to,
        note: d.note,
    };
    match (d.range, v) {
        // The core judges values it can represent; negative times never reach it.
        (Range::Integer(from, to), ParameterValue::Integer(i))
            if match d.checked {
                Checked::Core => *i < 0,
                Checked::Range | Checked::OffOr(_) => !(from..=to).contains(i),
            } =>
        {
            Err(out(i.to_string(), from.to_string(), to.to_string()))
        }
        (Range::Double(from, to), ParameterValue::Double(x)) => {
            let from = match d.checked {
                Checked::Core => return Ok(()),
                // 0 is "off"; any other value inside the advertised range must lie in min..=to
                // (a rate must give a period the node can sleep for: 1/1e-20 s is no Duration).
                Checked::OffOr(min) if *x != 0.0 && (from..=to).contains(x) => min,
                Checked::OffOr(_) | Checked::Range => from,
            };
            if (from..=to).contains(x) {
                Ok(())
            } else {
                Err(out(
                    format!("{x:?}"),
                    format!("{from:?}"),
                    format!("{to:?}"),
                ))
            }
        }
        _ => Ok(()),
    }
}

/// `(index, suffix)` when `name` is a channel parameter `pwNN.suffix`.
pub fn channel_of(name: &str) -> Option<(usize, &str)> {
    let (prefix, rest) = name.split_once('.')?;
    channel_index(prefix).map(|i| (i, rest))
}

/// The index of channel `name` (`pw01` = 0) when it has a channel's form `pwNN`.
pub fn channel_index(name: &str) -> Option<usize> {
    let digits = name.strip_prefix("pw")?;
    if digits.len() != 2 || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let n: usize = digits.parse().ok()?;
    n.checked_sub(1)
}

/// Checks a string against its accepted choices.
fn check_choice(d: &Descriptor, v: &ParameterValue) -> Result<(), ParamError> {
    match (v, d.choices) {
        (ParameterValue::String(s), Some(accepts)) => {
            accepts(s).map_err(|source| ParamError::BadChoice {
                name: d.name.clone(),
                source,
            })
        }
        _ => Ok(()),
    }
}

/// The descriptor of parameter `name` declared by `d`, of channel or valve `at` (0 for a node
/// parameter).
fn make(name: String, d: &table::Decl, at: usize) -> Descriptor {
    Descriptor {
        name,
        ptype: d.ptype,
        default: (d.default)(),
        description: d.description.to_string(),
        constraints: d.constraints.to_string(),
        read_only: d.read_only.is_some(),
        why_read_only: d.read_only.unwrap_or(""),
        range: d.range,
        note: d.note,
        checked: d.checked,
        choices: d.choices,
        access: d.access,
        at,
    }
}

#[cfg(test)]
mod tests;
