//! The reply paths of the requests that wait for the output thread's answer: a heater's
//! `~/<ch>/reset_fault`, a valve's `~/valve/<NAME>/reset` and the autotune action's reports.
//!
//! A request that waits makes its own [`tokio::sync::oneshot`] channel, files the sender under
//! its ticket ([`ReplySlots::expect`]) before the request goes to the output thread, and awaits
//! the receiver with its timeout ([`Reply::within`]): no polling, no sleep, no thread held
//! while it waits. The output thread answers as it always has, in its reports (a core event or
//! a valve's snapshot carrying the ticket): its requests and reports travel by value through
//! wait-free ring buffers, so it never allocates, frees, locks or wakes a task for the ROS
//! side. The report thread, which takes those reports, hands each answer to the sender filed
//! under its ticket ([`ReplySlots::answer`]).
//!
//! Bounded: one waiting request per key (a channel, a valve), which is all there can be since
//! a service answers its requests one at a time. A request that gave up (timed out) leaves
//! its sender behind until its late answer or the key's next request takes it; sending on it
//! then fails, which is ignored: a late answer is dropped harmlessly, and never answers a
//! later request (its ticket differs).
//!
//! The autotune action's reports are many per run: they wait in a bounded mailbox per
//! channel ([`Mailbox`]) that wakes the action's task when one is filed.

use crate::output::panic_off::lock_ignore_poison as lock;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Mutex;
use std::time::Duration;
use tokio::sync::{oneshot, Notify};

/// Tickets for requests that wait: unique in the process (wrapping after 2^32 requests).
#[derive(Debug)]
pub struct Tickets(AtomicU32);

impl Default for Tickets {
    fn default() -> Tickets {
        Tickets(AtomicU32::new(1))
    }
}

impl Tickets {
    /// A fresh ticket.
    pub fn next(&self) -> u32 {
        self.0.fetch_add(1, Ordering::Relaxed)
    }
}

/// Per key (a channel, a valve), the reply path of the one request that waits, with its
/// ticket (see the module documentation).
#[derive(Debug)]
pub struct ReplySlots<T> {
    slots: Box<[Mutex<Option<Waiting<T>>>]>,
}

/// The request that waits: its ticket and its reply path's sender.
type Waiting<T> = (u32, oneshot::Sender<T>);

/// The waiting end of one request's reply path.
#[derive(Debug)]
#[must_use = "a reply is awaited with `within`"]
pub struct Reply<T>(oneshot::Receiver<T>);

impl<T> Reply<T> {
    /// The answer, once it comes within `wait`; `None` when it did not (the request gave up:
    /// its late answer will be dropped) or its path was closed (a newer request of the same
    /// key took the slot, or the key does not exist).
    pub async fn within(self, wait: Duration) -> Option<T> {
        match tokio::time::timeout(wait, self.0).await {
            Ok(Ok(answer)) => Some(answer),
            Ok(Err(_)) | Err(_) => None,
        }
    }
}

impl<T> ReplySlots<T> {
    /// Slots for `keys` keys.
    pub fn new(keys: usize) -> ReplySlots<T> {
        ReplySlots {
            slots: (0..keys).map(|_| Mutex::new(None)).collect(),
        }
    }

    /// Files the reply path of the request with `ticket` of `key` (before the request is sent,
    /// so its answer cannot come first); a request of the same key that still waited is given
    /// up. A key that does not exist gives a reply that never comes.
    pub fn expect(&self, key: usize, ticket: u32) -> Reply<T> {
        let (tx, rx) = oneshot::channel();
        if let Some(slot) = self.slots.get(key) {
            *lock(slot) = Some((ticket, tx));
        }
        Reply(rx)
    }

    /// The answer to the request with `ticket` of `key`: handed to its reply path, when that
    /// request is the one filed; returns whether a request still waited for it (`false`: it
    /// had given up, or the answer is not the one it waits for, and the answer is dropped).
    /// Never blocks beyond the slot's lock, held for a swap.
    pub fn answer(&self, key: usize, ticket: u32, answer: T) -> bool {
        let Some(slot) = self.slots.get(key) else {
            return false;
        };
        let tx = {
            let mut s = lock(slot);
            match s.take() {
                Some((t, tx)) if t == ticket => tx,
                other => {
                    *s = other;
                    return false;
                }
            }
        };
        tx.send(answer).is_ok()
    }
}

/// How many autotune reports wait per channel at most.
pub const AUTOTUNE_REPORTS: usize = 64;

pub use crate::core::heater::autotune::Report as AutotuneReport;

/// One channel's reports waiting for the action, with their tickets.
type Reports = VecDeque<(u32, AutotuneReport)>;

/// Per channel, the autotune reports the action has not taken yet, with their tickets; filing
/// one wakes the action's task ([`Mailbox::filed`]).
#[derive(Debug)]
pub struct Mailbox {
    queues: Box<[Mutex<Reports>]>,
    filed: Box<[Notify]>,
}

impl Mailbox {
    /// Mailboxes for `channels` channels.
    pub fn new(channels: usize) -> Mailbox {
        Mailbox {
            queues: (0..channels).map(|_| Mutex::new(VecDeque::new())).collect(),
            filed: (0..channels).map(|_| Notify::new()).collect(),
        }
    }

    /// Files a report of the autotune with `ticket` of `channel` for its action to take, and
    /// wakes the action. At most [`AUTOTUNE_REPORTS`] wait; beyond, the oldest progress report
    /// goes (a run's end is never dropped for one).
    pub fn file(&self, channel: usize, ticket: u32, report: AutotuneReport) {
        let (Some(slot), Some(filed)) = (self.queues.get(channel), self.filed.get(channel)) else {
            return;
        };
        {
            let mut q = lock(slot);
            if q.len() >= AUTOTUNE_REPORTS {
                if let Some(i) = q
                    .iter()
                    .position(|(_, r)| matches!(r, AutotuneReport::Progress(_)))
                {
                    q.remove(i);
                } else {
                    q.pop_front();
                }
            }
            q.push_back((ticket, report));
        }
        // Stores a wake-up when the action is not waiting yet: none is lost.
        filed.notify_one();
    }

    /// Takes the reports of the autotune with `ticket` of `channel` that have come, oldest
    /// first (reports of other tickets are dropped: one run per channel at a time).
    pub fn take(&self, channel: usize, ticket: u32) -> Vec<AutotuneReport> {
        let Some(slot) = self.queues.get(channel) else {
            return Vec::new();
        };
        lock(slot)
            .drain(..)
            .filter(|(t, _)| *t == ticket)
            .map(|(_, r)| r)
            .collect()
    }

    /// Completes once a report was filed for `channel` since the last time this completed (at
    /// once when one was filed meanwhile); never for a channel that does not exist.
    pub async fn filed(&self, channel: usize) {
        match self.filed.get(channel) {
            Some(n) => n.notified().await,
            None => std::future::pending().await,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::heater::autotune::{Phase, Progress};

    const WAIT: Duration = Duration::from_secs(1);

    // With tokio's clock paused, a wait that looked again every few ms would move the clock on;
    // an answer that wakes the request leaves it where it was.
    #[tokio::test(start_paused = true)]
    async fn an_answer_wakes_its_request_without_any_time_passing() {
        let slots = std::sync::Arc::new(ReplySlots::<u8>::new(2));
        let reply = slots.expect(1, 7);
        let start = tokio::time::Instant::now();
        let answering = std::sync::Arc::clone(&slots);
        let report = tokio::spawn(async move {
            tokio::task::yield_now().await;
            answering.answer(1, 7, 42)
        });
        assert_eq!(reply.within(WAIT).await, Some(42));
        assert_eq!(start.elapsed(), Duration::ZERO);
        assert!(report.await.unwrap());
        // Taken: a repeat of the same answer finds nobody waiting.
        assert!(!slots.answer(1, 7, 42));
    }

    #[tokio::test(start_paused = true)]
    async fn an_answer_from_the_report_thread_wakes_a_waiting_request() {
        let slots = std::sync::Arc::new(ReplySlots::<u8>::new(1));
        let reply = slots.expect(0, 3);
        let waiting = tokio::spawn(reply.within(WAIT));
        // The request waits (its task has run up to its await) before the answer comes.
        tokio::task::yield_now().await;
        let start = tokio::time::Instant::now();
        let answering = std::sync::Arc::clone(&slots);
        let report_thread = std::thread::spawn(move || answering.answer(0, 3, 8));
        assert!(report_thread.join().unwrap());
        assert_eq!(waiting.await.unwrap(), Some(8));
        assert_eq!(start.elapsed(), Duration::ZERO);
    }

    #[tokio::test(start_paused = true)]
    async fn a_late_answer_is_dropped_and_never_answers_the_next_request() {
        let slots = ReplySlots::<u8>::new(1);
        let start = tokio::time::Instant::now();
        assert_eq!(slots.expect(0, 1).within(WAIT).await, None);
        assert_eq!(start.elapsed(), WAIT);
        // The answer to the request that gave up: dropped, nothing panics.
        assert!(!slots.answer(0, 1, 5));
        // The next request waits for its own ticket only.
        let reply = slots.expect(0, 2);
        assert!(!slots.answer(0, 1, 5));
        assert!(slots.answer(0, 2, 6));
        assert_eq!(reply.within(WAIT).await, Some(6));
    }

    #[tokio::test(start_paused = true)]
    async fn an_answer_that_comes_after_the_timeout_but_before_the_next_request_is_dropped() {
        let slots = ReplySlots::<u8>::new(1);
        let reply = slots.expect(0, 3);
        assert_eq!(reply.within(WAIT).await, None);
        // The receiver is gone; the sender was still filed: the send fails, harmlessly.
        assert!(!slots.answer(0, 3, 9));
    }

    #[tokio::test(start_paused = true)]
    async fn a_newer_request_of_the_same_key_closes_the_older_one_path() {
        let slots = ReplySlots::<u8>::new(1);
        let old = slots.expect(0, 1);
        let new = slots.expect(0, 2);
        let start = tokio::time::Instant::now();
        assert_eq!(old.within(WAIT).await, None);
        assert_eq!(start.elapsed(), Duration::ZERO);
        assert!(slots.answer(0, 2, 1));
        assert_eq!(new.within(WAIT).await, Some(1));
        // A key that does not exist: no answer, no panic.
        assert!(!slots.answer(5, 1, 1));
        assert_eq!(slots.expect(5, 1).within(WAIT).await, None);
    }

    #[test]
    fn tickets_differ() {
        let t = Tickets::default();
        assert_ne!(t.next(), t.next());
    }

    fn progress(cycles: u32) -> AutotuneReport {
        AutotuneReport::Progress(Progress {
            phase: Phase::Relay,
            cycles,
            amplitude_c: 1.0,
            period_s: 10.0,
            dead_time: None,
        })
    }

    #[tokio::test(start_paused = true)]
    async fn a_filed_report_wakes_the_action_without_any_time_passing() {
        let m = std::sync::Arc::new(Mailbox::new(2));
        let start = tokio::time::Instant::now();
        let filing = std::sync::Arc::clone(&m);
        let waiting = tokio::spawn(async move {
            filing.filed(1).await;
            filing.take(1, 4)
        });
        tokio::task::yield_now().await;
        let report_thread = {
            let m = std::sync::Arc::clone(&m);
            std::thread::spawn(move || m.file(1, 4, AutotuneReport::Started))
        };
        report_thread.join().unwrap();
        assert_eq!(waiting.await.unwrap(), vec![AutotuneReport::Started]);
        assert_eq!(start.elapsed(), Duration::ZERO);
        // A report filed before the action waits is not lost either.
        m.file(0, 4, progress(1));
        tokio::time::timeout(WAIT, m.filed(0))
            .await
            .expect("the wake-up was kept");
        assert_eq!(start.elapsed(), Duration::ZERO);
    }

    #[test]
    fn the_mailbox_is_bounded_and_keeps_a_run_end() {
        let m = Mailbox::new(1);
        m.file(0, 1, AutotuneReport::Started);
        for c in 0..(AUTOTUNE_REPORTS as u32 + 10) {
            m.file(0, 1, progress(c));
        }
        m.file(0, 2, progress(0));
        let taken = m.take(0, 1);
        assert_eq!(taken.len(), AUTOTUNE_REPORTS - 1);
        // The oldest progress reports went; the start stayed.
        assert_eq!(taken[0], AutotuneReport::Started);
        assert_eq!(taken.last(), Some(&progress(AUTOTUNE_REPORTS as u32 + 9)));
        // Reports of another ticket are dropped with the take.
        assert!(m.take(0, 2).is_empty());
    }
}
