//! What the node tells its service manager, over systemd's `sd_notify` protocol (through the
//! `sd-notify` crate): `READY=1` once the lines are requested, the output thread runs and the
//! ROS side is up, and `STOPPING=1` when it begins to stop. With `Type=notify` systemd counts
//! the unit as started only on `READY=1`, so units ordered after it start once the outputs are
//! really under control.
//!
//! Without `NOTIFY_SOCKET` in the environment (not started by systemd with `Type=notify`) each
//! call does nothing. A failure to notify is logged and never stops the node. `WATCHDOG=1` is
//! not sent: the output thread reports no liveness yet, so `WatchdogSec=` must stay unset.

use sd_notify::NotifyState;

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
