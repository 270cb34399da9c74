//! The two clocks the node reads: CLOCK_MONOTONIC for all timing, CLOCK_REALTIME only to stamp
//! ROS messages. Both are vDSO calls on Linux: no syscall, no allocation.

use crate::core::Nanos;
use nix::time::{clock_gettime, ClockId};

/// Monotonic time in ns (CLOCK_MONOTONIC), the time base of every deadline.
pub fn monotonic_ns() -> Nanos {
    // CLOCK_MONOTONIC cannot fail on Linux; 0 would only ever show up as a huge lateness.
    clock_gettime(ClockId::CLOCK_MONOTONIC)
        .map(|t| t.tv_sec() as Nanos * 1_000_000_000 + t.tv_nsec() as Nanos)
        .unwrap_or(0)
}

/// Wall-clock time in ns since the Unix epoch (CLOCK_REALTIME), for message stamps.
pub fn wall_ns() -> i64 {
    clock_gettime(ClockId::CLOCK_REALTIME)
        .map(|t| t.tv_sec() * 1_000_000_000 + t.tv_nsec())
        .unwrap_or(0)
}
