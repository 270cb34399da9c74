//! The line guard: the output line as really written, and every change of level the schedule
//! asks for held back until the line has kept its level for its minimum (counted from the last
//! real edge); the maximum on time's cut of a high line.

use super::{Channel, Event, Level, Line, Nanos};

impl Channel {
    /// Times the cut of a high line at `max_on_ms` after its last real rise, but not before
    /// `floor`; none when the line is low or no maximum is set. With a time base the cut lies
    /// on the grid when the rise did (the maximum is whole ticks); one already overdue (a late
    /// poll, a maximum lowered during the run) happens at `floor`, off the grid: the maximum
    /// is a promise about the line.
    pub(super) fn retime_cut(&mut self, floor: Nanos) {
        self.line.cut = match (self.line.level, self.line.since) {
            (Level::High, Some(since)) if self.cfg.max_on > 0 => {
                Some(since.saturating_add(self.cfg.max_on).max(floor))
            }
            _ => None,
        };
    }

    /// Moves a change held back for the line to no earlier than the end of the minimum of the
    /// phase the line is in (after the phase's start or the minima changed).
    pub(super) fn retime_held(&mut self) {
        if let Some((level, at)) = self.line.held {
            let (when, due) = self.earliest(level, self.line.held_due);
            self.line.held = Some((level, when.max(at)));
            self.line.held_due = due;
        }
    }

    /// Holds back the change to `level` the schedule asks for at `at` until the guard lets it
    /// through (see [`Channel::earliest`]).
    pub(super) fn hold(&mut self, level: Level, at: Nanos) {
        let (when, due) = self.earliest(level, at);
        self.line.held = Some((level, when));
        self.line.held_due = due;
    }

    /// The earliest instant at or after `at` the line may change to `level`: once the line has
    /// kept its level for its minimum, and with a time base on the next instant of the tick
    /// grid. The grid is the instants `k * tick` of the monotonic clock; the minima are whole
    /// ticks, so a change asked for on the grid after a phase that began on it is not moved,
    /// and one asked for between two ticks waits for the next. A phase that began off the
    /// grid (a safety off) ends on it all the same, at least its minimum later.
    ///
    /// A phase due on the grid but written late (a late wake-up, the write itself) keeps its
    /// whole ticks: it ends on the grid as if it had begun when it was due, or, where that is
    /// before its minimum from the real edge (a phase of exactly its minimum), at that
    /// minimum, off the grid by the lateness. It is not rounded up a whole tick for a write's
    /// microseconds, which would lengthen every pulse or break of exactly its minimum and
    /// drift the delivered duty from the command. A lateness of a tick or more, or gathered
    /// over phases of exactly their minima to a tick, is waited out to the next tick.
    ///
    /// Returns that instant, and the instant the change then counts as due: the grid instant
    /// it would have had with no lateness (the instant itself where it is not late).
    pub(super) fn earliest(&self, level: Level, at: Nanos) -> (Nanos, Nanos) {
        debug_assert_ne!(level, self.line.level);
        let min = self.min_for(self.line.level);
        let Some(since) = self.line.since else {
            let when = self.cfg.tick_at_or_after(at);
            return (when, when);
        };
        let real = since.saturating_add(min);
        if self.late_on_grid() {
            let due = self
                .cfg
                .tick_at_or_after(self.line.due.saturating_add(min).max(at));
            (due.max(real), due)
        } else {
            let when = self.cfg.tick_at_or_after(real.max(at));
            (when, when)
        }
    }

    /// With a time base: the line's phase was due on the grid and reached the line less than
    /// a tick after (see [`Channel::earliest`]).
    fn late_on_grid(&self) -> bool {
        let tick = self.cfg.tick;
        match self.line.since {
            Some(since) if tick > 0 => {
                self.line.due.is_multiple_of(tick) && since.saturating_sub(self.line.due) < tick
            }
            _ => false,
        }
    }

    /// Where the line's phase counts from for the schedule, ns: the grid instant it was due,
    /// where it reached the line less than a tick after (with a time base); else when it
    /// really began. `None` while the line has never changed.
    pub(super) fn phase_due(&self) -> Option<Nanos> {
        let since = self.line.since?;
        Some(if self.late_on_grid() {
            self.line.due
        } else {
            since
        })
    }

    /// The minimum time the line must keep `level` once it has it, ns.
    pub(super) fn min_for(&self, level: Level) -> Nanos {
        match level {
            Level::High => self.cfg.min_on,
            Level::Low => self.cfg.min_off,
        }
    }

    /// When the line's current break reaches its minimum, if the line is low and has ever
    /// been high.
    pub(super) fn break_ends_at(&self) -> Option<Nanos> {
        match (self.line.level, self.line.since) {
            (Level::Low, Some(since)) => Some(since.saturating_add(self.cfg.min_off)),
            _ => None,
        }
    }

    /// The schedule asks for `level` at `at`: the line follows at once if it has kept its level
    /// for its minimum, else the change is held back until it has. Asking for the level the
    /// line has cancels a change held back (that pulse or break never reaches the line).
    pub(super) fn set_level(&mut self, level: Level, at: Nanos, emit: &mut dyn FnMut(Event)) {
        self.level = level;
        if self.latched() && level == Level::High {
            // Latched: the line stays low and nothing is held back for later.
            return;
        }
        if level == self.line.level {
            // A change held back by the interlock never reached the line: two edges missed.
            // One held while the line is held inactive was never meant to reach it.
            if self.line.held.take().is_some() && self.live && !self.line.resumes {
                emit(Event::Missed { edges: 2 });
            }
            return;
        }
        let (when, due) = self.earliest(level, at);
        if when == at && !(self.no_rise() && level == Level::High) {
            self.write_line(level, at, emit);
        } else {
            // Asking again for the rise that resumes after a cut keeps it one.
            let held = Some((level, when));
            self.line.resumes &= self.line.held == held;
            self.line.held = held;
            self.line.held_due = due;
        }
    }

    /// A safety off (falling EN, watchdog trip): the line goes low at `at`, whatever its
    /// minimum on time.
    pub(super) fn force_low(&mut self, at: Nanos, emit: &mut dyn FnMut(Event)) {
        self.level = Level::Low;
        self.line.held = None;
        if self.line.level != Level::Low {
            self.write_line(Level::Low, at, emit);
        }
    }

    pub(super) fn write_line(&mut self, level: Level, at: Nanos, emit: &mut dyn FnMut(Event)) {
        if level == Level::High && self.no_rise() {
            // The last line: whatever asked for this rise, a gate forbids it now (the board of
            // the node's lines above all, which no flag set before the action can have
            // missed). It waits, held back, as a rise the interlock holds.
            self.line.held = Some((Level::High, at));
            self.line.held_due = at;
            return;
        }
        // A change the guard held back counts as due when it would have been with no
        // lateness; any other at the instant it is written.
        let due = match self.line.held {
            Some(held) if held == (level, at) => self.line.held_due,
            _ => at,
        };
        if let Some(seat) = &self.seat {
            seat.set(level);
        }
        if let (Level::High, Some(since)) = (self.line.level, self.line.since) {
            self.avg_fall(since, at);
        }
        self.line = Line {
            level,
            since: Some(at),
            due,
            held: None,
            held_due: 0,
            locked: self.line.locked,
            cut: None,
            resumes: false,
        };
        self.retime_cut(at);
        emit(Event::Edge { at, level });
    }

    /// `max_on_ms` has run out on the high line at `t`: it goes low now (its minimum on time
    /// has passed, as `max_on_ms` is never below it) and the schedule's rise, if it still asks
    /// for one, is held back for the minimum break. A line held on by 004's hold stays off.
    pub(super) fn cut(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        let resume = self.enabled && self.level == Level::High;
        self.write_line(Level::Low, t, emit);
        if resume {
            self.hold(Level::High, t);
            self.line.resumes = true;
        } else {
            self.level = Level::Low;
        }
        self.cuts.raise(true);
        self.report_flags(emit);
    }
}
