//! A virtual-time bench for one channel: inputs at chosen instants, deadlines processed one by
//! one exactly when due, every event recorded with its cause. `wave()` prints the edges the way
//! the seeds draw timing diagrams: `H@0 L@370 H@1000` (level @ ms).

use crate::core::{Channel, ChannelParams, Command, Event, Level, Nanos, Plan, Status, NS_PER_MS};

/// One millisecond in ns.
pub const MS: Nanos = NS_PER_MS;

/// What made the channel act.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cause {
    /// A deadline (step end or watchdog).
    Deadline,
    /// A duty command.
    Command,
    /// A rising enable.
    Enable,
    /// A falling enable.
    Disable,
    /// A configuration change.
    Config,
    /// The emergency stop latched or released.
    EStop,
    /// The line held inactive or let live.
    Live,
}

/// An event with when and why it happened.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Logged {
    pub now: Nanos,
    pub cause: Cause,
    pub event: Event,
}

pub struct Bench {
    pub ch: Channel,
    pub now: Nanos,
    pub log: Vec<Logged>,
}

impl Bench {
    pub fn new(params: ChannelParams) -> Bench {
        Bench {
            ch: Channel::new(params.validate().expect("test parameters are valid"), 0),
            now: 0,
            log: Vec::new(),
        }
    }

    fn record(&mut self, cause: Cause, f: impl FnOnce(&mut Channel, Nanos, &mut dyn FnMut(Event))) {
        let now = self.now;
        let log = &mut self.log;
        f(&mut self.ch, now, &mut |event| {
            log.push(Logged { now, cause, event })
        });
    }

    /// Runs every deadline up to and including `t` ns, each at its own instant.
    pub fn run_to(&mut self, t: Nanos) -> &mut Self {
        while let Some(d) = self.ch.poll_at() {
            if d > t {
                break;
            }
            assert!(d >= self.now, "deadline {d} lies before now {}", self.now);
            self.now = d;
            self.record(Cause::Deadline, |ch, now, emit| ch.poll(now, emit));
        }
        self.now = t;
        self
    }

    /// Polls once at `t` ns, however many deadlines lie before it: a caller that woke late.
    pub fn poll_late(&mut self, t: Nanos) -> &mut Self {
        assert!(t >= self.now);
        self.now = t;
        self.record(Cause::Deadline, |ch, now, emit| ch.poll(now, emit));
        self
    }

    /// Runs to `ms` milliseconds.
    pub fn at(&mut self, ms: f64) -> &mut Self {
        self.run_to((ms * MS as f64).round() as Nanos)
    }

    pub fn enable(&mut self) -> &mut Self {
        self.record(Cause::Enable, |ch, now, emit| {
            ch.set_enable(now, true, emit)
        });
        self
    }

    pub fn disable(&mut self) -> &mut Self {
        self.record(Cause::Disable, |ch, now, emit| {
            ch.set_enable(now, false, emit)
        });
        self
    }

    pub fn estop(&mut self, latched: bool) -> &mut Self {
        self.record(Cause::EStop, |ch, now, emit| {
            ch.set_estop(now, latched, emit)
        });
        self
    }

    pub fn live(&mut self, live: bool) -> &mut Self {
        self.record(Cause::Live, |ch, now, emit| ch.set_live(now, live, emit));
        self
    }

    pub fn command(&mut self, c: Command) -> &mut Self {
        self.record(Cause::Command, |ch, now, emit| ch.command(now, c, emit));
        self
    }

    pub fn duty(&mut self, percent: f64) -> &mut Self {
        self.command(Command::Percent(percent))
    }

    pub fn params(&mut self, p: ChannelParams) -> &mut Self {
        let cfg = p.validate().expect("test parameters are valid");
        self.record(Cause::Config, |ch, now, emit| ch.set_config(now, cfg, emit));
        self
    }

    pub fn status(&self) -> Status {
        self.ch.status(self.now)
    }

    /// Every edge: (time ns, level).
    pub fn edges(&self) -> Vec<(Nanos, Level)> {
        self.log
            .iter()
            .filter_map(|l| match l.event {
                Event::Edge { at, level } => Some((at, level)),
                _ => None,
            })
            .collect()
    }

    /// The edges as a timing diagram: `H@0 L@370 H@1000`, times in ms.
    pub fn wave(&self) -> String {
        self.edges()
            .iter()
            .map(|(t, l)| {
                let ms = *t as f64 / MS as f64;
                let c = if l.is_high() { 'H' } else { 'L' };
                format!("{c}@{}", trim(ms))
            })
            .collect::<Vec<_>>()
            .join(" ")
    }

    /// Events other than edges and plans, for asserting flags, watchdog and rejections.
    pub fn notes(&self) -> Vec<(Nanos, Event)> {
        self.log
            .iter()
            .filter(|l| !matches!(l.event, Event::Edge { .. } | Event::Plan(_)))
            .map(|l| (l.now, l.event))
            .collect()
    }

    /// Total on time within [from, to), ns.
    pub fn on_time(&self, from: Nanos, to: Nanos) -> Nanos {
        let mut total = 0;
        let mut level = Level::Low;
        let mut since = 0;
        for (t, l) in self.edges() {
            if level.is_high() {
                total += t.clamp(from, to) - since.clamp(from, to);
            }
            level = l;
            since = t;
        }
        if level.is_high() {
            total += to - since.clamp(from, to);
        }
        total
    }
    /// The line's high spans `[rise, fall)`, ns, in order; a running one ends now.
    pub fn high_spans(&self) -> Vec<(Nanos, Nanos)> {
        high_spans(&self.edges(), self.now)
    }

    /// The most on time any window of `w` ns up to now holds, ns, and where that window ends.
    pub fn max_window_on(&self, w: Nanos) -> (Nanos, Nanos) {
        self.windows_on(w)
            .into_iter()
            .max()
            .unwrap_or((0, self.now))
    }

    /// The on time of the windows of `w` ns up to now that may hold the most, ns, each with
    /// where it ends: a window holds the most when it ends at a fall or begins at a rise (or
    /// ends now), so only those are listed.
    pub fn windows_on(&self, w: Nanos) -> Vec<(Nanos, Nanos)> {
        let spans = self.high_spans();
        let mut before = vec![0];
        for (a, z) in &spans {
            before.push(before.last().unwrap() + (z - a));
        }
        // On time in [0, x).
        let on_before = |x: Nanos| -> Nanos {
            let i = spans.partition_point(|(a, _)| *a < x);
            if i == 0 {
                0
            } else {
                let (a, z) = spans[i - 1];
                before[i - 1] + (x.min(z) - a)
            }
        };
        spans
            .iter()
            .flat_map(|(a, z)| [*z, a.saturating_add(w)])
            .chain([self.now])
            .filter(|end| *end <= self.now)
            .map(|end| (on_before(end) - on_before(end.saturating_sub(w)), end))
            .collect()
    }
}

/// A constant command `pct` from 0 for `n` periods of `params` (sent again every `repeat` ns,
/// if given, as a controller publishing at a rate does), driven by a thread that wakes and
/// writes each edge late by the next of `late` (wake-up, write) ns in turn, as the output
/// thread does: the line's high spans as really written, ns, and every plan the channel made.
pub fn late_steady(
    params: ChannelParams,
    pct: f64,
    n: u64,
    repeat: Option<Nanos>,
    late: &[(Nanos, Nanos)],
) -> (Vec<(Nanos, Nanos)>, Vec<Plan>) {
    let cfg = params.validate().unwrap();
    let end = n * cfg.period;
    let mut ch = Channel::new(cfg, 0);
    let mut plans = Vec::new();
    let mut edges: Vec<(Nanos, Level)> = Vec::new();
    let mut k = 0usize;
    let mut now = 0;
    let mut ev = Vec::new();
    ch.command(0, Command::Percent(pct), &mut |e| ev.push(e));
    ch.set_enable(0, true, &mut |e| ev.push(e));
    plans.push(*ch.plan());
    let mut next_command = repeat.map_or(Nanos::MAX, |r| r.max(1));
    loop {
        for e in ev.drain(..) {
            match e {
                Event::Edge { level, .. } => {
                    let written = now + late[k % late.len()].1;
                    k += 1;
                    ch.edge_written(written);
                    edges.push((written, level));
                }
                Event::Plan(p) => plans.push(p),
                _ => {}
            }
        }
        let due = ch.poll_at().filter(|d| *d < end);
        if next_command < end && due.is_none_or(|d| next_command < d) {
            now = next_command.max(now);
            next_command = next_command.saturating_add(repeat.unwrap_or(Nanos::MAX).max(1));
            ch.command(now, Command::Percent(pct), &mut |e| ev.push(e));
            continue;
        }
        let Some(d) = due else {
            break;
        };
        now = d.max(now) + late[k % late.len()].0;
        ch.poll(now, &mut |e| ev.push(e));
    }
    (high_spans(&edges, end.max(now)), plans)
}

/// The spans `[rise, fall)` a line was high, ns, in order, from its edges (level @ ns): a
/// repeated rise keeps the first, a zero-length pulse (rise and fall at one instant, which the
/// output thread merges away) is no span, and a span still open ends at `now`.
pub fn high_spans(edges: &[(Nanos, Level)], now: Nanos) -> Vec<(Nanos, Nanos)> {
    let mut spans = Vec::new();
    let mut rise = None;
    for &(t, level) in edges {
        match level {
            Level::High => rise = rise.or(Some(t)),
            Level::Low => spans.extend(rise.take().map(|a| (a, t))),
        }
    }
    spans.extend(rise.map(|a| (a, now)));
    spans.retain(|(a, z)| a < z);
    spans
}

fn trim(ms: f64) -> String {
    let s = format!("{ms:.4}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    s.to_string()
}
