//! Split-range pairs as the user states them (001's "Hot/Cold or Split Range case"): the
//! start-up parameter `split`, a comma-separated list of `NAME:HOT:COLD[:DEADBAND_PCT]`, checked
//! against the channels there are. Each pair gets a topic `~/split/<NAME>/command`.
//!
//! Only parsing and checking live here; the output thread keeps the two lines of a pair apart
//! (`core::Interlocks`) and `core::split_command` maps a signed command to the two duties.

use crate::core::config::ShortStr;

/// At most this many pairs (each needs two channels of at most 99).
pub const MAX_PAIRS: usize = 49;

/// Longest pair name, bytes (it becomes a topic name segment).
pub const MAX_NAME_LEN: usize = 32;

/// One split-range pair.
#[derive(Debug, Clone, PartialEq)]
pub struct SplitPair {
    /// The pair's name, the `<NAME>` of `~/split/<NAME>/command`.
    pub name: String,
    /// Index of the channel driven by positive commands (heating).
    pub hot: usize,
    /// Index of the channel driven by negative commands (cooling).
    pub cold: usize,
    /// Dead band around 0, percent 0..=100: commands within it drive neither channel.
    pub deadband_pct: f64,
}

/// Why the `split` parameter is refused (the node does not start: exit 2).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SplitError {
    /// An entry that is not `NAME:HOT:COLD[:DEADBAND_PCT]`.
    #[error("split: `{entry}` is not NAME:HOT:COLD[:DEADBAND_PCT] (e.g. zone1:pw01:pw02:2)")]
    Form {
        /// The entry (its first 32 bytes).
        entry: ShortStr,
    },
    /// A pair name that cannot be a topic name segment.
    #[error(
        "split: pair name `{name}` must start with a letter and hold only letters, digits and \
         `_`, at most {MAX_NAME_LEN} bytes"
    )]
    Name {
        /// The name (its first 32 bytes).
        name: ShortStr,
    },
    /// Two pairs with one name.
    #[error("split: two pairs are named `{name}`")]
    DuplicateName {
        /// The name.
        name: ShortStr,
    },
    /// A channel that does not exist.
    #[error("split: `{channel}` is not a channel of this node (pw01..pw{last:02})")]
    NoSuchChannel {
        /// The name given (its first 32 bytes).
        channel: ShortStr,
        /// The number of the last channel.
        last: usize,
    },
    /// Hot and cold are one channel, or a channel is in two pairs.
    #[error("split: channel {channel} is used twice (pair `{name}`); each channel is in one pair at most, on one side")]
    ChannelTwice {
        /// The channel.
        channel: ShortStr,
        /// The pair where it appeared again.
        name: ShortStr,
    },
    /// A dead band that is not a number in 0..=100.
    #[error("split: dead band `{value}` of pair `{name}` is not a percentage 0..100")]
    Deadband {
        /// The value given (its first 32 bytes).
        value: ShortStr,
        /// The pair.
        name: ShortStr,
    },
    /// More pairs than channels allow.
    #[error("split: more than {MAX_PAIRS} pairs")]
    TooMany,
}

/// Parses `text` against the channel names in order (`pw01`, `pw02`, ...). Empty text: no
/// pairs.
pub fn parse(text: &str, channels: &[String]) -> Result<Vec<SplitPair>, SplitError> {
    let entries: Vec<&str> = text
        .split(',')
        .map(str::trim)
        .filter(|e| !e.is_empty())
        .collect();
    if entries.len() > MAX_PAIRS {
        return Err(SplitError::TooMany);
    }
    let mut pairs: Vec<SplitPair> = Vec::new();
    for entry in entries {
        let fields: Vec<&str> = entry.split(':').map(str::trim).collect();
        if !(3..=4).contains(&fields.len()) {
            return Err(SplitError::Form {
                entry: ShortStr::new(entry),
            });
        }
        let name = fields[0];
        let valid_name = name.len() <= MAX_NAME_LEN
            && name.chars().next().is_some_and(|c| c.is_ascii_alphabetic())
            && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
        if !valid_name {
            return Err(SplitError::Name {
                name: ShortStr::new(name),
            });
        }
        if pairs.iter().any(|p| p.name == name) {
            return Err(SplitError::DuplicateName {
                name: ShortStr::new(name),
            });
        }
        let index = |ch: &str| {
            channels
                .iter()
                .position(|c| c == ch)
                .ok_or(SplitError::NoSuchChannel {
                    channel: ShortStr::new(ch),
                    last: channels.len(),
                })
        };
        let (hot, cold) = (index(fields[1])?, index(fields[2])?);
        for (ch, text) in [(hot, fields[1]), (cold, fields[2])] {
            let used = pairs.iter().any(|p| p.hot == ch || p.cold == ch);
            if used || hot == cold {
                return Err(SplitError::ChannelTwice {
                    channel: ShortStr::new(text),
                    name: ShortStr::new(name),
                });
            }
        }
        let deadband_pct = match fields.get(3) {
            None => 0.0,
            Some(v) => v
                .parse::<f64>()
                .ok()
                .filter(|d| (0.0..=100.0).contains(d))
                .ok_or(SplitError::Deadband {
                    value: ShortStr::new(v),
                    name: ShortStr::new(name),
                })?,
        };
        pairs.push(SplitPair {
            name: name.to_string(),
            hot,
            cold,
            deadband_pct,
        });
    }
    Ok(pairs)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chans(n: usize) -> Vec<String> {
        (1..=n).map(|i| format!("pw{i:02}")).collect()
    }

    #[test]
    fn pairs_parse_with_an_optional_dead_band() {
        assert_eq!(parse("", &chans(2)), Ok(vec![]));
        assert_eq!(
            parse(" zone1:pw01:pw02:2.5 , b:pw04:pw03", &chans(4)),
            Ok(vec![
                SplitPair {
                    name: "zone1".into(),
                    hot: 0,
                    cold: 1,
                    deadband_pct: 2.5
                },
                SplitPair {
                    name: "b".into(),
                    hot: 3,
                    cold: 2,
                    deadband_pct: 0.0
                }
            ])
        );
    }

    #[test]
    fn bad_pairs_are_refused_with_the_reason() {
        let c = chans(3);
        let e = |t: &str| parse(t, &c).unwrap_err().to_string();
        assert!(e("zone").contains("is not NAME:HOT:COLD"));
        assert!(e("1zone:pw01:pw02").contains("must start with a letter"));
        assert!(e("a/b:pw01:pw02").contains("must start with a letter"));
        assert!(e("z:pw01:pw09").contains("`pw09` is not a channel of this node (pw01..pw03)"));
        assert!(e("z:pw01:pw01").contains("used twice"));
        assert!(e("z:pw01:pw02,y:pw03:pw02").contains("used twice"));
        assert!(e("z:pw01:pw02,z:pw03:pw02").contains("two pairs are named"));
        assert!(e("z:pw01:pw02:-1").contains("not a percentage"));
        assert!(e("z:pw01:pw02:NaN").contains("not a percentage"));
        let long = format!("z:pw01:{}", "x".repeat(10_000));
        assert!(e(&long).len() < 200, "echoed input is bounded");
        let many = vec!["a:pw01:pw02"; MAX_PAIRS + 1].join(",");
        assert_eq!(parse(&many, &c), Err(SplitError::TooMany));
    }
}
