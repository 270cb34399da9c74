//! The output thread's work in virtual time: the very [`Worker`] the thread runs, fed requests
//! and safety inputs at random instants, woken late at random, with an output that checks at
//! every write what no path may put on the lines: the two lines of a split-range pair high
//! together, or a rise that leaves more lines high than `max_simultaneous_on`.

use super::safety::SafetySlot;
use super::worker::Worker;
use super::{Input, Report, Request};
use crate::core::{
    ApplyAt, Bank, ChannelParams, Command, Level, Nanos, OutputKind, Phase, Profile, NS_PER_MS,
};
use crate::output::{EmergencyOff, LineChange, Output};
use proptest::prelude::*;
use std::cell::{Cell, RefCell};
use std::sync::atomic::AtomicU64;
use std::sync::Arc;

const MS: Nanos = NS_PER_MS;
/// How long a write takes in virtual time, ns.
const WRITE_NS: Nanos = 30_000;

thread_local! {
    static NOW: Cell<Nanos> = const { Cell::new(0) };
    /// The rules the output checks, and what it saw.
    static LINES: RefCell<Lines> = RefCell::new(Lines::default());
}

fn now() -> Nanos {
    NOW.with(Cell::get)
}

fn set_now(t: Nanos) {
    NOW.with(|n| n.set(t));
}

#[derive(Default)]
struct Lines {
    high: Vec<bool>,
    pairs: Vec<(usize, usize)>,
    /// The limit in force for the writes from now on (0: none).
    max_on: usize,
    violations: Vec<String>,
    rises: usize,
    /// Every level written per line, at the instant the write completed (ns).
    edges: Vec<Vec<(Nanos, bool)>>,
}

/// An output that checks the rules across lines at every write, after the whole batch.
struct CheckedOutput {
    lines: usize,
}

struct NoEmergency;
impl EmergencyOff for NoEmergency {
    fn all_inactive(&self) {}
}

impl Output for CheckedOutput {
    type Error = std::convert::Infallible;

    fn line_count(&self) -> usize {
        self.lines
    }

    fn set_levels(&mut self, changes: &[LineChange]) -> Result<(), Self::Error> {
        LINES.with(|l| {
            let mut l = l.borrow_mut();
            let mut rose = false;
            let done = now() + WRITE_NS;
            for c in changes {
                if c.line < l.high.len() {
                    rose |= c.level == Level::High && !l.high[c.line];
                    l.high[c.line] = c.level.is_high();
                    l.edges[c.line].push((done, c.level.is_high()));
                }
            }
            let t = now();
            for &(a, b) in &l.pairs.clone() {
                if l.high[a] && l.high[b] {
                    l.violations
                        .push(format!("lines {a} and {b} high together at {t} ns"));
                }
            }
            let count = l.high.iter().filter(|h| **h).count();
            if rose {
                l.rises += 1;
                if l.max_on > 0 && count > l.max_on {
                    let max = l.max_on;
                    l.violations.push(format!(
                        "a rise left {count} lines high (max {max}) at {t} ns"
                    ));
                }
            }
        });
        // The write takes time: the edge reaches the line later than it was decided.
        set_now(now() + WRITE_NS);
        Ok(())
    }

    fn set_all_inactive(&mut self) -> Result<(), Self::Error> {
        LINES.with(|l| l.borrow_mut().high.iter_mut().for_each(|h| *h = false));
        Ok(())
    }

    fn emergency_off(&self) -> Arc<dyn EmergencyOff> {
        Arc::new(NoEmergency)
    }
}

/// The worker with its queues, driven as the output thread drives it.
struct Bench {
    worker: Worker<CheckedOutput>,
    tx: rtrb::Producer<Request>,
    rx: rtrb::Consumer<Request>,
    reports: rtrb::Consumer<Report>,
    slot: Arc<SafetySlot>,
}

impl Bench {
    fn new(params: &[ChannelParams], pairs: &[(usize, usize)], held: bool) -> Bench {
        set_now(1_000 * MS);
        let n = params.len();
        LINES.with(|l| {
            *l.borrow_mut() = Lines {
                high: vec![false; n],
                edges: vec![Vec::new(); n],
                pairs: pairs.to_vec(),
                ..Lines::default()
            }
        });
        let configs: Vec<_> = params
            .iter()
            .map(|p| p.validate().expect("valid test parameters"))
            .collect();
        let (tx, rx) = rtrb::RingBuffer::new(4096);
        let (rep_tx, reports) = rtrb::RingBuffer::new(1 << 16);
        let slot = Arc::new(SafetySlot::new(!held, Bank::default()));
        let mut worker = Worker::new(
            &configs,
            CheckedOutput { lines: n },
            rep_tx,
            Arc::new(AtomicU64::new(0)),
            now(),
            Arc::clone(&slot),
        )
        .with_clock(now);
        if held {
            worker.set_live(now(), false);
        }
        let mut b = Bench {
            worker,
            tx,
            rx,
            reports,
            slot,
        };
        for &(a, c) in pairs {
            b.send(a, Input::Pair(c));
            b.send(c, Input::Pair(a));
        }
        b.wake();
        b
    }

    fn send(&mut self, channel: usize, input: Input) {
        match input {
            Input::EStop(on) => {
                self.slot.estop(on);
            }
            Input::Live(on) => {
                self.slot.live(on);
            }
            Input::Bank(bank) => {
                LINES.with(|l| l.borrow_mut().max_on = bank.max_on);
                self.slot.bank(bank);
            }
            input => self
                .tx
                .push(Request { channel, input })
                .expect("queue has room"),
        }
    }

    /// One wake-up now, as the thread's loop does it.
    fn wake(&mut self) {
        if self.worker.run(&mut self.rx).is_err() {
            unreachable!("the checked output never fails");
        }
        while self.reports.pop().is_ok() {}
    }

    /// Runs every deadline up to `t`, each woken `late` ns after it is due.
    fn run_to(&mut self, t: Nanos, late: Nanos) {
        while let Some(d) = self.worker.next_deadline() {
            let at = d.max(now()) + late;
            if at > t {
                break;
            }
            set_now(at);
            self.wake();
        }
        set_now(t.max(now()));
    }
}

fn violations() -> Vec<String> {
    LINES.with(|l| l.borrow().violations.clone())
}

fn rises() -> usize {
    LINES.with(|l| l.borrow().rises)
}

/// The most on time line `line` had in any window of `window` ns, counting each high span from
/// the end of the rise's write to the end of the fall's write.
fn most_on_in_a_window(line: usize, window: Nanos) -> Nanos {
    most_on_after(line, window, 0)
}

/// [`most_on_in_a_window`] over the windows that start at or after `from` (ns) only.
fn most_on_after(line: usize, window: Nanos, from: Nanos) -> Nanos {
    let edges = LINES.with(|l| l.borrow().edges[line].clone());
    let mut spans = Vec::new();
    let mut rose = None;
    for (t, high) in edges {
        match (high, rose) {
            (true, None) => rose = Some(t),
            (false, Some(r)) => {
                spans.push((r, t));
                rose = None;
            }
            _ => {}
        }
    }
    spans
        .iter()
        .filter(|&&(_, end)| end >= from + window)
        .map(|&(_, end)| {
            let start = end - window;
            spans
                .iter()
                .map(|&(a, b)| b.min(end).saturating_sub(a.max(start)))
                .sum::<Nanos>()
        })
        .max()
        .unwrap_or(0)
}

fn params(period_ms: u64, min_on_ms: u64, apply_at: Option<ApplyAt>) -> ChannelParams {
    ChannelParams {
        period_ms,
        min_on_ms,
        apply_at,
        output_kind: OutputKind::Transistor,
        ..ChannelParams::default()
    }
}

#[test]
fn a_pulse_started_by_a_slot_hand_over_never_overlaps_its_split_partner() {
    // The case: 4 channels, pw01/pw02 a split pair, max 2 on, periods 200 ms, duties
    // 50/20/30/40; pw03 and pw04 enabled, pw01 20 ms later, pw02 80 ms after that.
    let p = params(200, 0, None);
    let mut b = Bench::new(&[p; 4], &[(0, 1)], false);
    b.send(
        0,
        Input::Bank(Bank {
            phase: Phase::Sync,
            max_on: 2,
        }),
    );
    for (ch, d) in [(0, 50.0), (1, 20.0), (2, 30.0), (3, 40.0)] {
        b.send(ch, Input::Command(Command::Percent(d)));
    }
    b.send(2, Input::Enable(true));
    b.send(3, Input::Enable(true));
    b.wake();
    let t0 = now();
    b.run_to(t0 + 20 * MS, 0);
    b.send(0, Input::Enable(true));
    b.wake();
    b.run_to(t0 + 100 * MS, 0);
    b.send(1, Input::Enable(true));
    b.wake();
    b.run_to(t0 + 3_000 * MS, 0);
    let per_line = LINES.with(|l| {
        l.borrow()
            .edges
            .iter()
            .map(|e| e.iter().filter(|(_, h)| *h).count())
            .collect::<Vec<_>>()
    });
    // pw03 and pw04 run; of the pair, a pulse that lies wholly within its partner's is held by
    // the interlock until it has passed, and is reported missed.
    assert!(per_line[2] >= 10 && per_line[3] >= 10, "{per_line:?} rises");
    assert!(per_line[0] + per_line[1] >= 10, "{per_line:?} rises");
    assert_eq!(violations(), Vec::<String>::new());
}

#[test]
fn activating_a_managed_node_never_raises_both_lines_of_a_pair() {
    // Both channels of a pair enabled at 95 % while the lines are held (inactive): at every
    // activation only one line may rise.
    let p = params(200, 0, None);
    let mut b = Bench::new(&[p; 2], &[(0, 1)], true);
    for ch in 0..2 {
        b.send(ch, Input::Command(Command::Percent(95.0)));
        b.send(ch, Input::Enable(true));
    }
    b.wake();
    for k in 0..10 {
        let t = now();
        b.run_to(t + 37 * MS * (k + 1), 0);
        b.send(0, Input::Live(true));
        b.wake();
        let t = now();
        b.run_to(t + 300 * MS, 0);
        b.send(0, Input::Live(false));
        b.wake();
    }
    assert!(rises() >= 10, "the lines ran: {} rises", rises());
    assert_eq!(violations(), Vec::<String>::new());
}

#[test]
fn safety_inputs_are_taken_before_the_queued_commands_and_acknowledged_after_the_write() {
    let p = params(100, 0, None);
    let mut b = Bench::new(&[p; 2], &[], false);
    b.send(0, Input::Command(Command::Percent(50.0)));
    b.send(0, Input::Enable(true));
    b.wake();
    assert!(LINES.with(|l| l.borrow().high[0]), "pw01 on");
    // A queue full of commands, then the e-stop: it is taken in the same wake-up, first, and
    // no command after it raises a line.
    for _ in 0..1000 {
        b.send(0, Input::Enable(true));
        b.send(0, Input::Command(Command::Percent(90.0)));
    }
    let r = b.slot.estop(true);
    assert!(!b.slot.taken(r));
    b.wake();
    assert!(b.slot.taken(r), "acknowledged once written");
    assert!(LINES.with(|l| !l.borrow().high[0]), "pw01 off");
    let before = rises();
    let t = now();
    b.run_to(t + 2_000 * MS, 0);
    assert_eq!(rises(), before, "nothing rises while latched");
    // A latch and a reset both made before the thread looks still disable the channel.
    let r = b.slot.estop(false);
    b.wake();
    assert!(b.slot.taken(r));
    b.send(0, Input::Enable(true));
    b.wake();
    let t = now();
    b.run_to(t + 200 * MS, 0);
    assert!(rises() > before, "runs again after reset and enable");
    b.slot.estop(true);
    b.slot.estop(false);
    b.wake();
    let after = rises();
    let t = now();
    b.run_to(t + 1_000 * MS, 0);
    assert_eq!(rises(), after, "the missed latch disabled the channel");
}

#[test]
fn a_lowered_limit_and_a_hold_act_whatever_waits_in_the_queue() {
    let p = params(100, 0, None);
    let mut b = Bench::new(&[p; 3], &[], false);
    for ch in 0..3 {
        b.send(ch, Input::Command(Command::Percent(60.0)));
        b.send(ch, Input::Enable(true));
    }
    b.wake();
    for _ in 0..1000 {
        b.send(1, Input::Command(Command::Percent(70.0)));
    }
    b.send(
        0,
        Input::Bank(Bank {
            phase: Phase::Sync,
            max_on: 1,
        }),
    );
    let t = now();
    b.run_to(t + 2_000 * MS, 0);
    assert_eq!(violations(), Vec::<String>::new());
    for _ in 0..1000 {
        b.send(2, Input::Command(Command::Percent(80.0)));
    }
    let r = b.slot.live(false);
    b.wake();
    assert!(b.slot.taken(r));
    assert!(
        LINES.with(|l| l.borrow().high.iter().all(|h| !h)),
        "all held off"
    );
    let before = rises();
    let t = now();
    b.run_to(t + 1_000 * MS, 0);
    assert_eq!(rises(), before, "nothing rises while held");
}

#[derive(Debug, Clone)]
enum Op {
    Duty(usize, f64),
    Split(f64),
    Enable(usize, bool),
    Live(bool),
    EStop(bool),
    Limit(usize, bool),
}

fn arb_op() -> impl Strategy<Value = Op> {
    prop_oneof![
        6 => (0usize..4, 10.0..100.0f64).prop_map(|(c, d)| Op::Duty(c, d)),
        2 => (-100.0..100.0f64).prop_map(Op::Split),
        4 => (0usize..4, prop::bool::weighted(0.8)).prop_map(|(c, on)| Op::Enable(c, on)),
        2 => any::<bool>().prop_map(Op::Live),
        1 => prop::bool::weighted(0.3).prop_map(Op::EStop),
        2 => (0usize..4, any::<bool>()).prop_map(|(m, s)| Op::Limit(m, s)),
    ]
}

fn arb_params() -> impl Strategy<Value = ChannelParams> {
    (
        prop::sample::select(vec![100u64, 150, 200]),
        prop_oneof![Just(0u64), 1u64..40],
        prop::sample::select(Profile::ALL.to_vec()),
        prop::option::of(prop::sample::select(vec![
            ApplyAt::NextPeriod,
            ApplyAt::NextStep,
            ApplyAt::Immediate,
        ])),
    )
        .prop_map(|(period_ms, min_on_ms, profile, apply_at)| ChannelParams {
            profile,
            ..params(period_ms, min_on_ms, apply_at)
        })
}

#[test]
fn the_average_cap_holds_on_the_line_with_late_falls() {
    // The case: period 10 ms, 50 % commanded, cap 30 % over 1 s; every write takes
    // 30 us and every wake-up is 0.1 ms late.
    let p = ChannelParams {
        avg_duty_limit_pct: 30.0,
        avg_window_s: 1,
        ..params(10, 0, None)
    };
    let mut b = Bench::new(&[p], &[], false);
    b.send(0, Input::Command(Command::Percent(50.0)));
    b.send(0, Input::Enable(true));
    b.wake();
    let t = now();
    b.run_to(t + 5_000 * MS, 100_000);
    let most = most_on_in_a_window(0, 1_000 * MS);
    assert!(most > 250 * MS, "the line ran at the cap: {most} ns");
    assert!(
        most <= 300 * MS,
        "{most} ns on in a 1 s window, 300 ms allowed"
    );
}

/// A wake-up late by as much as the break after a 99.78 % pulse handles the fall and the next
/// period's start in one batch: the fall never reaches the line, which stays on. The cap's
/// decision at that period start counts the line on until the wake-up, so the first window
/// holds no more than the cap and the first fall's lateness beyond the margin kept for it.
#[test]
fn a_break_swallowed_by_a_late_wake_up_counts_against_the_average_cap() {
    let late = 223_977;
    let limit = 12.833_770_986_117_996;
    let p = ChannelParams {
        avg_duty_limit_pct: limit,
        avg_window_s: 1,
        ..params(100, 0, None)
    };
    let mut b = Bench::new(&[p], &[], false);
    // A break of 100 ms x (1 - 0.9977602...) = 223,977 ns: exactly the lateness.
    b.send(0, Input::Command(Command::Percent(99.776_023_349_732_03)));
    b.send(0, Input::Enable(true));
    b.wake();
    let t = now();
    b.run_to(t + 2_000 * MS, late);
    let allowed = (limit / 100.0 * 1e9).floor() as Nanos;
    let most = most_on_in_a_window(0, 1_000 * MS);
    // Without the swallowed break counted: allowed + 377,954 ns (twice the lateness).
    assert!(
        most <= allowed + late + WRITE_NS,
        "{most} ns on in a window, {allowed} allowed (+{} ns unforeseen)",
        late + WRITE_NS
    );
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]

    /// The rolling-average cap holds on the line as written: falls that reach the line late
    /// (a late wake-up, the write itself) count, and each decision keeps a margin of the
    /// lateness falls have shown. A fall later than every one before it (the first fall among
    /// them) can overshoot by that extra lateness once; it is then counted and taken off what
    /// follows, so with the lateness steady no later window holds more than the cap.
    #[test]
    fn no_window_on_the_line_holds_more_than_the_average_cap(
        period_ms in prop::sample::select(vec![10u64, 20, 50, 100]),
        duty in 20.0..100.0f64,
        limit in 5.0..60.0f64,
        window_s in 1u64..3,
        late in 0u64..300_000,
        spike in prop::option::of(0u64..300_000),
    ) {
        let p = ChannelParams {
            avg_duty_limit_pct: limit,
            avg_window_s: window_s,
            ..params(period_ms, 0, None)
        };
        let mut b = Bench::new(&[p], &[], false);
        b.send(0, Input::Command(Command::Percent(duty)));
        b.send(0, Input::Enable(true));
        b.wake();
        let window = window_s * 1_000 * MS;
        let t = now() + 2 * window;
        b.run_to(t, late);
        // One wake-up later than all before it, then steady again.
        let extra = spike.unwrap_or(0);
        let t = now() + period_ms * MS;
        b.run_to(t, late + extra);
        let t = now() + 2 * window;
        b.run_to(t, late);
        let allowed = (limit / 100.0 * window as f64).floor() as Nanos;
        // The first fall and the spike are later than any fall before them.
        let unforeseen = late + WRITE_NS + extra;
        let most = most_on_in_a_window(0, window);
        prop_assert!(
            most <= allowed + unforeseen,
            "{} ns on in a window, {} allowed (+{} ns unforeseen)", most, allowed, unforeseen
        );
        // After the first two windows (the spike's and the first fall's), exact.
        let settled = most_on_after(0, window, t.saturating_sub(window));
        prop_assert!(settled <= allowed, "{} ns on in a late window, {} allowed", settled, allowed);
    }

    /// Whatever decided a rise — a slot handed over, an activation, a hold or an e-stop
    /// released, a late wake-up, a command re-timing a pulse — the lines of a split-range pair
    /// are never high together and no rise leaves more lines high than `max_simultaneous_on`.
    #[test]
    fn no_path_puts_a_pair_high_together_or_more_lines_high_than_the_limit(
        chans in prop::collection::vec(arb_params(), 4),
        held in any::<bool>(),
        ops in prop::collection::vec(((0u64..400).prop_map(|ms| ms * MS), arb_op()), 1..60),
        late in prop::collection::vec(prop_oneof![3 => Just(0u64), 1 => 0u64..5 * MS], 60),
    ) {
        let mut b = Bench::new(&chans, &[(0, 1)], held);
        for (k, (dt, op)) in ops.into_iter().enumerate() {
            let t = now() + dt;
            b.run_to(t, late[k]);
            match op {
                Op::Duty(c, d) => b.send(c, Input::Command(Command::Percent(d))),
                Op::Split(pct) => {
                    let (h, c) = crate::core::split_command(pct, 0.0);
                    b.send(0, Input::Command(h));
                    b.send(1, Input::Command(c));
                }
                Op::Enable(c, on) => b.send(c, Input::Enable(on)),
                Op::Live(on) => b.send(0, Input::Live(on)),
                Op::EStop(on) => b.send(0, Input::EStop(on)),
                Op::Limit(max_on, stagger) => b.send(0, Input::Bank(Bank {
                    phase: if stagger { Phase::Stagger } else { Phase::Sync },
                    max_on,
                })),
            }
            b.wake();
        }
        let t = now() + 2_000 * MS;
        b.run_to(t, 0);
        prop_assert_eq!(violations(), Vec::<String>::new());
    }
}

#[test]
fn a_status_the_full_report_queue_refused_is_sent_at_the_next_wake_up() {
    set_now(1_000 * MS);
    LINES.with(|l| {
        *l.borrow_mut() = Lines {
            high: vec![false],
            edges: vec![Vec::new()],
            ..Lines::default()
        }
    });
    let cfg = params(100, 0, None).validate().unwrap();
    let (mut tx, mut rx) = rtrb::RingBuffer::new(64);
    let (rep_tx, mut reports) = rtrb::RingBuffer::new(4);
    let slot = Arc::new(SafetySlot::new(true, Bank::default()));
    let mut worker = Worker::new(
        &[cfg],
        CheckedOutput { lines: 1 },
        rep_tx,
        Arc::new(AtomicU64::new(0)),
        now(),
        Arc::clone(&slot),
    )
    .with_clock(now);
    // Commands whose reports (a new plan each) fill the queue before the status is taken.
    for k in 0..10 {
        let input = Input::Command(Command::Percent(10.0 + k as f64));
        tx.push(Request { channel: 0, input }).unwrap();
    }
    let r = slot.estop(true);
    assert!(worker.run(&mut rx).is_ok());
    assert!(slot.taken(r));
    let statuses = |reports: &mut rtrb::Consumer<Report>| {
        let mut last = None;
        while let Ok(rep) = reports.pop() {
            if let Report::Status { status, .. } = rep {
                last = Some(status);
            }
        }
        last
    };
    assert!(statuses(&mut reports).is_none(), "the queue was full");
    // The e-stopped channel has no edge to come: the thread wakes for the resend alone.
    let resend = worker
        .next_deadline()
        .expect("a wake-up for the refused status");
    assert_eq!(resend, now() + super::worker::STATUS_RESEND_NS);
    set_now(resend);
    assert!(worker.run(&mut rx).is_ok());
    let status = statuses(&mut reports).expect("the status, sent again");
    assert!(status.estopped && !status.enabled, "{status:?}");
    // Sent: nothing more is due.
    assert_eq!(worker.next_deadline(), None);
}

#[test]
fn a_heater_fault_stops_the_heartbeat_and_can_latch_the_estop_of_every_channel() {
    let heater = ChannelParams {
        heater: crate::core::heater::HeaterParams {
            feedback: true,
            temp_max_c: 300.0,
            ..Default::default()
        },
        ..params(1000, 0, None)
    };
    let mut b = Bench::new(&[heater, params(1000, 0, None)], &[], false);
    // The heartbeat is line 2, recorded like the channels' lines.
    LINES.with(|l| {
        let mut l = l.borrow_mut();
        l.high.push(false);
        l.edges.push(Vec::new());
    });
    b.worker.start_heartbeat(2, 50 * MS, now());
    b.send(0, Input::HeaterEstop(true));
    for ch in 0..2 {
        b.send(ch, Input::Command(crate::core::Command::Percent(100.0)));
        b.send(ch, Input::Enable(true));
    }
    b.send(
        0,
        Input::Feedback {
            celsius: 25.0,
            age: None,
        },
    );
    b.wake();
    b.run_to(now() + 1_000 * MS, 0);
    let toggles = |l: &Lines| l.edges[2].len();
    let before = LINES.with(|l| toggles(&l.borrow()));
    assert!(before >= 18, "the heartbeat runs: {before} toggles");
    assert!(LINES.with(|l| l.borrow().high[0] && l.borrow().high[1]));
    // A reading above temp_max_c: channel 0's line off at once, and with it, through the
    // e-stop, channel 1's; the heartbeat rests inactive.
    b.send(
        0,
        Input::Feedback {
            celsius: 350.0,
            age: None,
        },
    );
    b.wake();
    LINES.with(|l| {
        let l = l.borrow();
        assert!(!l.high[0] && !l.high[1] && !l.high[2], "{:?}", l.high);
    });
    assert!(b.slot.estop_latched());
    let after = LINES.with(|l| toggles(&l.borrow()));
    b.run_to(now() + 2_000 * MS, 0);
    assert_eq!(
        LINES.with(|l| toggles(&l.borrow())),
        after,
        "the heartbeat stopped"
    );
    assert!(LINES.with(|l| !l.borrow().high.iter().any(|h| *h)));
}

#[test]
fn an_autotune_goal_taken_after_its_start_by_never_starts() {
    use crate::core::heater::autotune::{Goal, Report as Tune};
    let heater = ChannelParams {
        heater: crate::core::heater::HeaterParams {
            feedback: true,
            temp_max_c: 300.0,
            ..Default::default()
        },
        ..params(100, 0, None)
    };
    let mut b = Bench::new(&[heater], &[], false);
    b.send(0, Input::Enable(true));
    b.send(
        0,
        Input::Feedback {
            celsius: 25.0,
            age: None,
        },
    );
    b.wake();
    // What one wake-up reports of the autotunes, by ticket.
    let tune_reports = |b: &mut Bench| {
        assert!(b.worker.run(&mut b.rx).is_ok());
        let mut got = Vec::new();
        while let Ok(r) = b.reports.pop() {
            if let Report::Core {
                event: crate::core::Event::Autotune { ticket, report },
                ..
            } = r
            {
                got.push((ticket, report));
            }
        }
        got
    };
    let goal = Goal {
        target_c: 60.0,
        amplitude_pct: 100.0,
        noise_band_c: 0.5,
    };
    // Taken 1 ns after the latest instant it could start: dropped, nothing reported, the line
    // stays off (the relay would drive it at 100 %: 25 °C is below the target).
    b.send(
        0,
        Input::Autotune {
            ticket: 1,
            goal,
            start_by: now() - 1,
        },
    );
    assert!(tune_reports(&mut b).is_empty());
    b.run_to(now() + 500 * MS, 0);
    assert_eq!(rises(), 0);
    // Taken at its start_by: it starts, and the relay turns the line on.
    b.send(
        0,
        Input::Autotune {
            ticket: 2,
            goal,
            start_by: now(),
        },
    );
    let got = tune_reports(&mut b);
    assert!(
        got.iter()
            .any(|(t, r)| *t == 2 && matches!(r, Tune::Started)),
        "{got:?}"
    );
    b.run_to(now() + 500 * MS, 0);
    assert!(rises() > 0);
    assert!(violations().is_empty(), "{:?}", violations());
}

/// The settings of the valves below: short travel times so a test covers many moves.
fn valve_params() -> crate::core::ValveParams {
    crate::core::ValveParams {
        travel_open_ms: 2_000,
        travel_close_ms: 1_600,
        deadband_pct: 0.5,
        min_pulse_ms: 40,
        reversal_pause_ms: 60,
        // The estimate is compared with the integral of the lines: no play to sit in.
        backlash_pct: 0.0,
        end_overrun_pct: 10.0,
        reference_at_start: crate::core::valve::ReferenceAtStart::Close,
        recalibrate_after_s: 0,
        ..crate::core::ValveParams::default()
    }
}

/// A bench of four channels with a valve on lines 2 (open) and 3 (close), whose lines the
/// output checks as a pair.
fn valve_bench(held: bool) -> Bench {
    let chans = [params(100, 0, None); 4];
    let mut b = Bench::new(&chans, &[(0, 1)], held);
    LINES.with(|l| l.borrow_mut().pairs.push((2, 3)));
    let config = valve_params().validate().unwrap();
    b.send(
        2,
        Input::AddValve {
            close: 3,
            config,
            start: Default::default(),
        },
    );
    b.wake();
    b
}

/// The valve's drive as written: the integral of the high spans of its lines (from the end of
/// each rise's write to the end of the fall's, the times the worker reports to the valve) over
/// the travel times, clamped to the stroke, in the order they came; a line still high counts
/// up to now, as the valve counts the drive under way.
fn integral_of_the_lines(p: &crate::core::ValveParams) -> f64 {
    let edges = LINES.with(|l| l.borrow().edges.clone());
    let mut all: Vec<(Nanos, usize, bool)> = [2usize, 3]
        .iter()
        .flat_map(|&i| edges[i].iter().map(move |&(t, h)| (t, i, h)))
        .collect();
    all.sort_by_key(|&(t, i, h)| (t, h, i));
    let mut rose: [Option<Nanos>; 4] = [None; 4];
    let mut pos = 0.0f64;
    let drive = |pos: f64, i: usize, from: Nanos, to: Nanos| {
        let (travel, sign) = if i == 2 {
            (p.travel_open_ms, 1.0)
        } else {
            (p.travel_close_ms, -1.0)
        };
        let ran = to.saturating_sub(from) as f64 / (travel as f64 * 1e6);
        (pos + sign * ran * 100.0).clamp(0.0, 100.0)
    };
    for (t, i, h) in all {
        if h {
            rose[i] = Some(t);
        } else if let Some(r) = rose[i].take() {
            pos = drive(pos, i, r, t);
        }
    }
    // Never both high (checked apart): at most one span is open.
    for i in [2usize, 3] {
        if let Some(r) = rose[i] {
            pos = drive(pos, i, r, now());
        }
    }
    pos
}

/// The valve lines as written: a rise of either comes at least the reversal pause after the
/// last fall of either, and every rise is followed by a fall (none left high at the end).
fn valve_pause_held(pause: Nanos) -> Result<(), String> {
    let edges = LINES.with(|l| l.borrow().edges.clone());
    let mut all: Vec<(Nanos, usize, bool)> = [2usize, 3]
        .iter()
        .flat_map(|&i| edges[i].iter().map(move |&(t, h)| (t, i, h)))
        .collect();
    all.sort_by_key(|&(t, i, h)| (t, h, i));
    let mut fell: Option<Nanos> = None;
    for (t, i, h) in all {
        if h {
            if let Some(f) = fell.filter(|&f| t < f + pause) {
                return Err(format!("line {i} rose at {t}, {} ns after a fall", t - f));
            }
        } else {
            fell = Some(t);
        }
    }
    Ok(())
}

#[test]
fn a_valve_references_then_follows_its_position_on_the_real_lines() {
    let mut b = valve_bench(false);
    let t = now();
    // The reference: 150 % of the closing travel, 2.4 s.
    b.run_to(t + 3_000 * MS, 0);
    let st = b.worker.valve(0).unwrap().status(now());
    assert!(st.referenced, "{st:?}");
    b.send(
        0,
        Input::ValvePosition {
            valve: 0,
            pct: 40.0,
        },
    );
    b.wake();
    b.run_to(now() + 2_000 * MS, 0);
    let est = b.worker.valve(0).unwrap().estimate(now());
    let p = valve_params();
    assert!((est - integral_of_the_lines(&p)).abs() < 1e-9);
    // 40 % of 2 s, plus the write's time, which the real edges carry.
    assert!((est - 40.0).abs() < 0.01, "{est}");
    assert_eq!(violations(), Vec::<String>::new());
}

#[test]
fn a_valve_channel_ignores_its_own_inputs_and_shut_down_drops_the_valve_lines() {
    let mut b = valve_bench(false);
    // The channel inputs of the closing line while the reference closes: no rise on line 2.
    b.send(2, Input::Command(Command::Percent(100.0)));
    b.send(2, Input::Enable(true));
    b.wake();
    b.run_to(now() + 500 * MS, 0);
    assert!(LINES.with(|l| l.borrow().edges[2].is_empty()));
    assert!(LINES.with(|l| l.borrow().high[3]), "the reference closes");
    let (_out, r) = b.worker.shut_down();
    assert!(r.is_ok());
    // Written as an edge of its own, before the blanket off (which records no edge).
    let last = LINES.with(|l| l.borrow().edges[3].last().copied());
    assert_eq!(last.map(|(_, high)| high), Some(false));
}

#[derive(Debug, Clone)]
enum ValveOp {
    Position(f64),
    Duty(usize, f64),
    Enable(usize, bool),
    Live(bool),
    EStop(bool),
    Switch(bool, bool),
}

fn arb_valve_op() -> impl Strategy<Value = ValveOp> {
    prop_oneof![
        8 => prop_oneof![Just(0.0), Just(100.0), 0.0..100.0f64].prop_map(ValveOp::Position),
        2 => (0usize..4, 0.0..100.0f64).prop_map(|(c, d)| ValveOp::Duty(c, d)),
        2 => (0usize..4, any::<bool>()).prop_map(|(c, on)| ValveOp::Enable(c, on)),
        1 => any::<bool>().prop_map(ValveOp::Live),
        1 => prop::bool::weighted(0.3).prop_map(ValveOp::EStop),
        1 => (any::<bool>(), any::<bool>()).prop_map(|(o, a)| ValveOp::Switch(o, a)),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    /// Through the output thread's work, woken late at random, with commands to the valve's own
    /// channels, e-stops, holds and end switches: the valve's lines are never high together, a
    /// rise comes at least the reversal pause after the last real fall, and — without end
    /// switches, which set the position — the integral of the real drive times over the
    /// travel times (an ideal actuator) lies within the bounds the valve reports, the
    /// estimate within its uncertainty of it.
    #[test]
    fn a_valve_never_drives_both_lines_nor_reverses_within_the_pause(
        held in any::<bool>(),
        ops in prop::collection::vec(((0u64..800).prop_map(|ms| ms * MS), arb_valve_op()), 1..60),
        late in prop::collection::vec(prop_oneof![3 => Just(0u64), 1 => 0u64..5 * MS], 60),
    ) {
        let mut b = valve_bench(held);
        let mut switched = false;
        for (k, (dt, op)) in ops.into_iter().enumerate() {
            let t = now() + dt;
            b.run_to(t, late[k]);
            match op {
                ValveOp::Position(pct) => b.send(0, Input::ValvePosition { valve: 0, pct }),
                ValveOp::Duty(c, d) => b.send(c, Input::Command(Command::Percent(d))),
                ValveOp::Enable(c, on) => b.send(c, Input::Enable(on)),
                ValveOp::Live(on) => b.send(0, Input::Live(on)),
                ValveOp::EStop(on) => b.send(0, Input::EStop(on)),
                ValveOp::Switch(open, active) => {
                    switched = true;
                    let dir = if open { crate::core::valve::Dir::Open } else { crate::core::valve::Dir::Close };
                    b.send(0, Input::ValveSwitch { valve: 0, dir, active });
                }
            }
            b.wake();
        }
        let t = now() + 5_000 * MS;
        b.run_to(t, 0);
        prop_assert_eq!(violations(), Vec::<String>::new());
        let p = valve_params();
        valve_pause_held(p.reversal_pause_ms * MS).map_err(TestCaseError::fail)?;
        if !switched {
            // The lines' integral is where an ideal actuator (the configured travel, no lag,
            // no play) stands: within the bounds the valve reports, as the true position must
            // be; the estimate the nominal drive gives, which the bounds clamp.
            let st = b.worker.valve(0).unwrap().status(now());
            let integral = integral_of_the_lines(&p);
            prop_assert!(
                st.low_pct - 1e-6 <= integral && integral <= st.high_pct + 1e-6,
                "lines {} outside the bounds {}..{} (estimate {})",
                integral, st.low_pct, st.high_pct, st.position_pct
            );
            prop_assert!(
                (st.position_pct - integral).abs() <= st.uncertainty_pct + 1e-6,
                "estimate {} vs lines {}, uncertainty {}",
                st.position_pct, integral, st.uncertainty_pct
            );
        }
    }
}

// The deadline order: a wake-up finds the channels whose deadline came through the deadlines
// kept in order, read again only for the channels acted on, instead of asking every channel.

#[test]
fn a_request_that_brings_a_deadline_forward_is_served_at_the_new_one() {
    // A 50 % pulse of a 1 s period, re-timed 50 ms in by a 10 % command applied at once: its
    // fall moves from 500 ms to 100 ms after the rise, and nothing else wakes the thread.
    let mut b = Bench::new(&[params(1000, 0, Some(ApplyAt::Immediate))], &[], false);
    let t0 = now();
    b.send(0, Input::Command(Command::Percent(50.0)));
    b.send(0, Input::Enable(true));
    b.wake();
    assert_eq!(b.worker.next_deadline(), Some(t0 + 500 * MS));
    b.run_to(t0 + 50 * MS, 0);
    b.send(0, Input::Command(Command::Percent(10.0)));
    b.wake();
    // Counted from the rise as it reached the line, at the end of its write.
    let fall = t0 + WRITE_NS + 100 * MS;
    assert_eq!(b.worker.next_deadline(), Some(fall));
    b.run_to(t0 + 1_000 * MS, 0);
    let edges = LINES.with(|l| l.borrow().edges[0].clone());
    assert_eq!(
        edges[..2],
        [(t0 + WRITE_NS, true), (fall + WRITE_NS, false)],
        "{edges:?}"
    );
}

#[test]
fn channels_with_equal_deadlines_are_all_served_at_one_wake_up() {
    // 130 channels (past two words of the sets a wake-up walks) of one period and duty,
    // enabled together: every deadline falls on every channel at once, on time and then late.
    let n = 130;
    let mut b = Bench::new(&vec![params(10, 0, None); n], &[], false);
    for ch in 0..n {
        b.send(ch, Input::Command(Command::Percent(37.0)));
        b.send(ch, Input::Enable(true));
    }
    b.wake();
    b.run_to(now() + 1_000 * MS, 0);
    b.run_to(now() + 1_000 * MS, 3 * MS);
    let edges = LINES.with(|l| l.borrow().edges.clone());
    assert!(edges[0].len() >= 250, "{} edges", edges[0].len());
    for (k, e) in edges.iter().enumerate() {
        assert_eq!(e, &edges[0], "line {k}");
    }
}

#[derive(Debug, Clone)]
enum Act {
    /// One of the planner, pair and safety paths above, on the first four channels.
    Op(Op),
    Config(usize, Box<ChannelParams>),
    Duty(usize, f64),
    Enable(usize, bool),
}

/// [`arb_params`] with a maximum on time, a time base, a watchdog and its fault value: more
/// deadlines of their own, and lines that go off while the schedule still asks for on.
fn arb_timed_params() -> impl Strategy<Value = ChannelParams> {
    (
        arb_params(),
        prop_oneof![2 => Just(0u64), 1 => 20u64..150],
        prop_oneof![2 => Just(0.0), 1 => Just(5.0), 1 => Just(10.0)],
        prop_oneof![2 => Just(0u64), 1 => 50u64..400],
        0.0..50.0f64,
    )
        .prop_map(
            |(p, max_on_ms, time_base_ms, command_timeout_ms, fault_duty_pct)| ChannelParams {
                max_on_ms,
                time_base_ms,
                command_timeout_ms,
                fault_duty_pct,
                ..p
            },
        )
        .prop_filter("valid parameters", |p| p.validate().is_ok())
}

fn arb_act() -> impl Strategy<Value = Act> {
    prop_oneof![
        3 => arb_op().prop_map(Act::Op),
        2 => (0usize..70, arb_timed_params()).prop_map(|(c, p)| Act::Config(c, Box::new(p))),
        4 => (0usize..70, 0.0..100.0f64).prop_map(|(c, d)| Act::Duty(c, d)),
        2 => (0usize..70, prop::bool::weighted(0.7)).prop_map(|(c, on)| Act::Enable(c, on)),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Whatever acted on the channels — commands and configurations re-timing them, enables,
    /// the interlock of a pair, the planner, holds, the e-stop, late wake-ups — after every
    /// wake-up the earliest deadline kept is the one a scan of every channel finds. (Debug
    /// builds also check, at every wake-up, that the walk over the due channels skipped none a
    /// scan would have served.)
    #[test]
    fn the_deadlines_kept_are_the_ones_a_scan_finds(
        chans in prop::collection::vec(arb_timed_params(), 4..70),
        held in any::<bool>(),
        acts in prop::collection::vec(((0u64..300).prop_map(|ms| ms * MS), arb_act()), 1..40),
        late in prop::collection::vec(prop_oneof![3 => Just(0u64), 1 => 0u64..5 * MS], 40),
    ) {
        let n = chans.len();
        let mut b = Bench::new(&chans, &[(0, 1)], held);
        for ch in 0..n {
            b.send(ch, Input::Command(Command::Percent(10.0 + (ch * 7 % 80) as f64)));
            b.send(ch, Input::Enable(true));
        }
        b.wake();
        for (k, (dt, act)) in acts.into_iter().enumerate() {
            let t = now() + dt;
            while let Some(d) = b.worker.next_deadline() {
                let (kept, scanned) = b.worker.channel_deadlines();
                prop_assert_eq!(kept, scanned);
                let at = d.max(now()) + late[k];
                if at > t {
                    break;
                }
                set_now(at);
                b.wake();
            }
            set_now(t.max(now()));
            match act {
                Act::Op(Op::Duty(c, d)) => b.send(c, Input::Command(Command::Percent(d))),
                Act::Op(Op::Split(pct)) => {
                    let (h, c) = crate::core::split_command(pct, 0.0);
                    b.send(0, Input::Command(h));
                    b.send(1, Input::Command(c));
                }
                Act::Op(Op::Enable(c, on)) => b.send(c, Input::Enable(on)),
                Act::Op(Op::Live(on)) => b.send(0, Input::Live(on)),
                Act::Op(Op::EStop(on)) => b.send(0, Input::EStop(on)),
                Act::Op(Op::Limit(max_on, stagger)) => b.send(0, Input::Bank(Bank {
                    phase: if stagger { Phase::Stagger } else { Phase::Sync },
                    max_on,
                })),
                Act::Config(c, p) => {
                    b.send(c % n, Input::Config(p.validate().expect("valid test parameters")))
                }
                Act::Duty(c, d) => b.send(c % n, Input::Command(Command::Percent(d))),
                Act::Enable(c, on) => b.send(c % n, Input::Enable(on)),
            }
            b.wake();
            let (kept, scanned) = b.worker.channel_deadlines();
            prop_assert_eq!(kept, scanned);
        }
        prop_assert_eq!(violations(), Vec::<String>::new());
    }
}

/// Wakes at every deadline up to `t`, and asserts before and after each wake-up that the
/// earliest deadline kept is the one a scan of every channel finds (an assertion that holds
/// in builds without debug assertions too).
fn run_checked(b: &mut Bench, t: Nanos) {
    loop {
        let (kept, scanned) = b.worker.channel_deadlines();
        assert_eq!(kept, scanned, "at {} ns", now());
        match b.worker.next_deadline() {
            Some(d) if d.max(now()) <= t => {
                set_now(d.max(now()));
                b.wake();
            }
            _ => break,
        }
    }
    set_now(t.max(now()));
}

#[test]
fn every_kind_of_action_keeps_the_deadlines_a_scan_finds() {
    // A heater that latches the e-stop of every channel, a channel cut by its maximum on time
    // and tripped by its watchdog into a fault value, a valve on lines 2 and 3, a split pair
    // on 4 and 5: the heater's own timers, the heater fault through the e-stop, the valve on
    // the board, the interlock, the planner, the hold.
    let heater = ChannelParams {
        heater: crate::core::heater::HeaterParams {
            feedback: true,
            temp_max_c: 300.0,
            ..Default::default()
        },
        ..params(1000, 0, None)
    };
    let timed = ChannelParams {
        max_on_ms: 150,
        command_timeout_ms: 500,
        fault_duty_pct: 20.0,
        ..params(200, 0, None)
    };
    let p = params(100, 0, None);
    let mut b = Bench::new(&[heater, timed, p, p, p, p], &[(4, 5)], false);
    let config = valve_params().validate().unwrap();
    b.send(
        2,
        Input::AddValve {
            close: 3,
            config,
            start: Default::default(),
        },
    );
    b.send(0, Input::HeaterEstop(true));
    for (ch, d) in [(0, 100.0), (1, 100.0), (4, 60.0), (5, 0.0)] {
        b.send(ch, Input::Command(Command::Percent(d)));
        b.send(ch, Input::Enable(true));
    }
    let feed = |b: &mut Bench, celsius| b.send(0, Input::Feedback { celsius, age: None });
    feed(&mut b, 25.0);
    b.wake();
    run_checked(&mut b, now() + 700 * MS);
    b.send(
        0,
        Input::ValvePosition {
            valve: 0,
            pct: 50.0,
        },
    );
    feed(&mut b, 26.0);
    run_checked(&mut b, now() + 700 * MS);
    b.send(4, Input::Command(Command::Percent(0.0)));
    b.send(5, Input::Command(Command::Percent(70.0)));
    b.send(
        0,
        Input::Bank(Bank {
            phase: Phase::Stagger,
            max_on: 1,
        }),
    );
    feed(&mut b, 27.0);
    run_checked(&mut b, now() + 700 * MS);
    b.send(
        0,
        Input::Bank(Bank {
            phase: Phase::Sync,
            max_on: 0,
        }),
    );
    b.send(0, Input::Live(false));
    b.wake();
    run_checked(&mut b, now() + 300 * MS);
    b.send(0, Input::Live(true));
    b.wake();
    // No reading any more: the heater's own timer latches its fault, and with it the e-stop.
    run_checked(&mut b, now() + 4_000 * MS);
    assert!(
        b.slot.estop_latched(),
        "the heater fault latched the e-stop"
    );
    LINES.with(|l| {
        let l = l.borrow();
        assert!(!l.high.iter().any(|h| *h), "{:?}", l.high);
    });
    b.send(0, Input::EStop(false));
    b.wake();
    run_checked(&mut b, now() + 1_000 * MS);
    assert_eq!(violations(), Vec::<String>::new());
}

#[test]
fn a_deadline_an_action_left_unmarked_is_read_again_within_a_second() {
    // A 50 % pulse of a 10 s period falls 5 s after its rise. 50 ms in, its duty drops to 1 %
    // at once by a path that does not mark the channel: the fall is due 100 ms after the rise,
    // but the deadline kept still says 5 s. The next wake-up more than a second after the last
    // full read reads every channel again, and the line goes off there, not 5 s on.
    let mut b = Bench::new(&[params(10_000, 0, Some(ApplyAt::Immediate))], &[], false);
    let t0 = now();
    b.send(0, Input::Command(Command::Percent(50.0)));
    b.send(0, Input::Enable(true));
    b.wake();
    assert!(LINES.with(|l| l.borrow().high[0]));
    set_now(t0 + 50 * MS);
    b.worker
        .channel_unmarked(0)
        .command(now(), Command::Percent(1.0), &mut |_| {});
    let (kept, scanned) = b.worker.channel_deadlines();
    assert_ne!(kept, scanned, "the change went unmarked");
    // A wake-up that comes anyway (a request, another line, the liveness tick).
    set_now(t0 + 1_100 * MS);
    b.wake();
    assert!(!LINES.with(|l| l.borrow().high[0]), "the line went off");
    let (kept, scanned) = b.worker.channel_deadlines();
    assert_eq!(kept, scanned);
    assert_eq!(violations(), Vec::<String>::new());
}
