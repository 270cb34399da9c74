//! The benchmark's baseline: the output thread's very same per-wake-up work, put to sleep by
//! tokio's `sleep_until` on a current-thread runtime, as an async node would naturally do it.
//! tokio's timer wheel has millisecond resolution, which is why the node does not use it for
//! edges; this module exists so that claim is measured, not asserted.
//!
//! Benchmark only: the node always starts its output thread with `output_thread::spawn`.

use pwm_actuator::clock;
use pwm_actuator::core::{ChannelConfig, Nanos};
use pwm_actuator::output::Output;
use pwm_actuator::output_thread::{
    self, OutputThread, OutputThreadError, OutputThreadOptions, ThreadLoop,
};
use std::os::fd::AsFd;
use std::time::Duration;
use tokio::io::unix::AsyncFd;
use tokio::io::Interest;

/// Starts an output thread that sleeps with tokio's `sleep_until` instead of a timerfd.
pub fn spawn<O: Output>(
    configs: Vec<ChannelConfig>,
    output: O,
    opts: OutputThreadOptions,
) -> Result<OutputThread, OutputThreadError> {
    output_thread::spawn_with(configs, output, opts, sleep_with_tokio)
}

/// The loop: `sleep_until` the next deadline, or until the request eventfd is readable.
fn sleep_with_tokio<O: Output>(thread: &mut ThreadLoop<O>) -> Result<(), OutputThreadError> {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(OutputThreadError::Spawn)?;
    rt.block_on(async {
        // tokio watches a duplicate of the request eventfd that it owns outright.
        let dup = thread
            .request_wake_fd()
            .as_fd()
            .try_clone_to_owned()
            .map_err(OutputThreadError::Spawn)?;
        // SAFETY: `dup` is an open descriptor owned by the AsyncFd for its whole lifetime.
        let wake = unsafe { AsyncFd::register_with_interest(dup, Interest::READABLE) }
            .map_err(|e| OutputThreadError::Spawn(e.into()))?;
        // Map monotonic ns onto tokio's clock (also CLOCK_MONOTONIC underneath).
        let base = tokio::time::Instant::now();
        let base_ns = clock::monotonic_ns();
        let at = |t: Nanos| base + Duration::from_nanos(t.saturating_sub(base_ns));
        while thread.work()? {
            let deadline = thread.next_deadline();
            tokio::select! {
                _ = async {
                    match deadline {
                        Some(t) => tokio::time::sleep_until(at(t)).await,
                        None => std::future::pending().await,
                    }
                } => {}
                guard = wake.readable() => {
                    if let Ok(mut g) = guard {
                        g.clear_ready();
                    }
                    thread.clear_request_wake();
                }
            }
        }
        Ok(())
    })
}
