//! The gates between the schedule and the line: the split-range interlock, the e-stop latch
//! and the hold of a managed node's inactive states. Each keeps every rise off the line; only
//! the e-stop and the hold also switch a high line off at once (safety offs).

use super::{Channel, Event, Level, Nanos};

impl Channel {
    /// Whether the line is interlocked (see [`Channel::set_interlock`]).
    pub fn interlocked(&self) -> bool {
        self.line.locked
    }

    /// Engages or releases the interlock at `now`: while engaged the line never goes high; a
    /// rise the schedule asks for is held back and written on release (still no earlier than
    /// the minimum break since the last real fall). Engaging it does not switch a high line
    /// off: the caller engages it only while the line is low (001's split range: the partner
    /// of a pair is high).
    pub fn set_interlock(&mut self, now: Nanos, on: bool, emit: &mut dyn FnMut(Event)) {
        if on == self.line.locked {
            return;
        }
        self.line.locked = on;
        self.release_held_rise(now, emit);
    }

    /// Whether the emergency stop is latched (see [`Channel::set_estop`]).
    pub fn estopped(&self) -> bool {
        self.estop
    }

    /// Latches or releases the emergency stop at `now`.
    ///
    /// Latching drives the line low at once, whatever its minimum on time or `on_disable`
    /// (the fault value included: the e-stop overrides it), and disables the channel. While
    /// latched the line never goes high: commands, enables and configurations are taken and
    /// reported as usual, but every rise is held back. Releasing disables the channel once
    /// more and drops every held rise, so nothing switches on by itself: the channel runs
    /// again on its next enable, and then only after the minimum break since the line's last
    /// real fall.
    pub fn set_estop(&mut self, now: Nanos, latched: bool, emit: &mut dyn FnMut(Event)) {
        if latched == self.estop {
            return;
        }
        if latched {
            self.finish_autotune(now, crate::core::heater::autotune::Stop::EStop, emit);
            self.estop = true;
            self.watchdog.end_fault_value();
            self.set_enable(now, false, emit);
            self.force_low(now, emit);
        } else {
            self.set_enable(now, false, emit);
            self.line.held = None;
            self.level = self.line.level;
            self.estop = false;
        }
    }

    /// Whether the line may follow the schedule (see [`Channel::set_live`]).
    pub fn live(&self) -> bool {
        self.live
    }

    /// Lets the line follow the schedule (`true`) or holds it inactive (`false`), at `now`: a
    /// managed node's lines are live only while it is ACTIVE.
    ///
    /// Holding drives the line low at once (a safety off, whatever its minimum on time) and
    /// keeps it low; the schedule goes on (commands, enables and configurations are taken and
    /// reported) and a rise it asks for is held back. Releasing writes a held rise at once if
    /// its time has come — never before the minimum break since the line's last real fall —
    /// and otherwise the line follows from the next edge the schedule asks for.
    pub fn set_live(&mut self, now: Nanos, live: bool, emit: &mut dyn FnMut(Event)) {
        if live == self.live {
            return;
        }
        if !live {
            self.finish_autotune(now, crate::core::heater::autotune::Stop::Deactivated, emit);
        }
        self.live = live;
        if !live {
            self.force_low(now, emit);
            // The schedule stays where it is; only the line is held.
            self.level = match self.step {
                Some(s) if self.enabled => s.level,
                _ => self.level,
            };
            if self.level == Level::High {
                self.hold(Level::High, now);
            }
        } else {
            self.release_held_rise(now, emit);
        }
    }

    /// After a gate opened at `now`: a rise held back whose time has come is written, unless
    /// another gate still keeps rises off the line.
    fn release_held_rise(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) {
        if self.no_rise() {
            return;
        }
        if let Some((Level::High, at)) = self.line.held {
            // With a time base a rise released between two ticks waits for the next.
            let tick = self.cfg.tick_at_or_after(now);
            if at <= now && tick == now {
                self.write_line(Level::High, now, emit);
            } else if at <= now {
                self.line.held = Some((Level::High, tick));
                self.line.held_due = tick;
            }
        }
    }

    /// No rise may reach the line: the interlock is engaged, the e-stop latched, the line is
    /// held inactive, or the board of the node's lines forbids it (see [`LineBoard`](crate::core::LineBoard)).
    pub(super) fn no_rise(&self) -> bool {
        self.line.locked || self.latched() || !self.live || self.board_refuses()
    }

    /// The e-stop or a heater fault is latched: the line stays low and nothing is held back
    /// for later.
    pub(super) fn latched(&self) -> bool {
        self.estop || self.heat.fault.is_some()
    }

    /// The board of the node's lines forbids a rise of this line now.
    pub(super) fn board_refuses(&self) -> bool {
        self.seat.as_ref().is_some_and(|s| !s.may_rise())
    }

    /// Whether a rise is held back (by a gate, the board of the node's lines or a minimum
    /// break). Only then can [`Channel::poll_at`] change without any action on this channel:
    /// it names the held rise only while the board allows it, and the board changes with the
    /// other lines.
    pub fn holds_rise(&self) -> bool {
        matches!(self.line.held, Some((Level::High, _)))
    }

    /// Whether a rise held back is due at `now` (its minimum break has passed) and no gate
    /// keeps it off the line: [`Channel::retry_rise`] would write it.
    pub fn rise_due(&self, now: Nanos) -> bool {
        matches!(self.line.held, Some((Level::High, at)) if at <= now) && !self.no_rise()
    }

    /// Writes a rise held back whose time has come, at `now`, if no gate keeps it off the
    /// line any more. The driver calls this after every batch of actions, for rises the board
    /// of the node's lines held back while another line was high.
    pub fn retry_rise(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) {
        self.release_held_rise(now, emit);
    }
}
