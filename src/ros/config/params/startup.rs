//! Start-up assembly: the values given on the command line and in parameter files become the
//! store and the configuration the node starts with.

use super::table::node_decls;
use super::DEFAULT_CHANNELS;
use super::{channel_name, check_range, coerce, make, ParamError, ParamStore, Stage};
use super::{ChannelValues, NodeSettings};
use crate::core::ChannelConfig;
use crate::output::{Backend, GpioLine, OutputSpec, TraceLimit};

/// The name of the heartbeat line (in traces and safe-off's report).
pub const HEARTBEAT_LINE: &str = "heartbeat";
use ros2_client::ParameterValue;
use std::path::PathBuf;

/// A parameter value given at start-up, with where it came from.
#[derive(Debug, Clone, PartialEq)]
pub struct StartValue {
    /// Parameter name.
    pub name: String,
    /// Value as given.
    pub value: ParameterValue,
    /// Where it came from (`--demo`, `-p`, `--params-file x.yaml`, ...).
    pub origin: String,
}

/// The store built from start-up values, and what was said about them.
#[derive(Debug, Clone)]
pub struct StartUp {
    /// The store with every start-up value applied.
    pub store: ParamStore,
    /// Coercion notes.
    pub notes: Vec<String>,
    /// Values for parameters this node does not have, ignored (as rclcpp ignores overrides of
    /// undeclared parameters), as `name (origin)`.
    pub ignored: Vec<String>,
    /// Values accepted by ROS convention but not honoured, with why (`use_sim_time: true`
    /// from a launch file that sets it for every node).
    pub warnings: Vec<String>,
}

/// Builds the store from start-up values applied in order (a later value wins). The channel
/// count comes from the last `channels` value; values for parameters the node does not
/// declare are ignored and listed.
pub fn start_up(values: &[StartValue]) -> Result<StartUp, ParamError> {
    let channels_decl = make("channels".into(), &node_decls()[0], 0);
    let mut channels = DEFAULT_CHANNELS;
    for v in values.iter().filter(|v| v.name == "channels") {
        let (c, _) = coerce(&channels_decl, &v.value)?;
        check_range(&channels_decl, &c)?;
        if let ParameterValue::Integer(i) = c {
            channels = i as usize;
        }
    }
    let mut store = ParamStore::new(channels);
    // The valves' parameters exist once the `valve` parameter names them (its last value).
    if let Some(v) = values.iter().rev().find(|v| v.name == "valve") {
        if let ParameterValue::String(text) = &v.value {
            store.declare_valves(&crate::ros::config::valve::names(text));
        }
    }
    let mut ignored = Vec::new();
    let mut warnings = Vec::new();
    let items: Vec<(String, ParameterValue)> = values
        .iter()
        .filter_map(|v| {
            if v.name == "use_sim_time" && v.value == ParameterValue::Boolean(true) {
                // Launch files often set it for every node; refusing to start would be worse
                // than saying plainly that it is not honoured.
                warnings.push(format!(
                    "use_sim_time true ({}) ignored: {}",
                    v.origin,
                    ParamError::SimTime
                ));
                None
            } else if store.descriptor(&v.name).is_some() {
                Some((v.name.clone(), v.value.clone()))
            } else {
                ignored.push(format!("{} ({})", v.name, v.origin));
                None
            }
        })
        .collect();
    let accepted = store.check(&items, Stage::StartUp)?;
    store.commit(&accepted);
    // Defaults are valid by construction, but say so if a channel is not.
    for ch in 0..store.channels() {
        store.channel_config(ch)?;
    }
    Ok(StartUp {
        store,
        notes: accepted.notes,
        ignored,
        warnings,
    })
}

/// One channel at start-up.
#[derive(Debug, Clone, PartialEq)]
pub struct ChannelStart {
    /// `pw01`, ...
    pub name: String,
    /// Validated configuration.
    pub config: ChannelConfig,
    /// Enabled at start-up.
    pub enable: bool,
    /// Duty at start-up, percent.
    pub duty_percent: f64,
    /// `feedback_topic`: the temperature topic, empty for none.
    pub feedback_topic: String,
    /// `feedforward_topic`: the feed-forward topic (`std_msgs/Float64`, %), empty for none.
    pub feedforward_topic: String,
    /// `ambient_topic`: the ambient temperature topic (`sensor_msgs/Temperature`), empty for
    /// none.
    pub ambient_topic: String,
}

/// What the node needs at start-up, read from the store.
#[derive(Debug, Clone, PartialEq)]
pub struct StartupConfig {
    /// Channels in order.
    pub channels: Vec<ChannelStart>,
    /// The output: backend, lines (with their polarity; the heartbeat line last, after the
    /// channels' lines), trace files.
    pub output: OutputSpec,
    /// The node-level settings.
    pub settings: NodeSettings,
}

impl StartupConfig {
    /// Reads the start-up configuration from a store built by [`start_up`].
    pub fn from_store(store: &ParamStore) -> Result<StartupConfig, ParamError> {
        let settings = store.node_settings();
        let mut channels = Vec::new();
        let values: Vec<&ChannelValues> = (0..store.channels())
            .filter_map(|ch| store.channel(ch))
            .collect();
        for (ch, v) in values.iter().enumerate() {
            channels.push(ChannelStart {
                name: channel_name(ch),
                config: store.channel_config(ch)?,
                enable: v.enable,
                duty_percent: v.duty,
                feedback_topic: v.feedback_topic.clone(),
                feedforward_topic: v.feedforward_topic.trim().to_string(),
                ambient_topic: v.ambient_topic.trim().to_string(),
            });
        }
        let heartbeat = settings.heartbeat_line;
        let backend = if settings.gpio {
            let mut lines = Vec::new();
            for (c, v) in channels.iter().zip(&values) {
                if v.gpio_line < 0 {
                    return Err(ParamError::MissingLine {
                        channel: c.name.clone(),
                    });
                }
                lines.push(GpioLine {
                    name: c.name.clone(),
                    chip: PathBuf::from(&v.gpio_chip),
                    offset: v.gpio_line.min(u32::MAX as i64) as u32,
                    active_low: v.active_low,
                });
            }
            if let Some(offset) = heartbeat {
                lines.push(GpioLine {
                    name: HEARTBEAT_LINE.into(),
                    chip: settings.heartbeat_chip.clone(),
                    offset,
                    active_low: false,
                });
            }
            Backend::Gpio { lines }
        } else {
            let mut names: Vec<String> = channels.iter().map(|c| c.name.clone()).collect();
            if heartbeat.is_some() {
                names.push(HEARTBEAT_LINE.into());
            }
            Backend::Sim { names }
        };
        let output = OutputSpec {
            backend,
            trace: settings.trace.clone(),
            trace_limit: TraceLimit::from_mb(settings.trace_max_mb),
            fault: None,
        };
        Ok(StartupConfig {
            channels,
            output,
            settings,
        })
    }

    /// The heartbeat line's frequency, Hz, when there is a heartbeat line.
    pub fn heartbeat_hz(&self) -> Option<f64> {
        self.settings
            .heartbeat_line
            .map(|_| self.settings.heartbeat_hz)
    }
}
