//! The node-level planner above the channel cores: phase staggering and the limit
//! on lines high at once, for the supply that feeds every load.
//!
//! Sans-IO like the channel: whoever drives the channels calls [`Bank::before`] before each
//! action on one of them and [`Bank::after`] after it, in channel order when several fall due
//! together. It never reads a clock and never writes an output.
//!
//! - `stagger`: the channels of equal period (a group) share one grid of whole periods on the
//!   monotonic clock, and each period's on phases are laid end to end in channel order: a
//!   channel's on phase starts where the on phases of the channels before it ended. No two
//!   lines of a group are ever on together: an on phase that would start while another line of
//!   its group is still on (a command re-timing a running pulse, a minimum time holding an
//!   edge back, a wait for a slot) waits for it like a slot, and is skipped if it cannot fit.
//!   While the duties sum to at most 100 % the layout leaves no such wait in steady state: the
//!   supply sees one load at a time and every duty is delivered. (Fixed offsets of T/N, as in
//!   PLC output modules, would overlap as soon as one duty exceeds 1/N.)
//! - `max_simultaneous_on`: at most that many channels hold a slot — a line high, or a
//!   schedule asking for high — at any instant. An on phase that starts with no slot free
//!   waits, off, keeping its whole length, and the break after it shrinks so the period keeps
//!   its end; the slot that frees first goes to the phase that has waited longest. A phase
//!   that can no longer fit in its period is skipped and reported. Lowered while running, the
//!   limit takes the slots of the latest-started pulses back at once (each still keeps its
//!   minimum on time). Nothing else here shortens a pulse or a break: the channel's line
//!   guard still holds every minimum.

use super::config::named_enum;
use super::{Channel, Event, Nanos};

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

named_enum!(Phase, "sync|stagger", [Phase::Sync, Phase::Stagger]);

/// The node-level settings: `phase` and `max_simultaneous_on`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Bank {
    /// How periods are placed.
    pub phase: Phase,
    /// At most this many channels hold a slot at once; 0: no limit.
    pub max_on: usize,
}

impl Bank {
    /// Sets channel `i` up for an action at `now` (ns): its place on the grid, and whether an
    /// on phase may start (a slot free, and under stagger no other line of its group on).
    /// Call before every action on it (a poll, an input). Changes no other channel.
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
        let free = self.slot_free(channels, i);
        let ch = &mut channels[i];
        ch.set_grid(stagger);
        ch.set_lead(after, others);
        ch.set_slot(free);
    }

    /// After an action, at `at` (ns; the instant a line went off, when one did): every on
    /// phase waiting that may start now does, the one that has waited longest first (then the
    /// lower channel); their events go to `emit` with the channel index. Call after every
    /// action on any channel.
    pub fn after(&self, channels: &mut [Channel], at: Nanos, emit: &mut dyn FnMut(usize, Event)) {
        if !self.plans() {
            return;
        }
        // Each grant ends one wait (started or skipped), so this ends.
        while let Some(k) = (0..channels.len())
            .filter_map(|k| channels[k].waiting_at(at).map(|t| (t, k)))
            .filter(|&(_, k)| self.slot_free(channels, k))
            .min()
            .map(|(_, k)| k)
        {
            channels[k].grant(at, &mut |e| emit(k, e));
        }
    }

    /// Whether [`Bank::after`] can act on any channel: a limit is set, or the phases are
    /// staggered.
    pub fn plans(&self) -> bool {
        self.max_on != 0 || self.phase == Phase::Stagger
    }

    /// After `max_simultaneous_on` was lowered at `at` (ns): the latest-started on phases give
    /// their slots up until no more than the limit hold one (each line still keeps its minimum
    /// on time before it goes off).
    pub fn shed(&self, channels: &mut [Channel], at: Nanos, emit: &mut dyn FnMut(usize, Event)) {
        if self.max_on == 0 {
            return;
        }
        let mut held = channels.iter().filter(|c| c.occupies()).count();
        while held > self.max_on {
            let Some(k) = (0..channels.len())
                .filter_map(|k| channels[k].on_since().map(|t| (t, k)))
                .max()
                .map(|(_, k)| k)
            else {
                return;
            };
            channels[k].yield_slot(at, &mut |e| emit(k, e));
            held -= 1;
        }
    }

    /// Whether an on phase of channel `i` may start: it holds a slot already, or one is free,
    /// and under stagger no other line of its group is on.
    fn slot_free(&self, channels: &[Channel], i: usize) -> bool {
        let ch = &channels[i];
        let limit = self.max_on == 0
            || ch.occupies()
            || channels.iter().filter(|c| c.occupies()).count() < self.max_on;
        let period = ch.config().period;
        let group_on = self.phase == Phase::Stagger
            && period > 0
            && channels
                .iter()
                .enumerate()
                .any(|(j, c)| j != i && c.config().period == period && c.occupies());
        limit && !group_on
    }
}

/// Where the on phases of the other channels of channel `i`'s group (same period) end in the
/// period of the grid that began at or before `now`, ns after its start, and the on time the
/// group's other running channels run per period: see [`Channel::set_lead`]. At a grid
/// instant the channels start in channel order, so each period's phases lie in channel order.
fn lead(channels: &[Channel], i: usize, now: Nanos) -> (Nanos, Nanos) {
    let period = channels[i].config().period;
    if period == 0 {
        return (0, 0);
    }
    let start = now / period * period;
    let (mut after, mut others) = (0, 0);
    for (j, c) in channels.iter().enumerate() {
        if j == i || !c.running() || c.config().period != period {
            continue;
        }
        others += c.plan().t_on;
        if let Some(end) = c.on_end() {
            after = after.max(end.saturating_sub(start));
        }
    }
    (after, others)
}
