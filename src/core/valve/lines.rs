//! The valve's line guard: the two lines as really written, and the rules that hold whatever
//! decided a change — the lines are never high together, a line rises only once both have been
//! low for the reversal pause (counted from the real fall), a drive lasts at least the minimum
//! pulse unless a safety off cuts it, and a line whose end switch is active never rises. It also
//! asks the node's [`LineBoard`](crate::core::LineBoard) (on which the two lines are a pair)
//! before a rise, so a rise decided anywhere else cannot get past it either.
//!
//! Every edge leaves through [`Lines::write`]; the output thread reports the time each edge
//! really reached the line ([`Lines::written`]), and the pause and the minimum count from those.
//! No line rises before the last fall's real time is reported: a fall and a rise are never
//! written in one batch, where a late wake-up would put them on the lines together.

use super::{Dir, ValveEvent};
use crate::core::board::Seat;
use crate::core::{Level, Nanos};

/// A line is low at least this long between two drives, even with no reversal pause, so a fall
/// and the next rise are never one write, ns.
pub const MIN_BREAK: Nanos = 1_000_000;

/// One line as written.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct LineState {
    pub(super) high: bool,
    /// When the line got its level (real time once reported); `None`: never changed.
    pub(super) since: Option<Nanos>,
    /// When the last edge was scheduled, for the report of its real time.
    sched: Nanos,
}

/// The guard of a valve's two lines.
#[derive(Debug, Clone)]
pub(super) struct Lines {
    pub(super) line: [LineState; 2],
    /// The real time the last fall of either line reached it (or the lines were known low).
    pub(super) fell: Option<Nanos>,
    /// The last fall's real time is not reported yet: no rise until it is, so the pause counts
    /// from the line and never from the schedule.
    unconfirmed: bool,
    pause: Nanos,
    min_pulse: Nanos,
    /// The pause in force at the last fall and the minimum in force at the last rise: a
    /// setting lowered afterwards does not shorten the break or the drive already under way.
    pause_at_fall: Nanos,
    min_at_rise: Nanos,
    /// An end switch holds the drive in that direction.
    pub(super) blocked: [bool; 2],
    seats: [Option<Seat>; 2],
}

impl Lines {
    /// The guard of two lines known low at `now` (the output requested them inactive): the
    /// first rise waits for the reversal pause from there, since a line may have been high
    /// until then (a restart after a kill mid-move).
    pub(super) fn new(pause: Nanos, min_pulse: Nanos, now: Nanos) -> Lines {
        Lines {
            line: [LineState::default(); 2],
            fell: Some(now),
            unconfirmed: false,
            pause,
            min_pulse,
            pause_at_fall: pause,
            min_at_rise: min_pulse,
            blocked: [false; 2],
            seats: [None, None],
        }
    }

    pub(super) fn set_seats(&mut self, open: Seat, close: Seat) {
        self.seats = [Some(open), Some(close)];
    }

    /// New pause and minimum pulse: a longer one acts at once, on the break or drive under way
    /// too; a shorter one from the next fall or rise (what was promised at an edge holds).
    pub(super) fn set_timing(&mut self, pause: Nanos, min_pulse: Nanos) {
        self.pause = pause;
        self.min_pulse = min_pulse;
    }

    /// The pause the break under way keeps: the longer of the one in force at its fall and now.
    fn pause_now(&self) -> Nanos {
        self.pause.max(self.pause_at_fall)
    }

    /// The minimum the drive under way keeps: the longer of the one in force at its rise and
    /// now.
    fn min_pulse_now(&self) -> Nanos {
        self.min_pulse.max(self.min_at_rise)
    }

    /// The line that is high, if one is.
    pub(super) fn driving(&self) -> Option<Dir> {
        Dir::BOTH.into_iter().find(|d| self.line[d.index()].high)
    }

    /// When line `d` rose (real time), if it is high.
    pub(super) fn rose(&self, d: Dir) -> Option<Nanos> {
        let l = self.line[d.index()];
        l.high.then_some(l.since).flatten()
    }

    /// The earliest instant at or after `at` line `d` may rise, or `None` while it may not rise
    /// at all (the other line high, its end switch active, the board refusing).
    pub(super) fn earliest_rise(&self, d: Dir, at: Nanos) -> Option<Nanos> {
        if self.line[d.other().index()].high || self.blocked[d.index()] || self.unconfirmed {
            return None;
        }
        if let Some(seat) = &self.seats[d.index()] {
            if !seat.may_rise() {
                return None;
            }
        }
        let after = self
            .fell
            .map_or(0, |f| f.saturating_add(self.pause_now().max(MIN_BREAK)));
        Some(at.max(after))
    }

    /// Raises line `d` at `at` if the rules allow it at `at`; returns whether it did.
    pub(super) fn rise(&mut self, d: Dir, at: Nanos, emit: &mut dyn FnMut(ValveEvent)) -> bool {
        if self.line[d.index()].high {
            return true;
        }
        if self.earliest_rise(d, at) != Some(at) {
            return false;
        }
        self.write(d, Level::High, at, emit);
        true
    }

    /// The earliest instant at or after `at` the high line `d` may fall: after its minimum pulse.
    pub(super) fn earliest_fall(&self, d: Dir, at: Nanos) -> Nanos {
        self.rose(d)
            .map_or(at, |r| at.max(r.saturating_add(self.min_pulse_now())))
    }

    /// Lowers line `d` at `at` — only once it has run its minimum pulse unless `force` (a safety
    /// off). Returns the drive from the real rise to `at`, ns, when it fell.
    pub(super) fn fall(
        &mut self,
        d: Dir,
        at: Nanos,
        force: bool,
        emit: &mut dyn FnMut(ValveEvent),
    ) -> Option<Nanos> {
        let rose = self.rose(d)?;
        if !force && at < self.earliest_fall(d, at) {
            return None;
        }
        let at = at.max(rose);
        self.write(d, Level::Low, at, emit);
        Some(at - rose)
    }

    fn write(&mut self, d: Dir, level: Level, at: Nanos, emit: &mut dyn FnMut(ValveEvent)) {
        let high = level.is_high();
        // Never both: the caller's checks make this unreachable; the line stays low if not.
        if high && self.line[d.other().index()].high {
            return;
        }
        if let Some(seat) = &self.seats[d.index()] {
            seat.set(level);
        }
        self.line[d.index()] = LineState {
            high,
            since: Some(at),
            sched: at,
        };
        if high {
            self.min_at_rise = self.min_pulse;
        } else {
            self.fell = Some(at);
            self.unconfirmed = true;
            self.pause_at_fall = self.pause;
        }
        emit(ValveEvent::Edge { dir: d, level, at });
    }

    /// The edge of line `d` to `level` scheduled last reached the line at `actual`: the pause
    /// and minimum count from there. Returns how much later than scheduled it came (negative:
    /// earlier), ns, or `None` when `level` is not the line's last edge.
    pub(super) fn written(&mut self, d: Dir, level: Level, actual: Nanos) -> Option<i128> {
        let l = &mut self.line[d.index()];
        if l.high != level.is_high() || l.since.is_none() {
            return None;
        }
        let late = i128::from(actual) - i128::from(l.sched);
        l.since = Some(actual);
        l.sched = actual;
        if !l.high {
            self.fell = Some(actual);
            self.unconfirmed = false;
        }
        Some(late)
    }
}
