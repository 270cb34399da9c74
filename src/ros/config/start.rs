//! What the node and `safe-off` make of their configuration before anything runs: the start-up
//! values (node options first, then the ROS arguments in order), the domain id, and every way
//! a configuration can be refused ([`StartupError`], exit status 2).

pub use crate::output::fault::FaultSpecError;
use crate::ros::config::args::{ArgsError, RosArgs};
use crate::ros::config::cli::{CliError, Flags};
use crate::ros::config::discovery::DiscoveryError;
use crate::ros::config::names::{NameError, NodeIdentity};
use crate::ros::config::params::{show_value, ParamError, StartValue};
use crate::ros::config::security::SecurityError;
use crate::ros::config::split::SplitError;
use crate::ros::config::valve::ValveError;
use log::info;

/// Highest `ROS_DOMAIN_ID` accepted (the DDS port mapping's limit).
pub const MAX_DOMAIN_ID: u16 = 232;

/// A configuration the node refuses before it touches any output (exit status 2).
#[derive(Debug, thiserror::Error)]
pub enum StartupError {
    /// Bad `--ros-args` or parameter file.
    #[error(transparent)]
    Args(#[from] ArgsError),
    /// Bad node option.
    #[error(transparent)]
    Cli(#[from] CliError),
    /// A name that does not resolve.
    #[error(transparent)]
    Name(#[from] NameError),
    /// `ROS_DOMAIN_ID` is not a domain id.
    #[error("ROS_DOMAIN_ID `{value}` is not a domain id: expected an integer 0..={max}")]
    DomainId {
        /// The value found.
        value: String,
        /// The highest id.
        max: u16,
    },
    /// A start-up parameter value refused.
    #[error(transparent)]
    Param(#[from] ParamError),
    /// The `split` parameter is refused.
    #[error(transparent)]
    Split(#[from] SplitError),
    /// The `valve` parameter or a valve's settings are refused.
    #[error(transparent)]
    Valve(#[from] ValveError),
    /// A discovery setting that cannot be honoured.
    #[error(transparent)]
    Discovery(#[from] DiscoveryError),
    /// Security is enforced and cannot be provided.
    #[error(transparent)]
    Security(#[from] SecurityError),
    /// `PWM_ACTUATOR_FAULT` is malformed.
    #[error(transparent)]
    Fault(#[from] FaultSpecError),
}

/// Reads `ROS_DOMAIN_ID` (unset or empty: 0).
pub fn domain_id_from(value: Option<&str>) -> Result<u16, StartupError> {
    match value.map(str::trim) {
        None | Some("") => Ok(0),
        Some(v) => v
            .parse::<u16>()
            .ok()
            .filter(|d| *d <= MAX_DOMAIN_ID)
            .ok_or_else(|| StartupError::DomainId {
                value: v.to_string(),
                max: MAX_DOMAIN_ID,
            }),
    }
}

/// The start-up values: options first, then the ROS arguments in order. Logs where a ROS
/// argument overrides an option.
pub fn start_values(
    flags: &Flags,
    ros: &RosArgs,
    id: &NodeIdentity,
    fqn: &str,
) -> Result<Vec<StartValue>, StartupError> {
    let mut v = flags.start_values();
    let from_options: Vec<(String, String)> = v
        .iter()
        .map(|s| (s.name.clone(), s.origin.clone()))
        .collect();
    for o in ros.overrides(&id.name, fqn)? {
        if let Some((_, opt)) = from_options.iter().find(|(n, _)| *n == o.name) {
            info!(
                "{} = {} from {} overrides {opt}",
                o.name,
                show_value(&o.value),
                o.origin
            );
        }
        v.push(StartValue {
            name: o.name,
            value: o.value,
            origin: o.origin,
        });
    }
    Ok(v)
}
