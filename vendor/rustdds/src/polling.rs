// Internal polling primitives for the two reactors (dp_event_loop and Discovery).
//
// Sockets are registered with mio 1.2. Everything that is not a socket — command
// queues, writer doorbells, reader commands, discovery sample readiness — shares
// one `Waker` per poll. `wake()` is coalesced, so the token only means "drain
// the queues": the sender enqueues the payload (or entity id) and then wakes.
// Timers are an in-loop deadline map. The poll timeout is the sooner of the next
// deadline and the loop's idle cap. Nothing here is registered as a mio 0.6
// `Evented` source; user-visible sample and status channels stay mio-extras.

use std::{
  collections::BTreeMap,
  sync::{mpsc, Arc, OnceLock},
  time::{Duration, Instant},
};

use mio1::{Poll, Token, Waker};

use crate::structure::guid::EntityId;

/// One waker for one `Poll`. Share clones freely. `wake` before [`install`](Self::install)
/// is a no-op; the event loop drains its queues once after installing so anything
/// enqueued earlier is still observed.
#[derive(Clone)]
pub(crate) struct LoopWaker {
  slot: Arc<OnceLock<Waker>>,
}

impl LoopWaker {
  pub(crate) fn new() -> Self {
    Self {
      slot: Arc::new(OnceLock::new()),
    }
  }

  /// Register the single waker of `poll` under `token`. Debug builds assert this
  /// happens once: mio 1.2 allows only one `Waker` per `Poll`.
  pub(crate) fn install(&self, poll: &Poll, token: Token) -> std::io::Result<()> {
    let waker = Waker::new(poll.registry(), token)?;
    if self.slot.set(waker).is_err() {
      debug_assert!(false, "LoopWaker::install called twice for one poll");
    }
    Ok(())
  }

  pub(crate) fn wake(&self) {
    if let Some(waker) = self.slot.get() {
      if let Err(e) = waker.wake() {
        log::debug!("LoopWaker::wake: {e}");
      }
    }
  }
}

/// Bounded queue whose send wakes `waker`'s poll.
pub(crate) struct WakeSender<T> {
  tx: mpsc::SyncSender<T>,
  waker: LoopWaker,
}

impl<T> Clone for WakeSender<T> {
  fn clone(&self) -> Self {
    Self {
      tx: self.tx.clone(),
      waker: self.waker.clone(),
    }
  }
}

impl<T> WakeSender<T> {
  pub(crate) fn try_send(&self, value: T) -> Result<(), mpsc::TrySendError<T>> {
    match self.tx.try_send(value) {
      Ok(()) => {
        self.waker.wake();
        Ok(())
      }
      Err(e) => Err(e),
    }
  }

  pub(crate) fn send(&self, value: T) -> Result<(), mpsc::SendError<T>> {
    match self.tx.send(value) {
      Ok(()) => {
        self.waker.wake();
        Ok(())
      }
      Err(e) => Err(e),
    }
  }

  /// Retry a full bounded send for a short time. Wakes the poll on success.
  pub(crate) fn try_send_timeout(
    &self,
    value: T,
    timeout: Duration,
  ) -> Result<(), mpsc::TrySendError<T>> {
    let mut value = value;
    match self.try_send(value) {
      Ok(()) => Ok(()),
      Err(mpsc::TrySendError::Disconnected(v)) => Err(mpsc::TrySendError::Disconnected(v)),
      Err(mpsc::TrySendError::Full(v)) => {
        value = v;
        let start = Instant::now();
        let mut delay = Duration::from_micros(1);
        while start.elapsed() < timeout {
          std::thread::sleep(delay);
          match self.try_send(value) {
            Ok(()) => return Ok(()),
            Err(mpsc::TrySendError::Full(v)) => {
              value = v;
              delay = (delay * 2).min(Duration::from_millis(2));
            }
            Err(other) => return Err(other),
          }
        }
        Err(mpsc::TrySendError::Full(value))
      }
    }
  }
}

pub(crate) struct WakeReceiver<T> {
  rx: mpsc::Receiver<T>,
}

impl<T> WakeReceiver<T> {
  pub(crate) fn try_recv(&self) -> Result<T, mpsc::TryRecvError> {
    self.rx.try_recv()
  }
}

pub(crate) fn wake_channel<T>(
  capacity: usize,
  waker: &LoopWaker,
) -> (WakeSender<T>, WakeReceiver<T>) {
  let (tx, rx) = mpsc::sync_channel(capacity);
  (
    WakeSender {
      tx,
      waker: waker.clone(),
    },
    WakeReceiver { rx },
  )
}

/// Unbounded queue whose send wakes `waker`'s poll. Used for stop commands.
#[derive(Clone)]
pub(crate) struct WakeUnboundedSender<T> {
  tx: mpsc::Sender<T>,
  waker: LoopWaker,
}

impl<T> WakeUnboundedSender<T> {
  pub(crate) fn send(&self, value: T) -> Result<(), mpsc::SendError<T>> {
    match self.tx.send(value) {
      Ok(()) => {
        self.waker.wake();
        Ok(())
      }
      Err(e) => Err(e),
    }
  }
}

pub(crate) fn wake_channel_unbounded<T>(
  waker: &LoopWaker,
) -> (WakeUnboundedSender<T>, WakeReceiver<T>) {
  let (tx, rx) = mpsc::channel();
  (
    WakeUnboundedSender {
      tx,
      waker: waker.clone(),
    },
    WakeReceiver { rx },
  )
}

/// Unbounded "something became ready" queue. The payload is the reason (an
/// entity id or a discovery token). Duplicate reasons in one drain are collapsed.
#[derive(Clone)]
pub(crate) struct ReadySender<T> {
  tx: mpsc::Sender<T>,
  waker: LoopWaker,
}

impl<T> ReadySender<T> {
  pub(crate) fn waker(&self) -> LoopWaker {
    self.waker.clone()
  }

  pub(crate) fn notify(&self, value: T) {
    if self.tx.send(value).is_ok() {
      self.waker.wake();
    }
  }
}

pub(crate) struct ReadyReceiver<T> {
  rx: mpsc::Receiver<T>,
}

impl<T: Eq> ReadyReceiver<T> {
  /// Drain every queued reason, keeping the first occurrence of each.
  pub(crate) fn drain_unique(&self) -> Vec<T> {
    let mut out = Vec::new();
    while let Ok(value) = self.rx.try_recv() {
      if !out.contains(&value) {
        out.push(value);
      }
    }
    out
  }
}

pub(crate) fn ready_channel<T>(waker: &LoopWaker) -> (ReadySender<T>, ReadyReceiver<T>) {
  let (tx, rx) = mpsc::channel();
  (
    ReadySender {
      tx,
      waker: waker.clone(),
    },
    ReadyReceiver { rx },
  )
}

/// Bounded command queue plus a shared ready-queue of entity ids. A successful
/// send records `entity_id` so the event loop, which has only one waker, knows
/// which endpoint to drain.
/// Reader commands are not sent today (`ResetRequestedDeadlineStatus` is
/// unimplemented). The sender stays so a future send still wakes the right
/// reader.
#[allow(dead_code)]
#[derive(Clone)]
pub(crate) struct BoundSender<T> {
  tx: WakeSender<T>,
  ready: ReadySender<EntityId>,
  entity_id: EntityId,
}

#[allow(dead_code)]
impl<T> BoundSender<T> {
  pub(crate) fn new(tx: WakeSender<T>, ready: ReadySender<EntityId>, entity_id: EntityId) -> Self {
    Self {
      tx,
      ready,
      entity_id,
    }
  }

  pub(crate) fn try_send(&self, value: T) -> Result<(), mpsc::TrySendError<T>> {
    self.tx.try_send(value)?;
    self.ready.notify(self.entity_id);
    Ok(())
  }
}

/// Writer doorbell. Ringing enqueues the writer's entity id and wakes the
/// participant poll. Replaces the mio 0.6 `Registration` previously registered
/// under the writer token.
#[derive(Clone)]
pub(crate) struct Doorbell {
  entity_id: EntityId,
  ready: ReadySender<EntityId>,
}

impl Doorbell {
  pub(crate) fn new(entity_id: EntityId, ready: ReadySender<EntityId>) -> Self {
    Self { entity_id, ready }
  }

  /// pwm_actuator: queues the writer's id without waking the loop, which
  /// takes it at its next wake-up for anything else
  /// (`WriterSendBuffer::notify_admitted`).
  pub(crate) fn queue(&self) {
    let _ = self.ready.tx.send(self.entity_id);
  }

  pub(crate) fn ring(&self) {
    // pwm_actuator: the wake-up may be held back by the writing thread (see
    // `hold_writer_wakes`, README.pwm_actuator.md).
    if self.ready.tx.send(self.entity_id).is_ok() {
      wake_or_hold(&self.ready.waker);
    }
  }
}

// pwm_actuator: writer wake-ups held back while a thread writes a batch.

/// A held wake-up is delivered at the latest at the first ring this long after
/// the first one held.
const HOLD_AT_MOST: Duration = Duration::from_millis(1);
/// At most this many rings are held before their wake-up is delivered.
const HOLD_AT_MOST_RINGS: u32 = 32;

struct Held {
  /// Nested holds of this thread.
  depth: u32,
  wakers: Vec<LoopWaker>,
  first: Option<Instant>,
  rings: u32,
}

impl Held {
  fn release(&mut self) {
    for w in self.wakers.drain(..) {
      w.wake();
    }
    self.first = None;
    self.rings = 0;
  }
}

thread_local! {
  static HELD: std::cell::RefCell<Held> = const {
    std::cell::RefCell::new(Held { depth: 0, wakers: Vec::new(), first: None, rings: 0 })
  };
}

/// While the returned guard lives, the samples this thread writes with
/// `DataWriter::write` are stored at once as ever, but the wake-up of their
/// participant's event loop is held back and delivered once, when the guard is
/// dropped, rather than once per sample: a thread that writes several samples
/// in a row wakes the event loop once instead of once each. No wake-up is held
/// longer than the first write at least `HOLD_AT_MOST` (1 ms) after the first
/// held one, nor past 32 held writes, nor across a write that must wait for
/// room in a reliable writer's window (which only the event loop can make).
/// Holds nest; the outermost one delivers.
#[must_use = "the wake-ups are delivered when the guard is dropped"]
pub fn hold_writer_wakes() -> WriterWakeHold {
  HELD.with(|h| h.borrow_mut().depth += 1);
  WriterWakeHold {
    _not_send: std::marker::PhantomData,
  }
}

/// The guard of [`hold_writer_wakes`]; not `Send`, the hold is its thread's.
pub struct WriterWakeHold {
  _not_send: std::marker::PhantomData<*const ()>,
}

impl Drop for WriterWakeHold {
  fn drop(&mut self) {
    HELD.with(|h| {
      let mut h = h.borrow_mut();
      h.depth = h.depth.saturating_sub(1);
      if h.depth == 0 {
        h.release();
      }
    });
  }
}

/// Delivers every wake-up this thread holds (before a write waits for room).
pub(crate) fn release_held_wakes() {
  HELD.with(|h| h.borrow_mut().release());
}

fn wake_or_hold(waker: &LoopWaker) {
  let held = HELD.with(|h| {
    let mut h = h.borrow_mut();
    if h.depth == 0 {
      return false;
    }
    if !h.wakers.iter().any(|w| Arc::ptr_eq(&w.slot, &waker.slot)) {
      h.wakers.push(waker.clone());
    }
    h.rings += 1;
    let first = *h.first.get_or_insert_with(Instant::now);
    if h.rings >= HOLD_AT_MOST_RINGS || first.elapsed() >= HOLD_AT_MOST {
      h.release();
    }
    true
  });
  if !held {
    waker.wake();
  }
}

/// In-loop deadlines. Not registered with `Poll`. `set_timeout` / `poll` keep
/// the call pattern readers, writers, and tests already use. Deadlines are
/// absolute `Instant`s, so there is no timer-wheel tick to round them up.
pub(crate) struct Timer<E> {
  next_id: u64,
  deadlines: BTreeMap<(Instant, u64), E>,
}

impl<E> Timer<E> {
  pub(crate) fn new() -> Self {
    Self {
      next_id: 0,
      deadlines: BTreeMap::new(),
    }
  }

  pub(crate) fn set_timeout(&mut self, delay: Duration, event: E) {
    let when = Instant::now()
      .checked_add(delay)
      .unwrap_or_else(Instant::now);
    let id = self.next_id;
    self.next_id = self.next_id.wrapping_add(1);
    self.deadlines.insert((when, id), event);
  }

  /// Sets `event` to fall due at the next instant after now that is a whole
  /// number of `period`s after one process-wide origin. Periodic events of
  /// one period set at different times (every writer's HEARTBEAT, its cache
  /// cleaning) then fall due at the same instants, and the loop wakes once
  /// for all of them instead of once for each. The first one may come sooner
  /// than `period`; each one after it comes one `period` later.
  pub(crate) fn set_on_grid(&mut self, period: Duration, event: E) {
    // The origin first: it is never after `now`, so `when` lies on the grid.
    let origin = grid_origin();
    let now = Instant::now();
    let period_ns = period.as_nanos().max(1);
    let since = now.saturating_duration_since(origin).as_nanos();
    let ahead = period_ns - since % period_ns;
    let delay = Duration::from_nanos(u64::try_from(ahead).unwrap_or(u64::MAX));
    let when = now.checked_add(delay).unwrap_or(now);
    let id = self.next_id;
    self.next_id = self.next_id.wrapping_add(1);
    self.deadlines.insert((when, id), event);
  }

  /// The earliest event whose deadline has passed, if any.
  pub(crate) fn poll(&mut self) -> Option<E> {
    let key = *self.deadlines.keys().next()?;
    if key.0 <= Instant::now() {
      self.deadlines.remove(&key)
    } else {
      None
    }
  }

  pub(crate) fn next_deadline(&self) -> Option<Instant> {
    self.deadlines.keys().next().map(|(when, _)| *when)
  }
}

/// The origin of [`Timer::set_on_grid`]'s grid: the first time it is asked.
pub(crate) fn grid_origin() -> Instant {
  static ORIGIN: OnceLock<Instant> = OnceLock::new();
  *ORIGIN.get_or_init(Instant::now)
}

pub(crate) type SharedTimer<E> = std::rc::Rc<std::cell::RefCell<Timer<E>>>;

pub(crate) fn new_shared_timer<E>() -> SharedTimer<E> {
  std::rc::Rc::new(std::cell::RefCell::new(Timer::new()))
}

/// Poll timeout: the sooner of `deadline` and `cap`. A deadline already due
/// yields a zero timeout so the loop drains it immediately.
pub(crate) fn timeout_until(deadline: Option<Instant>, cap: Duration) -> Duration {
  match deadline {
    Some(when) => {
      let now = Instant::now();
      if when <= now {
        Duration::ZERO
      } else {
        (when - now).min(cap)
      }
    }
    None => cap,
  }
}

#[cfg(test)]
mod hold_tests {
  use super::*;

  fn doorbell() -> (Poll, Doorbell, ReadyReceiver<EntityId>) {
    let poll = Poll::new().unwrap();
    let waker = LoopWaker::new();
    waker.install(&poll, Token(7)).unwrap();
    let (tx, rx) = ready_channel(&waker);
    (poll, Doorbell::new(EntityId::UNKNOWN, tx), rx)
  }

  /// Wake-up events the poll sees now.
  fn events(poll: &mut Poll) -> usize {
    let mut ev = mio1::Events::with_capacity(8);
    poll.poll(&mut ev, Some(Duration::ZERO)).unwrap();
    ev.iter().count()
  }

  // Rings under a hold are queued at once, but the loop is woken only when
  // the hold ends; without a hold each ring wakes it.
  #[test]
  fn rings_under_a_hold_wake_the_loop_once_when_it_ends() {
    let (mut poll, bell, rx) = doorbell();
    bell.ring();
    assert_eq!(events(&mut poll), 1, "a ring without a hold wakes at once");
    assert_eq!(rx.drain_unique().len(), 1);
    {
      let _hold = hold_writer_wakes();
      let _inner = hold_writer_wakes();
      drop(_inner);
      for _ in 0..3 {
        bell.ring();
      }
      assert_eq!(events(&mut poll), 0, "held");
      assert_eq!(rx.drain_unique().len(), 1, "queued at once");
    }
    assert_eq!(events(&mut poll), 1, "woken when the hold ends");
    assert_eq!(events(&mut poll), 0);
  }

  // A hold never keeps a wake-up back longer than its bounds: the 32nd ring,
  // the first ring 1 ms after the first held one, and a write that must wait
  // for room deliver it.
  #[test]
  fn a_hold_delivers_after_its_bounds() {
    let (mut poll, bell, _rx) = doorbell();
    let _hold = hold_writer_wakes();
    for _ in 0..HOLD_AT_MOST_RINGS - 1 {
      bell.ring();
    }
    assert_eq!(events(&mut poll), 0);
    bell.ring();
    assert_eq!(events(&mut poll), 1, "delivered at the 32nd ring");
    bell.ring();
    std::thread::sleep(HOLD_AT_MOST);
    assert_eq!(events(&mut poll), 0);
    bell.ring();
    assert_eq!(events(&mut poll), 1, "delivered 1 ms after the first held");
    bell.ring();
    release_held_wakes();
    assert_eq!(events(&mut poll), 1, "delivered before a write waits");
  }
}

#[cfg(test)]
mod grid_tests {
  use super::*;

  // Two periodic events set 30 ms apart fall due at the same instant (or,
  // when a grid point passed between the two calls, exactly one period
  // apart), each within one period from when it was set. With `set_timeout`
  // they would be 30 ms apart: two wake-ups of the loop instead of one.
  #[test]
  fn events_set_on_the_grid_at_different_times_fall_due_together() {
    let period = Duration::from_millis(200);
    let mut t = Timer::new();
    let origin = grid_origin();
    let first_set = Instant::now();
    t.set_on_grid(period, 1);
    std::thread::sleep(Duration::from_millis(30));
    let second_set = Instant::now();
    t.set_on_grid(period, 2);
    let due: Vec<(Instant, u8)> = t.deadlines.iter().map(|((w, _), e)| (*w, *e)).collect();
    let at = |e: u8| due.iter().find(|(_, x)| *x == e).unwrap().0;
    let (a, b) = (at(1), at(2));
    assert!(a > first_set && a <= first_set + period);
    assert!(b > second_set && b <= second_set + period);
    for when in [a, b] {
      let since = when.saturating_duration_since(origin).as_nanos();
      assert_eq!(since % period.as_nanos(), 0, "on the grid");
    }
    let apart = b.saturating_duration_since(a);
    assert!(
      apart == Duration::ZERO || apart == period,
      "due {apart:?} apart, not on one grid"
    );
  }
}
