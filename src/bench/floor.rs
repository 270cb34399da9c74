//! The benchmark's floor: a bare timerfd loop that wakes at the very deadlines the output thread
//! was given in the same run and does nothing else, on the same thread set-up (priority, timer
//! slack, mlockall) because it is started with `output_thread::spawn_with` too. Its lateness is
//! measured when the timer's wake-up has been read, so it is what any user-space timer thread
//! reaches on this kernel and machine; the output thread cannot do better than that.
//!
//! Benchmark only.

use nix::sys::timerfd::TimerFd;
use pwm_actuator::clock;
use pwm_actuator::core::{ChannelConfig, Nanos};
use pwm_actuator::output::Output;
use pwm_actuator::output_thread::{
    self, OutputThreadError, OutputThreadHandle, OutputThreadOptions, ThreadLoop,
};
use std::sync::mpsc;

/// A running floor loop.
pub struct Floor {
    /// Stops the thread (after its last deadline, or early).
    pub handle: OutputThreadHandle,
    /// The lateness of every deadline, ns, in order; sent once the thread stops.
    pub lateness: mpsc::Receiver<Vec<i64>>,
}

/// Starts a thread that sleeps until each of `deadlines` (monotonic ns, ascending) and records
/// how late it woke, once per entry; every deadline already due at a wake-up is taken by it.
/// `configs` and `output` only give the thread its usual set-up: no channel is ever enabled,
/// no request sent, no edge written.
pub fn spawn<O: Output>(
    configs: Vec<ChannelConfig>,
    output: O,
    opts: OutputThreadOptions,
    deadlines: Vec<Nanos>,
) -> Result<Floor, OutputThreadError> {
    let timer = output_thread::monotonic_timer()?;
    let (tx, rx) = mpsc::channel();
    let started = output_thread::spawn_with(configs, output, opts, move |thread| {
        // Allocated before the first deadline, as the output thread's buffers are.
        let mut lateness = Vec::with_capacity(deadlines.len());
        let result = sleep_until_each(thread, &timer, &deadlines, &mut lateness);
        let _ = tx.send(lateness);
        result
    })?;
    Ok(Floor {
        handle: started.handle,
        lateness: rx,
    })
}

/// The loop: the same syscalls per wake-up as the output thread's loop (its
/// [`ThreadLoop::sleep_on`]: arm the timer with an absolute deadline, poll it beside the
/// request eventfd, clear a request wake-up), then one clock read.
/// A deadline not yet due when the timer is armed cannot be taken early: the timer is
/// absolute.
/// After the last deadline it only waits for the stop.
fn sleep_until_each<O: Output>(
    thread: &mut ThreadLoop<O>,
    timer: &TimerFd,
    deadlines: &[Nanos],
    lateness: &mut Vec<i64>,
) -> Result<(), OutputThreadError> {
    let mut next = 0;
    while !thread.stop_requested() {
        if thread.sleep_on(timer, deadlines.get(next).copied())? {
            let now = clock::monotonic_ns();
            // Every deadline that is due is taken at this wake-up, as the output thread writes
            // every due edge in one go; re-arming for a deadline already past would cost the
            // floor syscalls ours does not make.
            while let Some(&t) = deadlines.get(next).filter(|t| **t <= now) {
                lateness.push(now as i64 - t as i64);
                next += 1;
            }
        }
    }
    Ok(())
}
