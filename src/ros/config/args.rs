//! The standard ROS 2 command-line arguments (`--ros-args ... [--]`), parsed the way rcl parses
//! them, and ROS 2 parameter files (`--params-file`).
//!
//! ros2-client does not parse `--ros-args`, so this module does. It only parses: it does not
//! resolve names against a node ([`crate::ros::config::names`] does) and does not apply parameters
//! ([`crate::ros::config::params`] does). Reading a parameter file is its only I/O.
//!
//! Supported inside a `--ros-args` block: `-r/--remap [node:]from:=to` (including `__node`,
//! `__name`, `__ns` and the `rostopic://` / `rosservice://` prefixes), `-p/--param
//! [node:]name:=value` (value in YAML), `--params-file FILE`, `--log-level [logger:=]LEVEL`,
//! `-e/--enclave` (see `ros::security`), `--log-config-file` (accepted, not used) and the
//! `--enable-*` / `--disable-*` switches for rosout, stdout and external-library logs. A block
//! ends at `--` or at the end of the command line; several blocks may be given. Anything else
//! inside a block is an error, as in rcl.

use ros2_client::ParameterValue;
use std::collections::HashMap;
use std::io::Read;
use std::path::{Path, PathBuf};
use yaml_rust2::parser::{Event, Parser};
use yaml_rust2::{Yaml, YamlLoader};

/// Largest parameter file read, bytes (1 MiB; a parameter file of this node is a few KiB).
pub const MAX_PARAMS_FILE_BYTES: u64 = 1 << 20;

/// Most YAML nodes a parameter file or a `-p` value may describe, aliases counted as expanded
/// (a "billion laughs" file of a few hundred bytes expands to gigabytes).
pub const MAX_YAML_NODES: u64 = 100_000;

/// Deepest nesting of YAML mappings and sequences in a parameter file or a `-p` value.
pub const MAX_YAML_DEPTH: usize = 64;

/// What is wrong with the YAML of a parameter file or of a `-p` value.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum YamlError {
    /// The text does not parse as YAML.
    #[error("not valid YAML: {0}")]
    Syntax(#[source] yaml_rust2::ScanError),
    /// Mappings and sequences nested deeper than [`MAX_YAML_DEPTH`].
    #[error("mappings and sequences nested deeper than {MAX_YAML_DEPTH} levels")]
    TooDeep,
    /// More than [`MAX_YAML_NODES`] nodes with every alias expanded.
    #[error("more than {MAX_YAML_NODES} nodes with its aliases expanded (an alias bomb?)")]
    TooManyNodes,
    /// A parameter file larger than [`MAX_PARAMS_FILE_BYTES`]; its size in bytes where known.
    #[error("the file is larger than 1 MiB{}", .0.map_or_else(String::new, |b| format!(" ({b} bytes)")))]
    FileTooLarge(Option<u64>),
    /// Nothing after `:=`.
    #[error("no value after `:=` (for an empty string write `''`)")]
    NoValue,
    /// A `-p` value of more than one YAML document.
    #[error("more than one YAML document")]
    SeveralDocuments,
    /// A real that is not a number YAML can read as one.
    #[error("not a number")]
    NotANumber,
    /// A YAML null where a value is expected.
    #[error("no value (YAML null; for an empty string write `''`)")]
    Null,
    /// A mapping where a value is expected.
    #[error("a mapping is not a parameter value")]
    Mapping,
    /// An alias or a value YAML itself could not type.
    #[error("unsupported YAML value")]
    Unsupported,
    /// `[]`: a parameter array needs an element type.
    #[error("an empty array has no element type")]
    EmptyArray,
    /// An array of numbers with an element that is not one.
    #[error("array element is not a number")]
    ArrayElementNotANumber,
    /// An array mixing bools, numbers and strings.
    #[error("array elements must all be of one type (bool, number or string)")]
    MixedArray,
    /// The top level of a parameter file is not a mapping of node names.
    #[error("the top level must map node names to `ros__parameters`")]
    TopLevel,
    /// `ros__parameters` at the top level.
    #[error("`ros__parameters` must be under a node name (or `/**`)")]
    ParametersWithoutNode,
    /// `ros__parameters` holding something other than a mapping.
    #[error("`ros__parameters` of `{node}` must be a mapping")]
    ParametersNotMapping {
        /// The node pattern.
        node: String,
    },
    /// A node name key that is not a string.
    #[error("node name {key} under `/{path}` is not a string")]
    NodeNameNotString {
        /// The key as YAML shows it.
        key: String,
        /// The node path above it.
        path: String,
    },
    /// A value outside `ros__parameters`.
    #[error(
        "`{key}` under `/{path}` holds a value, but only node names and `ros__parameters` may \
         appear outside `ros__parameters`"
    )]
    ValueOutsideParameters {
        /// The key holding the value.
        key: String,
        /// The node path above it.
        path: String,
    },
    /// A parameter name key that is not a string, integer or bool.
    #[error("parameter name {0} is not a string")]
    ParameterNameNotString(String),
    /// A problem inside the parameters of one node section.
    #[error("under `{node}`: {source}")]
    UnderNode {
        /// The node pattern.
        node: String,
        /// The problem.
        #[source]
        source: Box<YamlError>,
    },
    /// A problem with the value of one parameter.
    #[error("`{name}`: {source}")]
    InParameter {
        /// The parameter's name.
        name: String,
        /// The problem.
        #[source]
        source: Box<YamlError>,
    },
}

/// Checks the bounds of a YAML text before it is loaded: at most [`MAX_YAML_NODES`] nodes with
/// every alias expanded, and at most [`MAX_YAML_DEPTH`] levels. Walks the parser's events
/// without building anything, so a text that breaks a bound costs no more than its size.
fn check_yaml_bounds(text: &str) -> Result<(), YamlError> {
    let mut parser = Parser::new_from_str(text);
    // Open collections: (anchor id, node count when it opened).
    let mut open: Vec<(usize, u64)> = Vec::new();
    // Anchored nodes' sizes, aliases inside them expanded.
    let mut sizes: HashMap<usize, u64> = HashMap::new();
    let mut nodes: u64 = 0;
    loop {
        let (event, _) = parser.next_token().map_err(YamlError::Syntax)?;
        match event {
            Event::StreamEnd => return Ok(()),
            Event::Scalar(_, _, anchor, _) => {
                nodes += 1;
                if anchor > 0 {
                    sizes.insert(anchor, 1);
                }
            }
            Event::SequenceStart(anchor, _) | Event::MappingStart(anchor, _) => {
                nodes += 1;
                open.push((anchor, nodes));
                if open.len() > MAX_YAML_DEPTH {
                    return Err(YamlError::TooDeep);
                }
            }
            Event::SequenceEnd | Event::MappingEnd => {
                if let Some((anchor, start)) = open.pop() {
                    if anchor > 0 {
                        sizes.insert(anchor, nodes - start + 1);
                    }
                }
            }
            Event::Alias(id) => {
                nodes = nodes.saturating_add(sizes.get(&id).copied().unwrap_or(1));
            }
            _ => {}
        }
        if nodes > MAX_YAML_NODES {
            return Err(YamlError::TooManyNodes);
        }
    }
}

/// Errors in the ROS arguments or in a parameter file.
#[derive(Debug, thiserror::Error)]
pub enum ArgsError {
    /// A flag that takes a value was last on the command line or followed by `--`.
    #[error("`{flag}` needs a value")]
    MissingValue {
        /// The flag.
        flag: String,
    },
    /// An argument inside `--ros-args` that rcl would not accept either.
    #[error(
        "unknown ROS argument `{0}` (end the ROS arguments with `--` to give the node its own \
         options)"
    )]
    UnknownRosArg(String),
    /// A malformed `-r` rule.
    #[error("bad remap rule `{arg}`: {reason}")]
    BadRemap {
        /// The rule as given.
        arg: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A malformed `-p` assignment.
    #[error("bad parameter assignment `{arg}`: {reason}")]
    BadParam {
        /// The assignment as given.
        arg: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A `--log-level` value that names no level.
    #[error(
        "bad log level `{arg}`: expected debug, info, warn, error or fatal, optionally as \
         LOGGER:=LEVEL"
    )]
    BadLogLevel {
        /// The value as given.
        arg: String,
    },
    /// A parameter file that cannot be read.
    #[error("cannot read parameter file {}", path.display())]
    ReadParamsFile {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A parameter file that is not a ROS 2 parameter file.
    #[error("parameter file {}: {reason}", path.display())]
    BadParamsFile {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        reason: YamlError,
    },
}

/// A ROS log severity as `--log-level` spells it (case-insensitive).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum LogLevel {
    /// `debug`.
    Debug,
    /// `info`.
    Info,
    /// `warn` (or `warning`).
    Warn,
    /// `error`.
    Error,
    /// `fatal`.
    Fatal,
}

impl LogLevel {
    /// Parses `debug|info|warn|warning|error|fatal`, in any case.
    pub fn parse(s: &str) -> Option<LogLevel> {
        match s.to_ascii_lowercase().as_str() {
            "debug" => Some(LogLevel::Debug),
            "info" => Some(LogLevel::Info),
            "warn" | "warning" => Some(LogLevel::Warn),
            "error" => Some(LogLevel::Error),
            "fatal" => Some(LogLevel::Fatal),
            _ => None,
        }
    }

    /// The `log` crate filter for this level (`fatal` maps to `error`, the highest it has).
    pub fn to_filter(self) -> log::LevelFilter {
        match self {
            LogLevel::Debug => log::LevelFilter::Debug,
            LogLevel::Info => log::LevelFilter::Info,
            LogLevel::Warn => log::LevelFilter::Warn,
            LogLevel::Error | LogLevel::Fatal => log::LevelFilter::Error,
        }
    }
}

/// Which names a remap rule applies to (`rostopic://` / `rosservice://` prefixes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RemapKind {
    /// Topics and services alike (no prefix).
    Any,
    /// Topics only (`rostopic://`).
    Topic,
    /// Services only (`rosservice://`).
    Service,
}

/// One `-r [node:]from:=to` rule.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Remap {
    /// Only for the node of this name, if given (`node:` prefix).
    pub node: Option<String>,
    /// Which kind of names the rule applies to.
    pub kind: RemapKind,
    /// The name to match (may be relative or start with `~`), or `__node` / `__ns`.
    pub from: String,
    /// The replacement.
    pub to: String,
}

/// One `-p [node:]name:=value` assignment.
#[derive(Debug, Clone, PartialEq)]
pub struct ParamAssignment {
    /// Only for the node of this name, if given (`node:` prefix).
    pub node: Option<String>,
    /// Parameter name, e.g. `pw01.period_ms`.
    pub name: String,
    /// The value, typed as YAML types it (`500` integer, `500.0` double, `true` bool, ...).
    pub value: ParameterValue,
}

/// Where parameter values come from, in command-line order (a later one wins).
#[derive(Debug, Clone, PartialEq)]
pub enum ParamSource {
    /// `-p name:=value`.
    Assignment(ParamAssignment),
    /// `--params-file FILE`.
    File(PathBuf),
}

/// One `--log-level [logger:=]LEVEL`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LogLevelArg {
    /// The logger the level is for; `None` sets the default level.
    pub logger: Option<String>,
    /// The level.
    pub level: LogLevel,
}

/// Everything found in the `--ros-args` blocks.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RosArgs {
    /// Remap rules, in order (rcl applies the first that matches).
    pub remaps: Vec<Remap>,
    /// Parameter assignments and files, in order (a later value wins).
    pub params: Vec<ParamSource>,
    /// Log levels, in order (a later one wins).
    pub log_levels: Vec<LogLevelArg>,
    /// `-e/--enclave`: the SROS2 enclave; see [`crate::ros::config::security`] for what is done with it.
    pub enclave: Option<String>,
    /// `--log-config-file` (accepted; this node configures logging from `--log-level` only).
    pub log_config_file: Option<PathBuf>,
    /// `--enable-rosout-logs` / `--disable-rosout-logs`; `None` = default (on).
    pub rosout_logs: Option<bool>,
    /// `--enable-stdout-logs` / `--disable-stdout-logs`; `None` = default (on). The node logs to
    /// stderr, as rcl's console logger does; this switch turns that off.
    pub stdout_logs: Option<bool>,
    /// `--enable-external-lib-logs` / `--disable-external-lib-logs`; `None` = default (off).
    pub external_lib_logs: Option<bool>,
}

/// The command line split into the node's own arguments and the ROS arguments.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ParsedArgs {
    /// Arguments outside any `--ros-args` block, in order.
    pub app: Vec<String>,
    /// The ROS arguments.
    pub ros: RosArgs,
}

/// Splits `args` (without the program name) into the node's own arguments and the ROS
/// arguments, and parses the latter.
pub fn parse(args: &[String]) -> Result<ParsedArgs, ArgsError> {
    let mut out = ParsedArgs::default();
    let mut in_ros = false;
    let mut it = args.iter();
    while let Some(arg) = it.next() {
        if !in_ros {
            if arg == "--ros-args" {
                in_ros = true;
            } else {
                out.app.push(arg.clone());
            }
            continue;
        }
        let mut value = |flag: &str| -> Result<String, ArgsError> {
            match it.next() {
                Some(v) if v != "--" => Ok(v.clone()),
                _ => Err(ArgsError::MissingValue {
                    flag: flag.to_string(),
                }),
            }
        };
        match arg.as_str() {
            "--" => in_ros = false,
            // rcl tolerates a repeated `--ros-args` inside a block.
            "--ros-args" => {}
            "-r" | "--remap" => {
                let v = value(arg)?;
                out.ros.remaps.push(parse_remap(&v)?);
            }
            "-p" | "--param" => {
                let v = value(arg)?;
                out.ros
                    .params
                    .push(ParamSource::Assignment(parse_assignment(&v)?));
            }
            "--params-file" => {
                let v = value(arg)?;
                out.ros.params.push(ParamSource::File(PathBuf::from(v)));
            }
            "--log-level" => {
                let v = value(arg)?;
                out.ros.log_levels.push(parse_log_level(&v)?);
            }
            "--log-config-file" => {
                let v = value(arg)?;
                out.ros.log_config_file = Some(PathBuf::from(v));
            }
            "-e" | "--enclave" => {
                let v = value(arg)?;
                out.ros.enclave = Some(v);
            }
            "--enable-rosout-logs" => out.ros.rosout_logs = Some(true),
            "--disable-rosout-logs" => out.ros.rosout_logs = Some(false),
            "--enable-stdout-logs" => out.ros.stdout_logs = Some(true),
            "--disable-stdout-logs" => out.ros.stdout_logs = Some(false),
            "--enable-external-lib-logs" => out.ros.external_lib_logs = Some(true),
            "--disable-external-lib-logs" => out.ros.external_lib_logs = Some(false),
            other => return Err(ArgsError::UnknownRosArg(other.to_string())),
        }
    }
    Ok(out)
}

/// Splits an optional `node:` prefix off the left-hand side of a `:=` rule.
fn split_node_prefix(lhs: &str) -> (Option<&str>, &str) {
    // `rostopic://x` and `rosservice://x` contain a colon that is not a node prefix.
    if lhs.starts_with("rostopic://") || lhs.starts_with("rosservice://") {
        return (None, lhs);
    }
    match lhs.split_once(':') {
        Some((node, rest)) => (Some(node), rest),
        None => (None, lhs),
    }
}

/// A node base name as ROS accepts it: `[A-Za-z_][A-Za-z0-9_]*`.
pub fn is_valid_base_name(s: &str) -> bool {
    let mut chars = s.chars();
    match chars.next() {
        Some(c) if c.is_ascii_alphabetic() || c == '_' => {}
        _ => return false,
    }
    chars.all(|c| c.is_ascii_alphanumeric() || c == '_')
}

/// Parses `[node:]from:=to`.
pub fn parse_remap(arg: &str) -> Result<Remap, ArgsError> {
    let bad = |reason: &str| ArgsError::BadRemap {
        arg: arg.to_string(),
        reason: reason.to_string(),
    };
    let (lhs, to) = arg
        .split_once(":=")
        .ok_or_else(|| bad("expected FROM:=TO"))?;
    let (node, from) = split_node_prefix(lhs);
    if let Some(n) = node {
        if !is_valid_base_name(n) {
            return Err(bad(&format!("`{n}` before `:` is not a node name")));
        }
    }
    let (kind, from) = if let Some(rest) = from.strip_prefix("rostopic://") {
        (RemapKind::Topic, rest)
    } else if let Some(rest) = from.strip_prefix("rosservice://") {
        (RemapKind::Service, rest)
    } else {
        (RemapKind::Any, from)
    };
    if from.is_empty() {
        return Err(bad("nothing to match before `:=`"));
    }
    if to.is_empty() {
        return Err(bad("no replacement after `:=`"));
    }
    let from = if from == "__name" { "__node" } else { from };
    match from {
        "__node" if !is_valid_base_name(to) => {
            return Err(bad(&format!(
                "`{to}` is not a valid node name (letters, digits and `_`, not starting with a \
                 digit)"
            )))
        }
        "__ns" if !to.starts_with('/') => {
            return Err(bad(&format!(
                "the namespace must be absolute, starting with `/`: got `{to}`"
            )))
        }
        _ => {}
    }
    if kind != RemapKind::Any && from.starts_with("__") {
        return Err(bad(
            "`__node` and `__ns` take no rostopic:// or rosservice:// prefix",
        ));
    }
    Ok(Remap {
        node: node.map(str::to_string),
        kind,
        from: from.to_string(),
        to: to.to_string(),
    })
}

/// A parameter name as ROS accepts it: tokens of `[A-Za-z0-9_]` separated by single dots.
pub fn is_valid_param_name(s: &str) -> bool {
    !s.is_empty()
        && s.split('.')
            .all(|t| !t.is_empty() && t.chars().all(|c| c.is_ascii_alphanumeric() || c == '_'))
}

/// Parses `[node:]name:=value`, the value typed as YAML types it.
pub fn parse_assignment(arg: &str) -> Result<ParamAssignment, ArgsError> {
    let bad = |reason: String| ArgsError::BadParam {
        arg: arg.to_string(),
        reason,
    };
    let (lhs, text) = arg
        .split_once(":=")
        .ok_or_else(|| bad("expected NAME:=VALUE".into()))?;
    let (node, name) = split_node_prefix(lhs);
    if let Some(n) = node {
        if !is_valid_base_name(n) {
            return Err(bad(format!("`{n}` before `:` is not a node name")));
        }
    }
    if !is_valid_param_name(name) {
        return Err(bad(format!(
            "`{name}` is not a parameter name (letters, digits, `_`, separated by `.`)"
        )));
    }
    let value = parse_yaml_value(text).map_err(|e| bad(e.to_string()))?;
    Ok(ParamAssignment {
        node: node.map(str::to_string),
        name: name.to_string(),
        value,
    })
}

/// Types the text after `:=` as YAML does: `500` integer, `500.0` double, `true` bool,
/// `[1, 2]` integer array, anything else a string. An empty value is refused (write `''` for
/// an empty string).
pub fn parse_yaml_value(text: &str) -> Result<ParameterValue, YamlError> {
    check_yaml_bounds(text)?;
    let docs = YamlLoader::load_from_str(text).map_err(YamlError::Syntax)?;
    match docs.as_slice() {
        [] => Err(YamlError::NoValue),
        [doc] => yaml_to_value(doc),
        _ => Err(YamlError::SeveralDocuments),
    }
}

/// Converts a YAML scalar or sequence to a parameter value.
pub fn yaml_to_value(y: &Yaml) -> Result<ParameterValue, YamlError> {
    match y {
        Yaml::Boolean(b) => Ok(ParameterValue::Boolean(*b)),
        Yaml::Integer(i) => Ok(ParameterValue::Integer(*i)),
        Yaml::Real(_) => y
            .as_f64()
            .map(ParameterValue::Double)
            .ok_or(YamlError::NotANumber),
        Yaml::String(s) => Ok(ParameterValue::String(s.clone())),
        Yaml::Array(items) => array_to_value(items),
        Yaml::Null => Err(YamlError::Null),
        Yaml::Hash(_) => Err(YamlError::Mapping),
        Yaml::Alias(_) | Yaml::BadValue => Err(YamlError::Unsupported),
    }
}

fn array_to_value(items: &[Yaml]) -> Result<ParameterValue, YamlError> {
    if items.is_empty() {
        return Err(YamlError::EmptyArray);
    }
    if items.iter().all(|y| matches!(y, Yaml::Boolean(_))) {
        return Ok(ParameterValue::BooleanArray(
            items.iter().filter_map(Yaml::as_bool).collect(),
        ));
    }
    if items.iter().all(|y| matches!(y, Yaml::Integer(_))) {
        return Ok(ParameterValue::IntegerArray(
            items.iter().filter_map(Yaml::as_i64).collect(),
        ));
    }
    if items
        .iter()
        .all(|y| matches!(y, Yaml::Integer(_) | Yaml::Real(_)))
    {
        // Mixed integers and reals: every integer is exactly a double here.
        let v: Vec<f64> = items
            .iter()
            .filter_map(|y| match y {
                Yaml::Integer(i) => Some(*i as f64),
                other => other.as_f64(),
            })
            .collect();
        if v.len() != items.len() {
            return Err(YamlError::ArrayElementNotANumber);
        }
        return Ok(ParameterValue::DoubleArray(v));
    }
    if items.iter().all(|y| matches!(y, Yaml::String(_))) {
        return Ok(ParameterValue::StringArray(
            items
                .iter()
                .filter_map(|y| y.as_str().map(str::to_string))
                .collect(),
        ));
    }
    Err(YamlError::MixedArray)
}

/// Parses `LEVEL` or `LOGGER:=LEVEL`.
pub fn parse_log_level(arg: &str) -> Result<LogLevelArg, ArgsError> {
    let bad = || ArgsError::BadLogLevel {
        arg: arg.to_string(),
    };
    match arg.split_once(":=") {
        Some((logger, level)) if !logger.is_empty() => Ok(LogLevelArg {
            logger: Some(logger.to_string()),
            level: LogLevel::parse(level).ok_or_else(bad)?,
        }),
        Some(_) => Err(bad()),
        None => Ok(LogLevelArg {
            logger: None,
            level: LogLevel::parse(arg).ok_or_else(bad)?,
        }),
    }
}

/// One node section of a parameter file.
#[derive(Debug, Clone, PartialEq)]
pub struct FileSection {
    /// The node pattern, normalised to an absolute name: `/**`, `/pwm_actuator`,
    /// `/ns/pwm_actuator`, `/*/pwm_actuator`.
    pub node: String,
    /// The parameters, nested keys joined with `.`, in file order.
    pub params: Vec<(String, ParameterValue)>,
}

/// The bytes of the file at `path` if it holds at most `max` of them, `None` if it holds more:
/// at most one byte more than the bound is read, whatever the file claims to be (a FIFO,
/// /dev/zero).
pub fn read_at_most(path: &Path, max: u64) -> std::io::Result<Option<Vec<u8>>> {
    let mut bytes = Vec::new();
    std::fs::File::open(path)?
        .take(max + 1)
        .read_to_end(&mut bytes)?;
    Ok((bytes.len() as u64 <= max).then_some(bytes))
}

/// Reads and parses a ROS 2 parameter file.
pub fn load_params_file(path: &Path) -> Result<Vec<FileSection>, ArgsError> {
    let read_err = |source| ArgsError::ReadParamsFile {
        path: path.to_path_buf(),
        source,
    };
    let Some(bytes) = read_at_most(path, MAX_PARAMS_FILE_BYTES).map_err(read_err)? else {
        let size = std::fs::metadata(path)
            .ok()
            .map(|m| m.len())
            .filter(|l| *l > MAX_PARAMS_FILE_BYTES);
        return Err(ArgsError::BadParamsFile {
            path: path.to_path_buf(),
            reason: YamlError::FileTooLarge(size),
        });
    };
    let text = String::from_utf8(bytes).map_err(|e| {
        read_err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            e.utf8_error(),
        ))
    })?;
    parse_params_yaml(&text).map_err(|reason| ArgsError::BadParamsFile {
        path: path.to_path_buf(),
        reason,
    })
}

/// Parses the text of a ROS 2 parameter file: node names (`/**`, `node`, `/ns/node`, or nested
/// `ns: node:`) holding `ros__parameters` mappings.
pub fn parse_params_yaml(text: &str) -> Result<Vec<FileSection>, YamlError> {
    check_yaml_bounds(text)?;
    let docs = YamlLoader::load_from_str(text).map_err(YamlError::Syntax)?;
    let mut sections = Vec::new();
    for doc in &docs {
        match doc {
            Yaml::Hash(h) => walk_nodes(&mut Vec::new(), h, &mut sections)?,
            Yaml::Null => {}
            _ => return Err(YamlError::TopLevel),
        }
    }
    Ok(sections)
}

fn walk_nodes(
    path: &mut Vec<String>,
    h: &yaml_rust2::yaml::Hash,
    out: &mut Vec<FileSection>,
) -> Result<(), YamlError> {
    for (k, v) in h {
        let key = k.as_str().ok_or_else(|| YamlError::NodeNameNotString {
            key: format!("{k:?}"),
            path: path.join("/"),
        })?;
        if key == "ros__parameters" {
            let node = normalise_node_pattern(path);
            if path.is_empty() {
                return Err(YamlError::ParametersWithoutNode);
            }
            let mut params = Vec::new();
            match v {
                Yaml::Hash(p) => {
                    flatten_params("", p, &mut params).map_err(|e| YamlError::UnderNode {
                        node: node.clone(),
                        source: Box::new(e),
                    })?
                }
                Yaml::Null => {}
                _ => return Err(YamlError::ParametersNotMapping { node }),
            }
            out.push(FileSection { node, params });
        } else {
            match v {
                Yaml::Hash(inner) => {
                    path.push(key.to_string());
                    walk_nodes(path, inner, out)?;
                    path.pop();
                }
                _ => {
                    return Err(YamlError::ValueOutsideParameters {
                        key: key.to_string(),
                        path: path.join("/"),
                    })
                }
            }
        }
    }
    Ok(())
}

/// Joins nested node keys (each of which may itself contain `/`) into one absolute pattern.
fn normalise_node_pattern(path: &[String]) -> String {
    let tokens: Vec<&str> = path
        .iter()
        .flat_map(|p| p.split('/'))
        .filter(|t| !t.is_empty())
        .collect();
    format!("/{}", tokens.join("/"))
}

fn flatten_params(
    prefix: &str,
    h: &yaml_rust2::yaml::Hash,
    out: &mut Vec<(String, ParameterValue)>,
) -> Result<(), YamlError> {
    for (k, v) in h {
        let key = match k {
            Yaml::String(s) => s.clone(),
            Yaml::Integer(i) => i.to_string(),
            Yaml::Boolean(b) => b.to_string(),
            other => return Err(YamlError::ParameterNameNotString(format!("{other:?}"))),
        };
        let name = if prefix.is_empty() {
            key
        } else {
            format!("{prefix}.{key}")
        };
        match v {
            Yaml::Hash(inner) => flatten_params(&name, inner, out)?,
            leaf => {
                let value = yaml_to_value(leaf).map_err(|e| YamlError::InParameter {
                    name: name.clone(),
                    source: Box::new(e),
                })?;
                out.push((name, value));
            }
        }
    }
    Ok(())
}

/// Whether a parameter-file node pattern matches a fully qualified node name. `*` matches
/// within one name token, `**` matches any number of tokens (rclcpp's wildcard rules).
pub fn node_pattern_matches(pattern: &str, fqn: &str) -> bool {
    let p: Vec<&str> = pattern.split('/').filter(|t| !t.is_empty()).collect();
    let n: Vec<&str> = fqn.split('/').filter(|t| !t.is_empty()).collect();
    match_tokens(&p, &n)
}

fn match_tokens(p: &[&str], n: &[&str]) -> bool {
    match p.split_first() {
        None => n.is_empty(),
        Some((&"**", rest)) => (0..=n.len()).any(|skip| match_tokens(rest, &n[skip..])),
        Some((tok, rest)) => match n.split_first() {
            Some((name, nrest)) => {
                glob(tok.as_bytes(), name.as_bytes()) && match_tokens(rest, nrest)
            }
            None => false,
        },
    }
}

/// `*` matches any run of characters; everything else matches itself.
fn glob(p: &[u8], s: &[u8]) -> bool {
    match p.split_first() {
        None => s.is_empty(),
        Some((b'*', rest)) => (0..=s.len()).any(|k| glob(rest, &s[k..])),
        Some((c, rest)) => s.first() == Some(c) && glob(rest, &s[1..]),
    }
}

/// Whether a pattern contains a wildcard.
fn is_wildcard(pattern: &str) -> bool {
    pattern.contains('*')
}

/// The parameters a file gives the node `fqn`, in the order they apply: every matching wildcard
/// section first (file order), then every exact section (file order), so that a section naming
/// the node wins over `/**`.
pub fn params_for_node(sections: &[FileSection], fqn: &str) -> Vec<(String, ParameterValue)> {
    let matching = |wild: bool| {
        sections
            .iter()
            .filter(move |s| is_wildcard(&s.node) == wild && node_pattern_matches(&s.node, fqn))
            .flat_map(|s| s.params.iter().cloned())
    };
    matching(true).chain(matching(false)).collect()
}

/// A parameter value and where it came from, for messages.
#[derive(Debug, Clone, PartialEq)]
pub struct Override {
    /// Parameter name.
    pub name: String,
    /// Value as given (before any coercion to the declared type).
    pub value: ParameterValue,
    /// `-p` or `--params-file FILE`, for log lines and errors.
    pub origin: String,
}

impl RosArgs {
    /// Every parameter value given for node `node_name` (fully qualified `fqn`), in the order
    /// they apply (a later one wins). Reads the parameter files.
    pub fn overrides(&self, node_name: &str, fqn: &str) -> Result<Vec<Override>, ArgsError> {
        let mut out = Vec::new();
        for src in &self.params {
            match src {
                ParamSource::Assignment(a) => {
                    if a.node.as_deref().is_none_or(|n| n == node_name) {
                        out.push(Override {
                            name: a.name.clone(),
                            value: a.value.clone(),
                            origin: "-p".into(),
                        });
                    }
                }
                ParamSource::File(path) => {
                    let sections = load_params_file(path)?;
                    for (name, value) in params_for_node(&sections, fqn) {
                        out.push(Override {
                            name,
                            value,
                            origin: format!("--params-file {}", path.display()),
                        });
                    }
                }
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(s: &[&str]) -> Vec<String> {
        s.iter().map(|a| a.to_string()).collect()
    }

    fn parse_ok(s: &[&str]) -> ParsedArgs {
        match parse(&args(s)) {
            Ok(p) => p,
            Err(e) => panic!("{s:?}: {e}"),
        }
    }

    #[test]
    fn app_args_outside_blocks_are_kept_in_order() {
        let p = parse_ok(&[
            "--demo",
            "--ros-args",
            "-r",
            "__node:=heater",
            "--",
            "--trace",
            "x.vcd",
            "--ros-args",
            "-p",
            "a:=1",
        ]);
        assert_eq!(p.app, args(&["--demo", "--trace", "x.vcd"]));
        assert_eq!(p.ros.remaps.len(), 1);
        assert_eq!(p.ros.params.len(), 1);
    }

    #[test]
    fn no_ros_args_means_everything_is_the_nodes() {
        let p = parse_ok(&["--output", "sim", "--", "-p"]);
        assert_eq!(p.app, args(&["--output", "sim", "--", "-p"]));
        assert_eq!(p.ros, RosArgs::default());
    }

    #[test]
    fn remaps_with_node_prefix_and_kinds() {
        let p = parse_ok(&[
            "--ros-args",
            "-r",
            "pwm_actuator:~/pw01/duty:=/heater/duty",
            "--remap",
            "rostopic://diagnostics:=/diag",
            "-r",
            "other:rosservice://x:=y",
            "-r",
            "__name:=renamed",
            "-r",
            "__ns:=/plant",
        ]);
        let r = &p.ros.remaps;
        assert_eq!(
            r[0],
            Remap {
                node: Some("pwm_actuator".into()),
                kind: RemapKind::Any,
                from: "~/pw01/duty".into(),
                to: "/heater/duty".into()
            }
        );
        assert_eq!((r[1].node.as_deref(), r[1].kind), (None, RemapKind::Topic));
        assert_eq!(r[1].from, "diagnostics");
        assert_eq!(
            (r[2].node.as_deref(), r[2].kind, r[2].from.as_str()),
            (Some("other"), RemapKind::Service, "x")
        );
        assert_eq!(r[3].from, "__node", "__name is the old spelling of __node");
        assert_eq!((r[4].from.as_str(), r[4].to.as_str()), ("__ns", "/plant"));
    }

    #[test]
    fn bad_remaps_and_params_say_why() {
        for (flag, rule, why) in [
            ("-r", "foo", "expected FROM:=TO"),
            ("-r", ":=bar", "nothing to match"),
            ("-r", "foo:=", "no replacement"),
            ("-r", "__node:=9lives", "not a valid node name"),
            ("-r", "__ns:=plant", "must be absolute"),
            ("-r", "bad-node:x:=y", "not a node name"),
            ("-p", "x", "expected NAME:=VALUE"),
            ("-p", "x:=", "no value"),
            ("-p", "x:=[]", "empty array"),
            ("-p", "x:=[1, a]", "one type"),
            ("-p", "x:={a: 1}", "mapping"),
            ("-p", "a..b:=1", "not a parameter name"),
            ("-p", "x:=[1, 2", "not valid YAML"),
        ] {
            let e = parse(&args(&["--ros-args", flag, rule])).unwrap_err();
            let kind = match e {
                ArgsError::BadRemap { .. } => "-r",
                ArgsError::BadParam { .. } => "-p",
                _ => "other",
            };
            assert!(
                kind == flag && e.to_string().contains(why),
                "{flag} {rule}: {e}"
            );
        }
    }

    #[test]
    fn param_values_are_yaml_typed() {
        let p = parse_ok(&[
            "--ros-args",
            "-p",
            "pw01.period_ms:=500",
            "-p",
            "pw01.duty:=37.5",
            "-p",
            "pw01.enable:=true",
            "-p",
            "pw01.profile:=twincat_ba",
            "-p",
            "trace:='a.vcd'",
            "-p",
            "pwm_actuator:lines:=[1, 2]",
            "--param",
            "d:=[1, 2.5]",
            "-p",
            "s:=''",
            "-p",
            "on:=on",
        ]);
        let v: Vec<(Option<String>, String, ParameterValue)> = p
            .ros
            .params
            .iter()
            .map(|s| match s {
                ParamSource::Assignment(a) => (a.node.clone(), a.name.clone(), a.value.clone()),
                ParamSource::File(_) => unreachable!(),
            })
            .collect();
        use ParameterValue as V;
        assert_eq!(v[0].2, V::Integer(500));
        assert_eq!(v[1].2, V::Double(37.5));
        assert_eq!(v[2].2, V::Boolean(true));
        assert_eq!(v[3].2, V::String("twincat_ba".into()));
        assert_eq!(v[4].2, V::String("a.vcd".into()));
        assert_eq!(
            (v[5].0.as_deref(), v[5].2.clone()),
            (Some("pwm_actuator"), V::IntegerArray(vec![1, 2]))
        );
        assert_eq!(v[6].2, V::DoubleArray(vec![1.0, 2.5]));
        assert_eq!(v[7].2, V::String(String::new()));
        // YAML 1.2: `on` is a string, not a bool.
        assert_eq!(v[8].2, V::String("on".into()));
    }

    #[test]
    fn special_float_values_parse() {
        assert!(matches!(parse_yaml_value(".nan"), Ok(ParameterValue::Double(d)) if d.is_nan()));
        assert_eq!(
            parse_yaml_value("-.inf"),
            Ok(ParameterValue::Double(f64::NEG_INFINITY))
        );
        assert_eq!(parse_yaml_value("1e3"), Ok(ParameterValue::Double(1000.0)));
    }

    #[test]
    fn log_levels() {
        let p = parse_ok(&[
            "--ros-args",
            "--log-level",
            "DEBUG",
            "--log-level",
            "pwm_actuator:=warn",
            "--log-level",
            "rustdds:=Error",
        ]);
        assert_eq!(
            p.ros.log_levels,
            vec![
                LogLevelArg {
                    logger: None,
                    level: LogLevel::Debug
                },
                LogLevelArg {
                    logger: Some("pwm_actuator".into()),
                    level: LogLevel::Warn
                },
                LogLevelArg {
                    logger: Some("rustdds".into()),
                    level: LogLevel::Error
                },
            ]
        );
        for bad in ["loud", ":=info", "x:=loud"] {
            let e = parse(&args(&["--ros-args", "--log-level", bad])).unwrap_err();
            assert!(matches!(e, ArgsError::BadLogLevel { .. }), "{bad}: {e}");
        }
        assert_eq!(LogLevel::Fatal.to_filter(), log::LevelFilter::Error);
    }

    #[test]
    fn flags_and_switches() {
        let p = parse_ok(&[
            "--ros-args",
            "--disable-rosout-logs",
            "--disable-stdout-logs",
            "--enable-external-lib-logs",
            "-e",
            "/enclave",
            "--log-config-file",
            "x.conf",
            "--params-file",
            "p.yaml",
        ]);
        assert_eq!(p.ros.rosout_logs, Some(false));
        assert_eq!(p.ros.stdout_logs, Some(false));
        assert_eq!(p.ros.external_lib_logs, Some(true));
        assert_eq!(p.ros.enclave.as_deref(), Some("/enclave"));
        assert_eq!(p.ros.params, vec![ParamSource::File("p.yaml".into())]);
    }

    #[test]
    fn errors_for_unknown_and_missing() {
        let e = parse(&args(&["--ros-args", "--demo"])).unwrap_err();
        assert!(
            matches!(e, ArgsError::UnknownRosArg(ref a) if a == "--demo"),
            "{e}"
        );
        assert!(e.to_string().contains("end the ROS arguments with `--`"));
        for flag in ["-r", "-p", "--params-file", "--log-level", "-e"] {
            let e = parse(&args(&["--ros-args", flag])).unwrap_err();
            assert!(matches!(e, ArgsError::MissingValue { .. }), "{flag}: {e}");
            let e = parse(&args(&["--ros-args", flag, "--"])).unwrap_err();
            assert!(
                matches!(e, ArgsError::MissingValue { .. }),
                "{flag} --: {e}"
            );
        }
    }

    const FILE: &str = r#"
/**:
  ros__parameters:
    status_rate_hz: 5
    pw01:
      period_ms: 2000
      profile: twincat_ba
pwm_actuator:
  ros__parameters:
    pw01.period_ms: 500
    pw02:
      edge_band: 0.25
/plant/pwm_actuator:
  ros__parameters:
    channels: 3
plant:
  heater:
    ros__parameters:
      trace: "h.vcd"
/*/heater:
  ros__parameters:
    rt_priority: 10
other_node:
  ros__parameters:
    x: 1
"#;

    #[test]
    fn params_file_sections_are_normalised() {
        let s = parse_params_yaml(FILE).unwrap();
        let nodes: Vec<&str> = s.iter().map(|s| s.node.as_str()).collect();
        assert_eq!(
            nodes,
            [
                "/**",
                "/pwm_actuator",
                "/plant/pwm_actuator",
                "/plant/heater",
                "/*/heater",
                "/other_node"
            ]
        );
        assert_eq!(
            s[0].params,
            vec![
                ("status_rate_hz".into(), ParameterValue::Integer(5)),
                ("pw01.period_ms".into(), ParameterValue::Integer(2000)),
                (
                    "pw01.profile".into(),
                    ParameterValue::String("twincat_ba".into())
                ),
            ]
        );
    }

    #[test]
    fn params_for_node_applies_wildcards_first_then_the_node() {
        let s = parse_params_yaml(FILE).unwrap();
        let names_for = |node: &str| -> Vec<String> {
            params_for_node(&s, node)
                .into_iter()
                .map(|(n, _)| n)
                .collect()
        };
        let common = ["status_rate_hz", "pw01.period_ms", "pw01.profile"];
        for (node, own) in [
            ("/pwm_actuator", &["pw01.period_ms", "pw02.edge_band"][..]),
            ("/plant/pwm_actuator", &["channels"][..]),
            ("/plant/heater", &["rt_priority", "trace"][..]),
        ] {
            let expected: Vec<&str> = common.iter().chain(own).copied().collect();
            assert_eq!(names_for(node), expected, "{node}");
        }
        // The node's own section comes last, so its 500 wins over /**'s 2000.
        let p = params_for_node(&s, "/pwm_actuator");
        assert_eq!(p[3].1, ParameterValue::Integer(500));
    }

    #[test]
    fn node_patterns() {
        assert!(node_pattern_matches("/**", "/pwm_actuator"));
        assert!(node_pattern_matches("/**", "/a/b/c"));
        assert!(node_pattern_matches("/**/pwm_actuator", "/pwm_actuator"));
        assert!(node_pattern_matches(
            "/**/pwm_actuator",
            "/a/b/pwm_actuator"
        ));
        assert!(!node_pattern_matches("/**/pwm_actuator", "/a/b/other"));
        assert!(node_pattern_matches("/*/pwm_actuator", "/a/pwm_actuator"));
        assert!(!node_pattern_matches("/*/pwm_actuator", "/pwm_actuator"));
        assert!(node_pattern_matches("/pwm_*", "/pwm_actuator"));
        assert!(!node_pattern_matches("/pwm_actuator", "/ns/pwm_actuator"));
        assert!(node_pattern_matches("/ns/pwm_actuator", "/ns/pwm_actuator"));
    }

    #[test]
    fn bad_params_files_say_why() {
        for (text, why) in [
            ("- 1\n- 2\n", "top level"),
            ("ros__parameters: {a: 1}\n", "must be under a node name"),
            ("node:\n  x: 1\n", "only node names"),
            ("node:\n  ros__parameters: 3\n", "must be a mapping"),
            ("node:\n  ros__parameters:\n    a: ~\n", "`a`: no value"),
            ("node:\n  ros__parameters:\n    a: [1, x]\n", "one type"),
            ("node: [", "not valid YAML"),
        ] {
            let e = parse_params_yaml(text).unwrap_err().to_string();
            assert!(e.contains(why), "{text:?}: {e}");
        }
        assert!(parse_params_yaml("").unwrap().is_empty());
    }

    /// A YAML "billion laughs": each level is `fan` aliases of the one before, so the text
    /// stays small and the expanded tree has `fan^levels` leaves.
    fn alias_bomb(levels: usize, fan: usize) -> String {
        let mut t = String::from("/**:\n  ros__parameters:\n    l0: &l0 [x]\n");
        for l in 1..=levels {
            let refs = vec![format!("*l{}", l - 1); fan].join(", ");
            t.push_str(&format!("    l{l}: &l{l} [{refs}]\n"));
        }
        t
    }

    #[test]
    fn params_files_are_bounded() {
        // 10^6 leaves from a 500-byte text.
        let bomb = alias_bomb(6, 10);
        assert!(bomb.len() < 600, "{}", bomb.len());
        let e = parse_params_yaml(&bomb).unwrap_err();
        assert_eq!(e, YamlError::TooManyNodes);
        assert!(e.to_string().contains("more than 100000 nodes"), "{e}");
        // A few aliases are fine.
        let small =
            parse_params_yaml("/**:\n  ros__parameters:\n    a: &v 5\n    b: *v\n").unwrap();
        assert_eq!(
            small[0].params,
            vec![
                ("a".to_string(), ParameterValue::Integer(5)),
                ("b".to_string(), ParameterValue::Integer(5))
            ]
        );
        // The same holds for `-p` values.
        let inline = format!(
            "[{}]",
            (0..6).fold(String::from("&a0 [x]"), |acc, l| format!(
                "[{acc}, &a{} [{}]]",
                l + 1,
                vec![format!("*a{l}"); 10].join(",")
            ))
        );
        assert_eq!(parse_yaml_value(&inline), Err(YamlError::TooManyNodes));
        // Nesting.
        let deep = format!(
            "/**:\n  ros__parameters:\n    a: {}1{}\n",
            "[".repeat(100),
            "]".repeat(100)
        );
        let e = parse_params_yaml(&deep).unwrap_err();
        assert_eq!(e, YamlError::TooDeep);
        assert!(e.to_string().contains("nested deeper than 64"), "{e}");
        // Size, checked before the file is parsed.
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let file = dir.join("big.yaml");
        let mut text = String::from("/**:\n  ros__parameters:\n    a: 1\n");
        while text.len() <= 1 << 20 {
            text.push_str("# padding padding padding padding padding padding padding\n");
        }
        std::fs::write(&file, &text).unwrap();
        let e = load_params_file(&file).unwrap_err();
        assert!(matches!(e, ArgsError::BadParamsFile { .. }), "{e}");
        assert!(e.to_string().contains("larger than 1 MiB"), "{e}");
    }

    #[test]
    fn overrides_keep_command_line_order_and_filter_by_node() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let file = dir.join("p.yaml");
        std::fs::write(&file, FILE).unwrap();
        let f = file.to_string_lossy().to_string();
        let p = parse_ok(&[
            "--ros-args",
            "-p",
            "pw01.period_ms:=100",
            "--params-file",
            &f,
            "-p",
            "other:pw01.period_ms:=7",
            "-p",
            "pwm_actuator:pw02.period_ms:=300",
        ]);
        let o = p.ros.overrides("pwm_actuator", "/pwm_actuator").unwrap();
        let got: Vec<(&str, &str)> = o
            .iter()
            .map(|o| (o.name.as_str(), &o.origin[..2]))
            .collect();
        assert_eq!(
            got,
            [
                ("pw01.period_ms", "-p"),
                ("status_rate_hz", "--"),
                ("pw01.period_ms", "--"),
                ("pw01.profile", "--"),
                ("pw01.period_ms", "--"),
                ("pw02.edge_band", "--"),
                ("pw02.period_ms", "-p"),
            ]
        );
        let missing = parse_ok(&["--ros-args", "--params-file", "/nonexistent/p.yaml"]);
        let e = missing
            .ros
            .overrides("pwm_actuator", "/pwm_actuator")
            .unwrap_err();
        assert!(matches!(e, ArgsError::ReadParamsFile { .. }), "{e}");
        assert!(e.to_string().contains("/nonexistent/p.yaml"));
    }
}
