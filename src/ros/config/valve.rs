//! Three-point valves as the user states them: the start-up parameter `valve`, a
//! comma-separated list of `NAME:OPEN:CLOSE`, checked against the channels there are and the
//! split-range pairs. Each valve gets `~/valve/<NAME>/position` and `~/valve/<NAME>/state`, and
//! its settings are the parameters `NAME.*`.
//!
//! Only parsing and checking live here; the output thread runs the valve (`core::valve`).

use crate::core::config::ShortStr;
use crate::core::valve::ValveConfigError;
use crate::output::bindings::normalize_chip_path;
use crate::output::gpio::{parse_line_addr, GpioLine};
use crate::ros::config::split::SplitPair;
use crate::ros::config::valve_state::StateDirError;
use std::path::PathBuf;

/// At most this many valves (each needs two channels of at most 99).
pub const MAX_VALVES: usize = 49;

/// Longest valve name, bytes (it becomes a topic name segment and a parameter prefix).
pub const MAX_NAME_LEN: usize = 32;

/// One valve.
#[derive(Debug, Clone, PartialEq)]
pub struct ValveSpec {
    /// The valve's name, the `<NAME>` of `~/valve/<NAME>/position` and of `NAME.*`.
    pub name: String,
    /// Index of the channel whose line drives the actuator open.
    pub open: usize,
    /// Index of the channel whose line drives it closed.
    pub close: usize,
}

/// Why the `valve` parameter or a valve's settings are refused (the node does not start:
/// exit 2).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ValveError {
    /// An entry that is not `NAME:OPEN:CLOSE`.
    #[error("valve: `{entry}` is not NAME:OPEN:CLOSE (e.g. mix:pw01:pw02)")]
    Form {
        /// The entry (its first 32 bytes).
        entry: ShortStr,
    },
    /// A name that cannot be a topic segment and parameter prefix, or has a channel's form.
    #[error(
        "valve: name `{name}` must start with a letter, hold only letters, digits and `_`, at \
         most {MAX_NAME_LEN} bytes, and not be of a channel's form (pwNN)"
    )]
    Name {
        /// The name (its first 32 bytes).
        name: ShortStr,
    },
    /// Two valves with one name.
    #[error("valve: two valves are named `{name}`")]
    DuplicateName {
        /// The name.
        name: ShortStr,
    },
    /// A channel that does not exist.
    #[error("valve: `{channel}` is not a channel of this node (pw01..pw{last:02})")]
    NoSuchChannel {
        /// The name given (its first 32 bytes).
        channel: ShortStr,
        /// The number of the last channel.
        last: usize,
    },
    /// A channel used twice, or already in a split-range pair.
    #[error(
        "valve: channel {channel} is used twice (valve `{name}`); each channel is in one \
         valve or split pair at most"
    )]
    ChannelTwice {
        /// The channel.
        channel: ShortStr,
        /// The valve where it appeared again.
        name: ShortStr,
    },
    /// More valves than channels allow.
    #[error("valve: more than {MAX_VALVES} valves")]
    TooMany,
    /// A limit line that is not `[CHIP:]OFFSET`.
    #[error("valve `{name}`: {param} `{value}` is not [CHIP:]OFFSET (e.g. 5 or gpiochip1:5)")]
    LimitForm {
        /// The valve.
        name: ShortStr,
        /// The parameter's suffix.
        param: &'static str,
        /// The value (its first 32 bytes).
        value: ShortStr,
    },
    /// Limit lines with the simulated output.
    #[error(
        "valve `{name}`: end switch lines need --output gpio (the simulated output has no \
         GPIO chips)"
    )]
    LimitNeedsGpio {
        /// The valve.
        name: ShortStr,
    },
    /// A limit line that is also an output line of the node, or a second limit line.
    #[error("valve `{name}`: {param} {chip}:{offset} is already {what}")]
    LimitLineTaken {
        /// The valve.
        name: ShortStr,
        /// The parameter's suffix.
        param: &'static str,
        /// The chip (its first 32 bytes).
        chip: ShortStr,
        /// The offset.
        offset: u32,
        /// What holds it (`the output line of pw01`, `an end switch line`).
        what: ShortStr,
    },
    /// `state_dir` is not a writable directory.
    #[error(transparent)]
    StateDir(#[from] StateDirError),
    /// A valve's settings refused by the core.
    #[error("valve `{name}`: {source}")]
    Settings {
        /// The valve.
        name: ShortStr,
        /// Why.
        #[source]
        source: ValveConfigError,
    },
}

/// Chip of a limit line given as a bare offset.
pub const DEFAULT_LIMIT_CHIP: &str = "/dev/gpiochip0";

/// An end switch's input line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LimitLine {
    /// The chip path as given (`/dev/gpiochip0` when only an offset was given).
    pub chip: PathBuf,
    /// The line offset.
    pub offset: u32,
}

/// A valve's end switches, from `NAME.open_limit_line`, `NAME.close_limit_line`,
/// `NAME.limit_active_low` and `NAME.limit_debounce_ms`.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct ValveLimits {
    /// The switch at the open end.
    pub open: Option<LimitLine>,
    /// The switch at the closed end.
    pub close: Option<LimitLine>,
    /// Both switches are active with their line electrically low.
    pub active_low: bool,
    /// Debounce period the kernel applies to both lines, ms.
    pub debounce_ms: u64,
}

impl ValveLimits {
    /// Whether the valve has a switch at all.
    pub fn any(&self) -> bool {
        self.open.is_some() || self.close.is_some()
    }
}

/// The limit line of parameter `param` of valve `name` from its text (empty: none).
pub fn limit_line(
    name: &str,
    param: &'static str,
    text: &str,
) -> Result<Option<LimitLine>, ValveError> {
    let text = text.trim();
    if text.is_empty() {
        return Ok(None);
    }
    let (chip, offset) = parse_line_addr(text).ok_or(ValveError::LimitForm {
        name: ShortStr::new(name),
        param,
        value: ShortStr::new(text),
    })?;
    Ok(Some(LimitLine {
        chip: PathBuf::from(chip.unwrap_or(DEFAULT_LIMIT_CHIP)),
        offset,
    }))
}

/// Checks the valves' limit lines (`(valve name, limits)` in order) against the output:
/// none under the simulated output (`outputs` = `None`), none on an output line of the node
/// nor two on one line (chip paths compared after normalisation).
pub fn check_limits(
    limits: &[(&str, &ValveLimits)],
    outputs: Option<&[GpioLine]>,
) -> Result<(), ValveError> {
    let mut seen: Vec<(PathBuf, u32)> = Vec::new();
    for (name, l) in limits {
        let Some(outputs) = outputs else {
            if l.any() {
                return Err(ValveError::LimitNeedsGpio {
                    name: ShortStr::new(name),
                });
            }
            continue;
        };
        let each = [("open_limit_line", &l.open), ("close_limit_line", &l.close)];
        for (param, line) in each {
            let Some(line) = line else { continue };
            let chip = normalize_chip_path(&line.chip);
            let taken = |what: String| ValveError::LimitLineTaken {
                name: ShortStr::new(name),
                param,
                chip: ShortStr::new(&line.chip.to_string_lossy()),
                offset: line.offset,
                what: ShortStr::new(&what),
            };
            if let Some(o) = outputs
                .iter()
                .find(|o| o.offset == line.offset && normalize_chip_path(&o.chip) == chip)
            {
                return Err(taken(format!("the output line of {}", o.name)));
            }
            if seen.contains(&(chip.clone(), line.offset)) {
                return Err(taken("an end switch line".into()));
            }
            seen.push((chip, line.offset));
        }
    }
    Ok(())
}

fn entries(text: &str) -> impl Iterator<Item = &str> {
    text.split(',').map(str::trim).filter(|e| !e.is_empty())
}

/// A channel's form: `pw` and two digits.
fn channel_form(name: &str) -> bool {
    name.strip_prefix("pw")
        .is_some_and(|d| d.len() == 2 && d.bytes().all(|b| b.is_ascii_digit()))
}

fn valid_name(name: &str) -> bool {
    name.len() <= MAX_NAME_LEN
        && name.chars().next().is_some_and(|c| c.is_ascii_alphabetic())
        && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        && !channel_form(name)
}

/// The valid names of the valves in `text`, at most [`MAX_VALVES`], each once: those whose
/// parameters are declared before the start-up values are applied ([`parse`] refuses the rest).
pub fn names(text: &str) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for e in entries(text).take(MAX_VALVES) {
        let name = e.split(':').next().unwrap_or("").trim();
        if valid_name(name) && !out.iter().any(|n| n == name) {
            out.push(name.to_string());
        }
    }
    out
}

/// Parses `text` against the channel names in order (`pw01`, `pw02`, ...) and the split-range
/// pairs. Empty text: no valves.
pub fn parse(
    text: &str,
    channels: &[String],
    splits: &[SplitPair],
) -> Result<Vec<ValveSpec>, ValveError> {
    let list: Vec<&str> = entries(text).collect();
    if list.len() > MAX_VALVES {
        return Err(ValveError::TooMany);
    }
    let mut valves: Vec<ValveSpec> = Vec::new();
    for entry in list {
        let fields: Vec<&str> = entry.split(':').map(str::trim).collect();
        if fields.len() != 3 {
            return Err(ValveError::Form {
                entry: ShortStr::new(entry),
            });
        }
        let name = fields[0];
        if !valid_name(name) {
            return Err(ValveError::Name {
                name: ShortStr::new(name),
            });
        }
        if valves.iter().any(|v| v.name == name) {
            return Err(ValveError::DuplicateName {
                name: ShortStr::new(name),
            });
        }
        let index = |ch: &str| {
            channels
                .iter()
                .position(|c| c == ch)
                .ok_or(ValveError::NoSuchChannel {
                    channel: ShortStr::new(ch),
                    last: channels.len(),
                })
        };
        let (open, close) = (index(fields[1])?, index(fields[2])?);
        for (ch, text) in [(open, fields[1]), (close, fields[2])] {
            let in_valve = valves.iter().any(|v| v.open == ch || v.close == ch);
            let in_split = splits.iter().any(|p| p.hot == ch || p.cold == ch);
            if in_valve || in_split || open == close {
                return Err(ValveError::ChannelTwice {
                    channel: ShortStr::new(text),
                    name: ShortStr::new(name),
                });
            }
        }
        valves.push(ValveSpec {
            name: name.to_string(),
            open,
            close,
        });
    }
    Ok(valves)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chans(n: usize) -> Vec<String> {
        (1..=n).map(|i| format!("pw{i:02}")).collect()
    }

    #[test]
    fn valves_parse() {
        assert_eq!(parse("", &chans(2), &[]), Ok(vec![]));
        assert_eq!(
            parse(" mix:pw01:pw02 , b:pw04:pw03", &chans(4), &[]),
            Ok(vec![
                ValveSpec {
                    name: "mix".into(),
                    open: 0,
                    close: 1
                },
                ValveSpec {
                    name: "b".into(),
                    open: 3,
                    close: 2
                }
            ])
        );
        assert_eq!(
            names("mix:pw01:pw02,9x:pw03:pw04,mix:a:b,pw07:x:y"),
            ["mix"]
        );
    }

    fn out(name: &str, chip: &str, offset: u32) -> GpioLine {
        GpioLine {
            name: name.into(),
            chip: chip.into(),
            offset,
            active_low: false,
        }
    }

    #[test]
    fn limit_lines_parse_as_chip_and_offset() {
        assert_eq!(limit_line("m", "open_limit_line", " "), Ok(None));
        let l = limit_line("m", "open_limit_line", "7").unwrap().unwrap();
        assert_eq!((l.chip.to_str(), l.offset), (Some(DEFAULT_LIMIT_CHIP), 7));
        let l = limit_line("m", "close_limit_line", "gpiochip1:4")
            .unwrap()
            .unwrap();
        assert_eq!((l.chip.to_str(), l.offset), (Some("gpiochip1"), 4));
        let e = limit_line("m", "close_limit_line", "x:y")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("close_limit_line `x:y` is not [CHIP:]OFFSET"),
            "{e}"
        );
        assert!(limit_line("m", "open_limit_line", "-1").is_err());
    }

    #[test]
    fn limit_lines_are_refused_on_outputs_twice_and_under_sim() {
        let line = |t: &str| limit_line("m", "close_limit_line", t).unwrap();
        let l = ValveLimits {
            close: line("/dev/gpiochip0:2"),
            ..ValveLimits::default()
        };
        let outputs = [
            out("pw01", "/dev/gpiochip0", 0),
            out("pw02", "gpiochip0", 2),
        ];
        let e = check_limits(&[("m", &l)], Some(&outputs))
            .unwrap_err()
            .to_string();
        assert!(e.contains("is already the output line of pw02"), "{e}");
        let e = check_limits(&[("m", &l)], None).unwrap_err().to_string();
        assert!(e.contains("need --output gpio"), "{e}");
        let none = ValveLimits::default();
        assert_eq!(check_limits(&[("m", &none)], None), Ok(()));
        let ok = ValveLimits {
            open: line("5"),
            close: line("gpiochip0:6"),
            ..ValveLimits::default()
        };
        assert_eq!(check_limits(&[("m", &ok)], Some(&outputs)), Ok(()));
        let twice = ValveLimits {
            open: line("6"),
            ..ValveLimits::default()
        };
        let e = check_limits(&[("m", &ok), ("n", &twice)], Some(&outputs))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("valve `n`") && e.contains("an end switch line"),
            "{e}"
        );
    }

    #[test]
    fn bad_valves_are_refused_with_the_reason() {
        let c = chans(4);
        let split = [SplitPair {
            name: "z".into(),
            hot: 2,
            cold: 3,
            deadband_pct: 0.0,
        }];
        let e = |t: &str| parse(t, &c, &split).unwrap_err().to_string();
        assert!(e("mix").contains("is not NAME:OPEN:CLOSE"));
        assert!(e("mix:pw01:pw02:3").contains("is not NAME:OPEN:CLOSE"));
        assert!(e("1mix:pw01:pw02").contains("must start with a letter"));
        assert!(e("pw01:pw01:pw02").contains("channel's form"));
        assert!(e("m:pw01:pw09").contains("`pw09` is not a channel of this node (pw01..pw04)"));
        assert!(e("m:pw01:pw01").contains("used twice"));
        assert!(
            e("m:pw01:pw03").contains("used twice"),
            "pw03 is in a split pair"
        );
        assert!(e("m:pw01:pw02,n:pw02:pw01").contains("used twice"));
        assert!(e("m:pw01:pw02,m:pw01:pw02").contains("two valves are named"));
        let long = format!("m:pw01:{}", "x".repeat(10_000));
        assert!(e(&long).len() < 200, "echoed input is bounded");
        let many = vec!["a:pw01:pw02"; MAX_VALVES + 1].join(",");
        assert_eq!(parse(&many, &c, &[]), Err(ValveError::TooMany));
    }
}
