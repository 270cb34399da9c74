//! The ROS messages the node exchanges, as serde structs laid out field for field like their
//! `.msg` definitions (CDR encodes fields in declaration order, so the order is the contract).
//!
//! `pwm_actuator_msgs/*` mirror `msg/*.msg` of this repository (checked by
//! `tests/integration/ros_msgs.rs`); the others mirror `std_msgs`, `diagnostic_msgs` and
//! `builtin_interfaces` of ROS 2 Jazzy. No logic lives here.

use ros2_client::builtin_interfaces::Time;
use ros2_client::{Message, MessageTypeName};
use serde::{Deserialize, Serialize};

/// A message type with its ROS package and name.
pub trait RosMessage: Message {
    /// ROS package, e.g. `std_msgs`.
    const PACKAGE: &'static str;
    /// Type name inside the package, e.g. `Float64`.
    const NAME: &'static str;

    /// The ros2-client type name.
    fn type_name() -> MessageTypeName {
        MessageTypeName::new(Self::PACKAGE, Self::NAME)
    }
}

macro_rules! ros_message {
    ($ty:ident, $pkg:literal, $name:literal) => {
        impl Message for $ty {}
        impl RosMessage for $ty {
            const PACKAGE: &'static str = $pkg;
            const NAME: &'static str = $name;
        }
    };
}

/// The package of this node's own messages.
pub const MSG_PACKAGE: &str = "pwm_actuator_msgs";

/// `std_msgs/Float64`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Float64 {
    /// The value.
    pub data: f64,
}
ros_message!(Float64, "std_msgs", "Float64");

/// `std_msgs/UInt16`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct UInt16 {
    /// The value.
    pub data: u16,
}
ros_message!(UInt16, "std_msgs", "UInt16");

/// `std_msgs/Bool`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Bool {
    /// The value.
    pub data: bool,
}
ros_message!(Bool, "std_msgs", "Bool");

/// `std_msgs/String`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct StringMsg {
    /// The text.
    pub data: String,
}
ros_message!(StringMsg, "std_msgs", "String");

/// `std_srvs/Trigger` response.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct TriggerResponse {
    /// Whether the trigger did what it is for.
    pub success: bool,
    /// Why not, or what it did.
    pub message: String,
}
impl Message for TriggerResponse {}

/// `lifecycle_msgs/State`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct LifecycleState {
    /// The state's id (`lifecycle_msgs/State` constants).
    pub id: u8,
    /// Its label (`unconfigured`, `inactive`, ...).
    pub label: String,
}

/// `lifecycle_msgs/Transition`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct LifecycleTransition {
    /// The transition's id (`lifecycle_msgs/Transition` constants).
    pub id: u8,
    /// Its label (`configure`, `activate`, ...).
    pub label: String,
}

/// `lifecycle_msgs/TransitionDescription`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct TransitionDescription {
    /// The transition.
    pub transition: LifecycleTransition,
    /// The state it starts from.
    pub start_state: LifecycleState,
    /// The state it leads to.
    pub goal_state: LifecycleState,
}

/// `lifecycle_msgs/TransitionEvent`, published on `~/transition_event`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct TransitionEvent {
    /// When, ns since the epoch.
    pub timestamp: u64,
    /// The transition taken.
    pub transition: LifecycleTransition,
    /// The state before.
    pub start_state: LifecycleState,
    /// The state after.
    pub goal_state: LifecycleState,
}
ros_message!(TransitionEvent, "lifecycle_msgs", "TransitionEvent");

/// `lifecycle_msgs/ChangeState` request.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct ChangeStateRequest {
    /// The transition asked for, by id, or by label when the id is 0.
    pub transition: LifecycleTransition,
}
impl Message for ChangeStateRequest {}

/// `lifecycle_msgs/ChangeState` response.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct ChangeStateResponse {
    /// Whether the transition succeeded.
    pub success: bool,
}
impl Message for ChangeStateResponse {}

/// A request with no field: `std_srvs/Trigger`, `lifecycle_msgs/GetState`,
/// `GetAvailableStates` and `GetAvailableTransitions`. rosidl gives an empty structure one
/// placeholder byte on the wire; so does this type.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct EmptyRequest {
    structure_needs_at_least_one_member: u8,
}
impl Message for EmptyRequest {}

/// `lifecycle_msgs/GetState` response.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct GetStateResponse {
    /// The state now.
    pub current_state: LifecycleState,
}
impl Message for GetStateResponse {}

/// `lifecycle_msgs/GetAvailableStates` response.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct GetAvailableStatesResponse {
    /// Every state of the machine.
    pub available_states: Vec<LifecycleState>,
}
impl Message for GetAvailableStatesResponse {}

/// `lifecycle_msgs/GetAvailableTransitions` response (also `~/get_transition_graph`).
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct GetAvailableTransitionsResponse {
    /// The transitions.
    pub available_transitions: Vec<TransitionDescription>,
}
impl Message for GetAvailableTransitionsResponse {}

/// `std_msgs/Header`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    /// Wall-clock time of the data.
    pub stamp: Time,
    /// Coordinate frame; empty here.
    pub frame_id: String,
}

/// `diagnostic_msgs/KeyValue`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct KeyValue {
    /// What the value is.
    pub key: String,
    /// The value as text.
    pub value: String,
}
ros_message!(KeyValue, "diagnostic_msgs", "KeyValue");

/// `diagnostic_msgs/DiagnosticStatus`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DiagnosticStatus {
    /// [`DiagnosticStatus::OK`], `WARN`, `ERROR` or `STALE` (a `byte` in the `.msg`).
    pub level: u8,
    /// `<node name>: <channel>`.
    pub name: String,
    /// One-line summary.
    pub message: String,
    /// The output line (`/dev/gpiochip0:17`) or `sim`.
    pub hardware_id: String,
    /// The status figures.
    pub values: Vec<KeyValue>,
}
ros_message!(DiagnosticStatus, "diagnostic_msgs", "DiagnosticStatus");

impl DiagnosticStatus {
    /// Everything is fine.
    pub const OK: u8 = 0;
    /// Working, but something needs attention.
    pub const WARN: u8 = 1;
    /// Not working as commanded.
    pub const ERROR: u8 = 2;
    /// No recent information.
    pub const STALE: u8 = 3;
}

/// `diagnostic_msgs/DiagnosticArray`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DiagnosticArray {
    /// Stamp of the report.
    pub header: Header,
    /// One status per channel.
    pub status: Vec<DiagnosticStatus>,
}
ros_message!(DiagnosticArray, "diagnostic_msgs", "DiagnosticArray");

/// `pwm_actuator_msgs/OutputEdge` (msg/OutputEdge.msg): one output transition.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct OutputEdge {
    /// Wall-clock (ROS) time at which the line was written.
    pub stamp: Time,
    /// Channel number: 1 = pw01, 2 = pw02, ...
    pub channel: u8,
    /// Logical level after the edge: true = on (active), whatever the line's polarity.
    pub level: bool,
    /// Per-channel sequence number, from 1; a gap means a lost message.
    pub seq: u64,
    /// Actual write time minus scheduled time, ns (monotonic clock).
    pub lateness_ns: i64,
}
ros_message!(OutputEdge, "pwm_actuator_msgs", "OutputEdge");

/// `pwm_actuator_msgs/ValveState` (msg/ValveState.msg): what a three-point valve is doing.
/// Positions in percent of the stroke, 0 = closed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ValveState {
    /// Wall-clock time of the snapshot.
    pub stamp: Time,
    /// The valve's name.
    pub name: String,
    /// The estimated position, percent.
    pub position_pct: f64,
    /// The target, percent; NaN before the first command.
    pub target_pct: f64,
    /// `stopped`, `opening` or `closing`.
    pub motion: String,
    /// `tracking`, `referencing`, `recalibrating` or `exercising`.
    pub activity: String,
    /// The estimate was set at a reference.
    pub referenced: bool,
    /// Drive time since the last reference, s.
    pub run_since_reference_s: f64,
    /// The estimate's uncertainty, percent.
    pub uncertainty_pct: f64,
    /// The lowest position the valve can be at, percent.
    pub position_low_pct: f64,
    /// The highest position the valve can be at, percent.
    pub position_high_pct: f64,
    /// The position was restored from the state file and no reference came since.
    pub restored: bool,
    /// A recalibration is due.
    pub recalibration_due: bool,
    /// The command timeout acted.
    pub timed_out: bool,
    /// The e-stop is latched.
    pub estop: bool,
    /// The open end switch is active.
    pub open_switch: bool,
    /// The close end switch is active.
    pub close_switch: bool,
    /// The latched fault (`motor_stalled`, `switch_implausible`, `travel_mismatch`), empty
    /// when none.
    pub fault: String,
    /// The last feedback sample, percent; NaN without one.
    pub feedback_pct: f64,
    /// Moves completed since start.
    pub moves: u64,
    /// Who sets the target: `position` or `pid`.
    pub control: String,
    /// What the loop is doing: `off`, `waiting`, `running`, `holding`, `safe`, `manual`,
    /// `paused` or `timed_out`.
    pub loop_state: String,
    /// The manual command in force (`open`, `close`, `stop`, `position`); empty in automatic.
    pub manual: String,
    /// The loop's setpoint, in the process value's unit; NaN before the first.
    pub setpoint: f64,
    /// The last fresh process value, in its unit; NaN before the first.
    pub process_value: f64,
    /// Its age when the state was taken, s; NaN before the first.
    pub process_age_s: f64,
    /// Stale process values since start.
    pub stale_readings: u64,
    /// Position commands refused since start.
    pub position_commands_refused: u64,
    /// Setpoints refused since start.
    pub setpoints_refused: u64,
    /// Process values refused since start.
    pub process_values_refused: u64,
    /// Manual commands refused since start.
    pub manual_refused: u64,
    /// Motor starts (rises of either line) since start.
    pub starts: u64,
    /// Motor starts within the last hour.
    pub starts_last_hour: u64,
    /// The budget in force, starts an hour; 0 = none.
    pub max_starts_per_h: u64,
}
ros_message!(ValveState, "pwm_actuator_msgs", "ValveState");

/// `pwm_actuator_msgs/ChannelStatus` (msg/ChannelStatus.msg). Times in ms, duties in percent.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelStatus {
    /// Wall-clock time of the snapshot.
    pub stamp: Time,
    /// Channel number: 1 = pw01, 2 = pw02, ...
    pub channel: u8,
    /// EN: the channel is enabled.
    pub enabled: bool,
    /// Enabled, period > 0 and watchdog not tripped (004's q_xActv).
    pub active: bool,
    /// Logical output level: true = on.
    pub output: bool,
    /// Last valid command after clamping, percent 0..100.
    pub duty_commanded: f64,
    /// Duty delivered by the plan in force (on time / period), percent 0..100.
    pub duty_applied: f64,
    /// The last valid command was out of range and was clamped.
    pub command_clamped: bool,
    /// Period in force, ms (0: no pulses).
    pub period_ms: f64,
    /// On time of the plan in force, ms (002's fActTiOn).
    pub on_time_ms: f64,
    /// Off time of the plan in force, ms (002's fActTiOff).
    pub off_time_ms: f64,
    /// Remaining time of the running on step, ms (002's nRemTiOn).
    pub remaining_on_ms: f64,
    /// Remaining time of the running off step, ms (002's nRemTiOff).
    pub remaining_off_ms: f64,
    /// E1 (000): the commanded duty could not be reproduced because of a minimum time, or
    /// max_on_ms cuts the line.
    pub e1: bool,
    /// A pulse or break was raised to its minimum (002's bLmtSwiTi), or max_on_ms cuts the
    /// line.
    pub min_time_limited: bool,
    /// No command for command_timeout_ms: output forced off until the next command.
    pub watchdog_tripped: bool,
    /// The rule that shaped the plan: exact, no_period, suppressed_pulse, suppressed_break,
    /// stretched_pulse, stretched_break, band_low, band_high, extended_pulse, extended_break.
    pub rule: String,
    /// The command in force after the power limits and the dead band, percent 0..100.
    pub duty_target: f64,
    /// The protections of the load acting now: max_on, max_duty, min_duty, slew, deadband,
    /// stagger, max_simultaneous_on, avg_duty.
    pub protections: Vec<String>,
    /// The time base in force, ms (0: off): every pulse and break is a whole number of ticks.
    pub time_base_ms: f64,
    /// On time the current input gives, ms (002's fActTiOn, continuously calculated).
    pub on_time_input_ms: f64,
    /// Off time the current input gives, ms (002's fActTiOff, continuously calculated).
    pub off_time_input_ms: f64,
    /// Remaining time of the running on step in whole seconds (002's UDINT nRemTiOn).
    pub remaining_on_s: u32,
    /// Remaining time of the running off step in whole seconds (002's UDINT nRemTiOff).
    pub remaining_off_s: u32,
    /// `open`, `pid` or `mpc`.
    pub control: String,
    /// The last reading, °C (NaN: none).
    pub temperature_c: f64,
    /// Age of the last reading, ms (-1: none).
    pub temperature_age_ms: f64,
    /// The setpoint in force, °C (NaN: none).
    pub setpoint_c: f64,
    /// The loop's proportional term, %.
    pub pid_p: f64,
    /// The loop's integral term, %.
    pub pid_i: f64,
    /// The loop's derivative term, %.
    pub pid_d: f64,
    /// The loop's output, %.
    pub pid_output: f64,
    /// The latched heater fault's check, or empty.
    pub heater_fault: String,
    /// Its message with the figures.
    pub heater_fault_message: String,
    /// Its condition still holds.
    pub heater_fault_lasts: bool,
    /// The thermal model's prediction at the last fresh reading, °C; NaN without a model.
    pub model_predicted_c: f64,
    /// The reading less the prediction (its slow offset taken out), °C; NaN without a model.
    pub model_residual_c: f64,
    /// Readings refused as stale by their stamp.
    pub stale_readings: u64,
    /// The age of the last one, ms (negative: stamped ahead); NaN: none.
    pub last_stale_age_ms: f64,
    /// The loop's target, °C: the setpoint, or on its way there at `setpoint_ramp_c_per_s`
    /// (NaN: no setpoint).
    pub target_c: f64,
}
ros_message!(ChannelStatus, "pwm_actuator_msgs", "ChannelStatus");

/// `sensor_msgs/Temperature`: a temperature in °C, with its variance (0 = unknown).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Temperature {
    /// When and where it was measured.
    pub header: Header,
    /// The temperature, °C.
    pub temperature: f64,
    /// Its variance, °C²; 0 = unknown.
    pub variance: f64,
}
ros_message!(Temperature, "sensor_msgs", "Temperature");

/// `pwm_actuator_msgs/ChannelParams` (msg/ChannelParams.msg): several parameters of one channel,
/// applied together or refused whole. Only the fields named in `set` are applied.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct ChannelParams {
    /// Names of the fields to apply, e.g. `["period_ms", "min_on_ms"]`. Must not be empty.
    pub set: Vec<String>,
    /// Period T, ms; 0 = no pulses.
    pub period_ms: i64,
    /// Minimum on time, ms; 0 = the hardware floor.
    pub min_on_ms: i64,
    /// Minimum off time, ms; -1 = as the profile says.
    pub min_off_ms: i64,
    /// `transistor` or `relay`.
    pub output_kind: String,
    /// `pico_gfx`, `twincat_ba`, `tcont_cp`, `schneider_pwm` or `frequency_output`.
    pub profile: String,
    /// `suppress`, `stretch`, `band`, `extend`, or "" = as the profile says.
    pub short_pulse: String,
    /// Frequency_Output edge band i_rEdge, 0..1.
    pub edge_band: f64,
    /// `next_period`, `next_step`, `immediate`, or "" = as the profile says.
    pub apply_at: String,
    /// `off`, `hold`, or "" = as the profile says.
    pub on_disable: String,
    /// Watchdog, ms; 0 disables.
    pub command_timeout_ms: i64,
    /// Invert the electrical level of the output line (read-only after start).
    pub active_low: bool,
}
ros_message!(ChannelParams, "pwm_actuator_msgs", "ChannelParams");

/// The goal of `pwm_actuator_msgs/action/Autotune` (msg/action/Autotune.action).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct AutotuneGoal {
    /// The temperature the relay oscillates around, °C.
    pub target_c: f64,
    /// The relay's on output, % duty; 0 = the channel's `max_duty_pct`.
    pub amplitude_pct: f64,
    /// The hysteresis on each side of the target, °C.
    pub noise_band_c: f64,
    /// On success, set the gains as parameters.
    pub apply: bool,
}
impl Message for AutotuneGoal {}

/// The result of `pwm_actuator_msgs/action/Autotune`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct AutotuneResult {
    /// Why it stopped (`converged`, `canceled`, ...).
    pub stop: String,
    /// The same in words, with the figures.
    pub message: String,
    /// Gains were found.
    pub converged: bool,
    /// Ultimate gain, % per °C.
    pub ku: f64,
    /// Ultimate period, s.
    pub tu_s: f64,
    /// % per °C.
    pub pid_kp: f64,
    /// % per °C·s.
    pub pid_ki: f64,
    /// % per °C/s.
    pub pid_kd: f64,
    /// The derivative's filter, s.
    pub pid_d_filter_s: f64,
    /// The rule that gave the gains.
    pub rule: String,
    /// The gains were set as parameters.
    pub applied: bool,
    /// `period_ms <= TI/5` with the new gains.
    pub period_ok: bool,
    /// The minimum times are at most a tenth of the period.
    pub min_times_ok: bool,
    /// TI/5, ms.
    pub recommended_period_ms: u32,
    /// The sizing rules broken.
    pub sizing: Vec<String>,
    /// Complete relay cycles, from the first switch on (the approach is not one).
    pub cycles: u32,
    /// The relay's on output as delivered, %.
    pub delivered_on_pct: f64,
    /// The run identified a thermal model.
    pub model_identified: bool,
    /// The model's gain, °C per %.
    pub model_gain_c_per_pct: f64,
    /// Its time constant, s.
    pub model_tau_s: f64,
    /// Its dead time, s.
    pub model_dead_time_s: f64,
    /// Its ambient, °C.
    pub model_ambient_c: f64,
    /// Its sensor's time constant, s.
    pub model_sensor_tau_s: f64,
}
impl Message for AutotuneResult {}

/// The feedback of `pwm_actuator_msgs/action/Autotune`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct AutotuneFeedback {
    /// `approach` or `relay`.
    pub phase: String,
    /// Complete relay cycles, from the first switch on (the approach is not one).
    pub cycles: u32,
    /// The last cycle's half peak-to-peak amplitude, °C.
    pub amplitude_c: f64,
    /// The last cycle's period, s.
    pub period_s: f64,
}
impl Message for AutotuneFeedback {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn type_names_are_the_ros_ones() {
        assert_eq!(
            OutputEdge::type_name().dds_msg_type(),
            "pwm_actuator_msgs::msg::dds_::OutputEdge_"
        );
        assert_eq!(
            DiagnosticArray::type_name().dds_msg_type(),
            "diagnostic_msgs::msg::dds_::DiagnosticArray_"
        );
        assert_eq!(
            Float64::type_name().dds_msg_type(),
            "std_msgs::msg::dds_::Float64_"
        );
        assert_eq!(OutputEdge::PACKAGE, MSG_PACKAGE);
    }
}
