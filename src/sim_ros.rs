//! What the simulated plants (`sim-heater`, `sim-valve`) share as ROS participants: the tokio
//! runtime they run on, their node on the environment's domain and discovery settings, and
//! topic creation.

use pwm_actuator::error::chain;
use pwm_actuator::ros::config::discovery::{self, DiscoveryError};
use pwm_actuator::ros::config::start::{domain_id_from, StartupError};
use pwm_actuator::ros::interface::type_hash::{self, TypeHashError};
use ros2_client::dds::NodeCreateError;
use ros2_client::names::NameError;
use ros2_client::{Context, CreateError, NodeName, NodeOptions, QosProfile};
use std::future::Future;
use std::path::PathBuf;

/// A simulated plant's option outside its range (exit status 2).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("--{option} {value} is outside {lo}..{hi}")]
pub struct OptionOutOfRange {
    /// The option, without its dashes.
    pub option: &'static str,
    /// The value given.
    pub value: f64,
    /// The lowest value accepted.
    pub lo: f64,
    /// The highest value accepted.
    pub hi: f64,
}

/// `value` of `--option` if it lies within `lo..=hi` (a NaN does not).
pub fn within(option: &'static str, value: f64, lo: f64, hi: f64) -> Result<(), OptionOutOfRange> {
    if (lo..=hi).contains(&value) {
        Ok(())
    } else {
        Err(OptionOutOfRange {
            option,
            value,
            lo,
            hi,
        })
    }
}

/// Why a simulated plant cannot run, or stops (exit status 1). The text follows the tool's
/// name on stderr.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// `ROS_DOMAIN_ID` is not a domain id.
    #[error(transparent)]
    DomainId(#[from] StartupError),
    /// The discovery settings of the environment cannot be honoured.
    #[error(transparent)]
    Discovery(#[from] DiscoveryError),
    /// The compiled-in message definitions give no type hashes.
    #[error(transparent)]
    TypeHash(#[from] TypeHashError),
    /// RustDDS cannot create the participant.
    #[error("the DDS participant: {0}")]
    Participant(#[source] rustdds::dds::CreateError),
    /// ros2-client cannot make a context of the participant.
    #[error("the DDS participant: {0}")]
    Context(#[source] CreateError),
    /// The node's name is not a ROS name.
    #[error(transparent)]
    NodeName(NameError),
    /// ros2-client cannot create the node.
    #[error("node: {0}")]
    Node(#[source] NodeCreateError),
    /// ros2-client cannot create the node's spinner.
    #[error("spinner: {0}")]
    Spinner(#[source] CreateError),
    /// A topic name is not a full ROS name.
    #[error("topic {topic}: {source}")]
    TopicName {
        /// The name given.
        topic: String,
        /// Why.
        #[source]
        source: NameError,
    },
    /// A topic, publisher or subscription cannot be created.
    #[error("{what} {topic}: {source}")]
    Endpoint {
        /// `topic`, `publisher` or `subscription`.
        what: &'static str,
        /// The topic's full name.
        topic: String,
        /// ros2-client's error.
        #[source]
        source: CreateError,
    },
    /// The `--record` file cannot be created.
    #[error("{}: {source}", path.display())]
    Record {
        /// The file.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// SIGTERM cannot be caught.
    #[error("SIGTERM: {0}")]
    Signal(#[source] std::io::Error),
}

impl SimError {
    /// Maps ros2-client's error creating a `what` (`topic`, `publisher`, `subscription`) on
    /// `topic` to [`SimError::Endpoint`].
    pub fn endpoint(what: &'static str, topic: &str) -> impl FnOnce(CreateError) -> SimError {
        let topic = topic.to_string();
        move |source| SimError::Endpoint {
            what,
            topic,
            source,
        }
    }

    /// Maps an error creating the `--record` file `path` to [`SimError::Record`].
    pub fn record(path: &std::path::Path) -> impl FnOnce(std::io::Error) -> SimError + '_ {
        move |source| SimError::Record {
            path: path.to_path_buf(),
            source,
        }
    }
}

/// Runs `serve` on a one-worker runtime; the exit status: 0 when it returns `Ok`, 1 when the
/// runtime cannot start or `serve` fails (the reason printed after `tool`).
pub fn block_on(tool: &str, serve: impl Future<Output = Result<(), SimError>>) -> i32 {
    let rt = match tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("{tool}: cannot start the runtime: {e}");
            return 1;
        }
    };
    match rt.block_on(serve) {
        Ok(()) => 0,
        Err(e) => {
            eprintln!("{tool}: {}", chain(&e));
            1
        }
    }
}

/// The node `/<name>` on `ROS_DOMAIN_ID` with the environment's discovery settings, without
/// rosout, its endpoints announcing their type hashes as the node's do, spun on the runtime.
/// Call it inside [`block_on`]'s future.
pub fn start_node(name: &str) -> Result<ros2_client::Node, SimError> {
    let domain = domain_id_from(std::env::var("ROS_DOMAIN_ID").ok().as_deref())?;
    let disc = discovery::read(|k| std::env::var(k).ok())?;
    type_hash::announce()?;
    let participant = disc
        .participant(domain, None)
        .map_err(SimError::Participant)?;
    let context = Context::from_domain_participant(participant).map_err(SimError::Context)?;
    let name = NodeName::new("/", name).map_err(SimError::NodeName)?;
    let mut node = context
        .new_node(name, NodeOptions::new().enable_rosout(false))
        .map_err(SimError::Node)?;
    let spinner = node.spinner().map_err(SimError::Spinner)?;
    tokio::spawn(async move {
        let _ = spinner.spin().await;
    });
    Ok(node)
}

/// The topic `name` (a full ROS name) of type `ty`.
pub fn make_topic(
    node: &ros2_client::Node,
    name: &str,
    ty: ros2_client::MessageTypeName,
    qos: &QosProfile,
) -> Result<rustdds::Topic, SimError> {
    let ros_name = make_topic_name(name)?;
    node.create_topic(&ros_name, ty, qos)
        .map_err(SimError::endpoint("topic", name))
}

/// `name` as a full ROS name.
fn make_topic_name(name: &str) -> Result<ros2_client::Name, SimError> {
    ros2_client::Name::parse(name).map_err(|source| SimError::TopicName {
        topic: name.to_string(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An option's range holds its ends and refuses what lies outside, a NaN included, with the
    /// option's name, the value and the range.
    #[test]
    fn an_option_outside_its_range_is_refused_with_its_range() {
        assert_eq!(within("tau", 0.1, 0.1, 10.0), Ok(()));
        assert_eq!(within("tau", 10.0, 0.1, 10.0), Ok(()));
        let e = within("tau", 10.5, 0.1, 10.0).unwrap_err();
        assert_eq!(e.to_string(), "--tau 10.5 is outside 0.1..10");
        assert!(within("tau", f64::NAN, 0.1, 10.0).is_err());
    }

    /// The texts printed after the tool's name: the endpoint and the cause, each once.
    #[test]
    fn errors_name_what_failed_and_why_once() {
        let bad = || CreateError::BadParameter {
            reason: "no such QoS".into(),
        };
        let e = SimError::endpoint("subscription", "/pwm_actuator/pw01/edges")(bad());
        assert_eq!(
            chain(&e),
            "subscription /pwm_actuator/pw01/edges: create bad parameter: no such QoS"
        );
        let e = make_topic_name("not a name").unwrap_err();
        assert!(chain(&e).starts_with("topic not a name: "), "{}", chain(&e));
        let dir = std::path::Path::new("/nonexistent-dir/record.csv");
        let e = std::fs::File::create(dir)
            .map_err(SimError::record(dir))
            .unwrap_err();
        assert_eq!(
            chain(&e),
            "/nonexistent-dir/record.csv: No such file or directory (os error 2)"
        );
        let e = SimError::from(domain_id_from(Some("300")).unwrap_err());
        assert_eq!(
            chain(&e),
            "ROS_DOMAIN_ID `300` is not a domain id: expected an integer 0..=232"
        );
    }
}
