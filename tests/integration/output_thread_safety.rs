//! The safety inputs reach the line whatever fills the request queue: with the output thread
//! stuck in a write (as a hung driver or CPU starvation would leave it) while commands fill the
//! queue, an e-stop, a hold of the lines and a lowered `max_simultaneous_on` are still taken —
//! first, as soon as the thread runs again — and acknowledged only once written; one the thread
//! does not take within the bound has the outputs switched off by the emergency handle, whether
//! or not anyone still waits for it.

use pwm_actuator::core::{Bank, ChannelParams, Command, Level, Phase};
use pwm_actuator::output::{EmergencyOff, ErrorKind, LineChange, Output, OutputError};
use pwm_actuator::output_thread::{
    self, Input, NotTaken, OutputThreadError, OutputThreadOptions, Request, SAFETY_TAKE_BOUND,
};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// What the stalling output shares with the test.
#[derive(Default)]
struct Shared {
    /// Line levels as written.
    high: Mutex<Vec<bool>>,
    /// (writes stall, a write is stalled now)
    gate: Mutex<(bool, bool)>,
    cv: Condvar,
    /// Rises written, per line.
    rises: Mutex<Vec<usize>>,
    /// Most lines high after a write with a rise.
    most_high_at_rise: Mutex<usize>,
    tripped: AtomicBool,
}

#[derive(Debug, thiserror::Error)]
#[error("tripped")]
struct Tripped;
impl OutputError for Tripped {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Tripped
    }
}

struct StallingOutput(Arc<Shared>);

struct Emergency(Arc<Shared>);
impl EmergencyOff for Emergency {
    fn all_inactive(&self) {
        self.0.tripped.store(true, Ordering::SeqCst);
        self.0
            .high
            .lock()
            .unwrap()
            .iter_mut()
            .for_each(|h| *h = false);
    }
}

impl Output for StallingOutput {
    type Error = Tripped;
    fn line_count(&self) -> usize {
        self.0.high.lock().unwrap().len()
    }
    fn set_levels(&mut self, changes: &[LineChange]) -> Result<(), Tripped> {
        {
            let mut g = self.0.gate.lock().unwrap();
            while g.0 {
                g.1 = true;
                self.0.cv.notify_all();
                g = self.0.cv.wait(g).unwrap();
            }
            g.1 = false;
        }
        if self.0.tripped.load(Ordering::SeqCst) {
            return Err(Tripped);
        }
        let mut high = self.0.high.lock().unwrap();
        let mut rose = false;
        for c in changes {
            if !high[c.line] && c.level == Level::High {
                rose = true;
                self.0.rises.lock().unwrap()[c.line] += 1;
            }
            high[c.line] = c.level.is_high();
        }
        if rose {
            let n = high.iter().filter(|h| **h).count();
            let mut most = self.0.most_high_at_rise.lock().unwrap();
            *most = (*most).max(n);
        }
        Ok(())
    }
    fn set_all_inactive(&mut self) -> Result<(), Tripped> {
        self.0
            .high
            .lock()
            .unwrap()
            .iter_mut()
            .for_each(|h| *h = false);
        Ok(())
    }
    fn emergency_off(&self) -> Arc<dyn EmergencyOff> {
        Arc::new(Emergency(Arc::clone(&self.0)))
    }
}

impl Shared {
    fn new(lines: usize) -> Arc<Shared> {
        let s = Shared::default();
        *s.high.lock().unwrap() = vec![false; lines];
        *s.rises.lock().unwrap() = vec![0; lines];
        Arc::new(s)
    }

    /// Makes the next write stall and waits until the thread is stuck in it.
    fn stall(&self) {
        let mut g = self.gate.lock().unwrap();
        g.0 = true;
        let start = Instant::now();
        while !g.1 {
            assert!(start.elapsed() < Duration::from_secs(5), "no write came");
            g = self
                .cv
                .wait_timeout(g, Duration::from_millis(10))
                .unwrap()
                .0;
        }
    }

    fn release(&self) {
        self.gate.lock().unwrap().0 = false;
        self.cv.notify_all();
    }

    fn rises(&self) -> usize {
        self.rises.lock().unwrap().iter().sum()
    }

    fn any_high(&self) -> bool {
        self.high.lock().unwrap().iter().any(|h| *h)
    }

    /// Every line is off now, and none rises in the next 300 ms.
    fn off_and_stays_off(&self, what: &str) {
        assert!(
            !self.any_high(),
            "the lines are off once the {what} is taken"
        );
        let rises = self.rises();
        std::thread::sleep(Duration::from_millis(300));
        assert_eq!(self.rises(), rises, "no rise while the {what} holds");
    }
}

const QUEUE: usize = 16;

fn start(channels: usize, duty: f64) -> (Arc<Shared>, output_thread::OutputThread) {
    let shared = Shared::new(channels);
    let cfg = ChannelParams {
        period_ms: 20,
        ..ChannelParams::default()
    }
    .validate()
    .unwrap();
    let opts = OutputThreadOptions {
        queue_capacity: QUEUE,
        ..OutputThreadOptions::default()
    };
    let mut e = output_thread::spawn(
        vec![cfg; channels],
        StallingOutput(Arc::clone(&shared)),
        opts,
    )
    .unwrap();
    for channel in 0..channels {
        for input in [Input::Command(Command::Percent(duty)), Input::Enable(true)] {
            e.requests.send(Request { channel, input }).unwrap();
        }
    }
    (shared, e)
}

/// Fills the request queue with duty commands until it refuses one.
fn fill(e: &mut output_thread::OutputThread) {
    for k in 0..10 * QUEUE {
        let r = e.requests.send(Request {
            channel: 0,
            input: Input::Command(Command::Percent(40.0 + (k % 20) as f64)),
        });
        if matches!(r, Err(OutputThreadError::QueueFull { .. })) {
            return;
        }
    }
    panic!("the queue never filled");
}

/// With the thread stuck in a write and the queue full, `input` is sent: it is accepted, and
/// taken as soon as the write returns (well within the bound), acknowledged only then.
fn taken_behind_a_full_queue(e: &mut output_thread::OutputThread, shared: &Shared, input: Input) {
    std::thread::sleep(Duration::from_millis(50));
    shared.stall();
    fill(e);
    let safety = e.requests.safety();
    e.requests
        .send(Request { channel: 0, input })
        .expect("a safety input is never refused for a full queue");
    let request = safety.store(input);
    std::thread::sleep(Duration::from_millis(50));
    assert!(!safety.taken(request), "not done while the thread is stuck");
    shared.release();
    let took = safety.wait(request, SAFETY_TAKE_BOUND);
    assert!(took.is_ok(), "taken once the write returned: {took:?}");
    assert!(!shared.tripped.load(Ordering::SeqCst));
}

#[test]
fn an_estop_behind_a_full_queue_is_taken_before_the_commands() {
    let (shared, mut e) = start(1, 50.0);
    taken_behind_a_full_queue(&mut e, &shared, Input::EStop(true));
    shared.off_and_stays_off("e-stop");
    e.handle.shutdown().unwrap();
}

#[test]
fn a_hold_behind_a_full_queue_is_taken_before_the_commands() {
    let (shared, mut e) = start(2, 50.0);
    taken_behind_a_full_queue(&mut e, &shared, Input::Live(false));
    shared.off_and_stays_off("hold");
    e.handle.shutdown().unwrap();
}

#[test]
fn a_lowered_limit_behind_a_full_queue_is_taken_before_the_commands() {
    let (shared, mut e) = start(3, 60.0);
    let limit = Input::Bank(Bank {
        phase: Phase::Sync,
        max_on: 1,
    });
    taken_behind_a_full_queue(&mut e, &shared, limit);
    *shared.most_high_at_rise.lock().unwrap() = 0;
    let rises = shared.rises();
    std::thread::sleep(Duration::from_millis(400));
    assert!(shared.rises() > rises, "the lines still run");
    assert_eq!(
        *shared.most_high_at_rise.lock().unwrap(),
        1,
        "never more than one line high after a rise once the limit is taken"
    );
    e.handle.shutdown().unwrap();
}

#[test]
fn a_safety_input_not_taken_in_time_switches_the_outputs_off_by_the_emergency_handle() {
    let (shared, e) = start(2, 90.0);
    std::thread::sleep(Duration::from_millis(50));
    shared.stall();
    let safety = e.requests.safety();
    let start = Instant::now();
    let r = safety.take(Input::EStop(true));
    assert_eq!(r, Err(NotTaken::Late(SAFETY_TAKE_BOUND)));
    assert!(start.elapsed() >= SAFETY_TAKE_BOUND);
    assert!(
        shared.tripped.load(Ordering::SeqCst),
        "emergency handle used"
    );
    assert!(!shared.any_high(), "every line off");
    shared.release();
    // The thread's next write fails (tripped): it stops, leaving every line off.
    let start = Instant::now();
    while !e.handle.is_finished() {
        assert!(start.elapsed() < Duration::from_secs(5), "the thread stops");
        std::thread::sleep(Duration::from_millis(10));
    }
    assert!(!shared.any_high());
    assert!(matches!(
        e.handle.shutdown(),
        Err(OutputThreadError::OutputFault { .. })
    ));
}

/// How often the calling thread has given up the CPU of its own accord so far (its sleeps and
/// waits), from `/proc/thread-self/status`.
fn voluntary_switches() -> u64 {
    let status = std::fs::read_to_string("/proc/thread-self/status").unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("voluntary_ctxt_switches:"))
        .and_then(|v| v.trim().parse().ok())
        .expect("voluntary_ctxt_switches in /proc/thread-self/status")
}

/// Stalls the thread's next write and releases it `after` from another thread.
fn stalled_for(shared: &Arc<Shared>, after: Duration) -> std::thread::JoinHandle<()> {
    std::thread::sleep(Duration::from_millis(50));
    shared.stall();
    let s = Arc::clone(shared);
    std::thread::spawn(move || {
        std::thread::sleep(after);
        s.release();
    })
}

/// The most wake-ups a waiter may see while the thread is stuck for 100 ms: it sleeps until the
/// thread has taken the input (a wake-up or two); one that looked at the counter every 50 µs
/// woke some 840 times here.
const WAKE_UPS: u64 = 20;

/// A plain thread (the lifecycle's transitions run on one) that waits for the acknowledgment
/// behind a write stuck for 100 ms sleeps until the thread has taken the input.
#[test]
fn a_waiting_thread_sleeps_until_the_input_is_taken() {
    let (shared, e) = start(1, 50.0);
    let safety = e.requests.safety();
    let release = stalled_for(&shared, Duration::from_millis(100));
    let before = voluntary_switches();
    let took = safety.take(Input::EStop(true));
    let woken = voluntary_switches() - before;
    release.join().unwrap();
    let took = took.expect("taken once the write returned");
    assert!(took >= Duration::from_millis(80), "{took:?}");
    assert!(woken <= WAKE_UPS, "the waiter woke {woken} times");
    assert!(!shared.tripped.load(Ordering::SeqCst));
    shared.off_and_stays_off("e-stop");
    e.handle.shutdown().unwrap();
}

/// Async code awaits the acknowledgment without holding its thread: a runtime's only thread
/// awaiting one behind a write stuck for 100 ms sleeps until the thread has taken it.
#[test]
fn an_awaited_acknowledgment_holds_no_thread() {
    let (shared, e) = start(2, 50.0);
    let safety = e.requests.safety();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let release = stalled_for(&shared, Duration::from_millis(100));
    let before = voluntary_switches();
    let took = rt.block_on(safety.take_async(Input::Live(false)));
    let woken = voluntary_switches() - before;
    release.join().unwrap();
    let took = took.expect("taken once the write returned");
    assert!(took >= Duration::from_millis(80), "{took:?}");
    assert!(woken <= WAKE_UPS, "the runtime's thread woke {woken} times");
    assert!(!shared.tripped.load(Ordering::SeqCst));
    shared.off_and_stays_off("hold");
    // A running thread answers at once.
    let took = rt.block_on(safety.take_async(Input::Live(true))).unwrap();
    assert!(took < SAFETY_TAKE_BOUND, "{took:?}");
    e.handle.shutdown().unwrap();
}

/// An awaited safety input the thread does not take in time ends at the bound with every output
/// switched off by the emergency handle; after the thread has stopped, one is answered at once.
#[test]
fn an_awaited_input_not_taken_in_time_switches_the_outputs_off() {
    let (shared, e) = start(2, 90.0);
    std::thread::sleep(Duration::from_millis(50));
    shared.stall();
    let safety = e.requests.safety();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let start = Instant::now();
    let r = rt.block_on(safety.take_async(Input::EStop(true)));
    assert_eq!(r, Err(NotTaken::Late(SAFETY_TAKE_BOUND)));
    assert!(start.elapsed() >= SAFETY_TAKE_BOUND);
    assert!(
        start.elapsed() < 4 * SAFETY_TAKE_BOUND,
        "{:?}",
        start.elapsed()
    );
    assert!(
        shared.tripped.load(Ordering::SeqCst),
        "emergency handle used"
    );
    assert!(!shared.any_high(), "every line off");
    shared.release();
    let start = Instant::now();
    while !e.handle.is_finished() {
        assert!(start.elapsed() < Duration::from_secs(5), "the thread stops");
        std::thread::sleep(Duration::from_millis(10));
    }
    let start = Instant::now();
    let r = rt.block_on(safety.take_async(Input::Live(false)));
    assert_eq!(r, Err(NotTaken::Stopped));
    assert!(start.elapsed() < SAFETY_TAKE_BOUND, "{:?}", start.elapsed());
    assert!(matches!(
        e.handle.shutdown(),
        Err(OutputThreadError::OutputFault { .. })
    ));
}

/// A waiter that gives up before the bound (a timeout around it, a cancelled task) takes no
/// part of the check with it: the input has been stored for the thread, so with the thread
/// stuck in a write every line still goes off through the emergency handle when the bound
/// passes.
#[test]
fn an_input_whose_waiter_gave_up_still_switches_the_outputs_off_at_the_bound() {
    let (shared, e) = start(2, 90.0);
    std::thread::sleep(Duration::from_millis(50));
    shared.stall();
    let safety = e.requests.safety();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let start = Instant::now();
    let gave_up = rt.block_on(async {
        tokio::time::timeout(
            Duration::from_millis(20),
            safety.take_async(Input::EStop(true)),
        )
        .await
    });
    assert!(gave_up.is_err(), "the waiter gave up before the bound");
    assert!(
        !shared.tripped.load(Ordering::SeqCst),
        "not before the bound"
    );
    // The runtime runs on, as the node's does, and with it the check.
    rt.block_on(async {
        while !shared.tripped.load(Ordering::SeqCst) {
            assert!(
                start.elapsed() < 4 * SAFETY_TAKE_BOUND,
                "no emergency handle within {:?}",
                start.elapsed()
            );
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    });
    assert!(
        start.elapsed() >= SAFETY_TAKE_BOUND,
        "{:?}",
        start.elapsed()
    );
    assert!(!shared.any_high(), "every line off");
    shared.release();
    let start = Instant::now();
    while !e.handle.is_finished() {
        assert!(start.elapsed() < Duration::from_secs(5), "the thread stops");
        std::thread::sleep(Duration::from_millis(10));
    }
    assert!(!shared.any_high());
    assert!(matches!(
        e.handle.shutdown(),
        Err(OutputThreadError::OutputFault { .. })
    ));
}

/// Stopping the thread from async code holds no thread: with the thread stuck in a write for
/// 150 ms, a current-thread runtime's other task keeps running while the stop waits.
#[test]
fn an_awaited_shutdown_holds_no_thread() {
    let (shared, e) = start(1, 50.0);
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let release = stalled_for(&shared, Duration::from_millis(150));
    let (result, ticks) = rt.block_on(async move {
        let stopping = Arc::new(AtomicBool::new(true));
        let ticker = {
            let stopping = Arc::clone(&stopping);
            tokio::spawn(async move {
                let mut ticks = 0u32;
                while stopping.load(Ordering::SeqCst) {
                    tokio::time::sleep(Duration::from_millis(5)).await;
                    ticks += 1;
                }
                ticks
            })
        };
        let result = e.handle.shutdown_async().await;
        stopping.store(false, Ordering::SeqCst);
        (result, ticker.await.unwrap())
    });
    release.join().unwrap();
    result.unwrap();
    assert!(
        ticks >= 5,
        "the runtime's other task ran {ticks} times while the stop waited"
    );
    assert!(!shared.any_high(), "every line off");
}

/// A change that must reach the output thread together (a parameter change touching several
/// channels and valves) is queued whole or not at all: with room for one request, two are
/// refused and the room is untouched.
#[test]
fn send_all_queues_all_or_nothing() {
    let (shared, mut e) = start(2, 50.0);
    std::thread::sleep(Duration::from_millis(50));
    shared.stall();
    let command = |channel| Request {
        channel,
        input: Input::Command(Command::Percent(30.0)),
    };
    while e.requests.room() > 1 {
        e.requests.send(command(0)).unwrap();
    }
    let two = [command(0), command(1)];
    let r = e.requests.send_all(&two);
    assert!(
        matches!(r, Err(OutputThreadError::QueueFull { .. })),
        "{r:?}"
    );
    assert_eq!(e.requests.room(), 1, "nothing of a refused batch is queued");
    let r = e.requests.send_all(&[command(1), command(2)]);
    assert!(
        matches!(r, Err(OutputThreadError::NoSuchChannel(2))),
        "{r:?}"
    );
    assert_eq!(e.requests.room(), 1);
    e.requests.send_all(&two[..1]).unwrap();
    assert_eq!(e.requests.room(), 0);
    shared.release();
    e.handle.shutdown().unwrap();
}
