//! The named choices of a channel's settings: the output kind, the policies for short pulses,
//! for when a command takes effect and for a falling enable, and the profiles that bundle
//! them after a vendor block; with their spellings and the error for an unknown one.

use super::{Nanos, NS_PER_MS};
use std::fmt;

/// The electrical kind of output, which sets the limits of 000's table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum OutputKind {
    /// Transistor (solid-state) output: period >= 5 ms, shortest on/off time 0.1 ms (000).
    #[default]
    Transistor,
    /// Relay output: period >= 100 ms, minimum on time >= 50 ms (000).
    Relay,
}

impl OutputKind {
    /// Shortest period accepted when the period is not 0, in ms (000: transistor 5, relay 100).
    pub const fn min_period_ms(self) -> u64 {
        match self {
            OutputKind::Transistor => 5,
            OutputKind::Relay => 100,
        }
    }

    /// The hardware floor for on and off times, in ns (000: transistor 0.1 ms, relay 50 ms).
    pub const fn floor_ns(self) -> Nanos {
        match self {
            OutputKind::Transistor => 100_000,
            OutputKind::Relay => 50 * NS_PER_MS,
        }
    }

    /// Shortest explicit (non-zero) minimum time accepted, in ms (000: relay min on 50 ms).
    pub const fn min_explicit_time_ms(self) -> u64 {
        match self {
            OutputKind::Transistor => 0,
            OutputKind::Relay => 50,
        }
    }

    /// The parameter spelling: `transistor` or `relay`.
    pub const fn as_str(self) -> &'static str {
        match self {
            OutputKind::Transistor => "transistor",
            OutputKind::Relay => "relay",
        }
    }
}

/// What happens to a pulse or break shorter than its minimum (SPEC §1.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum ShortPulse {
    /// 000, 001, 003: a too-short pulse is not emitted (output 0 for the period), a too-short
    /// break is not emitted (output 1 for the period); E1 is set.
    #[default]
    Suppress,
    /// 002: a too-short pulse is raised to the minimum (bLmtSwiTi), the break shrinks to keep the
    /// period; likewise a too-short break is raised to its minimum.
    Stretch,
    /// 004: the Frequency_Output edge band `edge_band` decides constant 0 / PWM / constant 1.
    Band,
    /// Cycle extension (PLC PWM output modules' "extend cycle"): the period grows so that the
    /// short pulse or break is exactly its minimum and the duty is kept, up to `extend_max`
    /// times the period; beyond that the pulse or break is suppressed, as with `suppress`.
    Extend,
}

impl ShortPulse {
    /// The parameter spelling.
    pub const fn as_str(self) -> &'static str {
        match self {
            ShortPulse::Suppress => "suppress",
            ShortPulse::Stretch => "stretch",
            ShortPulse::Band => "band",
            ShortPulse::Extend => "extend",
        }
    }
}

/// When a new command takes effect (SPEC §1.3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum ApplyAt {
    /// 000: the running period completes with the times computed at its start.
    #[default]
    NextPeriod,
    /// 002: the running on or off step completes with its latched time.
    NextStep,
    /// 003: the running pulse or break is extended or ended at once (never below its minimum).
    Immediate,
}

impl ApplyAt {
    /// The parameter spelling.
    pub const fn as_str(self) -> &'static str {
        match self {
            ApplyAt::NextPeriod => "next_period",
            ApplyAt::NextStep => "next_step",
            ApplyAt::Immediate => "immediate",
        }
    }
}

/// What a falling edge of enable does to the output (SPEC §1.4).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum OnDisable {
    /// 000, 002: the output goes to 0 at once.
    #[default]
    Off,
    /// 004: the output keeps its current level until enabled again.
    Hold,
}

impl OnDisable {
    /// The parameter spelling.
    pub const fn as_str(self) -> &'static str {
        match self {
            OnDisable::Off => "off",
            OnDisable::Hold => "hold",
        }
    }
}

/// A coherent set of policies named after the vendor block it reproduces.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Profile {
    /// Eaton Pico GFX PW01/PW02 (000): suppress, next_period, off; min off = min on.
    #[default]
    PicoGfx,
    /// Beckhoff FB_BA_PWM (002): stretch the on time only, next_step, off; min off = floor.
    TwincatBa,
    /// Siemens TCONT_CP pulse generator (003): suppress, immediate, off; min off = min on.
    TcontCp,
    /// Schneider PWM (001): suppress, next_period, off; min off = floor (T_MINI is a minimum
    /// pulse).
    SchneiderPwm,
    /// Schneider Frequency_Output (004): band, next_period, hold; min off = min on.
    FrequencyOutput,
}

impl Profile {
    /// Every profile, in documentation order.
    pub const ALL: [Profile; 5] = [
        Profile::PicoGfx,
        Profile::TwincatBa,
        Profile::TcontCp,
        Profile::SchneiderPwm,
        Profile::FrequencyOutput,
    ];

    /// The parameter spelling.
    pub const fn as_str(self) -> &'static str {
        match self {
            Profile::PicoGfx => "pico_gfx",
            Profile::TwincatBa => "twincat_ba",
            Profile::TcontCp => "tcont_cp",
            Profile::SchneiderPwm => "schneider_pwm",
            Profile::FrequencyOutput => "frequency_output",
        }
    }

    /// The short-pulse policy this profile implies.
    pub const fn short_pulse(self) -> ShortPulse {
        match self {
            Profile::TwincatBa => ShortPulse::Stretch,
            Profile::FrequencyOutput => ShortPulse::Band,
            _ => ShortPulse::Suppress,
        }
    }

    /// The apply-at policy this profile implies.
    pub const fn apply_at(self) -> ApplyAt {
        match self {
            Profile::TwincatBa => ApplyAt::NextStep,
            Profile::TcontCp => ApplyAt::Immediate,
            _ => ApplyAt::NextPeriod,
        }
    }

    /// The disable policy this profile implies.
    pub const fn on_disable(self) -> OnDisable {
        match self {
            Profile::FrequencyOutput => OnDisable::Hold,
            _ => OnDisable::Off,
        }
    }

    /// Whether an unset `min_off_ms` follows `min_on_ms` (000) or falls to the hardware floor
    /// (002: nMinSwiTi limits the switch-on time only; 001: T_MINI is "a minimum pulse").
    pub const fn min_off_follows_min_on(self) -> bool {
        !matches!(self, Profile::TwincatBa | Profile::SchneiderPwm)
    }

    /// The vendor block this profile reproduces, for documentation and diagnostics.
    pub const fn vendor_block(self) -> &'static str {
        match self {
            Profile::PicoGfx => "Eaton Pico GFX PW01/PW02",
            Profile::TwincatBa => "Beckhoff TwinCAT FB_BA_PWM",
            Profile::TcontCp => "Siemens S7 TCONT_CP pulse generator",
            Profile::SchneiderPwm => "Schneider process library PWM",
            Profile::FrequencyOutput => "Schneider Frequency_Output",
        }
    }
}

/// A policy or profile name that is not one of the accepted spellings.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("`{value}` is not one of: {accepted}")]
pub struct UnknownName {
    /// What was asked for (truncated to its first 32 bytes when longer).
    pub value: ShortStr,
    /// The accepted spellings, `|`-separated.
    pub accepted: &'static str,
}

/// A short, `Copy` string for error values (at most 32 bytes, cut at a char boundary).
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct ShortStr {
    buf: [u8; 32],
    len: u8,
}

impl ShortStr {
    /// Keeps the first 32 bytes of `s` (at a char boundary).
    pub fn new(s: &str) -> Self {
        let mut end = s.len().min(32);
        while !s.is_char_boundary(end) {
            end -= 1;
        }
        let mut buf = [0u8; 32];
        buf[..end].copy_from_slice(&s.as_bytes()[..end]);
        ShortStr {
            buf,
            len: end as u8,
        }
    }

    /// The kept text.
    pub fn as_str(&self) -> &str {
        // Always cut at a char boundary of valid UTF-8 in `new`.
        std::str::from_utf8(&self.buf[..self.len as usize]).unwrap_or("")
    }
}

impl fmt::Display for ShortStr {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl fmt::Debug for ShortStr {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self.as_str(), f)
    }
}

/// `FromStr` (refusing other spellings with [`UnknownName`]) and `Display` for an enum of named
/// choices with an `as_str`, from the list of its values.
macro_rules! named_enum {
    ($ty:ty, $accepted:literal, [$($v:expr),+ $(,)?]) => {
        impl std::str::FromStr for $ty {
            type Err = $crate::core::config::UnknownName;
            fn from_str(s: &str) -> Result<Self, Self::Err> {
                [$($v),+]
                    .into_iter()
                    .find(|v| v.as_str() == s)
                    .ok_or($crate::core::config::UnknownName {
                        value: $crate::core::config::ShortStr::new(s),
                        accepted: $accepted,
                    })
            }
        }
        impl std::fmt::Display for $ty {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(self.as_str())
            }
        }
    };
}
pub(crate) use named_enum;

named_enum!(
    OutputKind,
    "transistor|relay",
    [OutputKind::Transistor, OutputKind::Relay]
);
named_enum!(
    ShortPulse,
    "suppress|stretch|band|extend",
    [
        ShortPulse::Suppress,
        ShortPulse::Stretch,
        ShortPulse::Band,
        ShortPulse::Extend
    ]
);
named_enum!(
    ApplyAt,
    "next_period|next_step|immediate",
    [ApplyAt::NextPeriod, ApplyAt::NextStep, ApplyAt::Immediate]
);
named_enum!(OnDisable, "off|hold", [OnDisable::Off, OnDisable::Hold]);
named_enum!(
    Profile,
    "pico_gfx|twincat_ba|tcont_cp|schneider_pwm|frequency_output",
    [
        Profile::PicoGfx,
        Profile::TwincatBa,
        Profile::TcontCp,
        Profile::SchneiderPwm,
        Profile::FrequencyOutput
    ]
);
