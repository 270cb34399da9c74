//! The timing core: pure, sans-IO channel logic of SPEC §1.
//!
//! Nothing in here reads a clock, sleeps, allocates on its paths, or touches GPIO or ROS. The
//! caller passes `now` in nanoseconds of a monotonic clock and gets back edges with their
//! scheduled times and the instant it should call again ([`Channel::poll_at`]).

pub mod bank;
pub mod board;
pub mod channel;
pub mod command;
pub mod config;
pub mod heater;
pub mod interlock;
pub mod plan;
pub mod valve;

pub use bank::{Bank, Phase};
pub use board::LineBoard;
pub use channel::{Channel, Event, Protections, Status};
pub use command::{Command, CommandError, Duty, SV_FULL_SCALE};
pub use config::{
    ApplyAt, ChannelConfig, ChannelParams, ConfigError, MinTime, OnDisable, OutputKind,
    PercentParam, Profile, ShortPulse, Sizing, NS_PER_MS,
};
pub use interlock::{split_command, Interlocks, PairError};
pub use plan::{Plan, Rule};
pub use valve::{Valve, ValveConfig, ValveEvent, ValveParams, ValveStatus};

/// Nanoseconds of a monotonic clock (an instant) or a duration in nanoseconds.
pub type Nanos = u64;

/// A logical output level: `High` means the actuator is on (active), whatever the electrical
/// polarity of the line (`active_low` is applied by the output backend).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Level {
    /// Off / inactive.
    #[default]
    Low,
    /// On / active.
    High,
}

impl Level {
    /// `true` for [`Level::High`].
    pub const fn is_high(self) -> bool {
        matches!(self, Level::High)
    }

    /// `High` for `true`.
    pub const fn from_bool(on: bool) -> Level {
        if on {
            Level::High
        } else {
            Level::Low
        }
    }
}

impl From<bool> for Level {
    fn from(on: bool) -> Level {
        Level::from_bool(on)
    }
}

#[cfg(test)]
mod tests;
