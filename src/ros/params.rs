//! The node's ROS parameters: their declarations (type, default, description, range), the one
//! store every door writes through (command line, parameter files, the parameter services, the
//! `~/<ch>/params` topic), and the checks a change must pass before it is applied.
//!
//! A change is checked whole: every value is coerced to its declared type, range-checked, and
//! every channel it touches is rebuilt as a [`ChannelParams`] and validated by the core
//! ([`ChannelParams::validate`]), so cross-parameter rules (`min_on_ms <= period_ms`, the
//! minima fitting the period) hold whatever order the values arrive in. A refused change leaves
//! the store untouched and says why. Nothing here talks to ROS or to the engine.
//!
//! Type coercion, the same through every door: an integer parameter accepts a double that is a
//! whole number (`500.0` becomes `500`), a double parameter accepts an integer (`1` becomes
//! `1.0`); both are lossless and reported as notes. Anything else of the wrong type is refused.

use super::msg;
use crate::core::config::{ShortStr, UnknownName};
use crate::core::{
    ApplyAt, ChannelConfig, ChannelParams, ConfigError, OnDisable, OutputKind, Profile, ShortPulse,
};
use ros2_client::parameters::raw;
use ros2_client::ParameterValue;
use std::collections::BTreeMap;
use std::path::PathBuf;

/// Most channels a node may have (names stay two digits: `pw01`..`pw99`).
pub const MAX_CHANNELS: usize = 99;

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

/// Who decides about a value's range.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Checked {
    /// The advertised range is checked here.
    Range,
    /// The core's validation gives the verdict (its messages are more precise); only values
    /// the core cannot represent (negative times) are refused here.
    Core,
}

/// A declared parameter (`rcl_interfaces/ParameterDescriptor` plus the default).
#[derive(Debug, Clone, PartialEq)]
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
    checked: Checked,
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
        /// The name asked for.
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
    #[error("parameter `{name}`: {source}")]
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
        /// The name given.
        field: String,
        /// The fields there are.
        fields: &'static str,
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
        ParameterValue::String(s) => format!("the string {s:?}"),
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
        note: special_note(&d.name),
    };
    match (d.range, v) {
        // The core judges values it can represent; negative times never reach it.
        (Range::Integer(from, to), ParameterValue::Integer(i))
            if match d.checked {
                Checked::Range => !(from..=to).contains(i),
                Checked::Core => *i < 0,
            } =>
        {
            Err(out(i.to_string(), from.to_string(), to.to_string()))
        }
        (Range::Double(from, to), ParameterValue::Double(x))
            if d.checked == Checked::Range && !(from..=to).contains(x) =>
        {
            Err(out(
                format!("{x:?}"),
                format!("{from:?}"),
                format!("{to:?}"),
            ))
        }
        _ => Ok(()),
    }
}

fn special_note(name: &str) -> &'static str {
    match suffix(name) {
        "min_off_ms" => " (-1 = as the profile says)",
        "gpio_line" => " (-1 = unset)",
        "status_rate_hz" => " (0 = on change only)",
        _ => "",
    }
}

/// The part after the channel prefix (`period_ms` of `pw01.period_ms`), or the whole name.
fn suffix(name: &str) -> &str {
    channel_of(name).map_or(name, |(_, s)| s)
}

/// `(index, suffix)` when `name` is a channel parameter `pwNN.suffix`.
pub fn channel_of(name: &str) -> Option<(usize, &str)> {
    let (prefix, rest) = name.split_once('.')?;
    let digits = prefix.strip_prefix("pw")?;
    if digits.len() != 2 || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let n: usize = digits.parse().ok()?;
    n.checked_sub(1).map(|i| (i, rest))
}

/// Checks a string against its accepted choices.
fn check_choice(d: &Descriptor, v: &ParameterValue) -> Result<(), ParamError> {
    let ParameterValue::String(s) = v else {
        return Ok(());
    };
    let bad = |source: UnknownName| ParamError::BadChoice {
        name: d.name.clone(),
        source,
    };
    match suffix(&d.name) {
        "output" => match s.as_str() {
            "sim" | "gpio" => Ok(()),
            _ => Err(bad(UnknownName {
                value: ShortStr::new(s),
                accepted: "sim|gpio",
            })),
        },
        "output_kind" => s.parse::<OutputKind>().map(drop).map_err(bad),
        "profile" => s.parse::<Profile>().map(drop).map_err(bad),
        "short_pulse" if !s.is_empty() => s.parse::<ShortPulse>().map(drop).map_err(bad),
        "apply_at" if !s.is_empty() => s.parse::<ApplyAt>().map(drop).map_err(bad),
        "on_disable" if !s.is_empty() => s.parse::<OnDisable>().map(drop).map_err(bad),
        _ => Ok(()),
    }
}

struct Decl {
    suffix: &'static str,
    ptype: ParamType,
    default: fn() -> ParameterValue,
    description: &'static str,
    constraints: &'static str,
    read_only: Option<&'static str>,
    range: Range,
    checked: Checked,
}

const START_UP: &str = "it is read at start-up only; restart the node to change it";

fn node_decls() -> Vec<Decl> {
    use ParamType::*;
    vec![
        Decl {
            suffix: "channels",
            ptype: Integer,
            default: || ParameterValue::Integer(DEFAULT_CHANNELS as i64),
            description: "Number of PWM channels, named pw01, pw02, ...",
            constraints: "",
            read_only: Some(START_UP),
            range: Range::Integer(1, MAX_CHANNELS as i64),
            checked: Checked::Range,
        },
        Decl {
            suffix: "output",
            ptype: String,
            default: || ParameterValue::String("sim".into()),
            description: "Output backend: sim (simulated sink, optional trace) or gpio (Linux \
                          GPIO character device, one line per channel).",
            constraints: "sim|gpio",
            read_only: Some(START_UP),
            range: Range::Unbounded,
            checked: Checked::Range,
        },
        Decl {
            suffix: "trace",
            ptype: String,
            default: || ParameterValue::String(std::string::String::new()),
            description: "Trace file(s) of the sim output, comma-separated; .vcd and/or .csv. \
                          Empty: no trace.",
            constraints: "sim output only",
            read_only: Some(START_UP),
            range: Range::Unbounded,
            checked: Checked::Range,
        },
        Decl {
            suffix: "status_rate_hz",
            ptype: Double,
            default: || ParameterValue::Double(10.0),
            description: "Rate of the periodic ~/<ch>/status messages, Hz (they are also sent \
                          on every change). 0: on change only.",
            constraints: "",
            read_only: None,
            range: Range::Double(0.0, 1000.0),
            checked: Checked::Range,
        },
        Decl {
            suffix: "edge_log_rate",
            ptype: Integer,
            default: || ParameterValue::Integer(10),
            description: "Console lines per second and channel showing edges (info level); \
                          edges beyond are summarised once a second. 0: no edge lines.",
            constraints: "",
            read_only: None,
            range: Range::Integer(0, 1000),
            checked: Checked::Range,
        },
        Decl {
            suffix: "split",
            ptype: String,
            default: || ParameterValue::String(std::string::String::new()),
            description: "Split-range pairs (001), comma-separated NAME:HOT:COLD[:DEADBAND_PCT]: \
                          ~/split/NAME/command (std_msgs/Float64, -100..100 %) drives HOT when \
                          positive and COLD when negative; the two lines are never high \
                          together. Empty: none.",
            constraints: "each channel in one pair at most",
            read_only: Some(START_UP),
            range: Range::Unbounded,
            checked: Checked::Range,
        },
        Decl {
            suffix: "rt_priority",
            ptype: Integer,
            default: || ParameterValue::Integer(0),
            description: "SCHED_FIFO priority of the output thread (with mlockall). 0: normal \
                          scheduling.",
            constraints: "needs CAP_SYS_NICE or an rtprio limit; refused cleanly otherwise",
            read_only: Some(START_UP),
            range: Range::Integer(0, 99),
            checked: Checked::Range,
        },
        Decl {
            suffix: "use_sim_time",
            ptype: Bool,
            default: || ParameterValue::Boolean(false),
            description: "Standard ROS parameter; always false here.",
            constraints: "only false: pulses are timed on CLOCK_MONOTONIC",
            read_only: None,
            range: Range::Unbounded,
            checked: Checked::Range,
        },
    ]
}

fn channel_decls() -> Vec<Decl> {
    use ParamType::*;
    let live = None;
    vec![
        Decl {
            suffix: "period_ms",
            ptype: Integer,
            default: || ParameterValue::Integer(1000),
            description: "Period T, ms. 0: no pulses, output held off (000).",
            constraints: "0, or >= 5 (transistor) / >= 100 (relay); takes effect at the next \
                          period boundary",
            read_only: live,
            range: Range::Integer(0, 3_600_000),
            checked: Checked::Core,
        },
        Decl {
            suffix: "min_on_ms",
            ptype: Integer,
            default: || ParameterValue::Integer(0),
            description: "Minimum on time, ms (ME / T_MINI / nMinSwiTi / P_B_TM). 0: the \
                          hardware floor (0.1 ms transistor, 50 ms relay).",
            constraints: "relay: 0 or >= 50; above period_ms acts as period_ms (every duty \
                          but 0 and 100 % then gives 0 or 1 with E1)",
            read_only: live,
            range: Range::Integer(0, 3_600_000),
            checked: Checked::Range,
        },
        Decl {
            suffix: "min_off_ms",
            ptype: Integer,
            default: || ParameterValue::Integer(-1),
            description: "Minimum off time, ms. -1: as the profile says (= min_on_ms, except \
                          twincat_ba: the hardware floor).",
            constraints: "relay: 0 or >= 50; above period_ms acts as period_ms",
            read_only: live,
            range: Range::Integer(-1, 3_600_000),
            checked: Checked::Range,
        },
        Decl {
            suffix: "output_kind",
            ptype: String,
            default: || ParameterValue::String("transistor".into()),
            description: "Limits of 000's table: transistor (period >= 5 ms, floor 0.1 ms) or \
                          relay (period >= 100 ms, min times >= 50 ms).",
            constraints: "transistor|relay",
            read_only: live,
            range: Range::Unbounded,
            checked: Checked::Range,
        },
        Decl {
            suffix: "profile",
            ptype: String,
            default: || ParameterValue::String("pico_gfx".into()),
            description: "Policy set of a vendor block: pico_gfx (000), schneider_pwm (001), \
                          twincat_ba (002), tcont_cp (003), frequency_output (004).",
            constraints: "pico_gfx|twincat_ba|tcont_cp|schneider_pwm|frequency_output",
            read_only: live,
            range: Range::Unbounded,
            checked: Checked::Range,
        },
        Decl {
            suffix: "short_pulse",
            ptype: String,
            default: || ParameterValue::String(std::string::String::new()),
            description: "Pulses or breaks below their minimum: suppress, stretch or band. \
                          Empty: as the profile says.",
            constraints: "suppress|stretch|band or empty",
            read_only: live,
            range: Range::Unbounded,
            checked: Checked::Range,
        },
        Decl {
            suffix: "edge_band",
            ptype: Double,
            default: || ParameterValue::Double(0.0),
            description: "Frequency_Output edge i_rEdge (004), fraction 0..1, used by \
                          short_pulse band.",
            constraints: "",
            read_only: live,
            range: Range::Double(0.0, 1.0),
            checked: Checked::Core,
        },
        Decl {
            suffix: "apply_at",
            ptype: String,
            default: || ParameterValue::String(std::string::String::new()),
            description: "When a new duty takes effect: next_period, next_step or immediate. \
                          Empty: as the profile says.",
            constraints: "next_period|next_step|immediate or empty",
            read_only: live,
            range: Range::Unbounded,
            checked: Checked::Range,
        },
        Decl {
            suffix: "on_disable",
            ptype: String,
            default: || ParameterValue::String(std::string::String::new()),
            description: "Output on disable: off or hold. Empty: as the profile says.",
            constraints: "off|hold or empty",
            read_only: live,
            range: Range::Unbounded,
            checked: Checked::Range,
        },
        Decl {
            suffix: "command_timeout_ms",
            ptype: Integer,
            default: || ParameterValue::Integer(0),
            description: "Watchdog, ms: no duty command for this long forces the output off \
                          until the next one. 0: off.",
            constraints: "",
            read_only: live,
            range: Range::Integer(0, 86_400_000),
            checked: Checked::Core,
        },
        Decl {
            suffix: "active_low",
            ptype: Bool,
            default: || ParameterValue::Boolean(false),
            description: "Invert the electrical level of the output line.",
            constraints: "start-up only",
            read_only: Some(
                "changing the polarity of a live line could glitch it; restart the node",
            ),
            range: Range::Unbounded,
            checked: Checked::Range,
        },
        Decl {
            suffix: "enable",
            ptype: Bool,
            default: || ParameterValue::Boolean(false),
            description: "Enable the channel at start-up. While running, use ~/<ch>/enable.",
            constraints: "start-up only",
            read_only: Some("it is the start-up value; while running, publish on ~/<ch>/enable"),
            range: Range::Unbounded,
            checked: Checked::Range,
        },
        Decl {
            suffix: "duty",
            ptype: Double,
            default: || ParameterValue::Double(0.0),
            description: "Duty at start-up, percent 0..100. While running, use ~/<ch>/duty or \
                          ~/<ch>/sv.",
            constraints: "start-up only",
            read_only: Some("it is the start-up value; while running, publish on ~/<ch>/duty"),
            range: Range::Double(0.0, 100.0),
            checked: Checked::Range,
        },
        Decl {
            suffix: "gpio_chip",
            ptype: String,
            default: || ParameterValue::String("/dev/gpiochip0".into()),
            description: "GPIO character device of the channel's line (output gpio).",
            constraints: "",
            read_only: Some(START_UP),
            range: Range::Unbounded,
            checked: Checked::Range,
        },
        Decl {
            suffix: "gpio_line",
            ptype: Integer,
            default: || ParameterValue::Integer(-1),
            description: "Line offset on gpio_chip (output gpio). -1: unset.",
            constraints: "required with output gpio; no line may serve two channels",
            read_only: Some(START_UP),
            range: Range::Integer(-1, u32::MAX as i64),
            checked: Checked::Range,
        },
    ]
}

fn make(name: String, d: &Decl) -> Descriptor {
    Descriptor {
        name,
        ptype: d.ptype,
        default: (d.default)(),
        description: d.description.to_string(),
        constraints: d.constraints.to_string(),
        read_only: d.read_only.is_some(),
        why_read_only: d.read_only.unwrap_or(""),
        range: d.range,
        checked: d.checked,
    }
}

/// The fields of `pwm_actuator_msgs/ChannelParams` that map onto channel parameters.
pub const MSG_FIELDS: &str = "period_ms, min_on_ms, min_off_ms, output_kind, profile, \
                              short_pulse, edge_band, apply_at, on_disable, command_timeout_ms, \
                              active_low";

/// Whether a parameter change is made at start-up (read-only ones allowed) or while running.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Defaults, flags, `-p` and parameter files.
    StartUp,
    /// Parameter services and the `~/<ch>/params` topic.
    Live,
}

/// A checked change, ready to commit.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Accepted {
    /// The coerced values that differ from the current ones, in the order given (last wins).
    pub changes: Vec<(String, ParameterValue)>,
    /// What was coerced, for the log.
    pub notes: Vec<String>,
    /// New configurations of channels whose timing settings changed: (index, config).
    pub configs: Vec<(usize, ChannelConfig)>,
}

/// Every parameter of the node with its current value.
#[derive(Debug, Clone)]
pub struct ParamStore {
    decls: BTreeMap<String, Descriptor>,
    values: BTreeMap<String, ParameterValue>,
    channels: usize,
}

impl ParamStore {
    /// Declares the node parameters and those of `channels` channels (clamped to
    /// 1..=[`MAX_CHANNELS`]), each at its default.
    pub fn new(channels: usize) -> ParamStore {
        let channels = channels.clamp(1, MAX_CHANNELS);
        let mut decls = BTreeMap::new();
        for d in node_decls() {
            decls.insert(d.suffix.to_string(), make(d.suffix.to_string(), &d));
        }
        for ch in 0..channels {
            for d in channel_decls() {
                let name = format!("{}.{}", channel_name(ch), d.suffix);
                decls.insert(name.clone(), make(name, &d));
            }
        }
        if let Some(d) = decls.get_mut("channels") {
            d.default = ParameterValue::Integer(channels as i64);
        }
        let values = decls
            .iter()
            .map(|(k, d)| (k.clone(), d.default.clone()))
            .collect();
        ParamStore {
            decls,
            values,
            channels,
        }
    }

    /// Number of channels.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// The current value of a parameter.
    pub fn get(&self, name: &str) -> Option<&ParameterValue> {
        self.values.get(name)
    }

    /// The declaration of a parameter.
    pub fn descriptor(&self, name: &str) -> Option<&Descriptor> {
        self.decls.get(name)
    }

    /// Every parameter name, sorted.
    pub fn names(&self) -> Vec<String> {
        self.values.keys().cloned().collect()
    }

    /// Every parameter with its current value, sorted by name.
    pub fn all(&self) -> Vec<(String, ParameterValue)> {
        self.values
            .iter()
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect()
    }

    /// An integer parameter's value.
    pub fn int(&self, name: &str) -> Option<i64> {
        match self.values.get(name) {
            Some(ParameterValue::Integer(i)) => Some(*i),
            _ => None,
        }
    }

    /// A double parameter's value.
    pub fn double(&self, name: &str) -> Option<f64> {
        match self.values.get(name) {
            Some(ParameterValue::Double(x)) => Some(*x),
            _ => None,
        }
    }

    /// A bool parameter's value.
    pub fn bool(&self, name: &str) -> Option<bool> {
        match self.values.get(name) {
            Some(ParameterValue::Boolean(b)) => Some(*b),
            _ => None,
        }
    }

    /// A string parameter's value.
    pub fn string(&self, name: &str) -> Option<&str> {
        match self.values.get(name) {
            Some(ParameterValue::String(s)) => Some(s),
            _ => None,
        }
    }

    /// Answers `list_parameters` the way rclcpp does: with no prefixes, names with fewer than
    /// `depth` dots (0 = any); otherwise names equal to a prefix or under `prefix.` within
    /// `depth` further levels. Returns `(names, prefixes)`.
    pub fn list(&self, prefixes: &[String], depth: u64) -> (Vec<String>, Vec<String>) {
        let within = |s: &str| depth == 0 || (s.matches('.').count() as u64) < depth;
        let mut names = Vec::new();
        let mut found_prefixes: Vec<String> = Vec::new();
        for name in self.values.keys() {
            let all = prefixes.is_empty() && within(name);
            let under = prefixes.iter().any(|p| {
                name == p
                    || name
                        .strip_prefix(p.as_str())
                        .and_then(|r| r.strip_prefix('.'))
                        .is_some_and(|r| within(&format!(".{r}")))
            });
            if all || under {
                names.push(name.clone());
                if let Some((ns, _)) = name.rsplit_once('.') {
                    if !found_prefixes.iter().any(|p| p == ns) {
                        found_prefixes.push(ns.to_string());
                    }
                }
            }
        }
        (names, found_prefixes)
    }

    /// The channel's parameters as the core's [`ChannelParams`], from `values`.
    fn channel_params_in(
        values: &BTreeMap<String, ParameterValue>,
        ch: usize,
    ) -> Result<ChannelParams, ParamError> {
        let prefix = channel_name(ch);
        let name = |s: &str| format!("{prefix}.{s}");
        let get = |s: &str| values.get(&name(s));
        let int = |s: &str| match get(s) {
            Some(ParameterValue::Integer(i)) => *i,
            _ => 0,
        };
        let text = |s: &str| match get(s) {
            Some(ParameterValue::String(v)) => v.clone(),
            _ => String::new(),
        };
        // Negative values were refused by the range checks; `max(0)` only guards the cast.
        let ms = |s: &str| int(s).max(0) as u64;
        let choice = |s: &str, source: UnknownName| ParamError::BadChoice {
            name: name(s),
            source,
        };
        fn opt<T: std::str::FromStr<Err = UnknownName>>(v: &str) -> Result<Option<T>, UnknownName> {
            if v.is_empty() {
                Ok(None)
            } else {
                v.parse().map(Some)
            }
        }
        Ok(ChannelParams {
            period_ms: ms("period_ms"),
            min_on_ms: ms("min_on_ms"),
            min_off_ms: match int("min_off_ms") {
                i if i < 0 => None,
                i => Some(i as u64),
            },
            output_kind: text("output_kind")
                .parse()
                .map_err(|e| choice("output_kind", e))?,
            profile: text("profile").parse().map_err(|e| choice("profile", e))?,
            short_pulse: opt(&text("short_pulse")).map_err(|e| choice("short_pulse", e))?,
            edge_band: match get("edge_band") {
                Some(ParameterValue::Double(x)) => *x,
                _ => 0.0,
            },
            apply_at: opt(&text("apply_at")).map_err(|e| choice("apply_at", e))?,
            on_disable: opt(&text("on_disable")).map_err(|e| choice("on_disable", e))?,
            command_timeout_ms: ms("command_timeout_ms"),
            active_low: matches!(get("active_low"), Some(ParameterValue::Boolean(true))),
        })
    }

    /// Channel `ch`'s settings as the core's [`ChannelParams`].
    pub fn channel_params(&self, ch: usize) -> Result<ChannelParams, ParamError> {
        Self::channel_params_in(&self.values, ch)
    }

    /// Channel `ch`'s validated configuration.
    pub fn channel_config(&self, ch: usize) -> Result<ChannelConfig, ParamError> {
        self.channel_params(ch)?
            .validate()
            .map_err(|source| ParamError::Channel {
                channel: channel_name(ch),
                source,
            })
    }

    /// Checks a change as a whole (see the module documentation). Nothing is modified.
    pub fn check(
        &self,
        items: &[(String, ParameterValue)],
        phase: Phase,
    ) -> Result<Accepted, ParamError> {
        let mut working = self.values.clone();
        let mut notes = Vec::new();
        let mut order: Vec<String> = Vec::new();
        for (name, value) in items {
            let d = self.decls.get(name).ok_or_else(|| ParamError::Undeclared {
                name: name.clone(),
                hint: self.undeclared_hint(name),
            })?;
            let (v, note) = coerce(d, value)?;
            check_range(d, &v)?;
            check_choice(d, &v)?;
            if name == "use_sim_time" && v == ParameterValue::Boolean(true) {
                return Err(ParamError::SimTime);
            }
            if phase == Phase::Live && d.read_only && self.values.get(name) != Some(&v) {
                return Err(ParamError::ReadOnly {
                    name: name.clone(),
                    why: d.why_read_only,
                });
            }
            notes.extend(note);
            working.insert(name.clone(), v);
            order.retain(|n| n != name);
            order.push(name.clone());
        }
        let changes: Vec<(String, ParameterValue)> = order
            .into_iter()
            .filter_map(|n| {
                let v = working.get(&n)?;
                (self.values.get(&n) != Some(v)).then(|| (n, v.clone()))
            })
            .collect();
        let mut touched: Vec<usize> = changes
            .iter()
            .filter_map(|(n, _)| channel_of(n).map(|(ch, _)| ch))
            .collect();
        touched.sort_unstable();
        touched.dedup();
        let mut configs = Vec::new();
        for ch in touched {
            let new = Self::channel_params_in(&working, ch)?;
            let config = new.validate().map_err(|source| ParamError::Channel {
                channel: channel_name(ch),
                source,
            })?;
            if Self::channel_params_in(&self.values, ch).ok() != Some(new) {
                configs.push((ch, config));
            }
        }
        Ok(Accepted {
            changes,
            notes,
            configs,
        })
    }

    fn undeclared_hint(&self, name: &str) -> String {
        match channel_of(name) {
            Some((ch, _)) if ch >= self.channels => format!(
                " (this node has {} channel{}: pw01..{})",
                self.channels,
                if self.channels == 1 { "" } else { "s" },
                channel_name(self.channels - 1)
            ),
            _ => String::new(),
        }
    }

    /// Applies a checked change; returns the changed parameters in wire form, for
    /// `/parameter_events`.
    pub fn commit(&mut self, accepted: &Accepted) -> Vec<raw::Parameter> {
        accepted
            .changes
            .iter()
            .map(|(name, value)| {
                self.values.insert(name.clone(), value.clone());
                raw::Parameter {
                    name: name.clone(),
                    value: value.clone().into(),
                }
            })
            .collect()
    }
}

/// The parameter changes a `~/<ch>/params` message asks for: the fields named in `set`, as
/// `pwNN.field` values.
pub fn items_from_msg(
    ch: usize,
    m: &msg::ChannelParams,
) -> Result<Vec<(String, ParameterValue)>, ParamError> {
    let channel = channel_name(ch);
    if m.set.is_empty() {
        return Err(ParamError::EmptySet { channel });
    }
    use ParameterValue as V;
    m.set
        .iter()
        .map(|field| {
            let v = match field.as_str() {
                "period_ms" => V::Integer(m.period_ms),
                "min_on_ms" => V::Integer(m.min_on_ms),
                "min_off_ms" => V::Integer(m.min_off_ms),
                "output_kind" => V::String(m.output_kind.clone()),
                "profile" => V::String(m.profile.clone()),
                "short_pulse" => V::String(m.short_pulse.clone()),
                "edge_band" => V::Double(m.edge_band),
                "apply_at" => V::String(m.apply_at.clone()),
                "on_disable" => V::String(m.on_disable.clone()),
                "command_timeout_ms" => V::Integer(m.command_timeout_ms),
                "active_low" => V::Boolean(m.active_low),
                _ => {
                    return Err(ParamError::UnknownField {
                        channel: channel.clone(),
                        field: field.clone(),
                        fields: MSG_FIELDS,
                    })
                }
            };
            Ok((format!("{channel}.{field}"), v))
        })
        .collect()
}

/// A parameter value given at start-up, with where it came from.
#[derive(Debug, Clone, PartialEq)]
pub struct StartValue {
    /// Parameter name.
    pub name: String,
    /// Value as given.
    pub value: ParameterValue,
    /// Where it came from (`--demo`, `-p`, `--params-file x.yaml`, ...).
    pub origin: String,
}

/// The store built from start-up values, and what was said about them.
#[derive(Debug, Clone)]
pub struct StartUp {
    /// The store with every start-up value applied.
    pub store: ParamStore,
    /// Coercion notes.
    pub notes: Vec<String>,
    /// Values for parameters this node does not have, ignored (as rclcpp ignores overrides of
    /// undeclared parameters), as `name (origin)`.
    pub ignored: Vec<String>,
    /// Values accepted by ROS convention but not honoured, with why (`use_sim_time: true`
    /// from a launch file that sets it for every node).
    pub warnings: Vec<String>,
}

/// Builds the store from start-up values applied in order (a later value wins). The channel
/// count comes from the last `channels` value; values for parameters the node does not
/// declare are ignored and listed.
pub fn start_up(values: &[StartValue]) -> Result<StartUp, ParamError> {
    let channels_decl = make("channels".into(), &node_decls()[0]);
    let mut channels = DEFAULT_CHANNELS;
    for v in values.iter().filter(|v| v.name == "channels") {
        let (c, _) = coerce(&channels_decl, &v.value)?;
        check_range(&channels_decl, &c)?;
        if let ParameterValue::Integer(i) = c {
            channels = i as usize;
        }
    }
    let mut store = ParamStore::new(channels);
    let mut ignored = Vec::new();
    let mut warnings = Vec::new();
    let items: Vec<(String, ParameterValue)> = values
        .iter()
        .filter_map(|v| {
            if v.name == "use_sim_time" && v.value == ParameterValue::Boolean(true) {
                // Launch files often set it for every node; refusing to start would be worse
                // than saying plainly that it is not honoured.
                warnings.push(format!(
                    "use_sim_time true ({}) ignored: {}",
                    v.origin,
                    ParamError::SimTime
                ));
                None
            } else if store.decls.contains_key(&v.name) {
                Some((v.name.clone(), v.value.clone()))
            } else {
                ignored.push(format!("{} ({})", v.name, v.origin));
                None
            }
        })
        .collect();
    let accepted = store.check(&items, Phase::StartUp)?;
    store.commit(&accepted);
    // Defaults are valid by construction, but say so if a channel is not.
    for ch in 0..store.channels {
        store.channel_config(ch)?;
    }
    Ok(StartUp {
        store,
        notes: accepted.notes,
        ignored,
        warnings,
    })
}

/// One channel's GPIO line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LineSpec {
    /// Channel name.
    pub channel: String,
    /// Chip path or name.
    pub chip: String,
    /// Line offset.
    pub offset: u32,
    /// Inverted polarity.
    pub active_low: bool,
}

/// Where the edges go.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum OutputChoice {
    /// The simulated sink, with trace files (possibly none).
    Sim {
        /// Trace files.
        trace: Vec<PathBuf>,
    },
    /// GPIO lines, one per channel.
    Gpio {
        /// The lines, in channel order.
        lines: Vec<LineSpec>,
        /// Trace files of what was written to the lines (possibly none).
        trace: Vec<PathBuf>,
    },
}

/// One channel at start-up.
#[derive(Debug, Clone, PartialEq)]
pub struct ChannelStart {
    /// `pw01`, ...
    pub name: String,
    /// Validated configuration.
    pub config: ChannelConfig,
    /// Enabled at start-up.
    pub enable: bool,
    /// Duty at start-up, percent.
    pub duty_percent: f64,
}

/// What the node needs at start-up, read from the store.
#[derive(Debug, Clone, PartialEq)]
pub struct StartupConfig {
    /// Channels in order.
    pub channels: Vec<ChannelStart>,
    /// Output backend.
    pub output: OutputChoice,
    /// Periodic status rate, Hz (0 = on change only).
    pub status_rate_hz: f64,
    /// Edge lines per second and channel (0 = none).
    pub edge_log_rate: u32,
    /// SCHED_FIFO priority, if asked for.
    pub rt_priority: Option<i32>,
}

impl StartupConfig {
    /// Reads the start-up configuration from a store built by [`start_up`].
    pub fn from_store(store: &ParamStore) -> Result<StartupConfig, ParamError> {
        let mut channels = Vec::new();
        for ch in 0..store.channels() {
            let name = channel_name(ch);
            channels.push(ChannelStart {
                config: store.channel_config(ch)?,
                enable: store.bool(&format!("{name}.enable")).unwrap_or(false),
                duty_percent: store.double(&format!("{name}.duty")).unwrap_or(0.0),
                name,
            });
        }
        let trace: Vec<PathBuf> = store
            .string("trace")
            .unwrap_or("")
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(PathBuf::from)
            .collect();
        let output = if store.string("output") == Some("gpio") {
            let mut lines = Vec::new();
            for c in &channels {
                let offset = store.int(&format!("{}.gpio_line", c.name)).unwrap_or(-1);
                if offset < 0 {
                    return Err(ParamError::MissingLine {
                        channel: c.name.clone(),
                    });
                }
                lines.push(LineSpec {
                    channel: c.name.clone(),
                    chip: store
                        .string(&format!("{}.gpio_chip", c.name))
                        .unwrap_or("/dev/gpiochip0")
                        .to_string(),
                    offset: offset.min(u32::MAX as i64) as u32,
                    active_low: c.config.params.active_low,
                });
            }
            OutputChoice::Gpio { lines, trace }
        } else {
            OutputChoice::Sim { trace }
        };
        let rt = store.int("rt_priority").unwrap_or(0);
        Ok(StartupConfig {
            channels,
            output,
            status_rate_hz: store.double("status_rate_hz").unwrap_or(10.0),
            edge_log_rate: store.int("edge_log_rate").unwrap_or(10).clamp(0, 1000) as u32,
            rt_priority: (rt > 0).then_some(rt.min(99) as i32),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::MinTime;
    use ParameterValue as V;

    fn sv(name: &str, value: V) -> StartValue {
        StartValue {
            name: name.into(),
            value,
            origin: "-p".into(),
        }
    }

    fn item(name: &str, value: V) -> (String, V) {
        (name.into(), value)
    }

    #[test]
    fn declares_node_and_channel_parameters_with_defaults() {
        let s = ParamStore::new(2);
        assert_eq!(s.int("channels"), Some(2));
        assert_eq!(s.int("pw01.period_ms"), Some(1000));
        assert_eq!(s.int("pw02.min_off_ms"), Some(-1));
        assert_eq!(s.string("pw02.profile"), Some("pico_gfx"));
        assert_eq!(s.get("pw03.period_ms"), None);
        assert_eq!(s.channel_config(0).unwrap(), ChannelConfig::default());
        let d = s.descriptor("pw01.period_ms").unwrap().to_raw();
        assert_eq!(d.r#type, raw::ParameterType::INTEGER);
        assert_eq!(d.integer_range[0].to_value, 3_600_000);
        assert!(!d.description.is_empty() && !d.read_only);
        assert!(s.descriptor("pw01.active_low").unwrap().read_only);
        let d = s.descriptor("pw01.edge_band").unwrap().to_raw();
        assert_eq!(d.floating_point_range[0].to_value, 1.0);
    }

    #[test]
    fn coercion_is_lossless_or_refused() {
        let s = ParamStore::new(1);
        let a = s
            .check(&[item("pw01.period_ms", V::Double(500.0))], Phase::Live)
            .unwrap();
        assert_eq!(a.changes, vec![item("pw01.period_ms", V::Integer(500))]);
        assert_eq!(
            a.notes,
            vec!["pw01.period_ms: double 500.0 taken as integer 500"]
        );
        let a = s
            .check(&[item("pw01.edge_band", V::Integer(1))], Phase::Live)
            .unwrap();
        assert_eq!(a.changes, vec![item("pw01.edge_band", V::Double(1.0))]);
        let e = s
            .check(&[item("pw01.period_ms", V::Double(500.5))], Phase::Live)
            .unwrap_err();
        assert_eq!(
            e.to_string(),
            "parameter `pw01.period_ms` is an integer; 500.5 is not a whole number"
        );
        let e = s
            .check(
                &[item("pw01.period_ms", V::String("500".into()))],
                Phase::Live,
            )
            .unwrap_err();
        assert_eq!(
            e.to_string(),
            "parameter `pw01.period_ms` is an integer; got the string \"500\""
        );
        assert!(matches!(
            s.check(&[item("pw01.period_ms", V::Double(f64::NAN))], Phase::Live),
            Err(ParamError::WrongType { .. })
        ));
        assert!(matches!(
            s.check(&[item("pw01.active_low", V::Integer(1))], Phase::StartUp),
            Err(ParamError::WrongType { .. })
        ));
    }

    #[test]
    fn the_core_judges_channel_settings_and_cross_rules() {
        let s = ParamStore::new(2);
        let e = s
            .check(&[item("pw01.period_ms", V::Integer(4))], Phase::Live)
            .unwrap_err();
        assert_eq!(
            e,
            ParamError::Channel {
                channel: "pw01".into(),
                source: ConfigError::PeriodTooShort {
                    period_ms: 4,
                    min_ms: 5,
                    kind: OutputKind::Transistor
                }
            }
        );
        assert_eq!(
            e.to_string(),
            "pw01: period_ms 4 is below the transistor minimum of 5 ms (0 stops the pulses)"
        );
        // The relay minimum (000), whichever order the values come in.
        let e = s
            .check(
                &[
                    item("pw02.min_on_ms", V::Integer(30)),
                    item("pw02.output_kind", V::String("relay".into())),
                ],
                Phase::Live,
            )
            .unwrap_err();
        assert!(matches!(
            e,
            ParamError::Channel {
                source: ConfigError::RelayMinTimeTooShort {
                    which: MinTime::On,
                    ..
                },
                ..
            }
        ));
        let both = [
            item("pw02.min_on_ms", V::Integer(2000)),
            item("pw02.period_ms", V::Integer(5000)),
        ];
        let a = s.check(&both, Phase::Live).unwrap();
        assert_eq!(a.configs.len(), 1);
        assert_eq!(a.configs[0].0, 1);
        assert_eq!(a.configs[0].1.period, 5000 * crate::core::NS_PER_MS);
        // Negative times never reach the core.
        let e = s
            .check(&[item("pw01.period_ms", V::Integer(-5))], Phase::Live)
            .unwrap_err();
        assert_eq!(
            e.to_string(),
            "parameter `pw01.period_ms`: -5 is outside 0..3600000"
        );
        let e = s
            .check(&[item("pw01.min_off_ms", V::Integer(-2))], Phase::Live)
            .unwrap_err();
        assert!(e.to_string().contains("(-1 = as the profile says)"), "{e}");
        let e = s
            .check(&[item("pw01.edge_band", V::Double(f64::NAN))], Phase::Live)
            .unwrap_err();
        assert!(
            e.to_string()
                .starts_with("pw01: edge_band NaN is outside 0..1"),
            "{e}"
        );
    }

    #[test]
    fn choices_are_checked_with_the_accepted_spellings() {
        let s = ParamStore::new(1);
        let e = s
            .check(
                &[item("pw01.profile", V::String("pico".into()))],
                Phase::Live,
            )
            .unwrap_err();
        assert_eq!(
            e.to_string(),
            "parameter `pw01.profile`: `pico` is not one of: \
             pico_gfx|twincat_ba|tcont_cp|schneider_pwm|frequency_output"
        );
        assert!(s
            .check(
                &[item("pw01.short_pulse", V::String(String::new()))],
                Phase::Live
            )
            .is_ok());
        assert!(s
            .check(
                &[item("pw01.short_pulse", V::String("band".into()))],
                Phase::Live
            )
            .is_ok());
        assert!(s
            .check(&[item("output", V::String("spi".into()))], Phase::StartUp)
            .is_err());
    }

    #[test]
    fn read_only_parameters_refuse_live_changes_but_accept_their_value() {
        let s = ParamStore::new(1);
        let e = s
            .check(&[item("pw01.active_low", V::Boolean(true))], Phase::Live)
            .unwrap_err();
        assert!(matches!(e, ParamError::ReadOnly { .. }));
        assert!(e.to_string().contains("glitch"), "{e}");
        let a = s
            .check(&[item("pw01.active_low", V::Boolean(false))], Phase::Live)
            .unwrap();
        assert!(a.changes.is_empty() && a.configs.is_empty());
        assert!(s
            .check(&[item("channels", V::Integer(3))], Phase::Live)
            .is_err());
        assert!(s
            .check(&[item("pw01.active_low", V::Boolean(true))], Phase::StartUp)
            .is_ok());
        assert_eq!(
            s.check(&[item("use_sim_time", V::Boolean(true))], Phase::Live),
            Err(ParamError::SimTime)
        );
    }

    #[test]
    fn a_refused_change_leaves_the_store_as_it_was() {
        let mut s = ParamStore::new(1);
        let a = s
            .check(&[item("pw01.period_ms", V::Integer(500))], Phase::Live)
            .unwrap();
        let changed = s.commit(&a);
        assert_eq!(changed.len(), 1);
        assert_eq!(changed[0].name, "pw01.period_ms");
        assert_eq!(changed[0].value.int_value, 500);
        let bad = [
            item("pw01.period_ms", V::Integer(200)),
            item("pw01.min_on_ms", V::Integer(30)),
            item("pw01.output_kind", V::String("relay".into())),
        ];
        assert!(s.check(&bad, Phase::Live).is_err());
        assert_eq!(s.int("pw01.period_ms"), Some(500));
        assert_eq!(s.int("pw01.min_on_ms"), Some(0));
    }

    #[test]
    fn undeclared_names_get_a_hint() {
        let s = ParamStore::new(2);
        let e = s
            .check(&[item("pw03.period_ms", V::Integer(1))], Phase::Live)
            .unwrap_err();
        assert_eq!(
            e.to_string(),
            "parameter `pw03.period_ms` is not declared (this node has 2 channels: pw01..pw02)"
        );
        let e = s
            .check(&[item("speed", V::Integer(1))], Phase::Live)
            .unwrap_err();
        assert_eq!(e.to_string(), "parameter `speed` is not declared");
    }

    #[test]
    fn unchanged_values_are_not_changes() {
        let s = ParamStore::new(1);
        let a = s
            .check(&[item("pw01.period_ms", V::Integer(1000))], Phase::Live)
            .unwrap();
        assert_eq!(a, Accepted::default());
        // The last of repeated values wins.
        let a = s
            .check(
                &[
                    item("pw01.period_ms", V::Integer(10)),
                    item("pw01.period_ms", V::Integer(20)),
                ],
                Phase::Live,
            )
            .unwrap();
        assert_eq!(a.changes, vec![item("pw01.period_ms", V::Integer(20))]);
    }

    #[test]
    fn list_follows_rclcpp() {
        let s = ParamStore::new(1);
        let (names, prefixes) = s.list(&[], 1);
        assert!(names.contains(&"channels".to_string()));
        assert!(!names.iter().any(|n| n.contains('.')));
        assert!(prefixes.is_empty());
        let (names, prefixes) = s.list(&["pw01".into()], 0);
        assert!(names.iter().all(|n| n.starts_with("pw01.")));
        assert!(names.contains(&"pw01.period_ms".to_string()));
        assert_eq!(prefixes, vec!["pw01".to_string()]);
    }

    #[test]
    fn msg_items_use_only_the_fields_in_set() {
        let m = msg::ChannelParams {
            set: vec!["period_ms".into(), "profile".into()],
            period_ms: 500,
            profile: "tcont_cp".into(),
            min_on_ms: 99_999,
            ..Default::default()
        };
        assert_eq!(
            items_from_msg(0, &m).unwrap(),
            vec![
                item("pw01.period_ms", V::Integer(500)),
                item("pw01.profile", V::String("tcont_cp".into()))
            ]
        );
        assert_eq!(
            items_from_msg(1, &msg::ChannelParams::default()),
            Err(ParamError::EmptySet {
                channel: "pw02".into()
            })
        );
        let bad = msg::ChannelParams {
            set: vec!["period".into()],
            ..Default::default()
        };
        assert!(matches!(
            items_from_msg(0, &bad),
            Err(ParamError::UnknownField { .. })
        ));
    }

    #[test]
    fn start_up_reads_channels_first_and_ignores_unknown_names() {
        let su = start_up(&[
            sv("pw03.period_ms", V::Integer(300)),
            sv("channels", V::Integer(3)),
            sv("other_node_param", V::Integer(1)),
            sv("pw01.duty", V::Integer(37)),
            sv("pw01.enable", V::Boolean(true)),
            sv("pw04.period_ms", V::Integer(1)),
        ])
        .unwrap();
        assert_eq!(su.store.channels(), 3);
        assert_eq!(su.store.int("pw03.period_ms"), Some(300));
        assert_eq!(
            su.ignored,
            vec!["other_node_param (-p)", "pw04.period_ms (-p)"]
        );
        assert_eq!(su.notes, vec!["pw01.duty: integer 37 taken as double 37.0"]);
        let cfg = StartupConfig::from_store(&su.store).unwrap();
        assert_eq!(cfg.channels.len(), 3);
        assert!(cfg.channels[0].enable);
        assert_eq!(cfg.channels[0].duty_percent, 37.0);
        assert_eq!(cfg.output, OutputChoice::Sim { trace: vec![] });
        assert_eq!(cfg.rt_priority, None);
        assert!(start_up(&[sv("channels", V::Integer(0))]).is_err());
        assert!(start_up(&[sv("channels", V::Integer(100))]).is_err());
        assert!(start_up(&[sv("pw01.duty", V::Double(150.0))]).is_err());
        let su = start_up(&[sv("use_sim_time", V::Boolean(true))]).unwrap();
        assert_eq!(su.store.bool("use_sim_time"), Some(false));
        assert!(su.warnings[0].starts_with("use_sim_time true (-p) ignored: "));
    }

    #[test]
    fn gpio_needs_lines_and_takes_a_trace() {
        let su = start_up(&[
            sv("channels", V::Integer(1)),
            sv("output", V::String("gpio".into())),
        ])
        .unwrap();
        assert_eq!(
            StartupConfig::from_store(&su.store),
            Err(ParamError::MissingLine {
                channel: "pw01".into()
            })
        );
        let su = start_up(&[
            sv("channels", V::Integer(1)),
            sv("output", V::String("gpio".into())),
            sv("pw01.gpio_line", V::Integer(17)),
            sv("pw01.active_low", V::Boolean(true)),
        ])
        .unwrap();
        let cfg = StartupConfig::from_store(&su.store).unwrap();
        assert_eq!(
            cfg.output,
            OutputChoice::Gpio {
                lines: vec![LineSpec {
                    channel: "pw01".into(),
                    chip: "/dev/gpiochip0".into(),
                    offset: 17,
                    active_low: true
                }],
                trace: vec![],
            }
        );
        let su = start_up(&[
            sv("channels", V::Integer(1)),
            sv("output", V::String("gpio".into())),
            sv("pw01.gpio_line", V::Integer(17)),
            sv("trace", V::String("a.vcd".into())),
        ])
        .unwrap();
        // Any output can be traced: with gpio the trace records what was written to the lines.
        let OutputChoice::Gpio { trace, .. } = StartupConfig::from_store(&su.store).unwrap().output
        else {
            panic!("output gpio not chosen");
        };
        assert_eq!(trace, [PathBuf::from("a.vcd")]);
        let su = start_up(&[sv("trace", V::String("a.vcd, b.csv".into()))]).unwrap();
        assert_eq!(
            StartupConfig::from_store(&su.store).unwrap().output,
            OutputChoice::Sim {
                trace: vec!["a.vcd".into(), "b.csv".into()]
            }
        );
    }

    #[test]
    fn channel_names() {
        assert_eq!(channel_name(0), "pw01");
        assert_eq!(channel_name(98), "pw99");
        assert_eq!(channel_of("pw01.period_ms"), Some((0, "period_ms")));
        assert_eq!(channel_of("pw12.duty"), Some((11, "duty")));
        assert_eq!(channel_of("pw1.duty"), None);
        assert_eq!(channel_of("pw00.duty"), None);
        assert_eq!(channel_of("channels"), None);
    }
}
