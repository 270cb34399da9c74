//! The work done at each wake-up, independent of how the wake-up happens: apply requests, poll
//! the channel cores, write the due edges in one call, and report. The output thread and the
//! benchmark's tokio baseline both run this same code, so they differ only in how they sleep.
//!
//! Nothing here sleeps, locks, or allocates after construction.

use super::deadlines::{Deadlines, Marks};
use super::safety::{SafetySlot, Wanted};
use super::{EdgeReport, Input, Report, Request};
use crate::clock;
use crate::core::valve::{self, Dir, Valve, ValveEvent};
use crate::core::{Bank, Channel, ChannelConfig, Event, Interlocks, Level, LineBoard, Nanos};
use crate::output::{LineChange, Output, OutputError};
use rtrb::{Consumer, Producer};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// Why the worker stopped.
#[derive(Debug)]
pub(crate) enum Stop<E> {
    /// Writing `channel` failed with `error`; every line was then driven inactive.
    Fault { channel: usize, error: E },
}

pub(crate) struct Worker<O: Output> {
    channels: Vec<Channel>,
    interlocks: Interlocks,
    /// The lines' real levels and the rules across them, read by every channel's line guard
    /// at the moment it writes a rise.
    board: Arc<LineBoard>,
    bank: Bank,
    /// Every channel's next deadline, kept in order: read again for the channels acted on.
    deadlines: Deadlines,
    /// Channels acted on since the last look for a heater fault.
    acted: Marks,
    /// The channels a wake-up walks (those whose deadline may have come, those that may hold a
    /// rise), kept here so the walk never allocates.
    walk: Marks,
    seq: Vec<u64>,
    /// Channels whose state changed since their last status snapshot.
    touched: Marks,
    changes: Vec<LineChange>,
    output: O,
    reports: Producer<Report>,
    dropped: Arc<AtomicU64>,
    /// Set when at least one report was pushed since the last `take_pushed`.
    pushed: bool,
    /// Set when a safety input was applied and written since the last `take_acked`.
    acked: bool,
    heartbeat: Option<Heartbeat>,
    /// The safety inputs' slot, and what of it has been applied.
    safety: Arc<SafetySlot>,
    seen: Wanted,
    /// The clock (the monotonic clock; virtual time in tests).
    clock: fn() -> Nanos,
    /// Which channels had a heater fault latched at the last look.
    heater_faulted: Vec<bool>,
    /// A heater fault latches the e-stop of every channel (`heater_fault_latches_estop`).
    heater_estop: bool,
    /// The three-point valves, their lines (open, close), and which were touched since their
    /// last snapshot. Reserved for one valve per two channels: adding one never allocates.
    valves: Vec<Valve>,
    valve_lines: Vec<[usize; 2]>,
    valve_touched: Vec<bool>,
    /// For each channel's line, the valve and direction it drives, if it belongs to a valve.
    owner: Vec<Option<(usize, Dir)>>,
    /// A status snapshot the full report queue refused is sent again at this instant, ns: the
    /// thread wakes for it even when no edge or request is due.
    resend_at: Option<Nanos>,
    /// When every channel's deadline was last read, monotonic ns (see [`FULL_READ_NS`]).
    full_read_at: Nanos,
}

/// At a wake-up at least this long after every channel's deadline was last read, ns, every
/// channel is read again (and looked at, as a scan would). The deadlines kept are exact as long
/// as every action on a channel marks it; this bounds how long a deadline missed by an action
/// that did not could stay unserved, at wake-ups that come anyway (another channel's edge, a
/// request, the liveness tick). It adds no wake-up, and costs one scan a second at most.
pub(crate) const FULL_READ_NS: Nanos = 1_000_000_000;

/// How long after the full report queue refused a status snapshot it is offered again, ns:
/// time for the reader to drain the queue.
pub(crate) const STATUS_RESEND_NS: Nanos = 10_000_000;

/// The heartbeat line: toggled every half period on an absolute grid while the thread runs.
struct Heartbeat {
    line: usize,
    half: Nanos,
    next: Nanos,
    level: Level,
}

impl Heartbeat {
    /// Puts the line to `level` at `at` (a change for the next write), unless it is there.
    fn set(&mut self, level: Level, at: Nanos, changes: &mut Vec<LineChange>) {
        if self.level != level {
            self.level = level;
            changes.push(LineChange {
                line: self.line,
                level,
                scheduled_ns: at,
            });
        }
    }
}

impl<O: Output> Worker<O> {
    pub(crate) fn new(
        configs: &[ChannelConfig],
        output: O,
        reports: Producer<Report>,
        dropped: Arc<AtomicU64>,
        now: Nanos,
        safety: Arc<SafetySlot>,
    ) -> Self {
        let n = configs.len();
        let board = LineBoard::new(n);
        let mut channels: Vec<Channel> = configs.iter().map(|c| Channel::new(*c, now)).collect();
        for (i, ch) in channels.iter_mut().enumerate() {
            ch.seat_on(&board, i);
        }
        Worker {
            deadlines: Deadlines::new(&channels),
            acted: Marks::new(n),
            walk: Marks::new(n),
            channels,
            interlocks: Interlocks::new(n),
            board,
            bank: Bank::default(),
            seq: vec![0; n],
            touched: Marks::new(n),
            // At most two edges per channel can come out of one wake-up (a request edge and a
            // deadline edge); reserve generously so the hot path never grows the vector.
            changes: Vec::with_capacity(4 * n + 4),
            output,
            reports,
            dropped,
            pushed: false,
            acked: false,
            heartbeat: None,
            seen: safety.wanted(),
            safety,
            clock: clock::monotonic_ns,
            heater_faulted: vec![false; n],
            heater_estop: false,
            valves: Vec::with_capacity(n / 2),
            valve_lines: Vec::with_capacity(n / 2),
            valve_touched: Vec::with_capacity(n / 2),
            owner: vec![None; n],
            resend_at: None,
            full_read_at: now,
        }
    }

    /// Reads time from `clock` instead of the monotonic clock (virtual time in tests).
    #[cfg(test)]
    pub(crate) fn with_clock(mut self, clock: fn() -> Nanos) -> Self {
        self.clock = clock;
        self
    }

    /// Valve `k`, for tests that compare its estimate with the lines.
    #[cfg(test)]
    pub(crate) fn valve(&self, k: usize) -> Option<&Valve> {
        self.valves.get(k)
    }

    /// The earliest channel deadline as kept in order, and as a scan of every channel finds it.
    #[cfg(test)]
    pub(crate) fn channel_deadlines(&self) -> (Option<Nanos>, Option<Nanos>) {
        let scanned = self.channels.iter().filter_map(Channel::poll_at).min();
        (self.deadlines.first(&self.channels), scanned)
    }

    /// Channel `i` for a test to change without the worker marking it: an action that forgets
    /// its mark.
    #[cfg(test)]
    pub(crate) fn channel_unmarked(&mut self, i: usize) -> &mut Channel {
        &mut self.channels[i]
    }

    /// Toggles output line `line` every `half` ns from `now + half` on (a half period of at
    /// least 1 ms is used).
    pub(crate) fn start_heartbeat(&mut self, line: usize, half: Nanos, now: Nanos) {
        let half = half.max(1_000_000);
        self.heartbeat = Some(Heartbeat {
            line,
            half,
            next: now + half,
            level: Level::Low,
        });
    }

    /// The earliest deadline of any channel or of the heartbeat, monotonic ns.
    pub(crate) fn next_deadline(&self) -> Option<Nanos> {
        let channels = self.deadlines.first(&self.channels);
        debug_assert_eq!(
            channels,
            self.channels.iter().filter_map(Channel::poll_at).min(),
            "the deadlines kept are every channel's own"
        );
        let valves = self
            .valves
            .iter()
            .filter_map(Valve::poll_at)
            .chain(valve::exercise_next(&self.valves))
            .min();
        let channels = match (channels, valves) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        let heartbeat = self.heartbeat.as_ref().filter(|_| self.heartbeat_runs());
        [heartbeat.map(|hb| hb.next), channels, self.resend_at]
            .into_iter()
            .flatten()
            .min()
    }

    /// Whether a report was pushed since the last call (the caller then wakes the reader once).
    pub(crate) fn take_pushed(&mut self) -> bool {
        std::mem::take(&mut self.pushed)
    }

    /// Whether a safety input was applied and written since the last call (the caller then
    /// signals the acknowledgment once).
    pub(crate) fn take_acked(&mut self) -> bool {
        std::mem::take(&mut self.acked)
    }

    /// Applies every queued request, then every due deadline, writes the resulting edges in one
    /// call, and reports them.
    pub(crate) fn run(&mut self, requests: &mut Consumer<Request>) -> Result<(), Stop<O::Error>> {
        let now = (self.clock)();
        // The safety inputs first, whatever waits in the queue.
        let mut taken = self.take_safety(now);
        while let Ok(req) = requests.pop() {
            self.apply(now, req);
        }
        let now = (self.clock)();
        if now.saturating_sub(self.full_read_at) >= FULL_READ_NS {
            // Now and then, every channel, as a scan would: whatever an action left unmarked.
            self.mark_all();
            self.full_read_at = now;
        }
        // In channel order, as a scan of every channel would: the channels whose deadline may
        // have come, and any channel acted on along the way (a partner, a slot handed on) that
        // comes later in that order.
        self.deadlines.take_due(now, &mut self.walk);
        let mut from = 0;
        while let Some(i) = self.walk.first_from(from) {
            self.debug_none_between(from, i, |c| c.poll_at().is_some_and(|t| t <= now));
            from = i + 1;
            if self.channels[i].poll_at().is_some_and(|t| t <= now) {
                let held = self.channels[i].occupies();
                self.bank.before(&mut self.channels, i, now);
                let mut sink = Sink::new(i, &mut self.changes, &mut self.reports, &self.dropped);
                self.channels[i].poll(now, &mut |e| sink.event(e));
                self.pushed |= sink.pushed;
                self.touched.set(i);
                self.mark(i);
                self.sync_pair(i, now);
                // Only a slot given up can let a waiting pulse start. It is handed on at the
                // fall's scheduled instant, so the next pulse starts where the last one ended,
                // whatever the wake-up latency.
                if held && !self.channels[i].occupies() {
                    let fell = self
                        .changes
                        .iter()
                        .rev()
                        .find(|c| c.line == i)
                        .filter(|c| c.level == Level::Low)
                        .map_or(now, |c| c.scheduled_ns);
                    self.sync_bank(fell);
                }
                self.walk.add(self.deadlines.stale());
            }
        }
        self.debug_none_between(from, self.channels.len(), |c| {
            c.poll_at().is_some_and(|t| t <= now)
        });
        self.walk.clear();
        self.retry_rises(now);
        self.run_valves(now);
        if let Some(r) = self.sync_heater_faults(now) {
            taken = Some(r);
        }
        // Without a heartbeat, or before its time, nothing more to look at.
        let due = self.heartbeat.as_ref().is_some_and(|hb| hb.next <= now);
        let toggle = due && self.heartbeat_runs();
        if let Some(hb) = self.heartbeat.as_mut().filter(|_| toggle) {
            let level = if hb.level.is_high() {
                Level::Low
            } else {
                Level::High
            };
            hb.set(level, hb.next, &mut self.changes);
            // On the grid; after a stall, from now (no burst of catch-up toggles).
            hb.next += hb.half;
            if hb.next <= now {
                hb.next = now + hb.half;
            }
        }
        let flushed = self.flush(now);
        self.deadlines.refresh(&self.channels);
        flushed?;
        if let Some(request) = taken {
            // Applied and written: only now is it done.
            self.safety.mark_taken(request);
            self.acked = true;
        }
        Ok(())
    }

    /// Applies what changed in the safety slot since the last look, at `now`: the e-stop
    /// (every latch and reset since, in order, folded: a latch and a reset both missed still
    /// disable every channel), the hold of the lines, the planner. Returns the request number
    /// it covers, if anything was asked since the last look.
    fn take_safety(&mut self, now: Nanos) -> Option<u64> {
        if self.safety.requested() == self.seen.request {
            return None;
        }
        let w = self.safety.wanted();
        let (from, to) = (self.seen.estop_epoch, w.estop_epoch);
        if to > from {
            // Latch, reset, latch, ... from the state applied; more than three steps repeat.
            let steps = if to - from > 2 {
                2 + (to - from) % 2
            } else {
                to - from
            };
            let mut latched = from % 2 == 1;
            for _ in 0..steps {
                latched = !latched;
                self.estop(now, latched);
            }
        }
        if w.live != self.seen.live {
            self.set_live(now, w.live);
        }
        if w.bank != self.seen.bank {
            self.set_bank(now, w.bank);
        }
        self.seen = w;
        Some(w.request)
    }

    /// After the channels acted at `now`: a heater fault newly latched stops the heartbeat (an
    /// external contactor drops) and, with `heater_fault_latches_estop`, latches the e-stop of
    /// every channel through the safety slot, so the ROS side sees it latched and its reset
    /// releases it. Returns the slot's request number when it latched the e-stop.
    fn sync_heater_faults(&mut self, now: Nanos) -> Option<u64> {
        let (mut changed, mut new) = (false, false);
        // Only an action on a channel latches or clears its fault.
        let mut from = 0;
        while let Some(i) = self.acted.first_from(from) {
            from = i + 1;
            let faulted = self.channels[i].heater_fault().is_some();
            let seen = &mut self.heater_faulted[i];
            if faulted != *seen {
                changed = true;
                new |= faulted;
                *seen = faulted;
            }
        }
        self.acted.clear();
        debug_assert!(
            self.channels
                .iter()
                .zip(&self.heater_faulted)
                .all(|(c, seen)| c.heater_fault().is_some() == *seen),
            "a heater fault changed on a channel not acted on"
        );
        let mut taken = None;
        if new && self.heater_estop && !self.safety.estop_latched() {
            self.safety.estop(true);
            taken = self.take_safety(now);
        }
        if changed {
            self.heartbeat_gate(now);
        }
        taken
    }

    /// Rises the board of the lines held back while another line was high, written now that
    /// it allows them, in channel order; each keeps the pair and the planner in step.
    fn retry_rises(&mut self, now: Nanos) {
        // Only a channel that held a rise at its last read, or was acted on since, holds one.
        self.deadlines.add_may_hold_rise(&mut self.walk);
        let mut from = 0;
        while let Some(i) = self.walk.first_from(from) {
            self.debug_none_between(from, i, |c| c.rise_due(now));
            from = i + 1;
            if !self.channels[i].rise_due(now) {
                continue;
            }
            let mut sink = Sink::new(i, &mut self.changes, &mut self.reports, &self.dropped);
            self.channels[i].retry_rise(now, &mut |e| sink.event(e));
            self.pushed |= sink.pushed;
            self.touched.set(i);
            self.mark(i);
            self.sync_pair(i, now);
            self.deadlines.add_may_hold_rise(&mut self.walk);
        }
        self.debug_none_between(from, self.channels.len(), |c| c.rise_due(now));
        self.walk.clear();
    }

    /// Channel `i` was acted on: its deadline is read again, and it is looked at for a heater
    /// fault.
    fn mark(&mut self, i: usize) {
        self.deadlines.mark(i);
        self.acted.set(i);
    }

    /// Every channel may have been acted on.
    fn mark_all(&mut self) {
        self.deadlines.mark_all();
        self.acted.set_all();
    }

    /// Debug builds: no channel in `from..to` is one `acts` says a wake-up acts on. The walks
    /// over the channels skip the ones not in their set; this checks at every wake-up of every
    /// test that they skip none that a scan of every channel would have acted on.
    fn debug_none_between(&self, from: usize, to: usize, acts: impl Fn(&Channel) -> bool) {
        if cfg!(debug_assertions) {
            for k in from..to.min(self.channels.len()) {
                assert!(!acts(&self.channels[k]), "channel {k} skipped by the walk");
            }
        }
    }

    /// After channel `i` acted: its split-range partner, if any, is interlocked while `i` is
    /// high and released (its held rise written in this same batch, after `i`'s fall) when not.
    fn sync_pair(&mut self, i: usize, now: Nanos) {
        let Some(p) = self.interlocks.partner(i) else {
            return;
        };
        self.across(|channels, pairs, _, emit| pairs.sync(channels, i, now, emit));
        self.touched.set(p);
        // The interlock acts on the pair only.
        self.mark(i);
        self.mark(p);
    }

    /// Runs a step of a planner over the channels (`f`: the split-range pairs, the node-level
    /// planner), routing the events it makes for any channel as that channel's own: edges to
    /// the write batch, the rest to the report queue, and a fresh status for the channel.
    fn across(
        &mut self,
        f: impl FnOnce(&mut [Channel], &Interlocks, Bank, &mut dyn FnMut(usize, Event)),
    ) {
        let (changes, reports, dropped) = (&mut self.changes, &mut self.reports, &self.dropped);
        let (touched, mut pushed) = (&mut self.touched, false);
        f(
            &mut self.channels,
            &self.interlocks,
            self.bank,
            &mut |c, e| {
                let mut sink = Sink::new(c, changes, reports, dropped);
                sink.event(e);
                pushed |= sink.pushed;
                touched.set(c);
            },
        );
        self.pushed |= pushed;
    }

    /// Sets the node-level planner (`phase`, `max_simultaneous_on`) at `now`: the phase takes
    /// effect at each channel's next period start, a lowered limit at once.
    pub(crate) fn set_bank(&mut self, now: Nanos, bank: Bank) {
        self.bank = bank;
        self.board.set_max_on(bank.max_on);
        for i in 0..self.channels.len() {
            self.bank.before(&mut self.channels, i, now);
        }
        // A lowered limit takes effect at once, a raised one lets waiting pulses start.
        self.across(|channels, _, bank, emit| bank.shed(channels, now, emit));
        self.mark_all();
        self.sync_bank(now);
        self.deadlines.refresh(&self.channels);
    }

    /// After any action, at `now` (the instant a line went off, when one did): on phases
    /// waiting for a slot that may start now do (written in this same batch).
    fn sync_bank(&mut self, now: Nanos) {
        if self.bank.plans() {
            self.across(|channels, _, bank, emit| bank.after(channels, now, emit));
            // It may start any channel's waiting on phase.
            self.mark_all();
        }
    }

    /// Latches or releases the e-stop of every channel and valve at `now`.
    fn estop(&mut self, now: Nanos, latched: bool) {
        self.each_valve(now, |v, now, emit| v.set_estop(now, latched, emit));
        self.each_channel(now, |ch, now, emit| ch.set_estop(now, latched, emit));
        self.heartbeat_gate(now);
    }

    /// Lets every line follow its channel, or holds every line inactive, at `now`.
    pub(crate) fn set_live(&mut self, now: Nanos, live: bool) {
        self.each_valve(now, |v, now, emit| v.set_live(now, live, emit));
        self.each_channel(now, |ch, now, emit| ch.set_live(now, live, emit));
        self.heartbeat_gate(now);
        self.deadlines.refresh(&self.channels);
    }

    /// Runs `f` on every channel at `now`, then keeps every split-range pair apart.
    fn each_channel(&mut self, now: Nanos, f: impl Fn(&mut Channel, Nanos, &mut dyn FnMut(Event))) {
        for i in 0..self.channels.len() {
            self.bank.before(&mut self.channels, i, now);
            let mut sink = Sink::new(i, &mut self.changes, &mut self.reports, &self.dropped);
            f(&mut self.channels[i], now, &mut |e| sink.event(e));
            self.pushed |= sink.pushed;
            self.touched.set(i);
        }
        self.mark_all();
        for i in 0..self.channels.len() {
            self.sync_pair(i, now);
        }
        self.sync_bank(now);
    }

    /// Whether the heartbeat toggles: every line live, no e-stop and no heater fault latched
    /// (the output thread sets the first two for every channel at once).
    fn heartbeat_runs(&self) -> bool {
        self.channels
            .iter()
            .all(|c| c.live() && !c.estopped() && c.heater_fault().is_none())
    }

    /// After an e-stop or a hold changed: a heartbeat that stopped rests inactive, and it
    /// resumes on a fresh grid.
    fn heartbeat_gate(&mut self, now: Nanos) {
        let stopped = !self.heartbeat_runs();
        if let Some(hb) = self.heartbeat.as_mut() {
            if stopped {
                hb.set(Level::Low, now, &mut self.changes);
            }
            // Toggling resumes on a fresh grid after the release.
            hb.next = now + hb.half;
        }
    }

    /// Handles one request at `now`.
    fn apply(&mut self, now: Nanos, req: Request) {
        match req.input {
            Input::EStop(latched) => return self.estop(now, latched),
            Input::Live(live) => return self.set_live(now, live),
            Input::Bank(bank) => return self.set_bank(now, bank),
            Input::HeaterEstop(on) => {
                self.heater_estop = on;
                return;
            }
            Input::AddValve {
                close,
                config,
                start,
            } => {
                return self.add_valve(now, req.channel, close, config, start);
            }
            Input::ValveFeedback { valve, pct } => {
                // NaN, infinities and values far off the stroke are refused by the valve.
                return self.on_valve(valve, now, |v, now, emit| {
                    let _ = v.feedback(now, pct, emit);
                });
            }
            Input::ValveReset { valve, ticket } => {
                return self.on_valve(valve, now, |v, now, emit| {
                    v.reset(now, ticket, emit);
                });
            }
            Input::ValvePosition { valve, pct } => {
                // NaN and infinities are refused by the valve; the target in force stays.
                return self.on_valve(valve, now, |v, now, emit| {
                    let _ = v.command(now, pct, emit);
                });
            }
            Input::ValveSetpoint { valve, value } => {
                // Refused (not a number, out of bounds, not under pid) and counted by the valve.
                return self.on_valve(valve, now, |v, now, emit| {
                    let _ = v.setpoint(now, value, emit);
                });
            }
            Input::ValveProcess { valve, value, age } => {
                return self.on_valve(valve, now, |v, now, _| {
                    let _ = v.process_value(now, value, age);
                });
            }
            Input::ValveManual { valve, manual } => {
                return self.on_valve(valve, now, |v, now, emit| {
                    let _ = match manual {
                        Ok(m) => v.manual(now, m, emit),
                        Err(bad) => v.manual_refused(bad),
                    };
                });
            }
            Input::ValveConfig { valve, config } => {
                return self.on_valve(valve, now, |v, now, emit| v.set_config(now, config, emit));
            }
            Input::ValveSwitch { valve, dir, active } => {
                return self.on_valve(valve, now, |v, now, emit| {
                    v.set_switch(now, dir, active, emit)
                });
            }
            _ => {}
        }
        if self.owner.get(req.channel).is_some_and(Option::is_some) {
            // A valve's line follows the valve only.
            return;
        }
        self.bank.before(&mut self.channels, req.channel, now);
        self.mark(req.channel);
        let Some(ch) = self.channels.get_mut(req.channel) else {
            return;
        };
        let mut sink = Sink::new(
            req.channel,
            &mut self.changes,
            &mut self.reports,
            &self.dropped,
        );
        let emit = &mut |e| sink.event(e);
        match req.input {
            Input::Command(c) => ch.command(now, c, emit),
            Input::Enable(on) => ch.set_enable(now, on, emit),
            Input::Config(cfg) => ch.set_config(now, cfg, emit),
            Input::Pair(partner) => {
                // Refused pairs (unknown channel, already paired) are checked by the caller at
                // start-up; here they are ignored rather than stop the thread.
                let valve_line = self.owner.get(partner).is_some_and(Option::is_some);
                if !valve_line && self.interlocks.pair(req.channel, partner).is_ok() {
                    self.board.pair(req.channel, partner);
                }
            }
            Input::Feedback { celsius, age } => ch.feedback_stamped(now, celsius, age, emit),
            Input::Setpoint(c) => ch.set_setpoint(now, c, emit),
            Input::Feedforward(pct) => ch.feedforward(now, pct, emit),
            Input::Ambient { celsius, age } => ch.ambient_reading(now, celsius, age, emit),
            Input::ResetFault(ticket) => ch.reset_heater_fault(now, ticket, emit),
            Input::Autotune {
                ticket,
                goal,
                start_by,
            } => {
                if now <= start_by {
                    ch.start_autotune(now, ticket, goal, emit)
                }
            }
            Input::AutotuneCancel(ticket) => ch.cancel_autotune(now, ticket, emit),
            Input::EStop(_)
            | Input::Live(_)
            | Input::Bank(_)
            | Input::HeaterEstop(_)
            | Input::AddValve { .. }
            | Input::ValvePosition { .. }
            | Input::ValveSetpoint { .. }
            | Input::ValveProcess { .. }
            | Input::ValveManual { .. }
            | Input::ValveConfig { .. }
            | Input::ValveFeedback { .. }
            | Input::ValveReset { .. }
            | Input::ValveSwitch { .. } => {}
        }
        self.pushed |= sink.pushed;
        self.touched.set(req.channel);
        self.sync_pair(req.channel, now);
        self.sync_bank(now);
    }

    /// Writes the collected edges, reports them with their actual time, and sends a status
    /// snapshot for every channel that was touched.
    fn flush(&mut self, now: Nanos) -> Result<(), Stop<O::Error>> {
        if !self.changes.is_empty() {
            if let Err(error) = self.output.set_levels(&self.changes) {
                let channel = error.line().unwrap_or(self.changes[0].line);
                self.changes.clear();
                // The write failed: leave nothing on, whatever state the other lines are in.
                let _ = self.output.set_all_inactive();
                self.push(Report::OutputFault { channel });
                return Err(Stop::Fault { channel, error });
            }
            let actual_ns = (self.clock)();
            let wall_ns = clock::wall_ns();
            self.report_status(now);
            for k in 0..self.changes.len() {
                let c = self.changes[k];
                if c.line >= self.channels.len() {
                    // The heartbeat line: not a channel, nothing to report.
                    continue;
                }
                if let Some((v, dir)) = self.owner[c.line] {
                    // The valve's estimate, pause and minimum count from the real write.
                    self.valves[v].edge_written(dir, c.level, actual_ns);
                    self.valve_touched[v] = true;
                } else {
                    // The minimum of the phase this edge begins counts from when it reached
                    // the line.
                    self.channels[c.line].edge_written(actual_ns);
                    self.mark(c.line);
                }
                self.seq[c.line] += 1;
                self.push(Report::Edge(EdgeReport {
                    channel: c.line,
                    level: c.level,
                    seq: self.seq[c.line],
                    scheduled_ns: c.scheduled_ns,
                    actual_ns,
                    wall_ns,
                }));
            }
            self.changes.clear();
        }
        self.report_status(now);
        Ok(())
    }

    /// Makes valve number `self.valves.len()` on lines `open` and `close` at `now`, unless a
    /// line does not exist, is the other, or already belongs to a valve or a split-range pair
    /// (the caller checks at start-up; here such a valve is ignored rather than stop the
    /// thread), or the reserved room is full.
    fn add_valve(
        &mut self,
        now: Nanos,
        open: usize,
        close: usize,
        config: valve::ValveConfig,
        start: valve::ValveStart,
    ) {
        let n = self.channels.len();
        let free =
            |i: usize| i < n && self.owner[i].is_none() && self.interlocks.partner(i).is_none();
        if open == close
            || !free(open)
            || !free(close)
            || self.valves.len() == self.valves.capacity()
        {
            return;
        }
        // The channels are switched off for good: from now on only the valve moves the lines.
        for i in [open, close] {
            let mut sink = Sink::new(i, &mut self.changes, &mut self.reports, &self.dropped);
            self.channels[i].set_enable(now, false, &mut |e| sink.event(e));
            self.pushed |= sink.pushed;
            self.mark(i);
        }
        let mut v = Valve::start(config, now, start);
        v.seat_on(&self.board, open, close);
        let k = self.valves.len();
        self.owner[open] = Some((k, Dir::Open));
        self.owner[close] = Some((k, Dir::Close));
        self.valves.push(v);
        self.valve_lines.push([open, close]);
        self.valve_touched.push(true);
        let (live, latched) = (self.seen.live, self.seen.estop_epoch % 2 == 1);
        self.on_valve(k, now, |v, now, emit| {
            v.set_estop(now, latched, emit);
            v.set_live(now, live, emit);
        });
    }

    /// Runs `f` on valve `k` at `now`, routing its edges to the write batch.
    fn on_valve(
        &mut self,
        k: usize,
        now: Nanos,
        f: impl FnOnce(&mut Valve, Nanos, &mut dyn FnMut(ValveEvent)),
    ) {
        let (Some(v), Some(&lines)) = (self.valves.get_mut(k), self.valve_lines.get(k)) else {
            return;
        };
        let changes = &mut self.changes;
        f(v, now, &mut |e| valve_edge(changes, lines, e));
        self.valve_touched[k] = true;
    }

    /// Runs `f` on every valve at `now`.
    fn each_valve(
        &mut self,
        now: Nanos,
        f: impl Fn(&mut Valve, Nanos, &mut dyn FnMut(ValveEvent)),
    ) {
        for k in 0..self.valves.len() {
            self.on_valve(k, now, &f);
        }
    }

    /// The valves' due deadlines, rises the board or an unreported fall held, and the exercise
    /// strokes (one valve at a time), at `now`.
    fn run_valves(&mut self, now: Nanos) {
        for k in 0..self.valves.len() {
            let v = &self.valves[k];
            if v.poll_at().is_some_and(|t| t <= now) || v.rise_waiting() {
                self.on_valve(k, now, |v, now, emit| v.poll(now, emit));
            }
        }
        if valve::exercise_next(&self.valves).is_some_and(|t| t <= now) {
            let (changes, lines, touched) = (
                &mut self.changes,
                &self.valve_lines,
                &mut self.valve_touched,
            );
            valve::exercise_turn(&mut self.valves, now, &mut |k, e| {
                valve_edge(changes, lines[k], e);
                touched[k] = true;
            });
        }
    }

    /// Sends a status snapshot for every channel touched since the last one. Called before the
    /// edge reports of a write, so a reader sees the state an edge belongs to before the edge.
    fn report_status(&mut self, now: Nanos) {
        for v in 0..self.valves.len() {
            if std::mem::take(&mut self.valve_touched[v]) {
                let status = self.valves[v].status(now);
                let sent = push_report(
                    &mut self.reports,
                    &self.dropped,
                    Report::Valve {
                        valve: v,
                        status,
                        at_ns: now,
                    },
                );
                self.pushed |= sent;
                self.valve_touched[v] = !sent;
            }
        }
        let mut from = 0;
        while let Some(i) = self.touched.first_from(from) {
            from = i + 1;
            let status = self.channels[i].status(now);
            let sent = push_report(
                &mut self.reports,
                &self.dropped,
                Report::Status {
                    channel: i,
                    status,
                    at_ns: now,
                },
            );
            self.pushed |= sent;
            // A status is the latest state, not an event: one the full queue refused is sent
            // again at the next wake-up, so the reader never keeps a stale one.
            if sent {
                self.touched.unset(i);
            }
        }
        // That next wake-up comes even when nothing else is due (a channel at 0 or 100 %, a
        // stopped valve): the state the reader shows never waits for an unrelated edge.
        let refused = !self.touched.is_empty() || self.valve_touched.iter().any(|t| *t);
        self.resend_at = refused.then_some(now + STATUS_RESEND_NS);
    }

    /// Drives every line inactive (recording the edges of lines that were on) and returns the
    /// output so the caller can drop it where it wants.
    pub(crate) fn shut_down(mut self) -> (O, Result<(), O::Error>) {
        let now = (self.clock)();
        for (i, ch) in self.channels.iter().enumerate() {
            // A valve's lines are on the board, not in their channels.
            if ch.level() == Level::High || self.board.is_high(i) {
                self.changes.push(LineChange {
                    line: i,
                    level: Level::Low,
                    scheduled_ns: now,
                });
            }
        }
        if let Some(hb) = self.heartbeat.as_mut() {
            hb.set(Level::Low, now, &mut self.changes);
        }
        let r = if self.changes.is_empty() {
            Ok(())
        } else {
            self.output.set_levels(&self.changes)
        };
        self.changes.clear();
        // Explicitly, whatever the cores believed.
        let r2 = self.output.set_all_inactive();
        (self.output, r.and(r2))
    }

    fn push(&mut self, report: Report) {
        let _ = push_report(&mut self.reports, &self.dropped, report);
        self.pushed = true;
    }
}

/// Pushes `report`; returns whether it was queued.
fn push_report(reports: &mut Producer<Report>, dropped: &AtomicU64, report: Report) -> bool {
    if reports.push(report).is_err() {
        // The reader lags: never wait for it, count what is lost.
        dropped.fetch_add(1, Ordering::Relaxed);
        return false;
    }
    true
}

/// Puts a valve's edge into the write batch on its line. The valve never writes a fall and a
/// rise of one line in one batch (a rise waits for the fall's reported write), so each line
/// appears at most once.
fn valve_edge(changes: &mut Vec<LineChange>, lines: [usize; 2], e: ValveEvent) {
    let ValveEvent::Edge { dir, level, at } = e;
    changes.push(LineChange {
        line: lines[dir.index()],
        level,
        scheduled_ns: at,
    });
}

/// Routes a channel's core events: edges to the write batch, the rest to the report queue.
struct Sink<'a> {
    channel: usize,
    changes: &'a mut Vec<LineChange>,
    reports: &'a mut Producer<Report>,
    dropped: &'a AtomicU64,
    pushed: bool,
}

impl<'a> Sink<'a> {
    fn new(
        channel: usize,
        changes: &'a mut Vec<LineChange>,
        reports: &'a mut Producer<Report>,
        dropped: &'a AtomicU64,
    ) -> Self {
        Sink {
            channel,
            changes,
            reports,
            dropped,
            pushed: false,
        }
    }

    fn event(&mut self, e: Event) {
        match e {
            Event::Edge { at, level } => {
                // A request and a deadline in one wake-up can both move a line: keep only the
                // last level per line, so no zero-width pulse is written.
                if let Some(prev) = self.changes.iter().position(|c| c.line == self.channel) {
                    self.changes.remove(prev);
                    self.event(Event::Missed { edges: 2 });
                } else {
                    self.changes.push(LineChange {
                        line: self.channel,
                        level,
                        scheduled_ns: at,
                    });
                }
            }
            event => {
                let _ = push_report(
                    self.reports,
                    self.dropped,
                    Report::Core {
                        channel: self.channel,
                        event,
                    },
                );
                self.pushed = true;
            }
        }
    }
}
