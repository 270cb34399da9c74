//! The node-level planner above the channel cores (issue 12): phase staggering and the limit
//! on lines high at once, for the supply that feeds every load.
//!
//! Sans-IO like the channel: whoever drives the channels calls [`Bank::before`] before each
//! action on one of them and [`Bank::after`] after it, in channel order when several fall due
//! together. It never reads a clock and never writes an output.
//!
//! - `stagger`: the channels of equal period share one grid of whole periods on the monotonic
//!   clock, and each period's on phases are laid end to end in channel order: a channel's on
//!   phase starts where the on phases of the channels before it ended. No two lines switch on
//!   together, and while the duties sum to at most 100 % no two on phases overlap: the supply
//!   sees one load at a time. (Fixed offsets of T/N, as in PLC output modules, would overlap as
//!   soon as one duty exceeds 1/N.)
//! - `max_simultaneous_on`: at most that many channels hold a slot — a line high, or a
//!   schedule asking for high — at any instant. An on phase that starts with no slot free
//!   waits, off, keeping its whole length, and the break after it shrinks so the period keeps
//!   its end; the slot that frees first goes to the phase that has waited longest. A phase
//!   that can no longer fit in its period is skipped and reported. Nothing here shortens a
//!   pulse or a break: the channel's line guard still holds every minimum.

use super::config::{ShortStr, UnknownName};
use super::{Channel, Event, Nanos};
use std::str::FromStr;

/// How the channels' periods are placed against each other (node parameter `phase`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Phase {
    /// Each channel's periods start where its enable (or its last period) put them.
    #[default]
    Sync,
    /// Channels of equal period share a grid and lay their on phases end to end.
    Stagger,
}

impl Phase {
    /// The spelling of the parameter value.
    pub const fn as_str(self) -> &'static str {
        match self {
            Phase::Sync => "sync",
            Phase::Stagger => "stagger",
        }
    }
}

impl FromStr for Phase {
    type Err = UnknownName;

    fn from_str(s: &str) -> Result<Phase, Self::Err> {
        match s {
            "sync" => Ok(Phase::Sync),
            "stagger" => Ok(Phase::Stagger),
            _ => Err(UnknownName {
                value: ShortStr::new(s),
                accepted: "sync|stagger",
            }),
        }
    }
}

impl std::fmt::Display for Phase {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The node-level settings: `phase` and `max_simultaneous_on`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Bank {
    /// How periods are placed.
    pub phase: Phase,
    /// At most this many channels hold a slot at once; 0: no limit.
    pub max_on: usize,
}

impl Bank {
    /// Sets channel `i` up for an action at `now` (ns): its place on the grid, and whether a
    /// slot is free for it. Call before every action on it (a poll, an input).
    pub fn before(&self, channels: &mut [Channel], i: usize, now: Nanos) {
        if i >= channels.len() {
            return;
        }
        let stagger = self.phase == Phase::Stagger;
        let (after, others) = if stagger {
            lead(channels, i, now)
        } else {
            (0, 0)
        };
        let free = self.max_on == 0
            || channels[i].occupies()
            || channels.iter().filter(|c| c.occupies()).count() < self.max_on;
        let ch = &mut channels[i];
        ch.set_grid(stagger);
        ch.set_lead(after, others);
        ch.set_slot(free);
    }

    /// After an action at `now`: every slot free goes to a waiting on phase, the one that has
    /// waited longest first (then the lower channel); their events go to `emit` with the
    /// channel index. Call after every action on any channel.
    pub fn after(&self, channels: &mut [Channel], now: Nanos, emit: &mut dyn FnMut(usize, Event)) {
        if self.max_on == 0 {
            return;
        }
        let mut held = channels.iter().filter(|c| c.occupies()).count();
        while held < self.max_on {
            let Some(k) = (0..channels.len())
                .filter_map(|k| channels[k].waiting_since().map(|t| (t, k)))
                .min()
                .map(|(_, k)| k)
            else {
                return;
            };
            channels[k].grant(now, &mut |e| emit(k, e));
            held += 1;
        }
    }
}

/// Where the on phases of the other channels of channel `i`'s group (same period) placed in
/// the period of the grid that began at or before `now` end, and the on time the group's
/// other running channels run per period: see [`Channel::set_lead`]. At a grid instant the
/// channels start in channel order, so each period's phases lie in channel order.
fn lead(channels: &[Channel], i: usize, now: Nanos) -> (Nanos, Nanos) {
    let period = channels[i].config().period;
    if period == 0 {
        return (0, 0);
    }
    let start = now / period * period;
    let group = channels
        .iter()
        .enumerate()
        .filter(|&(j, c)| j != i && c.running() && c.config().period == period)
        .map(|(_, c)| c);
    let (mut after, mut others) = (0, 0);
    for c in group {
        others += c.plan().t_on;
        if c.period_start() == start {
            after = after.max(c.placed_end());
        }
    }
    (after, others)
}
