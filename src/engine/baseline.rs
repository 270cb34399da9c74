//! The benchmark's baseline: the same per-wake-up work as the output thread, scheduled by
//! tokio's `sleep_until` on a current-thread runtime, as an async node would naturally do it.
//! tokio's timer wheel has millisecond resolution, which is why the node does not use it for
//! edges; this module exists so that claim is measured, not asserted.

use super::thread::{spawn_with, Driver, Ends};
use super::worker::Worker;
use super::{Engine, EngineError, EngineOptions};
use crate::clock;
use crate::core::{ChannelConfig, Nanos};
use crate::output::Output;
use std::os::fd::AsFd;
use std::time::Duration;
use tokio::io::unix::AsyncFd;
use tokio::io::Interest;

/// Starts an output thread that sleeps with tokio's `sleep_until` instead of a timerfd.
/// For comparison only (`pwm_actuator_node bench`); the node always uses [`super::spawn`].
pub fn spawn_tokio_baseline<O: Output>(
    configs: Vec<ChannelConfig>,
    output: O,
    opts: EngineOptions,
) -> Result<Engine, EngineError> {
    spawn_with(configs, output, opts, Driver::TokioSleep)
}

pub(crate) fn run<O: Output>(mut worker: Worker<O>, mut ends: Ends<'_>) -> Result<(), EngineError> {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(EngineError::Spawn)?;
    let result = rt.block_on(async {
        // tokio watches a duplicate of the request eventfd that it owns outright.
        let dup = ends
            .req_wake
            .as_fd()
            .try_clone_to_owned()
            .map_err(EngineError::Spawn)?;
        // SAFETY: `dup` is an open descriptor owned by the AsyncFd for its whole lifetime.
        let wake = unsafe { AsyncFd::register_with_interest(dup, Interest::READABLE) }
            .map_err(|e| EngineError::Spawn(e.into()))?;
        // Map monotonic ns onto tokio's clock (also CLOCK_MONOTONIC underneath).
        let base = tokio::time::Instant::now();
        let base_ns = clock::monotonic_ns();
        let at = |t: Nanos| base + Duration::from_nanos(t.saturating_sub(base_ns));
        while ends.work(&mut worker)? {
            let deadline = worker.next_deadline();
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
                    let _ = ends.req_wake.read();
                }
            }
        }
        Ok(())
    });
    let finish = ends.finish(worker);
    result.and(finish)
}
