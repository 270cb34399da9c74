//! What the node tells its service manager, over systemd's `sd_notify` protocol (through the
//! `sd-notify` crate): `READY=1` once the lines are requested, the output thread runs and the
//! ROS side is up, `STOPPING=1` when it begins to stop, and, when the unit sets `WatchdogSec=`,
//! `WATCHDOG=1` at half that interval while the output thread keeps its schedule. With
//! `Type=notify` systemd counts the unit as started only on `READY=1`, so units ordered after it
//! start once the outputs are really under control; with `WatchdogSec=` a hung or starved
//! output thread gets the process killed, and `ExecStopPost=` (safe-off) switches the lines off.
//!
//! Without `NOTIFY_SOCKET` in the environment (not started by systemd with `Type=notify`) each
//! call does nothing. A failure to notify is logged and never stops the node.

use crate::clock;
use crate::output_thread::Liveness;
use sd_notify::NotifyState;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

/// Sends `READY=1`. Returns whether a message was sent (`false` without `NOTIFY_SOCKET` or on
/// an error, which is logged as a warning).
pub fn ready() -> bool {
    send(NotifyState::Ready, "READY=1")
}

/// Sends `STOPPING=1`; as [`ready`].
pub fn stopping() -> bool {
    send(NotifyState::Stopping, "STOPPING=1")
}

fn send(state: NotifyState, what: &str) -> bool {
    if std::env::var_os("NOTIFY_SOCKET").is_none() {
        return false;
    }
    match sd_notify::notify(false, &[state]) {
        Ok(()) => true,
        Err(e) => {
            log::warn!("cannot tell the service manager {what}: {e}");
            false
        }
    }
}

/// The watchdog interval the service manager asks for (`WatchdogSec=`, passed as
/// `WATCHDOG_USEC`), if any, read as libsystemd's `sd_watchdog_enabled` reads it: a
/// `WATCHDOG_PID` naming another process means the watchdog is not ours; without one it is.
/// (The sd-notify crate's `watchdog_enabled` also demands `WATCHDOG_PID`.)
pub fn watchdog_interval() -> Option<Duration> {
    std::env::var_os("NOTIFY_SOCKET")?;
    watchdog_interval_from(
        std::env::var("WATCHDOG_USEC").ok().as_deref(),
        std::env::var("WATCHDOG_PID").ok().as_deref(),
        std::process::id(),
    )
}

/// [`watchdog_interval`] from the two variables' values and this process's id.
pub fn watchdog_interval_from(usec: Option<&str>, pid: Option<&str>, me: u32) -> Option<Duration> {
    let usec: u64 = usec?.trim().parse().ok()?;
    if pid.is_some_and(|p| p.trim().parse::<u32>().ok() != Some(me)) {
        return None;
    }
    (usec > 0).then(|| Duration::from_micros(usec))
}

/// Whether the output thread counts as alive for the watchdog: running, and at most `grace`
/// behind the wake-up it promised.
pub fn keeps_schedule(lag_ns: Option<u64>, grace: Duration) -> bool {
    lag_ns.is_some_and(|lag| lag <= grace.as_nanos() as u64)
}

/// The thread that sends `WATCHDOG=1` every `interval / 2` while the output thread keeps its
/// schedule (within `interval / 2`), until `stop` is set. A hung output thread thus goes
/// unreported and systemd acts at most 1.5 x `interval` after the hang began.
pub struct WatchdogPinger {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl WatchdogPinger {
    /// Starts pinging for `liveness` at `interval / 2`.
    pub fn start(liveness: Liveness, interval: Duration) -> std::io::Result<WatchdogPinger> {
        let stop = Arc::new(AtomicBool::new(false));
        let half = interval / 2;
        log::info!(
            "systemd watchdog: WATCHDOG=1 every {} ms while the output thread keeps its schedule",
            half.as_millis()
        );
        let thread = {
            let stop = Arc::clone(&stop);
            std::thread::Builder::new()
                .name("pwm-watchdog".into())
                .spawn(move || {
                    let mut reported = false;
                    while !stop.load(Ordering::Acquire) {
                        let lag = liveness.lag_ns(clock::monotonic_ns());
                        if keeps_schedule(lag, half) {
                            reported = false;
                            send(NotifyState::Watchdog, "WATCHDOG=1");
                        } else if !reported {
                            reported = true;
                            log::error!(
                                "output thread {}: not telling the service manager it is alive",
                                match lag {
                                    Some(l) => format!("{} ms behind its schedule", l / 1_000_000),
                                    None => "stopped".into(),
                                }
                            );
                        }
                        // Short sleeps, so a stop is seen quickly.
                        let until = std::time::Instant::now() + half;
                        while !stop.load(Ordering::Acquire) && std::time::Instant::now() < until {
                            std::thread::sleep(half.min(Duration::from_millis(50)));
                        }
                    }
                })?
        };
        Ok(WatchdogPinger {
            stop,
            thread: Some(thread),
        })
    }
}

impl Drop for WatchdogPinger {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_watchdog_interval_is_read_as_libsystemd_reads_it() {
        let d = Some(Duration::from_millis(400));
        assert_eq!(watchdog_interval_from(Some("400000"), None, 7), d);
        assert_eq!(watchdog_interval_from(Some("400000"), Some("7"), 7), d);
        assert_eq!(watchdog_interval_from(Some("400000"), Some("8"), 7), None);
        assert_eq!(watchdog_interval_from(Some("400000"), Some("x"), 7), None);
        assert_eq!(watchdog_interval_from(Some("0"), None, 7), None);
        assert_eq!(watchdog_interval_from(Some("soon"), None, 7), None);
        assert_eq!(watchdog_interval_from(None, Some("7"), 7), None);
    }

    #[test]
    fn alive_means_running_and_not_behind_by_more_than_the_grace() {
        let grace = Duration::from_millis(500);
        assert!(keeps_schedule(Some(0), grace));
        assert!(keeps_schedule(Some(500_000_000), grace));
        assert!(!keeps_schedule(Some(500_000_001), grace));
        assert!(
            !keeps_schedule(None, grace),
            "a stopped thread is not alive"
        );
    }
}
