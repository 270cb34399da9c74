//! GPIO lines requested later than the output is built: a managed node requests its lines on
//! `configure` and releases them on `cleanup`, while its output thread runs from start-up.
//!
//! [`SlotOutput`] is the output the thread writes to; it holds the [`GpioOutput`] while the
//! lines are requested and writes nowhere while they are not. [`LineSlot`] is the other end,
//! used by the lifecycle transitions: [`LineSlot::attach`] requests the lines (as outputs,
//! inactive), [`LineSlot::detach`] drives them inactive and releases them. The thread takes
//! the slot's mutex for each write; the transitions take it only while they request or release
//! the lines, so it is contended only then. The caller holds every line inactive
//! ([`crate::core::Channel::set_live`]) whenever the lines are not requested, so no write is
//! lost that mattered.

use super::gpio::{ChipPlan, GpioError, GpioOutput};
use super::panic_off::{lock_bounded, lock_ignore_poison as lock, EMERGENCY_LOCK_BUDGET};
use super::{EmergencyOff, LineChange, Output};
use std::sync::{Arc, Mutex};

struct Shared {
    out: Mutex<Option<GpioOutput>>,
    /// The emergency handle of the requested lines, kept apart so the panic hook never waits
    /// on a write.
    emergency: Mutex<Option<Arc<dyn EmergencyOff>>>,
    plans: Vec<ChipPlan>,
    count: usize,
}

/// The output side of a slot (see the module documentation).
pub struct SlotOutput(Arc<Shared>);

/// The lifecycle side of a slot: requests and releases the lines.
#[derive(Clone)]
pub struct LineSlot(Arc<Shared>);

/// An empty slot for the `count` lines planned in `plans` ([`plan_requests`](super::gpio::plan_requests), which checks
/// that no line is bound twice), and its two ends. Nothing is requested yet.
pub fn slot(plans: Vec<ChipPlan>, count: usize) -> (SlotOutput, LineSlot) {
    let shared = Arc::new(Shared {
        out: Mutex::new(None),
        emergency: Mutex::new(None),
        plans,
        count,
    });
    (SlotOutput(Arc::clone(&shared)), LineSlot(shared))
}

impl LineSlot {
    /// Requests the lines (outputs, inactive, with their polarity); does nothing when they
    /// are requested already. A missing chip or a busy line is an error naming it, and
    /// nothing stays requested.
    pub fn attach(&self) -> Result<(), GpioError> {
        let mut out = lock(&self.0.out);
        if out.is_none() {
            let gpio = GpioOutput::open_planned(&self.0.plans, self.0.count)?;
            *lock(&self.0.emergency) = Some(gpio.emergency_off());
            *out = Some(gpio);
        }
        Ok(())
    }

    /// Drives the lines inactive and releases them; does nothing when none are requested.
    pub fn detach(&self) {
        let gpio = lock(&self.0.out).take();
        *lock(&self.0.emergency) = None;
        // Dropping the output drives every line inactive before the request is released.
        drop(gpio);
    }

    /// Whether the lines are requested.
    pub fn attached(&self) -> bool {
        lock(&self.0.out).is_some()
    }
}

impl Output for SlotOutput {
    type Error = GpioError;

    fn line_count(&self) -> usize {
        self.0.count
    }

    fn set_levels(&mut self, changes: &[LineChange]) -> Result<(), GpioError> {
        match lock(&self.0.out).as_mut() {
            Some(gpio) => gpio.set_levels(changes),
            None => Ok(()),
        }
    }

    fn set_all_inactive(&mut self) -> Result<(), GpioError> {
        match lock(&self.0.out).as_mut() {
            Some(gpio) => gpio.set_all_inactive(),
            None => Ok(()),
        }
    }

    fn emergency_off(&self) -> Arc<dyn EmergencyOff> {
        Arc::new(SlotEmergencyOff(Arc::clone(&self.0)))
    }
}

struct SlotEmergencyOff(Arc<Shared>);

impl EmergencyOff for SlotEmergencyOff {
    fn all_inactive(&self) {
        let handle = lock_bounded(&self.0.emergency, EMERGENCY_LOCK_BUDGET).and_then(|h| h.clone());
        if let Some(h) = handle {
            h.all_inactive();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::gpio::{plan_requests, GpioLine};

    #[test]
    fn an_empty_slot_writes_nowhere_and_refuses_a_missing_chip_on_attach() {
        let lines = [GpioLine {
            name: "pw01".into(),
            chip: "/dev/gpiochip-slot-none".into(),
            offset: 2,
            active_low: false,
        }];
        let (mut out, lines) = slot(plan_requests(&lines).unwrap(), lines.len());
        assert_eq!(out.line_count(), 1);
        let on = [LineChange {
            line: 0,
            level: crate::core::Level::High,
            scheduled_ns: 0,
        }];
        assert!(out.set_levels(&on).is_ok(), "no lines: nothing to write");
        out.emergency_off().all_inactive();
        assert!(matches!(
            lines.attach(),
            Err(GpioError::ChipNotFound { .. })
        ));
        assert!(!lines.attached());
        lines.detach();
    }
}
