//! The last line before the lines: the levels every channel's line really has, shared by the
//! channels of one node, and the two rules across channels that hold whatever decided a rise —
//! the lines of a split-range pair (and of a valve) are never high together, and no more than
//! `max_simultaneous_on` lines are high at once.
//!
//! The split-range interlock ([`Interlocks`](super::Interlocks)) and the node-level planner
//! ([`Bank`](super::Bank)) decide when a rise may come; they act on flags set before each
//! action, which a rise decided elsewhere in the same wake-up (a slot handed over, a hold
//! released, a late wake-up writing several edges) can leave stale. The board is read at the
//! moment a channel's line guard writes a rise ([`Channel::write_line`](super::Channel)), so
//! nothing gets past it: a rise it refuses is held back like one the interlock holds, and is
//! written once the board allows it (the driver calls [`Channel::retry_rise`](super::Channel::retry_rise)
//! after every batch; [`Channel::poll_at`](super::Channel::poll_at) names it too).
//!
//! Sans-IO like the channels: it holds levels, never reads a clock or writes an output. Atomics
//! with relaxed ordering make it shareable (the channels live on one thread; the board is read
//! and written only there).

use super::Level;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering::Relaxed};
use std::sync::Arc;

/// No partner.
const NONE: usize = usize::MAX;

/// The real levels of the lines of one node's channels, and the rules across them.
#[derive(Debug)]
pub struct LineBoard {
    high: Vec<AtomicBool>,
    partner: Vec<AtomicUsize>,
    /// Lines that do not count against `max_on` (a valve's motor lines).
    exempt: Vec<AtomicBool>,
    /// At most this many counted lines may be high after a rise; 0: no limit.
    max_on: AtomicUsize,
    count: AtomicUsize,
}

impl LineBoard {
    /// A board for `lines` lines, all low, no pairs, no limit.
    pub fn new(lines: usize) -> Arc<LineBoard> {
        Arc::new(LineBoard {
            high: (0..lines).map(|_| AtomicBool::new(false)).collect(),
            partner: (0..lines).map(|_| AtomicUsize::new(NONE)).collect(),
            exempt: (0..lines).map(|_| AtomicBool::new(false)).collect(),
            max_on: AtomicUsize::new(0),
            count: AtomicUsize::new(0),
        })
    }

    /// Number of lines.
    pub fn lines(&self) -> usize {
        self.high.len()
    }

    /// Lines `a` and `b` are never high together from now on. Out-of-range indices are ignored
    /// (the caller checks pairs, see [`Interlocks::pair`](super::Interlocks::pair)).
    pub fn pair(&self, a: usize, b: usize) {
        if a < self.lines() && b < self.lines() && a != b {
            self.partner[a].store(b, Relaxed);
            self.partner[b].store(a, Relaxed);
        }
    }

    /// Line `i` no longer counts against `max_simultaneous_on` (a valve's motor line: its drive
    /// cannot wait for a slot). Set at start-up, while the line is low.
    pub fn exempt(&self, i: usize) {
        if let Some(e) = self.exempt.get(i) {
            if !self.is_high(i) {
                e.store(true, Relaxed);
            }
        }
    }

    /// No rise may make more than `max_on` lines high (0: no limit). Lowering it switches no
    /// line off: lines already high stay until they fall, and no line rises meanwhile.
    pub fn set_max_on(&self, max_on: usize) {
        self.max_on.store(max_on, Relaxed);
    }

    /// Whether line `i` may go high now: its partner, if any, is low, and fewer lines than the
    /// limit are high.
    pub fn may_rise(&self, i: usize) -> bool {
        let Some(high) = self.high.get(i) else {
            return true;
        };
        if high.load(Relaxed) {
            return true;
        }
        let partner = self.partner[i].load(Relaxed);
        if partner != NONE && self.high[partner].load(Relaxed) {
            return false;
        }
        if self.exempt[i].load(Relaxed) {
            return true;
        }
        let max_on = self.max_on.load(Relaxed);
        max_on == 0 || self.count.load(Relaxed) < max_on
    }

    /// Line `i` was written to `level`.
    pub fn set(&self, i: usize, level: Level) {
        let Some(high) = self.high.get(i) else { return };
        let was = high.swap(level.is_high(), Relaxed);
        if self.exempt[i].load(Relaxed) {
            return;
        }
        match (was, level.is_high()) {
            (false, true) => {
                self.count.fetch_add(1, Relaxed);
            }
            (true, false) => {
                self.count.fetch_sub(1, Relaxed);
            }
            _ => {}
        }
    }

    /// Whether line `i` is high.
    pub fn is_high(&self, i: usize) -> bool {
        self.high.get(i).is_some_and(|h| h.load(Relaxed))
    }

    /// How many counted lines are high.
    pub fn high_count(&self) -> usize {
        self.count.load(Relaxed)
    }
}

/// A channel's seat on a board: the board and its line's index.
#[derive(Debug, Clone)]
pub(crate) struct Seat {
    pub(crate) board: Arc<LineBoard>,
    pub(crate) line: usize,
}

impl Seat {
    pub(crate) fn may_rise(&self) -> bool {
        self.board.may_rise(self.line)
    }

    pub(crate) fn set(&self, level: Level) {
        self.board.set(self.line, level);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pair_is_never_high_together() {
        let b = LineBoard::new(3);
        b.pair(0, 1);
        assert!(b.may_rise(0));
        b.set(0, Level::High);
        assert!(!b.may_rise(1), "partner high");
        assert!(b.may_rise(2), "not in the pair");
        b.set(0, Level::Low);
        assert!(b.may_rise(1));
    }

    #[test]
    fn no_rise_beyond_the_limit_and_a_lowered_limit_switches_nothing_off() {
        let b = LineBoard::new(4);
        b.set_max_on(2);
        b.set(0, Level::High);
        b.set(1, Level::High);
        assert!(!b.may_rise(2));
        assert!(b.may_rise(1), "a high line stays high");
        b.set_max_on(1);
        assert_eq!(b.high_count(), 2);
        b.set(0, Level::Low);
        assert!(!b.may_rise(2), "still one high, limit 1");
        b.set(1, Level::Low);
        assert!(b.may_rise(2));
        b.set(1, Level::Low);
        assert_eq!(b.high_count(), 0, "a repeated low counts once");
    }
}
