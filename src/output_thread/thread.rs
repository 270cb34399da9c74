//! The dedicated output thread: sleeps on a timerfd armed with absolute CLOCK_MONOTONIC
//! deadlines (no drift, no rounding to a timer wheel), wakes early only when a request arrives
//! on its eventfd, and never blocks on the ROS side.
//!
//! Real-time set-up is opt-in (`rt_priority`): SCHED_FIFO and mlockall, each refused cleanly
//! with one log line when the process lacks the privilege.

use super::safety::SafetySlot;
use super::worker::{Stop, Worker};
use super::{Input, Report, Request};
use crate::clock;
use crate::core::{Bank, ChannelConfig, Nanos};
use crate::output::{EmergencyOff, ErrorKind, Output, OutputError};
use nix::poll::{poll, ppoll, PollFd, PollFlags, PollTimeout};
use nix::sys::eventfd::{EfdFlags, EventFd};
use nix::sys::time::TimeSpec;
use nix::sys::timerfd::{ClockId, Expiration, TimerFd, TimerFlags, TimerSetTimeFlags};
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, RawFd};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;
use tokio::io::unix::AsyncFd;
use tokio::io::Interest;

/// Options of the output thread.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OutputThreadOptions {
    /// SCHED_FIFO priority 1..=99 for the output thread (and mlockall); `None` = normal
    /// scheduling.
    pub rt_priority: Option<i32>,
    /// Capacity of each ring buffer (requests in, reports out), entries.
    pub queue_capacity: usize,
    /// The heartbeat line's half period, ns: the thread toggles the output line after the
    /// channels' lines (index = number of channels) every half period while it runs, so an
    /// external watchdog relay sees a square wave at 1 / (2 x half period). `None`: no
    /// heartbeat line.
    pub heartbeat_half_period_ns: Option<Nanos>,
    /// Start with every line held inactive until an [`Input::Live`](super::Input::Live)`(true)` (a managed node
    /// starts unconfigured).
    pub start_held: bool,
    /// The node-level planner at start-up: `phase` and `max_simultaneous_on`.
    pub bank: Bank,
    /// The thread wakes at least this often even with nothing to do, so that a watcher of its
    /// [`Liveness`] (the systemd watchdog's pinger) sees a stall within it, ns. `None`: it
    /// sleeps until its next deadline or request, however far (a node without a watchdog: an
    /// idle thread costs nothing).
    pub liveness_tick_ns: Option<Nanos>,
}

impl Default for OutputThreadOptions {
    fn default() -> Self {
        OutputThreadOptions {
            rt_priority: None,
            queue_capacity: 4096,
            heartbeat_half_period_ns: None,
            start_held: false,
            bank: Bank::default(),
            liveness_tick_ns: Some(LIVENESS_TICK_NS),
        }
    }
}

/// Errors of the output thread.
#[derive(Debug, thiserror::Error)]
pub enum OutputThreadError {
    /// No channel was configured.
    #[error("no channel configured")]
    NoChannels,
    /// The output drives fewer lines than there are channels.
    #[error("the output has {lines} lines for {channels} channels")]
    LineCount {
        /// Lines the output drives.
        lines: usize,
        /// Channels configured.
        channels: usize,
    },
    /// A request named a channel that does not exist.
    #[error("no channel with index {0}")]
    NoSuchChannel(usize),
    /// The request queue is full (the output thread is not keeping up).
    #[error("request queue full ({capacity} entries); request dropped")]
    QueueFull {
        /// Queue capacity, entries.
        capacity: usize,
    },
    /// The output thread has stopped.
    #[error("the output thread has stopped")]
    Stopped,
    /// A system call needed by the output thread failed.
    #[error("{what} failed")]
    Sys {
        /// What was being done.
        what: &'static str,
        /// The OS error.
        #[source]
        source: nix::Error,
    },
    /// Starting the thread failed.
    #[error("could not start the output thread")]
    Spawn(#[source] std::io::Error),
    /// Writing an output failed; every line was driven inactive and the thread stopped.
    #[error("writing the line of channel index {channel} failed ({kind})")]
    OutputFault {
        /// Channel whose write failed (the first of the write when the backend cannot tell).
        channel: usize,
        /// What kind of failure the backend reported.
        kind: ErrorKind,
        /// The backend's error.
        #[source]
        source: Arc<dyn std::error::Error + Send + Sync>,
    },
    /// Driving the lines inactive when the thread stopped failed.
    #[error(
        "driving the lines inactive failed{} ({kind})",
        channel.map(|c| format!(" at channel index {c}")).unwrap_or_default()
    )]
    ShutdownFault {
        /// The channel whose line could not be written, when the backend can tell.
        channel: Option<usize>,
        /// What kind of failure the backend reported.
        kind: ErrorKind,
        /// The backend's error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The output thread did not end when asked (hung, e.g. in a write); the outputs were
    /// driven inactive through the emergency handle and the thread was left behind.
    #[error("the output thread did not stop within {waited_ms} ms; outputs switched off by the emergency handle")]
    Hung {
        /// How long the stop waited, ms.
        waited_ms: u64,
    },
    /// The output thread panicked.
    #[error("the output thread panicked")]
    Panicked,
}

/// The output fault that stopped the thread, as [`OutputThreadHandle::fault`] keeps it for the
/// node's exit message (the same error the thread's result carries).
#[derive(Debug, Clone)]
pub struct WriteFault {
    /// Channel (index) whose write failed (the first of the write when the backend cannot tell).
    pub channel: usize,
    /// What kind of failure the backend reported.
    pub kind: ErrorKind,
    /// The backend's error.
    pub error: Arc<dyn std::error::Error + Send + Sync>,
}

impl From<WriteFault> for OutputThreadError {
    fn from(f: WriteFault) -> Self {
        OutputThreadError::OutputFault {
            channel: f.channel,
            kind: f.kind,
            source: f.error,
        }
    }
}

impl OutputThreadError {
    /// The channel (index) an output or shutdown fault concerns, when known.
    pub fn channel(&self) -> Option<usize> {
        match self {
            OutputThreadError::OutputFault { channel, .. } => Some(*channel),
            OutputThreadError::ShutdownFault { channel, .. } => *channel,
            _ => None,
        }
    }
}

/// How long a safety input may wait for the output thread to take it before the outputs are
/// switched off through the emergency handle instead ([`SafetyPath::take_async`],
/// [`SafetyPath::take`]). The thread takes one within microseconds when it runs; only a thread
/// stuck in a write or starved of CPU for this long misses it.
pub const SAFETY_TAKE_BOUND: Duration = Duration::from_millis(250);

/// The output thread's acknowledgment of the safety inputs: an eventfd it writes once at each
/// wake-up at which it applied a safety input and wrote the lines, and once more when it has
/// stopped. Nothing else: an idle thread, or one that runs with no safety input pending, never
/// writes it. One waiter at a time reads it (`reader`) and then looks at the slot's counter, so
/// no acknowledgment is consumed by a waiter it was not for.
pub(crate) struct Ack {
    fd: EventFd,
    reader: tokio::sync::Mutex<()>,
}

impl Ack {
    pub(crate) fn new() -> Result<Ack, nix::Error> {
        Ok(Ack {
            fd: EventFd::from_flags(EfdFlags::EFD_CLOEXEC | EfdFlags::EFD_NONBLOCK)?,
            reader: tokio::sync::Mutex::new(()),
        })
    }

    /// The output thread's signal: one `write` on the eventfd (never blocks: EAGAIN only when
    /// the counter is saturated, and then a signal is pending anyway).
    pub(crate) fn signal(&self) {
        let _ = self.fd.write(1);
    }

    /// Resets the eventfd (EAGAIN: nothing was pending).
    fn clear(&self) {
        let _ = self.fd.read();
    }
}

/// The acknowledgment's eventfd as tokio's reactor registers it, for the time of one wait (the
/// eventfd itself stays open with the path).
struct AckFd(Arc<Ack>);

impl AsRawFd for AckFd {
    fn as_raw_fd(&self) -> RawFd {
        self.0.fd.as_raw_fd()
    }
}

/// The safety inputs' path to the output thread (see [`safety`](super::safety)): the e-stop,
/// the hold of the lines and the planner's limits, as latest values the thread reads at every
/// wake-up before any queued request. Never full, never blocks; cheap to clone.
///
/// A safety input is stored and the thread woken first; the caller then waits for the
/// acknowledgment, which the thread gives once it has applied the input and written the lines:
/// it stores the slot's "taken" counter and writes an eventfd (`Ack`). Async code awaits that
/// eventfd through tokio's reactor ([`SafetyPath::take_async`]); a plain thread sleeps in
/// `ppoll` on it ([`SafetyPath::take`]). Neither polls the counter on a clock.
#[derive(Clone)]
pub struct SafetyPath {
    slot: Arc<SafetySlot>,
    wake: Arc<EventFd>,
    ack: Arc<Ack>,
    emergency: Arc<dyn EmergencyOff>,
    alive: Arc<AtomicBool>,
}

/// A safety input the output thread did not take within the bound.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum NotTaken {
    /// The thread runs but did not take it in time (stuck in a write, starved of CPU).
    #[error("the output thread did not take it within {} ms", .0.as_millis())]
    Late(Duration),
    /// The thread has stopped (after an output fault or a shutdown).
    #[error("the output thread has stopped")]
    Stopped,
}

impl SafetyPath {
    /// Stores `input` (an [`Input::EStop`], [`Input::Live`] or [`Input::Bank`]; anything else
    /// is ignored and returns 0) and wakes the thread; returns the request number to wait for.
    pub fn store(&self, input: Input) -> u64 {
        let request = match input {
            Input::EStop(latched) => self.slot.estop(latched),
            Input::Live(live) => self.slot.live(live),
            Input::Bank(bank) => self.slot.bank(bank),
            _ => return 0,
        };
        // EAGAIN: the counter is saturated, a wake-up is pending anyway.
        let _ = self.wake.write(1);
        request
    }

    /// Whether the e-stop is latched in the slot, by the ROS side or by the output thread (a
    /// heater fault under `heater_fault_latches_estop`).
    pub fn estop_latched(&self) -> bool {
        self.slot.estop_latched()
    }

    /// The planner's settings (`phase`, `max_simultaneous_on`) the slot holds: what the output
    /// thread applies at its next wake-up, and what it has applied once the latest request is
    /// taken.
    pub fn bank(&self) -> Bank {
        self.slot.wanted().bank
    }

    /// Where request `request` stands now: taken (`Ok`), the thread stopped without taking it,
    /// or neither yet (`None`).
    fn look(&self, request: u64) -> Option<Result<(), NotTaken>> {
        if self.slot.taken(request) {
            return Some(Ok(()));
        }
        if !self.alive.load(Ordering::Acquire) {
            return Some(Err(NotTaken::Stopped));
        }
        None
    }

    /// Where request `request` stands once `bound` has passed.
    fn at_bound(&self, request: u64, bound: Duration) -> Result<(), NotTaken> {
        self.look(request).unwrap_or(Err(NotTaken::Late(bound)))
    }

    /// Waits up to `bound` until the output thread has applied request `request` and written
    /// the lines; returns how long that took (on tokio's clock). Holds no thread meanwhile: it
    /// awaits the thread's acknowledgment eventfd through tokio's reactor, so it returns as
    /// soon as the thread has written it (a stopped thread writes it too: then
    /// [`NotTaken::Stopped`] at once), and [`NotTaken::Late`] exactly at `bound`. Only waits:
    /// the emergency handle's fallback is [`SafetyPath::acknowledgment`]'s.
    ///
    /// # Panics
    ///
    /// In a runtime without an I/O driver (the node's runtime and tokio's test runtimes have
    /// one: `enable_all`), as every tokio I/O does.
    pub async fn wait_async(&self, request: u64, bound: Duration) -> Result<Duration, NotTaken> {
        let start = tokio::time::Instant::now();
        self.wait_until(request, start + bound, bound)
            .await
            .map(|()| start.elapsed())
    }

    /// [`SafetyPath::wait_async`] up to `deadline` (on tokio's clock); `bound` is what a late
    /// answer names.
    async fn wait_until(
        &self,
        request: u64,
        deadline: tokio::time::Instant,
        bound: Duration,
    ) -> Result<(), NotTaken> {
        match tokio::time::timeout_at(deadline, self.until_taken(request)).await {
            Ok(r) => r,
            Err(_) => self.at_bound(request, bound),
        }
    }

    /// [`SafetyPath::wait_async`]'s wait, without the bound (the caller's timeout ends it).
    async fn until_taken(&self, request: u64) -> Result<(), NotTaken> {
        if let Some(r) = self.look(request) {
            return r;
        }
        let _reader = self.ack.reader.lock().await;
        // SAFETY: the eventfd stays open while `AckFd` holds its `Arc`, and `as_raw_fd` always
        // returns it.
        let registered = unsafe {
            AsyncFd::register_with_interest(AckFd(Arc::clone(&self.ack)), Interest::READABLE)
        };
        let fd = match registered {
            Ok(fd) => fd,
            Err(e) => {
                let (_, e) = e.into_parts();
                log::error!(
                    "cannot await the output thread's acknowledgment ({e}): waiting for the bound"
                );
                return std::future::pending().await;
            }
        };
        loop {
            // Registered before this look: a signal after it makes the eventfd readable.
            if let Some(r) = self.look(request) {
                return r;
            }
            match fd.readable().await {
                Ok(mut ready) => {
                    // Read before looking again, so that a later signal wakes the next await.
                    ready.get_inner().0.clear();
                    ready.clear_ready();
                }
                // The runtime is shutting down: the bound decides.
                Err(_) => std::future::pending::<()>().await,
            }
        }
    }

    /// As [`SafetyPath::wait_async`], for a plain thread (a thread of tokio's blocking pool, a
    /// test): sleeps in `ppoll` on the acknowledgment eventfd, up to `bound`, and returns how
    /// long it waited (on the monotonic clock). Returns at once when the request is already
    /// taken or the thread has stopped.
    ///
    /// # Panics
    ///
    /// When it has to wait and is called from async code (tokio refuses to block a worker
    /// there): async code uses [`SafetyPath::wait_async`].
    pub fn wait(&self, request: u64, bound: Duration) -> Result<Duration, NotTaken> {
        let start = std::time::Instant::now();
        if let Some(r) = self.look(request) {
            return r.map(|()| start.elapsed());
        }
        // A waiter ahead of this one is woken by its own request being taken (at the latest
        // when this one is, the counter only grows) or by its bound, begun before this one's.
        let _reader = self.ack.reader.blocking_lock();
        loop {
            if let Some(r) = self.look(request) {
                return r.map(|()| start.elapsed());
            }
            let left = bound.saturating_sub(start.elapsed());
            if left.is_zero() {
                return Err(NotTaken::Late(bound));
            }
            let mut fds = [PollFd::new(self.ack.fd.as_fd(), PollFlags::POLLIN)];
            let timeout = TimeSpec::from_duration(left);
            if let Ok(n) = ppoll(&mut fds, Some(timeout), None) {
                if n > 0 {
                    self.ack.clear();
                }
            }
        }
    }

    /// Checks that the output thread takes request `request` (as [`SafetyPath::store`] has just
    /// returned it) within [`SAFETY_TAKE_BOUND`] from now, and answers how long it took. A
    /// thread that still runs but did not take it in time has every output switched off
    /// through the emergency handle (the outputs stay off for the rest of the process: the
    /// thread's next write fails and it stops with an output fault); a stopped thread has left
    /// them off. Either way no line is on when the answer is an error.
    ///
    /// The check runs apart from the answer: in a task of its own on the current tokio runtime
    /// (on a plain thread where none runs, or for the rest of the bound when the runtime drops
    /// the task). Dropping the [`Acknowledgment`] — its awaiting task cancelled, a timeout
    /// around it — gives up only the answer: the input has been stored for the thread, so the
    /// bound is checked all the same and the fallback still switches every output off.
    pub fn acknowledgment(&self, request: u64) -> Acknowledgment {
        let (reply, answer) = tokio::sync::oneshot::channel();
        let check = Check {
            path: self.clone(),
            request,
            start: tokio::time::Instant::now(),
        };
        match tokio::runtime::Handle::try_current() {
            Ok(runtime) => {
                // The task is detached: the answer comes back through `reply`. The guard is
                // the task's before its first poll: a runtime that has shut down drops the
                // task unpolled, and the check goes to a plain thread all the same.
                let pending = Unanswered {
                    check,
                    reply: Some(reply),
                };
                drop(runtime.spawn(pending.run()));
            }
            Err(_) => check.on_plain_thread(reply),
        }
        Acknowledgment {
            answer,
            emergency: Arc::clone(&self.emergency),
        }
    }

    /// [`SafetyPath::store`], then its [`SafetyPath::acknowledgment`] awaited: answered once
    /// the output thread has applied the input and written the lines, or at
    /// [`SAFETY_TAKE_BOUND`] with every output switched off through the emergency handle.
    ///
    /// The input is stored, and its check begun, before the first await: dropping the future
    /// stores it all the same and gives up only the answer, never the emergency handle's
    /// fallback.
    pub async fn take_async(&self, input: Input) -> Result<Duration, NotTaken> {
        self.acknowledgment(self.store(input)).await
    }

    /// As [`SafetyPath::take_async`], for a plain thread: waits with [`SafetyPath::wait`] (the
    /// lifecycle's transitions, which run on tokio's blocking pool).
    ///
    /// # Panics
    ///
    /// As [`SafetyPath::wait`], when called from async code and the thread has not taken the
    /// input yet.
    pub fn take(&self, input: Input) -> Result<Duration, NotTaken> {
        let request = self.store(input);
        let r = self.wait(request, SAFETY_TAKE_BOUND);
        if r.is_err() {
            self.emergency.all_inactive();
        }
        r
    }

    /// Whether request `request` has been taken.
    pub fn taken(&self, request: u64) -> bool {
        self.slot.taken(request)
    }
}

/// The answer of one safety input's check ([`SafetyPath::acknowledgment`]): a future of how
/// long the output thread took to apply the input and write the lines, or why it did not. The
/// check itself runs apart from this future; dropping it gives up only the answer.
pub struct Acknowledgment {
    answer: tokio::sync::oneshot::Receiver<Result<Duration, NotTaken>>,
    emergency: Arc<dyn EmergencyOff>,
}

impl std::future::Future for Acknowledgment {
    type Output = Result<Duration, NotTaken>;

    fn poll(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Self::Output> {
        std::pin::Pin::new(&mut self.answer).poll(cx).map(|answer| {
            answer.unwrap_or_else(|_| {
                // The check ended without an answer (it panicked): nothing says the input was
                // taken, so every output goes off.
                self.emergency.all_inactive();
                Err(NotTaken::Late(SAFETY_TAKE_BOUND))
            })
        })
    }
}

/// Where a check's answer goes.
type Reply = tokio::sync::oneshot::Sender<Result<Duration, NotTaken>>;

/// One safety input's check: request `request`, stored at `start` (tokio's clock), must be
/// taken by `start` + [`SAFETY_TAKE_BOUND`].
#[derive(Clone)]
struct Check {
    path: SafetyPath,
    request: u64,
    start: tokio::time::Instant,
}

impl Check {
    /// The check for the rest of the bound on a plain thread of its own (asleep in `ppoll` on
    /// the acknowledgment eventfd). A thread that cannot be started leaves nothing to check
    /// the bound: every output goes off at once.
    fn on_plain_thread(self, reply: Reply) {
        let left =
            (self.start + SAFETY_TAKE_BOUND).saturating_duration_since(tokio::time::Instant::now());
        let waited_before = self.start.elapsed();
        let emergency = Arc::clone(&self.path.emergency);
        let spawned = std::thread::Builder::new()
            .name("pwm-safety-ack".into())
            .spawn(move || {
                let answer = match self.path.wait(self.request, left) {
                    Ok(waited) => self.outcome(Ok(()), waited_before + waited),
                    Err(e) => self.outcome(Err(e), left),
                };
                let _ = reply.send(answer);
            });
        if spawned.is_err() {
            log::error!(
                "cannot start a thread to check a safety input's acknowledgment: every output \
                 switched off by the emergency handle"
            );
            emergency.all_inactive();
        }
    }

    /// The answer for `r` after `took`; an error first switches every output off.
    fn outcome(&self, r: Result<(), NotTaken>, took: Duration) -> Result<Duration, NotTaken> {
        match r {
            Ok(()) => Ok(took),
            Err(e) => {
                self.path.emergency.all_inactive();
                Err(match e {
                    NotTaken::Late(_) => NotTaken::Late(SAFETY_TAKE_BOUND),
                    stopped => stopped,
                })
            }
        }
    }
}

/// A check not answered yet: dropped so (its task dropped by a runtime that shuts down, or
/// unwinding), it hands the rest of the bound to a plain thread.
struct Unanswered {
    check: Check,
    reply: Option<Reply>,
}

impl Unanswered {
    /// The check as a task: awaits the acknowledgment up to the bound. Should the runtime drop
    /// the task first (it shuts down, or had shut down before the task's first poll), the drop
    /// checks the rest on a plain thread.
    async fn run(mut self) {
        let check = &self.check;
        let r = check
            .path
            .wait_until(
                check.request,
                check.start + SAFETY_TAKE_BOUND,
                SAFETY_TAKE_BOUND,
            )
            .await;
        let answer = check.outcome(r, check.start.elapsed());
        if let Some(reply) = self.reply.take() {
            let _ = reply.send(answer);
        }
    }
}

impl Drop for Unanswered {
    fn drop(&mut self) {
        if let Some(reply) = self.reply.take() {
            self.check.clone().on_plain_thread(reply);
        }
    }
}

/// The ROS side's end of the request queue.
pub struct Requests {
    tx: rtrb::Producer<Request>,
    wake: Arc<EventFd>,
    channels: usize,
    safety: SafetyPath,
}

impl Requests {
    /// Queues a request and wakes the output thread. Never blocks. The safety inputs
    /// ([`Input::EStop`], [`Input::Live`], [`Input::Bank`]) go through the
    /// [`SafetyPath`] instead, which is never full; use [`Requests::safety`] to wait until
    /// the thread has taken them.
    pub fn send(&mut self, request: Request) -> Result<(), OutputThreadError> {
        if request.channel >= self.channels {
            return Err(OutputThreadError::NoSuchChannel(request.channel));
        }
        if self.tx.is_abandoned() {
            return Err(OutputThreadError::Stopped);
        }
        if let Input::EStop(_) | Input::Live(_) | Input::Bank(_) = request.input {
            self.safety.store(request.input);
            return Ok(());
        }
        self.tx
            .push(request)
            .map_err(|_| OutputThreadError::QueueFull {
                capacity: self.tx.buffer().capacity(),
            })?;
        // EAGAIN here means the counter is saturated, i.e. a wake-up is pending anyway.
        let _ = self.wake.write(1);
        Ok(())
    }

    /// Queues all of `requests` or none: refused whole (nothing queued) when one names no
    /// channel, the thread has stopped, or the queue lacks room for them all. For changes that
    /// must reach the output thread together (a parameter change touching several channels
    /// and valves).
    pub fn send_all(&mut self, requests: &[Request]) -> Result<(), OutputThreadError> {
        if let Some(r) = requests.iter().find(|r| r.channel >= self.channels) {
            return Err(OutputThreadError::NoSuchChannel(r.channel));
        }
        if self.tx.is_abandoned() {
            return Err(OutputThreadError::Stopped);
        }
        if self.tx.slots() < requests.len() {
            return Err(OutputThreadError::QueueFull {
                capacity: self.tx.buffer().capacity(),
            });
        }
        for r in requests {
            self.send(*r)?;
        }
        Ok(())
    }

    /// Requests the queue has room for now.
    pub fn room(&self) -> usize {
        self.tx.slots()
    }

    /// Number of channels.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// The safety inputs' path, for callers that hold it apart from the queue's lock.
    pub fn safety(&self) -> SafetyPath {
        self.safety.clone()
    }
}

/// The ROS side's end of the report queue.
pub struct Reports {
    rx: rtrb::Consumer<Report>,
    wake: Arc<EventFd>,
    dropped: Arc<AtomicU64>,
}

impl Reports {
    /// The next report, if any.
    pub fn try_recv(&mut self) -> Option<Report> {
        self.rx.pop().ok()
    }

    /// An eventfd that is readable when reports may be waiting (poll it, or wrap it in an
    /// async reactor); call [`Reports::clear_wake`] before draining with
    /// [`Reports::try_recv`].
    pub fn wake_fd(&self) -> BorrowedFd<'_> {
        self.wake.as_fd()
    }

    /// Resets the wake-up eventfd.
    pub fn clear_wake(&self) {
        // EAGAIN: nothing was pending.
        let _ = self.wake.read();
    }

    /// Reports lost because this side did not drain fast enough.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// A handle that wakes this reader from any thread ([`ReportWaker::wake`]): for a reader
    /// that sleeps until its next deadline and must look at something else now (a note from a
    /// ROS callback, a request to stop).
    pub fn waker(&self) -> ReportWaker {
        ReportWaker(Arc::clone(&self.wake))
    }

    /// Blocks up to `timeout` for the wake-up eventfd (for non-async readers such as tests and
    /// the benchmark). Returns true when it became readable. The timeout is rounded up to whole
    /// milliseconds, so a reader never wakes before the deadline it computed.
    pub fn wait(&self, timeout: Duration) -> bool {
        let ms = timeout.as_nanos().div_ceil(1_000_000).min(i32::MAX as u128) as i32;
        let mut fds = [PollFd::new(self.wake.as_fd(), PollFlags::POLLIN)];
        matches!(poll(&mut fds, PollTimeout::try_from(ms).unwrap_or(PollTimeout::MAX)), Ok(n) if n > 0)
    }

    /// Whether the output thread has ended (its end of the queue is gone).
    pub fn is_abandoned(&self) -> bool {
        self.rx.is_abandoned()
    }

    /// Hands every report to `on_report`, batch by batch, calling `after_batch` after each
    /// batch, until `stop()` is true or the output thread has ended. Returns true in the latter
    /// case, after handing over the thread's last reports. Sleeps on the wake-up eventfd
    /// between batches, as long as the last `after_batch` said (a reader with clocks of its
    /// own): it looks at `stop` only when woken, so whoever makes `stop()` true wakes it
    /// ([`Reports::waker`]).
    pub fn serve(
        &mut self,
        stop: impl Fn() -> bool,
        mut on_report: impl FnMut(Report),
        mut after_batch: impl FnMut(&Reports) -> Duration,
    ) -> bool {
        let mut wait = Duration::ZERO;
        while !stop() {
            self.wait(wait);
            // Cleared before draining, so a report queued meanwhile wakes the next wait at once.
            self.clear_wake();
            while let Some(r) = self.try_recv() {
                on_report(r);
            }
            wait = after_batch(self);
            if self.is_abandoned() {
                while let Some(r) = self.try_recv() {
                    on_report(r);
                }
                return true;
            }
        }
        false
    }
}

/// Wakes the reader of [`Reports`] from any thread (see [`Reports::waker`]). Cheap to clone;
/// a wake-up costs one `write` on an eventfd, and wake-ups before the reader runs merge.
#[derive(Clone)]
pub struct ReportWaker(Arc<EventFd>);

impl ReportWaker {
    /// Wakes the reader now (it then drains the reports and runs its `after_batch`).
    pub fn wake(&self) {
        // EAGAIN: the counter is saturated, a wake-up is pending anyway.
        let _ = self.0.write(1);
    }
}

impl std::fmt::Debug for ReportWaker {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ReportWaker")
    }
}

/// How long [`OutputThreadHandle::shutdown`] waits for the output thread to end before it switches
/// the outputs off through the emergency handle and leaves the thread behind.
pub const SHUTDOWN_WAIT: Duration = Duration::from_secs(2);

/// The output thread's default [`OutputThreadOptions::liveness_tick_ns`]: it wakes at least this
/// often, even with nothing to do, so that its liveness can be seen from outside
/// ([`Liveness`]), ns.
pub const LIVENESS_TICK_NS: Nanos = 100_000_000;

/// Whether the output thread keeps its schedule, readable from any thread (the systemd
/// watchdog's pinger reads it). Before each sleep the thread publishes the deadline it will
/// wake at (never more than [`OutputThreadOptions::liveness_tick_ns`] ahead, when set); a thread
/// that is hung, stuck in a write, or starved of CPU falls behind that promise.
#[derive(Clone)]
pub struct Liveness(Arc<LivenessState>);

struct LivenessState {
    /// The deadline the thread promised to wake at, monotonic ns.
    due_by: AtomicU64,
    /// The thread has left its loop.
    stopped: AtomicBool,
}

impl Liveness {
    fn new(now: Nanos) -> Liveness {
        Liveness(Arc::new(LivenessState {
            due_by: AtomicU64::new(now.saturating_add(LIVENESS_TICK_NS)),
            stopped: AtomicBool::new(false),
        }))
    }

    fn promise(&self, deadline: Nanos) {
        self.0.due_by.store(deadline, Ordering::Release);
    }

    /// How far the output thread is behind the wake-up it promised, at `now` (monotonic ns):
    /// 0 when on time; `None` once it has stopped (after a fault or a shutdown).
    pub fn lag_ns(&self, now: Nanos) -> Option<Nanos> {
        if self.0.stopped.load(Ordering::Acquire) {
            return None;
        }
        Some(now.saturating_sub(self.0.due_by.load(Ordering::Acquire)))
    }
}

/// Controls the output thread's life.
pub struct OutputThreadHandle {
    thread: Option<JoinHandle<Result<(), OutputThreadError>>>,
    stop: Arc<AtomicBool>,
    wake: Arc<EventFd>,
    emergency: Arc<dyn EmergencyOff>,
    fault: Arc<Mutex<Option<WriteFault>>>,
    liveness: Liveness,
}

impl OutputThreadHandle {
    /// The thread's liveness, for a watchdog.
    pub fn liveness(&self) -> Liveness {
        self.liveness.clone()
    }

    /// Stops the thread: every output is driven inactive, then the output is dropped (which
    /// flushes traces) and the thread joined. Returns the thread's own error, if it had one.
    ///
    /// A thread that has not ended after [`SHUTDOWN_WAIT`] (hung in a write) is left behind:
    /// every output is driven inactive through the emergency handle instead, and the result
    /// is [`OutputThreadError::Hung`].
    pub fn shutdown(mut self) -> Result<(), OutputThreadError> {
        self.stop_and_join()
    }

    /// [`OutputThreadHandle::shutdown`] for async code: it runs on tokio's blocking pool (it
    /// may wait up to [`SHUTDOWN_WAIT`], 2 s, for a thread stuck in a write), so no async
    /// worker is held meanwhile.
    ///
    /// # Panics
    ///
    /// Outside a tokio runtime.
    pub async fn shutdown_async(self) -> Result<(), OutputThreadError> {
        tokio::task::spawn_blocking(move || self.shutdown())
            .await
            // The shutdown panicked, or the runtime dropped it before it ran: either way the
            // handle, dropped, has stopped the thread.
            .unwrap_or(Err(OutputThreadError::Panicked))
    }

    /// [`OutputThreadHandle::shutdown`]'s work, for it and for dropping the handle.
    fn stop_and_join(&mut self) -> Result<(), OutputThreadError> {
        self.stop.store(true, Ordering::SeqCst);
        let _ = self.wake.write(1);
        let start = std::time::Instant::now();
        while !self.is_finished() {
            if start.elapsed() >= SHUTDOWN_WAIT {
                self.emergency.all_inactive();
                // Dropping the handle detaches the hung thread.
                self.thread = None;
                return Err(OutputThreadError::Hung {
                    waited_ms: start.elapsed().as_millis() as u64,
                });
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(r)) => r,
            Some(Err(_)) => Err(OutputThreadError::Panicked),
            None => Ok(()),
        }
    }

    /// Whether the thread has ended (after a fault, or after shutdown).
    pub fn is_finished(&self) -> bool {
        self.thread.as_ref().is_none_or(JoinHandle::is_finished)
    }

    /// A handle that drives every output inactive from any thread.
    pub fn emergency_off(&self) -> Arc<dyn EmergencyOff> {
        self.emergency.clone()
    }

    /// The output fault that stopped the thread, if one did.
    pub fn fault(&self) -> Option<WriteFault> {
        self.fault.lock().map(|f| f.clone()).unwrap_or(None)
    }
}

impl Drop for OutputThreadHandle {
    fn drop(&mut self) {
        if self.thread.is_some() {
            let _ = self.stop_and_join();
        }
    }
}

/// A running output thread and both ends of its queues.
pub struct OutputThread {
    /// Requests in.
    pub requests: Requests,
    /// Reports out.
    pub reports: Reports,
    /// The thread's life.
    pub handle: OutputThreadHandle,
}

/// A non-blocking timerfd on CLOCK_MONOTONIC, for a loop that sleeps with
/// [`ThreadLoop::sleep_on`].
pub fn monotonic_timer() -> Result<TimerFd, OutputThreadError> {
    TimerFd::new(
        ClockId::CLOCK_MONOTONIC,
        TimerFlags::TFD_CLOEXEC | TimerFlags::TFD_NONBLOCK,
    )
    .map_err(|source| OutputThreadError::Sys {
        what: "timerfd_create",
        source,
    })
}

/// Starts the output thread with one channel per config (channel `i` drives output line `i`).
/// Every channel starts disabled with its output low. The thread sleeps on a timerfd armed
/// with absolute CLOCK_MONOTONIC deadlines.
pub fn spawn<O: Output>(
    configs: Vec<ChannelConfig>,
    output: O,
    opts: OutputThreadOptions,
) -> Result<OutputThread, OutputThreadError> {
    check_lines(&configs, &output, opts.heartbeat_half_period_ns.is_some())?;
    let timer = monotonic_timer()?;
    spawn_with(configs, output, opts, move |thread| {
        sleep_on_timerfd(thread, &timer)
    })
}

/// Writes every slot of a new ring buffer once and takes it back, so that its pages are
/// resident before the output thread starts: a slot used for the first time hours into a run
/// would otherwise cost a page fault on the thread, and the resident size would creep up by one
/// page at a time until the whole ring had been used once.
fn prefault<T: Copy>(tx: &mut rtrb::Producer<T>, rx: &mut rtrb::Consumer<T>, filler: T) {
    while tx.push(filler).is_ok() {}
    while rx.pop().is_ok() {}
}

/// Starts the output thread like [`spawn`], but with `run` as the loop that puts it to sleep
/// between wake-ups. `run` calls [`ThreadLoop::work`] at every wake-up until it returns
/// `Ok(false)` (stop requested) and then returns `Ok(())`; the thread then drives every line
/// inactive. An `Err` from `work` (an output fault) should be returned as is.
///
/// The node always uses [`spawn`]; this exists so that other ways of sleeping (the
/// benchmark's tokio baseline, its bare timer floor) run on the very same thread set-up:
/// priority, timer slack, queues and per-wake-up work.
pub fn spawn_with<O, R>(
    configs: Vec<ChannelConfig>,
    output: O,
    opts: OutputThreadOptions,
    run: R,
) -> Result<OutputThread, OutputThreadError>
where
    O: Output,
    R: FnOnce(&mut ThreadLoop<O>) -> Result<(), OutputThreadError> + Send + 'static,
{
    check_lines(&configs, &output, opts.heartbeat_half_period_ns.is_some())?;
    let sys = |what| move |source| OutputThreadError::Sys { what, source };
    let flags = EfdFlags::EFD_CLOEXEC | EfdFlags::EFD_NONBLOCK;
    let req_wake = Arc::new(EventFd::from_flags(flags).map_err(sys("eventfd"))?);
    let rep_wake = Arc::new(EventFd::from_flags(flags).map_err(sys("eventfd"))?);
    let (mut req_tx, mut req_rx) = rtrb::RingBuffer::new(opts.queue_capacity.max(16));
    let (mut rep_tx, mut rep_rx) = rtrb::RingBuffer::new(opts.queue_capacity.max(16));
    let filler = Request {
        channel: 0,
        input: Input::Enable(false),
    };
    prefault(&mut req_tx, &mut req_rx, filler);
    prefault(&mut rep_tx, &mut rep_rx, Report::OutputFault { channel: 0 });
    let dropped = Arc::new(AtomicU64::new(0));
    let stop = Arc::new(AtomicBool::new(false));
    let fault = Arc::new(Mutex::new(None));
    let emergency = output.emergency_off();
    let channels = configs.len();
    let liveness = Liveness::new(clock::monotonic_ns());
    let slot = Arc::new(SafetySlot::new(!opts.start_held, opts.bank));
    let alive = Arc::new(AtomicBool::new(true));
    let ack = Arc::new(Ack::new().map_err(sys("eventfd"))?);

    let thread = {
        let (req_wake, rep_wake, stop, fault, dropped, liveness) = (
            req_wake.clone(),
            rep_wake.clone(),
            stop.clone(),
            fault.clone(),
            dropped.clone(),
            liveness.clone(),
        );
        let (slot, alive, ack) = (slot.clone(), alive.clone(), ack.clone());
        std::thread::Builder::new()
            .name("pwm-output".into())
            .spawn(move || {
                real_time_setup(opts.rt_priority);
                let now = clock::monotonic_ns();
                let mut worker = Worker::new(&configs, output, rep_tx, dropped, now, slot);
                if let Some(half) = opts.heartbeat_half_period_ns {
                    worker.start_heartbeat(configs.len(), half, now);
                }
                worker.set_bank(now, opts.bank);
                if opts.start_held {
                    worker.set_live(now, false);
                }
                let mut thread = ThreadLoop {
                    worker,
                    liveness,
                    liveness_tick_ns: opts.liveness_tick_ns,
                    last_work: now,
                    requests: req_rx,
                    req_wake,
                    rep_wake,
                    ack: Arc::clone(&ack),
                    stop,
                    fault,
                    last_wake: 0,
                    wake_pending: false,
                };
                // Every way out of the loop drives every line inactive: after an output fault
                // the worker has already tried, and tries once more here; after a failed
                // system call (timerfd, poll) this is the only place that does it.
                let ran = run(&mut thread);
                let finished = thread.finish();
                alive.store(false, Ordering::Release);
                // A waiter for a safety input learns at once that it will not be taken.
                ack.signal();
                ran.and(finished)
            })
            .map_err(OutputThreadError::Spawn)?
    };
    Ok(OutputThread {
        requests: Requests {
            tx: req_tx,
            wake: req_wake.clone(),
            channels,
            safety: SafetyPath {
                slot,
                wake: req_wake.clone(),
                ack,
                emergency: emergency.clone(),
                alive,
            },
        },
        reports: Reports {
            rx: rep_rx,
            wake: rep_wake,
            dropped,
        },
        handle: OutputThreadHandle {
            thread: Some(thread),
            stop,
            wake: req_wake,
            emergency,
            fault,
            liveness,
        },
    })
}

/// Refuses an empty channel list; checks that the output has a line per channel, and one more for the heartbeat.
fn check_lines<O: Output>(
    configs: &[ChannelConfig],
    output: &O,
    heartbeat: bool,
) -> Result<(), OutputThreadError> {
    if configs.is_empty() {
        return Err(OutputThreadError::NoChannels);
    }
    let needed = configs.len() + usize::from(heartbeat);
    if output.line_count() < needed {
        return Err(OutputThreadError::LineCount {
            lines: output.line_count(),
            channels: needed,
        });
    }
    Ok(())
}

/// The output thread as its sleeping loop sees it: the channel cores and the output (behind
/// [`ThreadLoop::work`]), the thread's ends of the request and report queues, and the
/// bookkeeping of reader wake-ups. Lives on the output thread only.
pub struct ThreadLoop<O: Output> {
    worker: Worker<O>,
    liveness: Liveness,
    /// [`OutputThreadOptions::liveness_tick_ns`].
    liveness_tick_ns: Option<Nanos>,
    /// When [`ThreadLoop::work`] last ran, monotonic ns.
    last_work: Nanos,
    requests: rtrb::Consumer<Request>,
    req_wake: Arc<EventFd>,
    rep_wake: Arc<EventFd>,
    /// The safety inputs' acknowledgment, signalled after a wake-up that took one.
    ack: Arc<Ack>,
    stop: Arc<AtomicBool>,
    fault: Arc<Mutex<Option<WriteFault>>>,
    /// When the reader was last woken, monotonic ns.
    last_wake: Nanos,
    /// Reports are waiting that the reader has not been woken for.
    wake_pending: bool,
}

/// The reader (the ROS side) is woken at most this often while edges come thick and fast, ns.
/// Each wake-up costs both threads a context switch and a cross-CPU wake; at 64 channels x
/// 100 Hz waking per edge doubled the CPU cost, and at 2 channels x 200 Hz (edges 0.55–1.85 ms
/// apart) a 2 ms interval still woke the reader for 3 edges of 4. A wake-up is only deferred
/// when the output thread will run again within the interval anyway (see [`wake_reader_now`]),
/// so deferring never adds a wake-up of its own, and a report reaches the reader at most this
/// long after it was pushed, plus the output thread's own lateness at that wake-up.
pub(crate) const READER_WAKE_INTERVAL_NS: Nanos = 5_000_000;

/// Whether the output thread, with reports pending, wakes the reader now (at `now`, the reader
/// last woken at `last_wake`, the thread's next deadline `next_deadline`): once the interval
/// since the last wake-up has passed, or when the thread will not run again before it ends.
pub(crate) fn wake_reader_now(now: Nanos, last_wake: Nanos, next_deadline: Option<Nanos>) -> bool {
    let due = last_wake.saturating_add(READER_WAKE_INTERVAL_NS);
    now >= due || next_deadline.is_none_or(|t| t >= due)
}

impl<O: Output> ThreadLoop<O> {
    /// One wake-up's work: apply the queued requests, write the edges that are due, report,
    /// and wake the reader when it is time. `Ok(false)` once a stop is requested (nothing was
    /// done); `Err` after an output fault (every line was driven inactive).
    pub fn work(&mut self) -> Result<bool, OutputThreadError> {
        if self.stop_requested() {
            return Ok(false);
        }
        self.last_work = clock::monotonic_ns();
        if let Err(Stop::Fault { channel, error }) = self.worker.run(&mut self.requests) {
            let fault = WriteFault {
                channel,
                kind: error.kind(),
                error: Arc::new(error),
            };
            if let Ok(mut f) = self.fault.lock() {
                *f = Some(fault.clone());
            }
            let _ = self.rep_wake.write(1);
            return Err(fault.into());
        }
        if self.worker.take_acked() {
            // Only after a wake-up that took a safety input: no cost at any other.
            self.ack.signal();
        }
        self.wake_pending |= self.worker.take_pushed();
        if self.wake_pending {
            let now = clock::monotonic_ns();
            // Defer only to a wake-up that is coming anyway before the interval ends.
            if wake_reader_now(now, self.last_wake, self.worker.next_deadline()) {
                let _ = self.rep_wake.write(1);
                self.last_wake = now;
                self.wake_pending = false;
            }
        }
        Ok(true)
    }

    /// The earliest deadline of any channel or of the heartbeat line, and, with a liveness
    /// tick ([`OutputThreadOptions::liveness_tick_ns`]), at the latest one tick after the last
    /// wake-up, monotonic ns; `None`: nothing is due until a request comes.
    pub fn next_deadline(&self) -> Option<Nanos> {
        let tick = self
            .liveness_tick_ns
            .map(|t| self.last_work.saturating_add(t));
        match (self.worker.next_deadline(), tick) {
            (Some(d), Some(t)) => Some(d.min(t)),
            (d, t) => d.or(t),
        }
    }

    /// Whether [`OutputThreadHandle::shutdown`] (or dropping the handle) asked the thread to stop.
    pub fn stop_requested(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }

    /// An eventfd that becomes readable when a request (or a stop) arrives; a loop sleeps on
    /// it beside its timer and calls [`ThreadLoop::clear_request_wake`] when it fired.
    pub fn request_wake_fd(&self) -> BorrowedFd<'_> {
        self.req_wake.as_fd()
    }

    /// Resets the request eventfd.
    pub fn clear_request_wake(&self) {
        // EAGAIN: nothing was pending.
        let _ = self.req_wake.read();
    }

    /// Sleeps on `timer` armed with the absolute CLOCK_MONOTONIC `deadline` (none: until a
    /// request), or on the request eventfd, whichever fires first, and clears a request wake-up. A late
    /// wake-up does not push later deadlines back: they are absolute. Returns whether the
    /// timer fired.
    pub fn sleep_on(
        &self,
        timer: &TimerFd,
        deadline: Option<Nanos>,
    ) -> Result<bool, OutputThreadError> {
        let sys = |what| move |source| OutputThreadError::Sys { what, source };
        self.liveness.promise(deadline.unwrap_or(Nanos::MAX));
        arm(timer, deadline).map_err(sys("timerfd_settime"))?;
        let mut fds = [
            PollFd::new(timer.as_fd(), PollFlags::POLLIN),
            PollFd::new(self.request_wake_fd(), PollFlags::POLLIN),
        ];
        match poll(&mut fds, PollTimeout::NONE) {
            Ok(_) | Err(nix::errno::Errno::EINTR) => {}
            Err(e) => return Err(sys("poll")(e)),
        }
        let fired = |fd: &PollFd| fd.revents().is_some_and(|r| r.contains(PollFlags::POLLIN));
        let (timer_fired, request_fired) = (fired(&fds[0]), fired(&fds[1]));
        // Every saved syscall is saved thousands of times a second. The timer's expiration is
        // not read: arming or disarming it before the next poll clears it (the kernel zeroes
        // the count in timerfd_settime), so a read would only stand between the wake-up and
        // the write.
        if request_fired {
            self.clear_request_wake();
        }
        Ok(timer_fired)
    }

    /// Drives every line inactive, drops the output (flushing traces) and wakes the reader.
    fn finish(self) -> Result<(), OutputThreadError> {
        self.liveness.0.stopped.store(true, Ordering::Release);
        let (output, result) = self.worker.shut_down();
        drop(output);
        let _ = self.rep_wake.write(1);
        result.map_err(|e| OutputThreadError::ShutdownFault {
            channel: e.line(),
            kind: e.kind(),
            source: Box::new(e),
        })
    }
}

/// Arms `timer` to fire at the absolute CLOCK_MONOTONIC `deadline`, ns, or disarms it (`None`).
/// Either clears an expiration not read yet (timerfd_settime zeroes the count).
fn arm(timer: &TimerFd, deadline: Option<Nanos>) -> nix::Result<()> {
    match deadline {
        Some(t) => timer.set(
            Expiration::OneShot(TimeSpec::from_duration(Duration::from_nanos(t))),
            TimerSetTimeFlags::TFD_TIMER_ABSTIME,
        ),
        None => timer.unset(),
    }
}

/// The node's loop: sleeps on `timer` armed with the next absolute CLOCK_MONOTONIC deadline,
/// or on the request eventfd, whichever fires first.
fn sleep_on_timerfd<O: Output>(
    thread: &mut ThreadLoop<O>,
    timer: &TimerFd,
) -> Result<(), OutputThreadError> {
    while thread.work()? {
        // A deferred reader wake-up always falls after the next deadline (see `work`), so the
        // channels' deadlines are the only ones.
        let deadline = thread.next_deadline();
        thread.sleep_on(timer, deadline)?;
    }
    Ok(())
}

/// Timer slack 1 ns always; SCHED_FIFO and mlockall when asked. Refusals are logged once and
/// the thread carries on with normal scheduling.
fn real_time_setup(rt_priority: Option<i32>) {
    if let Err(e) = nix::sys::prctl::set_timerslack(1) {
        log::warn!("could not set timer slack to 1 ns: {e}");
    }
    let Some(prio) = rt_priority else { return };
    let param = libc::sched_param {
        sched_priority: prio,
    };
    // SAFETY: plain syscall on the calling thread with a valid, initialised sched_param.
    let rc = unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) };
    if rc != 0 {
        log::warn!(
            "SCHED_FIFO priority {prio} refused ({}); running with normal scheduling \
             (see docs/realtime.md: rtprio limit or CAP_SYS_NICE)",
            std::io::Error::last_os_error()
        );
        return;
    }
    use nix::sys::mman::{mlockall, MlockAllFlags};
    if let Err(e) = mlockall(MlockAllFlags::MCL_CURRENT | MlockAllFlags::MCL_FUTURE) {
        log::warn!("mlockall refused ({e}); pages may fault on the output path");
    }
    log::info!("output thread running SCHED_FIFO priority {prio}");
}

#[cfg(test)]
mod timer_tests {
    use super::*;

    fn readable(timer: &TimerFd) -> bool {
        let mut fds = [PollFd::new(timer.as_fd(), PollFlags::POLLIN)];
        poll(&mut fds, PollTimeout::ZERO).unwrap() == 1
    }

    // The output thread's loop never reads its timer's expirations: it relies on arming (or
    // disarming) the timer to clear them, so that a fired timer does not wake the next poll.
    #[test]
    fn arming_or_disarming_the_timer_clears_an_expiration_never_read() {
        let timer = monotonic_timer().unwrap();
        let now = crate::clock::monotonic_ns();
        arm(&timer, Some(now.saturating_sub(1_000_000))).unwrap();
        assert!(readable(&timer), "a deadline in the past fires at once");
        arm(&timer, Some(now + 60_000_000_000)).unwrap();
        assert!(!readable(&timer), "armed again: the old expiration is gone");
        arm(&timer, Some(now.saturating_sub(1_000_000))).unwrap();
        assert!(readable(&timer));
        arm(&timer, None).unwrap();
        assert!(!readable(&timer), "disarmed: the old expiration is gone");
    }
}

#[cfg(test)]
mod reader_wake_tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        // The output thread runs at each of its deadlines (gaps of 10 us to 12 ms) and pushes a
        // report at each: every report reaches the reader within READER_WAKE_INTERVAL_NS of
        // being pushed.
        #[test]
        fn a_report_waits_for_the_reader_at_most_the_interval(
            gaps in proptest::collection::vec(10_000u64..12_000_000, 1..200),
        ) {
            let mut runs = vec![1_000_000_000u64];
            for g in &gaps {
                let t = runs[runs.len() - 1] + g;
                runs.push(t);
            }
            let mut last_wake = 0;
            let mut oldest_pending: Option<Nanos> = None;
            for (i, &now) in runs.iter().enumerate() {
                oldest_pending.get_or_insert(now);
                let next = runs.get(i + 1).copied();
                if wake_reader_now(now, last_wake, next) {
                    let waited = now - oldest_pending.take().unwrap();
                    prop_assert!(waited <= READER_WAKE_INTERVAL_NS, "waited {waited} ns");
                    last_wake = now;
                }
            }
            // The last run has no next deadline: it always wakes the reader.
            prop_assert!(oldest_pending.is_none());
        }
    }

    #[test]
    fn the_reader_is_woken_when_no_run_comes_before_the_interval_ends() {
        let ms = 1_000_000;
        // Last woken at 10 ms: at 11 ms with the next run at 12 ms, deferred; with the next run
        // at 15 ms or later, or none, now; at 15 ms, now.
        assert!(!wake_reader_now(11 * ms, 10 * ms, Some(12 * ms)));
        assert!(wake_reader_now(11 * ms, 10 * ms, Some(15 * ms)));
        assert!(wake_reader_now(11 * ms, 10 * ms, None));
        assert!(wake_reader_now(15 * ms, 10 * ms, Some(15 * ms + 1)));
    }
}

#[cfg(test)]
mod safety_ack_tests {
    //! The safety inputs' acknowledgment, with the test playing the output thread: a task that
    //! sleeps on the thread's request eventfd as the thread does, and on a wake-up applies what
    //! the slot holds and signals the acknowledgment, as [`ThreadLoop::work`] does.
    use super::*;
    use std::sync::atomic::AtomicUsize;

    /// An emergency handle that counts its uses.
    #[derive(Default)]
    struct CountingOff(AtomicUsize);

    impl EmergencyOff for CountingOff {
        fn all_inactive(&self) {
            self.0.fetch_add(1, Ordering::SeqCst);
        }
    }

    fn fake() -> (SafetyPath, Arc<CountingOff>) {
        let off = Arc::new(CountingOff::default());
        let flags = EfdFlags::EFD_CLOEXEC | EfdFlags::EFD_NONBLOCK;
        let path = SafetyPath {
            slot: Arc::new(SafetySlot::new(true, Bank::default())),
            wake: Arc::new(EventFd::from_flags(flags).unwrap()),
            ack: Arc::new(Ack::new().unwrap()),
            emergency: off.clone(),
            alive: Arc::new(AtomicBool::new(true)),
        };
        (path, off)
    }

    /// Waits, on this thread, until the fake emergency handle `off` was called, and checks it
    /// was not before the bound from `start`.
    fn wait_off_at_the_bound(off: &AtomicUsize, start: std::time::Instant) {
        while off.load(Ordering::SeqCst) == 0 {
            assert!(
                start.elapsed() < 8 * SAFETY_TAKE_BOUND,
                "never switched off"
            );
            std::thread::sleep(Duration::from_millis(5));
        }
        assert!(
            start.elapsed() >= SAFETY_TAKE_BOUND,
            "{:?}",
            start.elapsed()
        );
    }

    struct WakeFd(Arc<EventFd>);
    impl AsRawFd for WakeFd {
        fn as_raw_fd(&self) -> RawFd {
            self.0.as_raw_fd()
        }
    }

    /// Plays the output thread: sleeps until a request wakes it, then applies what the slot
    /// holds and signals the acknowledgment (`stops`: leaves instead, as a thread that stopped).
    fn thread(path: &SafetyPath, stops: bool) -> tokio::task::JoinHandle<()> {
        let path = path.clone();
        tokio::spawn(async move {
            // SAFETY: the eventfd stays open while `WakeFd` holds its `Arc`.
            let wake = unsafe {
                AsyncFd::register_with_interest(WakeFd(Arc::clone(&path.wake)), Interest::READABLE)
            }
            .unwrap();
            wake.readable().await.unwrap().clear_ready();
            if stops {
                path.alive.store(false, Ordering::Release);
            } else {
                path.slot.mark_taken(path.slot.wanted().request);
            }
            path.ack.signal();
        })
    }

    #[tokio::test(start_paused = true)]
    async fn an_acknowledgment_arrives_with_no_time_passing() {
        let (path, off) = fake();
        let thread = thread(&path, false);
        let start = tokio::time::Instant::now();
        // The task playing the thread shares this runtime's only thread: a wait that blocked
        // it (a sleep between looks at the counter) would never let it run.
        let r = path.take_async(Input::EStop(true)).await;
        assert_eq!(r, Ok(Duration::ZERO));
        assert_eq!(tokio::time::Instant::now(), start, "no time passed");
        assert_eq!(off.0.load(Ordering::SeqCst), 0, "no emergency off");
        assert!(path.estop_latched());
        thread.await.unwrap();
        // Already taken: answered without waiting.
        assert_eq!(
            path.wait_async(1, SAFETY_TAKE_BOUND).await,
            Ok(Duration::ZERO)
        );
    }

    #[tokio::test(start_paused = true)]
    async fn a_late_acknowledgment_ends_exactly_at_the_bound_with_everything_off() {
        let (path, off) = fake();
        let start = tokio::time::Instant::now();
        let r = path.take_async(Input::Live(false)).await;
        assert_eq!(r, Err(NotTaken::Late(SAFETY_TAKE_BOUND)));
        assert_eq!(
            r.unwrap_err().to_string(),
            "the output thread did not take it within 250 ms"
        );
        assert_eq!(tokio::time::Instant::now() - start, SAFETY_TAKE_BOUND);
        assert_eq!(
            off.0.load(Ordering::SeqCst),
            1,
            "every output switched off once"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn a_stopped_thread_answers_stopped_at_once() {
        // Stopped before the input.
        let (path, off) = fake();
        path.alive.store(false, Ordering::Release);
        let start = tokio::time::Instant::now();
        assert_eq!(
            path.take_async(Input::EStop(true)).await,
            Err(NotTaken::Stopped)
        );
        assert_eq!(tokio::time::Instant::now(), start);
        assert_eq!(off.0.load(Ordering::SeqCst), 1);
        // Stopping while the input waits.
        let (path, off) = fake();
        let thread = thread(&path, true);
        let r = path.take_async(Input::Live(false)).await;
        assert_eq!(r, Err(NotTaken::Stopped));
        assert_eq!(r.unwrap_err().to_string(), "the output thread has stopped");
        assert_eq!(tokio::time::Instant::now(), start, "no time passed");
        assert_eq!(off.0.load(Ordering::SeqCst), 1);
        thread.await.unwrap();
    }

    #[tokio::test(start_paused = true)]
    async fn waiters_at_once_are_all_answered_by_one_acknowledgment() {
        let (path, off) = fake();
        let (a, b) = (
            path.store(Input::EStop(true)),
            path.store(Input::Live(false)),
        );
        let thread = thread(&path, false);
        let start = tokio::time::Instant::now();
        let (ra, rb) = tokio::join!(
            path.wait_async(a, SAFETY_TAKE_BOUND),
            path.wait_async(b, SAFETY_TAKE_BOUND)
        );
        assert_eq!((ra, rb), (Ok(Duration::ZERO), Ok(Duration::ZERO)));
        assert_eq!(tokio::time::Instant::now(), start);
        assert_eq!(off.0.load(Ordering::SeqCst), 0);
        thread.await.unwrap();
    }

    /// A waiter that gives up before the bound (a timeout around it, its task cancelled)
    /// leaves the check running: every output goes off exactly at the bound all the same.
    #[tokio::test(start_paused = true)]
    async fn a_dropped_wait_still_switches_everything_off_at_the_bound() {
        let (path, off) = fake();
        let start = tokio::time::Instant::now();
        let gave_up =
            tokio::time::timeout(SAFETY_TAKE_BOUND / 5, path.take_async(Input::EStop(true))).await;
        assert!(gave_up.is_err(), "the waiter gave up before the bound");
        assert!(path.estop_latched(), "the input is stored all the same");
        tokio::time::sleep_until(start + SAFETY_TAKE_BOUND - Duration::from_millis(1)).await;
        assert_eq!(off.0.load(Ordering::SeqCst), 0, "not before the bound");
        tokio::time::sleep_until(start + SAFETY_TAKE_BOUND + Duration::from_millis(1)).await;
        assert_eq!(
            off.0.load(Ordering::SeqCst),
            1,
            "every output off at the bound"
        );
        // A task that waits is aborted: the same.
        let (path, off) = fake();
        let start = tokio::time::Instant::now();
        let waiter = {
            let path = path.clone();
            tokio::spawn(async move { path.take_async(Input::Live(false)).await })
        };
        tokio::time::sleep(SAFETY_TAKE_BOUND / 5).await;
        waiter.abort();
        assert!(waiter.await.unwrap_err().is_cancelled());
        tokio::time::sleep_until(start + SAFETY_TAKE_BOUND + Duration::from_millis(1)).await;
        assert_eq!(off.0.load(Ordering::SeqCst), 1);
        // An acknowledgment never awaited: the same.
        let (path, off) = fake();
        drop(path.acknowledgment(path.store(Input::Live(false))));
        tokio::time::sleep(SAFETY_TAKE_BOUND + Duration::from_millis(1)).await;
        assert_eq!(off.0.load(Ordering::SeqCst), 1);
    }

    /// One taken in time after its waiter gave up switches nothing off.
    #[tokio::test(start_paused = true)]
    async fn a_dropped_wait_taken_in_time_switches_nothing_off() {
        let (path, off) = fake();
        let gave_up =
            tokio::time::timeout(SAFETY_TAKE_BOUND / 5, path.take_async(Input::EStop(true))).await;
        assert!(gave_up.is_err());
        // The store has woken the task playing the thread: it takes the input at once.
        thread(&path, false).await.unwrap();
        tokio::time::sleep(2 * SAFETY_TAKE_BOUND).await;
        assert_eq!(off.0.load(Ordering::SeqCst), 0);
    }

    /// A runtime that shuts down while a check runs hands the rest of the bound to a plain
    /// thread; with no runtime at all the check runs on one from the start.
    #[test]
    fn a_check_outlives_its_runtime() {
        let (path, off) = fake();
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let start = std::time::Instant::now();
        let gave_up = rt.block_on(async {
            tokio::time::timeout(
                Duration::from_millis(20),
                path.take_async(Input::EStop(true)),
            )
            .await
        });
        assert!(gave_up.is_err());
        drop(rt);
        assert_eq!(off.0.load(Ordering::SeqCst), 0, "not before the bound");
        wait_off_at_the_bound(&off.0, start);
        // No runtime: a plain thread checks, and the answer can still be awaited.
        let (path, off) = fake();
        let start = std::time::Instant::now();
        let ack = path.acknowledgment(path.store(Input::Live(false)));
        let answer = futures::executor::block_on(ack);
        assert_eq!(answer, Err(NotTaken::Late(SAFETY_TAKE_BOUND)));
        assert!(
            start.elapsed() >= SAFETY_TAKE_BOUND,
            "{:?}",
            start.elapsed()
        );
        assert_eq!(off.0.load(Ordering::SeqCst), 1);
    }

    /// A runtime that has shut down drops a task spawned on it before its first poll: the
    /// check goes to a plain thread all the same. Taken in time, it is answered so, with no
    /// emergency off; never taken, with its answer given up, every output goes off at the
    /// bound.
    #[test]
    fn a_check_begun_on_a_runtime_that_has_shut_down_runs_on_a_plain_thread() {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let handle = rt.handle().clone();
        drop(rt);
        let _entered = handle.enter();
        let (path, off) = fake();
        let request = path.store(Input::EStop(true));
        let taker = {
            let path = path.clone();
            std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(20));
                path.slot.mark_taken(path.slot.wanted().request);
                path.ack.signal();
            })
        };
        let answer = futures::executor::block_on(path.acknowledgment(request));
        taker.join().unwrap();
        let took = answer.expect("taken in time");
        assert!(took >= Duration::from_millis(20), "{took:?}");
        assert_eq!(off.0.load(Ordering::SeqCst), 0, "no emergency off");
        // Never taken, the answer given up: the bound is checked all the same.
        let (path, off) = fake();
        let start = std::time::Instant::now();
        drop(path.acknowledgment(path.store(Input::Live(false))));
        wait_off_at_the_bound(&off.0, start);
    }

    #[test]
    fn a_plain_thread_waits_without_a_runtime() {
        let (path, off) = fake();
        let request = path.store(Input::EStop(true));
        let taker = {
            let path = path.clone();
            std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(20));
                path.slot.mark_taken(path.slot.wanted().request);
                path.ack.signal();
            })
        };
        let took = path.wait(request, SAFETY_TAKE_BOUND).unwrap();
        assert!(took >= Duration::from_millis(20), "{took:?}");
        taker.join().unwrap();
        // Nobody takes it: late at the bound, every output off.
        let start = std::time::Instant::now();
        assert_eq!(
            path.take(Input::Live(false)),
            Err(NotTaken::Late(SAFETY_TAKE_BOUND))
        );
        assert!(start.elapsed() >= SAFETY_TAKE_BOUND);
        assert_eq!(off.0.load(Ordering::SeqCst), 1);
    }
}
