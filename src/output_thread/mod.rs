//! The output thread: the only place where time is read and outputs are written.
//!
//! Requests arrive from the ROS side through a wait-free ring buffer and an eventfd wake-up;
//! the safety inputs (e-stop, the hold of the lines, the planner's limits) through a
//! latest-value slot read at every wake-up before the queue ([`safety`]), so a full queue
//! cannot lose or delay them;
//! the thread sleeps on a timerfd armed with absolute CLOCK_MONOTONIC deadlines, polls the
//! channel cores, writes edges to the [`Output`](crate::output::Output) and sends reports back
//! through a second ring buffer that never blocks it (a full buffer drops and counts).

use crate::core::valve::{Dir, ValveStart};
use crate::core::{Bank, ChannelConfig, Command, Event, Level, Nanos, Status};
use crate::core::{ValveConfig, ValveStatus};

/// An input for one channel.
#[derive(Debug, Clone, Copy, PartialEq)]
// Inputs travel by value through the wait-free ring buffer: boxing the configuration would
// allocate on the ROS side and free on the output thread.
#[allow(clippy::large_enum_variant)]
pub enum Input {
    /// A duty command (percent, SV or fraction).
    Command(Command),
    /// EN.
    Enable(bool),
    /// A validated configuration.
    Config(ChannelConfig),
    /// Pairs the channel with another for split range (001): from then on the two lines are
    /// never high together. Sent once at start-up; a channel already paired ignores it.
    Pair(usize),
    /// Latches (`true`) or releases (`false`) the emergency stop of every channel at once
    /// (see [`Channel::set_estop`](crate::core::Channel::set_estop)); the request's channel is
    /// ignored. While latched the heartbeat line stops toggling and rests inactive.
    EStop(bool),
    /// Lets every line follow its channel (`true`) or holds every line inactive (`false`), as
    /// a managed node's ACTIVE state and the others (see
    /// [`Channel::set_live`](crate::core::Channel::set_live)); the request's channel is
    /// ignored. While held the heartbeat line rests inactive.
    Live(bool),
    /// Sets the node-level planner: `phase` and `max_simultaneous_on` (see
    /// [`Bank`]); the request's channel is ignored. Takes effect at each
    /// channel's next period start.
    Bank(Bank),
    /// A temperature reading of the channel's feedback, °C (any value: NaN and infinities
    /// latch `temperature_out_of_range`); it counts as arriving when the thread takes it.
    /// `age`: how long after its stamp it arrived, ns (negative: stamped in the future;
    /// `None`: unstamped), see
    /// [`Channel::feedback_stamped`](crate::core::Channel::feedback_stamped).
    Feedback {
        /// The reading, °C.
        celsius: f64,
        /// Arrival less stamp, ns.
        age: Option<i64>,
    },
    /// A setpoint for the channel's loop, °C (see
    /// [`Channel::set_setpoint`](crate::core::Channel::set_setpoint)).
    Setpoint(f64),
    /// A feed-forward for the channel's loop: a known disturbance in % of the heater's full
    /// power (see [`Channel::feedforward`](crate::core::Channel::feedforward)).
    Feedforward(f64),
    /// An ambient reading for the channel's model, °C; `age` as for `Feedback` (see
    /// [`Channel::ambient_reading`](crate::core::Channel::ambient_reading)).
    Ambient {
        /// The reading, °C.
        celsius: f64,
        /// Arrival less stamp, ns.
        age: Option<i64>,
    },
    /// Clears the channel's heater fault if its condition is gone; the answer comes back as
    /// the core's `FaultReset` event with this ticket.
    ResetFault(u32),
    /// Starts an autotune of the channel; the answers come back as the core's `Autotune`
    /// events with this ticket (see
    /// [`Channel::start_autotune`](crate::core::Channel::start_autotune)).
    Autotune {
        /// The caller's number for the run.
        ticket: u32,
        /// What is asked.
        goal: crate::core::heater::autotune::Goal,
        /// The latest instant the run may start, monotonic ns: a goal the thread takes later
        /// is dropped unanswered (its caller has given up on it by then), so no run starts
        /// longer than the caller allowed after its goal was sent.
        start_by: Nanos,
    },
    /// Cancels the channel's autotune with this ticket.
    AutotuneCancel(u32),
    /// Whether a heater fault of any channel latches the e-stop of every channel
    /// (`heater_fault_latches_estop`); the request's channel is ignored. Sent at start-up.
    HeaterEstop(bool),
    /// Makes a three-point valve of the request's channel (its opening line) and channel
    /// `close` (its closing line); valves are numbered 0, 1, ... in the order made. Sent once
    /// at start-up; a channel already in a valve or a split-range pair refuses it. The two
    /// channels then follow only the valve: their own inputs are ignored.
    AddValve {
        /// The closing line's channel.
        close: usize,
        /// The valve's settings.
        config: ValveConfig,
        /// What it starts with: a restored position, its end switches, a feedback.
        start: ValveStart,
    },
    /// A position command for valve `valve`, percent (0 = closed); the request's channel is
    /// ignored.
    ValvePosition {
        /// Valve index.
        valve: usize,
        /// Target, percent.
        pct: f64,
    },
    /// A setpoint for valve `valve`'s loop, in the process's unit; the request's channel is
    /// ignored.
    ValveSetpoint {
        /// Valve index.
        valve: usize,
        /// The setpoint.
        value: f64,
    },
    /// A process value reading for valve `valve`'s loop; the request's channel is ignored.
    ValveProcess {
        /// Valve index.
        valve: usize,
        /// The reading, in the process's unit.
        value: f64,
        /// How long after its stamp it arrived, ns; `None` when unstamped.
        age: Option<i64>,
    },
    /// A manual command for valve `valve`; the request's channel is ignored.
    ValveManual {
        /// Valve index.
        valve: usize,
        /// Open, close, stop, a position or auto; or the word that is none of them, to be
        /// counted with the valve's refusals.
        manual: Result<crate::core::valve::Manual, crate::core::valve::BadManual>,
    },
    /// New settings for valve `valve`; the request's channel is ignored.
    ValveConfig {
        /// Valve index.
        valve: usize,
        /// The settings.
        config: ValveConfig,
    },
    /// A position feedback sample of valve `valve`, percent; it counts as arriving when the
    /// thread takes it.
    ValveFeedback {
        /// Valve index.
        valve: usize,
        /// The feedback, percent.
        pct: f64,
    },
    /// Clears the latched fault of valve `valve` if its cause is gone; the answer comes back
    /// in the valve's next snapshot with this ticket.
    ValveReset {
        /// Valve index.
        valve: usize,
        /// The caller's number for the reset.
        ticket: u32,
    },
    /// The end switch of direction `dir` of valve `valve` became `active`.
    ValveSwitch {
        /// Valve index.
        valve: usize,
        /// Which end.
        dir: Dir,
        /// Whether it is active.
        active: bool,
    },
}

/// An input addressed to a channel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Request {
    /// Channel index, 0 = pw01.
    pub channel: usize,
    /// What to do.
    pub input: Input,
}

/// One edge as it reached the line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EdgeReport {
    /// Channel index, 0 = pw01.
    pub channel: usize,
    /// The new logical level.
    pub level: Level,
    /// Per-channel sequence number, from 1.
    pub seq: u64,
    /// When the core scheduled the edge, monotonic ns.
    pub scheduled_ns: Nanos,
    /// When the write returned, monotonic ns.
    pub actual_ns: Nanos,
    /// When the write returned, wall-clock ns since the Unix epoch.
    pub wall_ns: i64,
}

impl EdgeReport {
    /// Actual minus scheduled time, ns (negative: early).
    pub fn lateness_ns(&self) -> i64 {
        self.actual_ns as i64 - self.scheduled_ns as i64
    }
}

/// What the output thread reports.
#[derive(Debug, Clone, Copy, PartialEq)]
// Reports travel by value through the wait-free ring buffer: boxing a status (the heater's
// figures made it the large variant) would allocate on the output thread.
#[allow(clippy::large_enum_variant)]
pub enum Report {
    /// An edge was written.
    Edge(EdgeReport),
    /// A core event other than an edge (flags, plan, watchdog, rejection, clamp, missed).
    Core {
        /// Channel index.
        channel: usize,
        /// The event.
        event: Event,
    },
    /// A status snapshot, taken at monotonic time `at_ns`, after anything changed.
    Status {
        /// Channel index.
        channel: usize,
        /// The snapshot.
        status: Status,
        /// Monotonic ns at which it was taken.
        at_ns: Nanos,
    },
    /// A valve's snapshot, taken at monotonic time `at_ns`, after anything changed.
    Valve {
        /// Valve index.
        valve: usize,
        /// The snapshot.
        status: ValveStatus,
        /// Monotonic ns at which it was taken.
        at_ns: Nanos,
    },
    /// Writing to the output failed: every other line was driven inactive and the thread
    /// stopped.
    OutputFault {
        /// Channel index whose write failed.
        channel: usize,
    },
}

mod deadlines;
pub mod safety;
mod thread;
pub(crate) mod worker;

#[cfg(test)]
mod tests;

pub use thread::{
    monotonic_timer, spawn, spawn_with, Acknowledgment, Liveness, NotTaken, OutputThread,
    OutputThreadError, OutputThreadHandle, OutputThreadOptions, ReportWaker, Reports, Requests,
    SafetyPath, ThreadLoop, WriteFault, LIVENESS_TICK_NS, SAFETY_TAKE_BOUND, SHUTDOWN_WAIT,
};
