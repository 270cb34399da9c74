//! The safety inputs' own path to the output thread: the e-stop, the hold of a managed node's
//! inactive states (and of shutdown), and the node-level planner's limits. They never travel
//! through the request queue, so a queue filled by commands cannot lose or delay them.
//!
//! Each is a latest-value slot of atomics: the ROS side stores the value and bumps a request
//! counter; the output thread reads the slot at every wake-up, before any queued request, applies
//! what changed, writes the lines, and only then stores the counter it has taken and signals the
//! acknowledgment eventfd (once per wake-up that took one). A caller that must not report a
//! safety action as done before the lines have it waits for that acknowledgment
//! ([`SafetyPath::take_async`](super::SafetyPath::take_async), or
//! [`SafetyPath::take`](super::SafetyPath::take) on a plain thread).
//!
//! The e-stop is an epoch, odd while latched: a latch and a reset that both happen before the
//! thread looks are still applied as a latch followed by a reset (every channel disabled),
//! never lost.

use crate::core::{Bank, Phase};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// The shared slot (see the module documentation).
#[derive(Debug)]
pub struct SafetySlot {
    /// E-stop epoch: odd while latched.
    estop: AtomicU64,
    /// Lines follow their channels (a managed node's ACTIVE state).
    live: AtomicBool,
    /// The planner: bit 0 = stagger, the rest = `max_simultaneous_on`.
    bank: AtomicU64,
    /// Bumped after every store.
    requested: AtomicU64,
    /// The last request counter the output thread has applied and written to the lines.
    taken: AtomicU64,
}

/// What the output thread has to apply from the slot.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Wanted {
    pub(crate) estop_epoch: u64,
    pub(crate) live: bool,
    pub(crate) bank: Bank,
    pub(crate) request: u64,
}

fn encode(bank: Bank) -> u64 {
    ((bank.max_on as u64) << 1) | u64::from(bank.phase == Phase::Stagger)
}

fn decode(v: u64) -> Bank {
    Bank {
        phase: if v & 1 == 1 {
            Phase::Stagger
        } else {
            Phase::Sync
        },
        max_on: usize::try_from(v >> 1).unwrap_or(usize::MAX),
    }
}

impl SafetySlot {
    /// A slot holding the start-up values: e-stop released, `live`, `bank`.
    pub(crate) fn new(live: bool, bank: Bank) -> SafetySlot {
        SafetySlot {
            estop: AtomicU64::new(0),
            live: AtomicBool::new(live),
            bank: AtomicU64::new(encode(bank)),
            requested: AtomicU64::new(0),
            taken: AtomicU64::new(0),
        }
    }

    fn bump(&self) -> u64 {
        self.requested.fetch_add(1, Ordering::AcqRel) + 1
    }

    /// Latches (`true`) or releases (`false`) the e-stop; returns the request number.
    pub(crate) fn estop(&self, latched: bool) -> u64 {
        let _ = self
            .estop
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |e| {
                (e % 2 == 1 && !latched || e % 2 == 0 && latched).then_some(e + 1)
            });
        self.bump()
    }

    /// Lets the lines follow their channels or holds them inactive; returns the request number.
    pub(crate) fn live(&self, live: bool) -> u64 {
        self.live.store(live, Ordering::Release);
        self.bump()
    }

    /// Sets the planner; returns the request number.
    pub(crate) fn bank(&self, bank: Bank) -> u64 {
        self.bank.store(encode(bank), Ordering::Release);
        self.bump()
    }

    /// What the slot holds now, with the request counter read before the values (so the values
    /// are at least as new as the counter).
    pub(crate) fn wanted(&self) -> Wanted {
        let request = self.requested.load(Ordering::Acquire);
        Wanted {
            estop_epoch: self.estop.load(Ordering::Acquire),
            live: self.live.load(Ordering::Acquire),
            bank: decode(self.bank.load(Ordering::Acquire)),
            request,
        }
    }

    /// Whether the e-stop is latched in the slot (by the ROS side, or by the output thread for
    /// a heater fault under `heater_fault_latches_estop`).
    pub(crate) fn estop_latched(&self) -> bool {
        self.estop.load(Ordering::Acquire) % 2 == 1
    }

    /// The counter of the requests made so far.
    pub(crate) fn requested(&self) -> u64 {
        self.requested.load(Ordering::Acquire)
    }

    /// The output thread has applied request `request` and written the lines.
    pub(crate) fn mark_taken(&self, request: u64) {
        self.taken.fetch_max(request, Ordering::AcqRel);
    }

    /// Whether request `request` has been applied and its lines written.
    pub fn taken(&self, request: u64) -> bool {
        self.taken.load(Ordering::Acquire) >= request
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_estop_epoch_is_odd_while_latched_and_repeats_change_nothing() {
        let s = SafetySlot::new(true, Bank::default());
        s.estop(true);
        s.estop(true);
        assert_eq!(s.wanted().estop_epoch, 1);
        s.estop(false);
        s.estop(false);
        assert_eq!(s.wanted().estop_epoch, 2);
        s.estop(true);
        assert_eq!(s.wanted().estop_epoch, 3);
        assert_eq!(s.wanted().request, 5);
    }

    #[test]
    fn the_bank_round_trips() {
        for bank in [
            Bank::default(),
            Bank {
                phase: Phase::Stagger,
                max_on: 7,
            },
            Bank {
                phase: Phase::Sync,
                max_on: 99,
            },
        ] {
            assert_eq!(decode(encode(bank)), bank);
        }
    }

    #[test]
    fn taken_only_once_marked() {
        let s = SafetySlot::new(true, Bank::default());
        let r = s.live(false);
        assert!(!s.taken(r));
        s.mark_taken(r);
        assert!(s.taken(r));
        assert!(!s.taken(s.live(true)));
    }
}
