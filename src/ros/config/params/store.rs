//! The one store every door writes through (command line, parameter files, the parameter
//! services, the `~/<ch>/params` topic), and the whole-change check a change must pass before
//! it is applied (see the module documentation of [`super`]).

use super::table::{self, channel_decls, node_decls, Access};
use super::MAX_CHANNELS;
use super::{channel_name, channel_of, check_choice, check_range, coerce, make, Descriptor};
use super::{shown, ChannelValues, NodeSettings, NodeValues, ParamError, ValveValues};
use crate::core::{ChannelConfig, ChannelParams, ValveConfig};
use crate::ros::interface::msg;
use ros2_client::parameters::raw;
use ros2_client::ParameterValue;
use std::collections::{BTreeMap, BTreeSet};
use std::ops::Bound;

/// At most this many distinct prefixes in one `list_parameters` request; a request with more
/// lists nothing (the node has at most a few thousand parameters, under far fewer prefixes).
pub const MAX_LIST_PREFIXES: usize = 4096;

/// Whether a parameter change is made at start-up (read-only ones allowed) or while running.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Defaults, flags, `-p` and parameter files.
    StartUp,
    /// Parameter services and the `~/<ch>/params` topic.
    Live,
}

/// A checked change, ready to commit.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Accepted {
    /// The coerced values that differ from the current ones, in the order given (last wins).
    pub changes: Vec<(String, ParameterValue)>,
    /// What was coerced, for the log.
    pub notes: Vec<String>,
    /// New configurations of channels whose timing settings changed: (index, config).
    pub configs: Vec<(usize, ChannelConfig)>,
    /// New configurations of valves whose settings changed: (index, config).
    pub valve_configs: Vec<(usize, ValveConfig)>,
}

/// Every parameter of the node with its current value: the declarations by name (the ROS
/// edge) and the values in typed settings, one struct for the node, one a channel and one a
/// valve.
#[derive(Debug, Clone)]
pub struct ParamStore {
    decls: BTreeMap<String, Descriptor>,
    values: Values,
    /// What the node-level values give, kept with them (made anew when a commit changes one).
    settings: NodeSettings,
    /// The valves' names, in the order they were declared (their index in the output thread
    /// and in `values.valves`).
    valves: Vec<String>,
}

/// The typed settings a store holds; a change is made on a copy.
#[derive(Debug, Clone, PartialEq, Default)]
struct Values {
    node: NodeValues,
    channels: Vec<ChannelValues>,
    valves: Vec<ValveValues>,
}

impl Values {
    /// The value of the parameter `d` declares.
    fn get(&self, d: &Descriptor) -> ParameterValue {
        match d.access {
            Access::Node(f) => (f.get)(&self.node),
            Access::Channel(f) => (f.get)(&self.channels[d.at]),
            Access::Valve(f) => (f.get)(&self.valves[d.at]),
        }
    }

    /// Sets the parameter `d` declares to `v` (of its declared type).
    fn set(&mut self, d: &Descriptor, v: &ParameterValue) {
        match d.access {
            Access::Node(f) => (f.set)(&mut self.node, v),
            Access::Channel(f) => (f.set)(&mut self.channels[d.at], v),
            Access::Valve(f) => (f.set)(&mut self.valves[d.at], v),
        }
    }
}

impl ParamStore {
    /// Declares the node parameters and those of `channels` channels (clamped to
    /// 1..=[`MAX_CHANNELS`]), each at its default.
    pub fn new(channels: usize) -> ParamStore {
        let channels = channels.clamp(1, MAX_CHANNELS);
        let mut decls = BTreeMap::new();
        for d in node_decls() {
            decls.insert(d.suffix.to_string(), make(d.suffix.to_string(), &d, 0));
        }
        for ch in 0..channels {
            for d in channel_decls() {
                let name = format!("{}.{}", channel_name(ch), d.suffix);
                decls.insert(name.clone(), make(name, &d, ch));
            }
        }
        if let Some(d) = decls.get_mut("channels") {
            d.default = ParameterValue::Integer(channels as i64);
        }
        let mut values = Values {
            channels: vec![ChannelValues::default(); channels],
            ..Values::default()
        };
        for d in decls.values() {
            values.set(d, &d.default);
        }
        ParamStore {
            decls,
            settings: table::node_settings(&values.node),
            values,
            valves: Vec::new(),
        }
    }

    /// Declares the parameters of each valve in `names` (`NAME.travel_open_ms`, ...), each at
    /// its default. Names are checked by the `valve` parameter's parser; one that would
    /// collide with a declared parameter is skipped.
    pub fn declare_valves(&mut self, names: &[String]) {
        for valve in names {
            let k = self.valves.len();
            self.valves.push(valve.clone());
            let mut values = ValveValues::default();
            for d in table::valve_decls() {
                let name = format!("{valve}.{}", d.suffix);
                let desc = make(name.clone(), &d, k);
                if let Access::Valve(f) = d.access {
                    (f.set)(&mut values, &desc.default);
                }
                self.decls.entry(name).or_insert(desc);
            }
            self.values.valves.push(values);
        }
    }

    /// Number of channels.
    pub fn channels(&self) -> usize {
        self.values.channels.len()
    }

    /// The node-level parameters' values.
    pub fn node(&self) -> &NodeValues {
        &self.values.node
    }

    /// Channel `ch`'s parameters' values.
    pub fn channel(&self, ch: usize) -> Option<&ChannelValues> {
        self.values.channels.get(ch)
    }

    /// Valve `valve`'s parameters' values (see [`ParamStore::declare_valves`]).
    pub fn valve(&self, valve: &str) -> Option<&ValveValues> {
        let k = self.valves.iter().position(|v| v == valve)?;
        self.values.valves.get(k)
    }

    /// Valve `valve`'s settings from its parameters (the defaults for a valve not declared).
    pub fn valve_params(&self, valve: &str) -> crate::core::ValveParams {
        match self.valve(valve) {
            Some(v) => table::valve_params(v),
            None => crate::core::ValveParams::default(),
        }
    }

    /// The current value of a parameter.
    pub fn get(&self, name: &str) -> Option<ParameterValue> {
        self.decls.get(name).map(|d| self.values.get(d))
    }

    /// The declaration of a parameter.
    pub fn descriptor(&self, name: &str) -> Option<&Descriptor> {
        self.decls.get(name)
    }

    /// Every parameter name, sorted.
    pub fn names(&self) -> Vec<String> {
        self.decls.keys().cloned().collect()
    }

    /// Every parameter with its current value, sorted by name.
    pub fn all(&self) -> Vec<(String, ParameterValue)> {
        self.decls
            .iter()
            .map(|(k, d)| (k.clone(), self.values.get(d)))
            .collect()
    }

    /// The node-level settings the store's values give.
    pub fn node_settings(&self) -> NodeSettings {
        self.settings.clone()
    }

    /// Answers `list_parameters` the way rclcpp does: with no prefixes, names with fewer than
    /// `depth` dots (0 = any); otherwise names equal to a prefix or under `prefix.` within
    /// `depth` further levels. Returns `(names, prefixes)`.
    pub fn list(&self, prefixes: &[String], depth: u64) -> (Vec<String>, Vec<String>) {
        // `dots` separators below the prefix are within `depth` (0: any depth).
        let within = |dots: usize| depth == 0 || (dots as u64) < depth;
        let mut found: BTreeSet<&str> = BTreeSet::new();
        if prefixes.is_empty() {
            found.extend(
                self.decls
                    .keys()
                    .map(String::as_str)
                    .filter(|n| within(n.matches('.').count())),
            );
        } else {
            // Each distinct prefix once, each by a range look-up: the cost is bounded by the
            // distinct prefixes (at most MAX_LIST_PREFIXES) times log(parameters), plus the
            // names found, never prefixes times parameters.
            let distinct: BTreeSet<&str> = prefixes.iter().map(String::as_str).collect();
            if distinct.len() > MAX_LIST_PREFIXES {
                log::debug!(
                    "list_parameters: {} distinct prefixes, more than {MAX_LIST_PREFIXES}; \
                     nothing listed",
                    distinct.len()
                );
                return (Vec::new(), Vec::new());
            }
            for p in distinct {
                if let Some((name, _)) = self.decls.get_key_value(p) {
                    found.insert(name.as_str());
                }
                let under = format!("{p}.");
                for name in self
                    .decls
                    .range::<str, _>((Bound::Included(under.as_str()), Bound::Unbounded))
                    .map(|(n, _)| n.as_str())
                    .take_while(|n| n.starts_with(under.as_str()))
                {
                    if within(1 + name[under.len()..].matches('.').count()) {
                        found.insert(name);
                    }
                }
            }
        }
        let mut found_prefixes: Vec<String> = Vec::new();
        for name in &found {
            if let Some((ns, _)) = name.rsplit_once('.') {
                if !found_prefixes.iter().any(|p| p == ns) {
                    found_prefixes.push(ns.to_string());
                }
            }
        }
        (
            found.into_iter().map(str::to_string).collect(),
            found_prefixes,
        )
    }

    /// The channel's settings in `values` as the core's [`ChannelParams`].
    fn channel_params_in(values: &Values, ch: usize) -> Result<ChannelParams, ParamError> {
        table::channel_params(&values.channels[ch]).map_err(|(suffix, source)| {
            ParamError::BadChoice {
                name: format!("{}.{suffix}", channel_name(ch)),
                source,
            }
        })
    }

    /// Channel `ch`'s settings as the core's [`ChannelParams`].
    pub fn channel_params(&self, ch: usize) -> Result<ChannelParams, ParamError> {
        Self::channel_params_in(&self.values, ch)
    }

    /// Channel `ch`'s validated configuration.
    pub fn channel_config(&self, ch: usize) -> Result<ChannelConfig, ParamError> {
        self.channel_params(ch)?
            .validate()
            .map_err(|source| ParamError::Channel {
                channel: channel_name(ch),
                source,
            })
    }

    /// Checks a change as a whole (see the module documentation): it is applied to a copy of
    /// the typed settings, and each channel and valve it touches is validated once. Nothing
    /// is modified.
    pub fn check(
        &self,
        items: &[(String, ParameterValue)],
        stage: Stage,
    ) -> Result<Accepted, ParamError> {
        let mut working = self.values.clone();
        let mut notes = Vec::new();
        let mut order: Vec<&Descriptor> = Vec::new();
        for (name, value) in items {
            let d = self.decls.get(name).ok_or_else(|| ParamError::Undeclared {
                name: shown(name),
                hint: self.undeclared_hint(name),
            })?;
            let (v, note) = coerce(d, value)?;
            check_range(d, &v)?;
            check_choice(d, &v)?;
            if name == "use_sim_time" && v == ParameterValue::Boolean(true) {
                return Err(ParamError::SimTime);
            }
            if stage == Stage::Live && d.read_only && self.values.get(d) != v {
                return Err(ParamError::ReadOnly {
                    name: name.clone(),
                    why: d.why_read_only,
                });
            }
            notes.extend(note);
            working.set(d, &v);
            order.retain(|n| n.name != d.name);
            order.push(d);
        }
        let changed: Vec<&Descriptor> = order
            .into_iter()
            .filter(|d| working.get(d) != self.values.get(d))
            .collect();
        let touched = |valves: bool| {
            let mut at: Vec<usize> = changed
                .iter()
                .filter(|d| match d.access {
                    Access::Channel(_) => !valves,
                    Access::Valve(_) => valves,
                    Access::Node(_) => false,
                })
                .map(|d| d.at)
                .collect();
            at.sort_unstable();
            at.dedup();
            at
        };
        let channels = touched(false);
        for &ch in &channels {
            let c = &working.channels[ch];
            let (min, max) = (c.expected_command_hz_min, c.expected_command_hz_max);
            if max > 0.0 && min > max {
                return Err(ParamError::RateBounds {
                    channel: channel_name(ch),
                    min,
                    max,
                });
            }
        }
        let mut configs = Vec::new();
        for ch in channels {
            let new = Self::channel_params_in(&working, ch)?;
            let config = new.validate().map_err(|source| ParamError::Channel {
                channel: channel_name(ch),
                source,
            })?;
            if Self::channel_params_in(&self.values, ch).ok() != Some(new) {
                configs.push((ch, config));
            }
        }
        // A valve's settings are checked together, as a channel's.
        let mut valve_configs = Vec::new();
        for k in touched(true) {
            let new = table::valve_params(&working.valves[k]);
            let config = new.validate().map_err(|source| ParamError::Valve {
                valve: self.valves[k].clone(),
                source,
            })?;
            if table::valve_params(&self.values.valves[k]) != new {
                valve_configs.push((k, config));
            }
        }
        Ok(Accepted {
            changes: changed
                .into_iter()
                .map(|d| (d.name.clone(), working.get(d)))
                .collect(),
            notes,
            configs,
            valve_configs,
        })
    }

    fn undeclared_hint(&self, name: &str) -> String {
        match channel_of(name) {
            Some((ch, _)) if ch >= self.channels() => format!(
                " (this node has {} channel{}: pw01..{})",
                self.channels(),
                if self.channels() == 1 { "" } else { "s" },
                channel_name(self.channels() - 1)
            ),
            _ => String::new(),
        }
    }

    /// Applies a checked change; returns the changed parameters in wire form, for
    /// `/parameter_events`.
    pub fn commit(&mut self, accepted: &Accepted) -> Vec<raw::Parameter> {
        let node = self.values.node.clone();
        let changed = accepted
            .changes
            .iter()
            .filter_map(|(name, value)| {
                let d = self.decls.get(name)?;
                self.values.set(d, value);
                Some(raw::Parameter {
                    name: name.clone(),
                    value: value.clone().into(),
                })
            })
            .collect();
        if self.values.node != node {
            self.settings = table::node_settings(&self.values.node);
        }
        changed
    }
}

/// The parameter changes a `~/<ch>/params` message asks for: the fields named in `set`, as
/// `pwNN.field` values, each read by its entry in the table.
pub fn items_from_msg(
    ch: usize,
    m: &msg::ChannelParams,
) -> Result<Vec<(String, ParameterValue)>, ParamError> {
    let channel = channel_name(ch);
    if m.set.is_empty() {
        return Err(ParamError::EmptySet { channel });
    }
    let decls = channel_decls();
    m.set
        .iter()
        .map(|field| {
            let from_msg = decls
                .iter()
                .find(|d| d.suffix == field.as_str())
                .and_then(|d| d.msg)
                .ok_or_else(|| ParamError::UnknownField {
                    channel: channel.clone(),
                    field: shown(field),
                    fields: table::msg_fields(),
                })?;
            Ok((format!("{channel}.{field}"), from_msg(m)))
        })
        .collect()
}
