//! REP-2016 type hashes (`RIHS01_<64 hex digits>`) of every interface the node uses, computed
//! from their `.msg`, `.srv` and `.action` definitions the way
//! `rosidl_generator_type_description` does, and announced in each endpoint's USER_DATA
//! (`typehash=RIHS01_...;`) as every ROS 2 middleware does since Iron.
//!
//! The definitions are compiled in: the node's own `msg/*.msg` and `msg/action/*.action`, and
//! the standard ones it uses (and those they reference) in `interfaces/<package>/{msg,srv}/`,
//! as ROS 2 Jazzy ships them.
//! The hash of a type is the SHA-256 of the canonical JSON of its `TypeDescription` (its
//! fields, with type ids, capacities, string capacities and nested type names, then every type
//! it references, sorted by name), without default values. A service has the type
//! `<pkg>/srv/<Name>` with the fields `request_message`, `response_message` and
//! `event_message`; its request and response are messages of their own
//! (`<Name>_Request`, `<Name>_Response`), and `<Name>_Event` is made from them. rmw_fastrtps
//! announces the request type's hash on a service's request topic and the response type's on
//! its reply topic; so does this node.
//!
//! An action `<pkg>/action/<Name>` is expanded as `rosidl_parser`'s `Action` does: the messages
//! `<Name>_Goal`, `<Name>_Result` and `<Name>_Feedback` of its three parts; the services
//! `<Name>_SendGoal` (request: `unique_identifier_msgs/UUID goal_id`, `<Name>_Goal goal`;
//! response: `bool accepted`, `builtin_interfaces/Time stamp`) and `<Name>_GetResult`
//! (request: `goal_id`; response: `int8 status`, `<Name>_Result result`), each with its
//! request, response and event; the message `<Name>_FeedbackMessage` (`goal_id`,
//! `<Name>_Feedback feedback`); and the action type itself, whose fields `goal`, `result`,
//! `feedback`, `send_goal_service`, `get_result_service` and `feedback_message` name them. The
//! action's topics carry the request and response types of its two services, its feedback
//! message, and `action_msgs`' `CancelGoal` and `GoalStatusArray`.
//!
//! `tests/rclpy/test_type_hashes.py` compares what every endpoint of the node announces with
//! the hashes rosidl wrote in its `.json` files.
//!
//! rmw_zenoh carries the same hashes in its key expressions and liveliness tokens, beside a
//! type name of its own for each endpoint ([`zenoh_type_name`]): there a service is one
//! endpoint, named and hashed as the service type, not as its request and response.

use sha2::{Digest, Sha256};
use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;

/// One interface definition: a `.msg`, `.srv` or `.action` file.
struct Definition {
    /// ROS package, e.g. `std_msgs`.
    package: &'static str,
    /// `msg`, `srv` or `action`.
    kind: &'static str,
    /// Type name inside the package, e.g. `Float64`.
    name: &'static str,
    /// The file's text.
    text: &'static str,
}

/// A definition of `interfaces/<pkg>/<kind>/<name>.<kind>`.
macro_rules! standard {
    ($pkg:literal, $kind:literal, $name:literal) => {
        Definition {
            package: $pkg,
            kind: $kind,
            name: $name,
            text: include_str!(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/interfaces/",
                $pkg,
                "/",
                $kind,
                "/",
                $name,
                ".",
                $kind
            )),
        }
    };
}

/// A message of this node's package, `msg/<name>.msg`.
macro_rules! own {
    ($name:literal) => {
        Definition {
            package: super::msg::MSG_PACKAGE,
            kind: "msg",
            name: $name,
            text: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/msg/", $name, ".msg")),
        }
    };
}

/// An action of this node's package, `msg/action/<name>.action`.
macro_rules! own_action {
    ($name:literal) => {
        Definition {
            package: super::msg::MSG_PACKAGE,
            kind: "action",
            name: $name,
            text: include_str!(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/msg/action/",
                $name,
                ".action"
            )),
        }
    };
}

/// Every definition compiled in. A unit test checks that this is every file of `msg/` and
/// `interfaces/`, and that every type they reference is here.
const DEFINITIONS: &[Definition] = &[
    own!("ChannelParams"),
    own!("ChannelStatus"),
    own!("OutputEdge"),
    own!("ValveState"),
    own_action!("Autotune"),
    standard!("action_msgs", "msg", "GoalInfo"),
    standard!("action_msgs", "msg", "GoalStatus"),
    standard!("action_msgs", "msg", "GoalStatusArray"),
    standard!("action_msgs", "srv", "CancelGoal"),
    standard!("builtin_interfaces", "msg", "Duration"),
    standard!("builtin_interfaces", "msg", "Time"),
    standard!("diagnostic_msgs", "msg", "DiagnosticArray"),
    standard!("diagnostic_msgs", "msg", "DiagnosticStatus"),
    standard!("diagnostic_msgs", "msg", "KeyValue"),
    standard!("lifecycle_msgs", "msg", "State"),
    standard!("lifecycle_msgs", "msg", "Transition"),
    standard!("lifecycle_msgs", "msg", "TransitionDescription"),
    standard!("lifecycle_msgs", "msg", "TransitionEvent"),
    standard!("lifecycle_msgs", "srv", "ChangeState"),
    standard!("lifecycle_msgs", "srv", "GetAvailableStates"),
    standard!("lifecycle_msgs", "srv", "GetAvailableTransitions"),
    standard!("lifecycle_msgs", "srv", "GetState"),
    standard!("rcl_interfaces", "msg", "FloatingPointRange"),
    standard!("rcl_interfaces", "msg", "IntegerRange"),
    standard!("rcl_interfaces", "msg", "ListParametersResult"),
    standard!("rcl_interfaces", "msg", "Log"),
    standard!("rcl_interfaces", "msg", "Parameter"),
    standard!("rcl_interfaces", "msg", "ParameterDescriptor"),
    standard!("rcl_interfaces", "msg", "ParameterEvent"),
    standard!("rcl_interfaces", "msg", "ParameterType"),
    standard!("rcl_interfaces", "msg", "ParameterValue"),
    standard!("rcl_interfaces", "msg", "SetParametersResult"),
    standard!("rcl_interfaces", "srv", "DescribeParameters"),
    standard!("rcl_interfaces", "srv", "GetParameterTypes"),
    standard!("rcl_interfaces", "srv", "GetParameters"),
    standard!("rcl_interfaces", "srv", "ListParameters"),
    standard!("rcl_interfaces", "srv", "SetParameters"),
    standard!("rcl_interfaces", "srv", "SetParametersAtomically"),
    standard!("rmw_dds_common", "msg", "Gid"),
    standard!("rmw_dds_common", "msg", "NodeEntitiesInfo"),
    standard!("rmw_dds_common", "msg", "ParticipantEntitiesInfo"),
    standard!("sensor_msgs", "msg", "Temperature"),
    standard!("service_msgs", "msg", "ServiceEventInfo"),
    standard!("std_msgs", "msg", "Bool"),
    standard!("std_msgs", "msg", "Float64"),
    standard!("std_msgs", "msg", "Header"),
    standard!("std_msgs", "msg", "String"),
    standard!("std_msgs", "msg", "UInt16"),
    standard!("std_srvs", "srv", "Trigger"),
    standard!("unique_identifier_msgs", "msg", "UUID"),
];

/// Why the definitions do not give a hash. The definitions are compiled in, so this is a
/// mistake in them, which the unit tests catch; the node then announces no hashes.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TypeHashError {
    /// A field line does not parse.
    #[error("{type_name}: cannot read the field line {line:?}: {why}")]
    Field {
        /// The type whose definition holds the line, e.g. `std_msgs/msg/Header`.
        type_name: String,
        /// The line, comment removed.
        line: String,
        /// What is wrong with it.
        why: &'static str,
    },
    /// A `.srv` or `.action` file without the sections (separated by `---`) it must have.
    #[error("{type_name}: {found} sections separated by '---', not {expected}")]
    Sections {
        /// The service or action, e.g. `std_srvs/srv/Trigger`.
        type_name: String,
        /// How many it has.
        found: usize,
        /// How many it must have: 2 for a service, 3 for an action.
        expected: usize,
    },
    /// A field names a type that has no definition here.
    #[error("{referenced_by} uses {type_name}, which has no definition")]
    Missing {
        /// The type named, e.g. `std_msgs/msg/Header`.
        type_name: String,
        /// The type whose field names it.
        referenced_by: String,
    },
}

/// FIELD_TYPE_* of `type_description_interfaces/msg/FieldType`: the base ids, before the
/// array (+48), bounded sequence (+96) or unbounded sequence (+144) offset.
mod type_id {
    pub const NESTED_TYPE: u8 = 1;
    pub const INT8: u8 = 2;
    pub const UINT8: u8 = 3;
    pub const INT16: u8 = 4;
    pub const UINT16: u8 = 5;
    pub const INT32: u8 = 6;
    pub const UINT32: u8 = 7;
    pub const INT64: u8 = 8;
    pub const UINT64: u8 = 9;
    pub const FLOAT: u8 = 10;
    pub const DOUBLE: u8 = 11;
    pub const BOOLEAN: u8 = 15;
    pub const BYTE: u8 = 16;
    pub const STRING: u8 = 17;
    pub const WSTRING: u8 = 18;
    pub const BOUNDED_STRING: u8 = 21;
    pub const BOUNDED_WSTRING: u8 = 22;
    pub const ARRAY: u8 = 48;
    pub const BOUNDED_SEQUENCE: u8 = 96;
    pub const UNBOUNDED_SEQUENCE: u8 = 144;
}

/// A field's type as the type description states it (`FieldType.msg`).
#[derive(Debug, Clone, PartialEq, Eq)]
struct FieldType {
    type_id: u8,
    /// Array size or sequence bound; 0 otherwise.
    capacity: u64,
    /// String bound of a bounded (w)string or of the elements of a sequence of them; 0
    /// otherwise.
    string_capacity: u64,
    /// `pkg/msg/Name` for a nested type (or a sequence of one); empty otherwise.
    nested_type_name: String,
}

/// A field: its name and type. Default values are not part of the hash.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Field {
    name: String,
    ty: FieldType,
}

/// One type without the types it references (`IndividualTypeDescription.msg`).
#[derive(Debug, Clone, PartialEq, Eq)]
struct Individual {
    type_name: String,
    fields: Vec<Field>,
}

/// What `rosidl_adapter` gives a message without fields (IDL has no empty structures).
fn placeholder_field() -> Field {
    Field {
        name: "structure_needs_at_least_one_member".into(),
        ty: scalar(type_id::UINT8),
    }
}

fn scalar(type_id: u8) -> FieldType {
    FieldType {
        type_id,
        capacity: 0,
        string_capacity: 0,
        nested_type_name: String::new(),
    }
}

fn nested(type_name: &str) -> FieldType {
    FieldType {
        nested_type_name: type_name.into(),
        ..scalar(type_id::NESTED_TYPE)
    }
}

/// The type id of a `.msg` primitive; `char` is `uint8` and `byte` is `octet` in IDL.
fn primitive(name: &str) -> Option<u8> {
    use type_id::*;
    Some(match name {
        "bool" => BOOLEAN,
        "byte" => BYTE,
        "char" | "uint8" => UINT8,
        "int8" => INT8,
        "int16" => INT16,
        "uint16" => UINT16,
        "int32" => INT32,
        "uint32" => UINT32,
        "int64" => INT64,
        "uint64" => UINT64,
        "float32" => FLOAT,
        "float64" => DOUBLE,
        "string" => STRING,
        "wstring" => WSTRING,
        _ => return None,
    })
}

/// Parses a field's type, e.g. `string<=256`, `Gid[]`, `float64[<=3]`,
/// `builtin_interfaces/Time`, in the package `package`.
fn field_type(ty: &str, package: &str) -> Result<FieldType, &'static str> {
    let (base, offset, capacity) = match ty.split_once('[') {
        None => (ty, 0, 0),
        Some((base, rest)) => {
            let inner = rest.strip_suffix(']').ok_or("no ']' after '['")?;
            if inner.is_empty() {
                (base, type_id::UNBOUNDED_SEQUENCE, 0)
            } else if let Some(bound) = inner.strip_prefix("<=") {
                let n = bound.parse().map_err(|_| "bad sequence bound")?;
                (base, type_id::BOUNDED_SEQUENCE, n)
            } else {
                let n = inner.parse().map_err(|_| "bad array size")?;
                (base, type_id::ARRAY, n)
            }
        }
    };
    let mut ft = if let Some((string, bound)) = base.split_once("<=") {
        let id = match string {
            "string" => type_id::BOUNDED_STRING,
            "wstring" => type_id::BOUNDED_WSTRING,
            _ => return Err("'<=' after a type that is not a string"),
        };
        FieldType {
            string_capacity: bound.parse().map_err(|_| "bad string bound")?,
            ..scalar(id)
        }
    } else if let Some(id) = primitive(base) {
        scalar(id)
    } else {
        let (pkg, name) = base.split_once('/').unwrap_or((package, base));
        let ident =
            |s: &str| !s.is_empty() && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
        if !ident(pkg) || !ident(name) || name.contains('/') {
            return Err("not a type name");
        }
        nested(&format!("{pkg}/msg/{name}"))
    };
    ft.type_id += offset;
    ft.capacity = capacity;
    Ok(ft)
}

/// The fields of one message body (a `.msg` file, or one side of a `.srv` file): every line
/// that is neither blank, a comment nor a constant (`TYPE NAME=VALUE`).
fn fields(type_name: &str, package: &str, body: &str) -> Result<Vec<Field>, TypeHashError> {
    let mut out = Vec::new();
    for raw in body.lines() {
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |why| TypeHashError::Field {
            type_name: type_name.into(),
            line: line.into(),
            why,
        };
        let (ty, rest) = line
            .split_once(char::is_whitespace)
            .ok_or_else(|| bad("no field name"))?;
        let rest = rest.trim_start();
        let end = rest
            .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
            .unwrap_or(rest.len());
        let (name, after) = rest.split_at(end);
        if name.is_empty() {
            return Err(bad("no field name"));
        }
        if after.trim_start().starts_with('=') {
            continue; // a constant: not a field
        }
        // What follows the name is a default value or a comment, neither of which is hashed.
        out.push(Field {
            name: name.into(),
            ty: field_type(ty, package).map_err(bad)?,
        });
    }
    if out.is_empty() {
        out.push(placeholder_field());
    }
    Ok(out)
}

/// The sections of a `.srv` or `.action` file, which lines of three dashes separate.
fn sections(text: &str) -> Vec<String> {
    let mut out = vec![String::new()];
    for line in text.split_inclusive('\n') {
        if line.trim() == "---" {
            out.push(String::new());
        } else {
            out.last_mut().expect("never empty").push_str(line);
        }
    }
    out
}

/// A field of a nested type.
fn member(name: &str, type_name: &str) -> Field {
    Field {
        name: name.into(),
        ty: nested(type_name),
    }
}

/// A field of a primitive type.
fn primitive_member(name: &str, type_id: u8) -> Field {
    Field {
        name: name.into(),
        ty: scalar(type_id),
    }
}

/// Individual types by type name.
type Individuals = BTreeMap<String, Individual>;

/// Adds the four types of the service `base` (`<pkg>/<kind>/<Name>`) with the given request
/// and response fields: `<base>_Request`, `<base>_Response`, `<base>_Event` (rosidl_parser's
/// `Service.event_message`) and the service itself.
fn add_service(all: &mut Individuals, base: &str, request: Vec<Field>, response: Vec<Field>) {
    let (req, resp, event) = (
        format!("{base}_Request"),
        format!("{base}_Response"),
        format!("{base}_Event"),
    );
    let one_of = |t: &str| FieldType {
        type_id: type_id::NESTED_TYPE + type_id::BOUNDED_SEQUENCE,
        capacity: 1,
        ..nested(t)
    };
    let event_fields = vec![
        member("info", "service_msgs/msg/ServiceEventInfo"),
        Field {
            name: "request".into(),
            ty: one_of(&req),
        },
        Field {
            name: "response".into(),
            ty: one_of(&resp),
        },
    ];
    let service_fields = vec![
        member("request_message", &req),
        member("response_message", &resp),
        member("event_message", &event),
    ];
    for (type_name, fields) in [
        (req, request),
        (resp, response),
        (event, event_fields),
        (base.to_string(), service_fields),
    ] {
        all.insert(type_name.clone(), Individual { type_name, fields });
    }
}

/// Adds the thirteen types of the action `base` (`<pkg>/action/<Name>`) whose goal, result and
/// feedback have the given fields, as rosidl_parser's `Action` derives them.
fn add_action(all: &mut Individuals, base: &str, parts: [Vec<Field>; 3]) {
    const UUID: &str = "unique_identifier_msgs/msg/UUID";
    let [goal, result, feedback] = parts;
    let name = |suffix: &str| format!("{base}_{suffix}");
    for (suffix, fields) in [("Goal", goal), ("Result", result), ("Feedback", feedback)] {
        let type_name = name(suffix);
        all.insert(type_name.clone(), Individual { type_name, fields });
    }
    add_service(
        all,
        &name("SendGoal"),
        vec![member("goal_id", UUID), member("goal", &name("Goal"))],
        vec![
            primitive_member("accepted", type_id::BOOLEAN),
            member("stamp", "builtin_interfaces/msg/Time"),
        ],
    );
    add_service(
        all,
        &name("GetResult"),
        vec![member("goal_id", UUID)],
        vec![
            primitive_member("status", type_id::INT8),
            member("result", &name("Result")),
        ],
    );
    let feedback_message = name("FeedbackMessage");
    all.insert(
        feedback_message.clone(),
        Individual {
            type_name: feedback_message.clone(),
            fields: vec![
                member("goal_id", UUID),
                member("feedback", &name("Feedback")),
            ],
        },
    );
    all.insert(
        base.to_string(),
        Individual {
            type_name: base.to_string(),
            fields: vec![
                member("goal", &name("Goal")),
                member("result", &name("Result")),
                member("feedback", &name("Feedback")),
                member("send_goal_service", &name("SendGoal")),
                member("get_result_service", &name("GetResult")),
                member("feedback_message", &feedback_message),
            ],
        },
    );
}

/// Every individual type the definitions give: one per `.msg`, four per `.srv` (the service,
/// its request, response and event), thirteen per `.action` (see [`add_action`]).
fn individuals() -> Result<Individuals, TypeHashError> {
    let mut all = BTreeMap::new();
    for d in DEFINITIONS {
        let base = format!("{}/{}/{}", d.package, d.kind, d.name);
        let parts = sections(d.text);
        let expected = match d.kind {
            "msg" => 1,
            "srv" => 2,
            _ => 3,
        };
        if parts.len() != expected {
            return Err(TypeHashError::Sections {
                type_name: base,
                found: parts.len(),
                expected,
            });
        }
        let part = |i: usize, suffix: &str| -> Result<Vec<Field>, TypeHashError> {
            fields(&format!("{base}{suffix}"), d.package, &parts[i])
        };
        match d.kind {
            "msg" => {
                all.insert(
                    base.clone(),
                    Individual {
                        fields: part(0, "")?,
                        type_name: base,
                    },
                );
            }
            "srv" => {
                let (request, response) = (part(0, "_Request")?, part(1, "_Response")?);
                add_service(&mut all, &base, request, response);
            }
            _ => {
                let parts = [
                    part(0, "_Goal")?,
                    part(1, "_Result")?,
                    part(2, "_Feedback")?,
                ];
                add_action(&mut all, &base, parts);
            }
        }
    }
    Ok(all)
}

/// A JSON string as Python's `json.dumps(..., ensure_ascii=True)` writes it.
fn json_string(out: &mut String, s: &str) {
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            c if c.is_ascii() && !c.is_ascii_control() => out.push(c),
            c => {
                let mut units = [0u16; 2];
                for u in c.encode_utf16(&mut units) {
                    let _ = write!(out, "\\u{u:04x}");
                }
            }
        }
    }
    out.push('"');
}

/// An individual type description as rosidl hashes it (no `default_value`).
fn json_individual(out: &mut String, t: &Individual) {
    out.push_str("{\"type_name\": ");
    json_string(out, &t.type_name);
    out.push_str(", \"fields\": [");
    for (i, f) in t.fields.iter().enumerate() {
        if i > 0 {
            out.push_str(", ");
        }
        out.push_str("{\"name\": ");
        json_string(out, &f.name);
        let _ = write!(
            out,
            ", \"type\": {{\"type_id\": {}, \"capacity\": {}, \"string_capacity\": {}, \
             \"nested_type_name\": ",
            f.ty.type_id, f.ty.capacity, f.ty.string_capacity
        );
        json_string(out, &f.ty.nested_type_name);
        out.push_str("}}");
    }
    out.push_str("]}");
}

/// The canonical JSON of the full type description of `type_name` that rosidl hashes:
/// `json.dumps` with separators `", "` and `": "`, keys in their order, the referenced types
/// sorted by name.
fn hashed_json(
    type_name: &str,
    all: &BTreeMap<String, Individual>,
) -> Result<String, TypeHashError> {
    let top = &all[type_name];
    let mut referenced = BTreeSet::new();
    let mut queue = vec![top];
    while let Some(t) = queue.pop() {
        for f in &t.fields {
            let n = &f.ty.nested_type_name;
            if n.is_empty() || referenced.contains(n) {
                continue;
            }
            let r = all.get(n).ok_or_else(|| TypeHashError::Missing {
                type_name: n.clone(),
                referenced_by: t.type_name.clone(),
            })?;
            referenced.insert(n.clone());
            queue.push(r);
        }
    }
    let mut out = String::from("{\"type_description\": ");
    json_individual(&mut out, top);
    out.push_str(", \"referenced_type_descriptions\": [");
    for (i, n) in referenced.iter().enumerate() {
        if i > 0 {
            out.push_str(", ");
        }
        json_individual(&mut out, &all[n]);
    }
    out.push_str("]}");
    Ok(out)
}

/// `RIHS01_` and the SHA-256 of `json`, in lowercase hex.
fn rihs01(json: &str) -> String {
    let digest = Sha256::digest(json.as_bytes());
    let mut s = String::with_capacity(7 + 64);
    s.push_str("RIHS01_");
    for b in digest {
        let _ = write!(s, "{b:02x}");
    }
    s
}

/// The RIHS01 hash of every type the definitions give, by ROS type name
/// (`std_msgs/msg/Float64`, `std_srvs/srv/Trigger_Request`, ...).
pub fn type_hashes() -> Result<BTreeMap<String, String>, TypeHashError> {
    let all = individuals()?;
    all.keys()
        .map(|name| Ok((name.clone(), rihs01(&hashed_json(name, &all)?))))
        .collect()
}

/// The DDS type name ros2-client gives the endpoints of a ROS type, for the types that are
/// the type of a topic: every message, a service's request and response
/// (`std_msgs::msg::dds_::Float64_`, `std_srvs::srv::dds_::Trigger_Request_`), and an
/// action's services' requests and responses and its feedback message
/// (`pkg::action::dds_::Autotune_SendGoal_Request_`, `pkg::action::dds_::Autotune_FeedbackMessage_`).
/// `None` for a service or action itself, a service's event, and an action's goal, result and
/// feedback, which no topic carries.
pub fn dds_type_name(ros_type: &str) -> Option<String> {
    let (pkg, rest) = ros_type.split_once('/')?;
    let (kind, name) = rest.split_once('/')?;
    let service_side = name.ends_with("_Request") || name.ends_with("_Response");
    let topic_type = match kind {
        "msg" => true,
        "srv" => service_side,
        "action" => service_side || name.ends_with("_FeedbackMessage"),
        _ => false,
    };
    topic_type.then(|| format!("{pkg}::{kind}::dds_::{name}_"))
}

/// The type name rmw_zenoh gives the Zenoh endpoints of a ROS type, in its data keys and
/// liveliness tokens: DDS-style (`<pkg>::<kind>::dds_::<Name>_`), for the types that are the
/// type of a topic or a service there. Every message (`std_msgs::msg::dds_::Float64_`); a
/// service itself, whose request and reply travel on one key
/// (`std_srvs::srv::dds_::Trigger_`); an action's two services and its feedback message
/// (`pkg::action::dds_::Autotune_SendGoal_`, `..._GetResult_`, `..._FeedbackMessage_`); the
/// action's cancel service and status topic are `action_msgs`' `CancelGoal` and
/// `GoalStatusArray`, which this gives as a service and a message. The hash that goes with
/// the name is the hash of the same ROS type (for a service, the service's, not its
/// request's). `None` for a service's request, response and event, and an action itself and
/// its goal, result and feedback, which no Zenoh endpoint carries as its type.
pub fn zenoh_type_name(ros_type: &str) -> Option<String> {
    let (pkg, rest) = ros_type.split_once('/')?;
    let (kind, name) = rest.split_once('/')?;
    let derived = |suffixes: &[&str]| suffixes.iter().any(|s| name.ends_with(s));
    let endpoint_type = match kind {
        "msg" => true,
        "srv" => !derived(&["_Request", "_Response", "_Event"]),
        "action" => derived(&["_SendGoal", "_GetResult", "_FeedbackMessage"]),
        _ => false,
    };
    (endpoint_type && !pkg.is_empty() && !name.is_empty())
        .then(|| format!("{pkg}::{kind}::dds_::{name}_"))
}

/// The USER_DATA a ROS 2 endpoint announces its type hash with (rmw_dds_common's
/// `encode_type_hash_for_user_data_qos`).
pub fn user_data(hash: &str) -> Vec<u8> {
    format!("typehash={hash};").into_bytes()
}

/// Tells the DDS layer the USER_DATA of every endpoint type the definitions give, so each
/// endpoint created afterwards (the node's, and those ros2-client makes for it: services,
/// actions, `/parameter_events`, `/rosout`, `ros_discovery_info`) announces its type hash. Returns how
/// many DDS types got one.
pub fn announce() -> Result<usize, TypeHashError> {
    let mut n = 0;
    for (ros_type, hash) in type_hashes()? {
        if let Some(dds) = dds_type_name(&ros_type) {
            let value = user_data(&hash);
            rustdds::set_user_data_for_type(&dds, rustdds::policy::UserData { value });
            n += 1;
        }
    }
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// How many individual types a definition gives: one per `.msg`, four per `.srv` (the service,
    /// its request, response and event), thirteen per `.action` (goal, result, feedback, two
    /// services of four, the feedback message, the action).
    fn types_per_definition(kind: &str) -> usize {
        match kind {
            "msg" => 1,
            "srv" => 4,
            _ => 13,
        }
    }

    #[test]
    fn every_definition_file_is_compiled_in_and_nothing_else() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        let mut on_disk = BTreeSet::new();
        for kind in ["msg", "action"] {
            let dir = if kind == "msg" { "msg" } else { "msg/action" };
            for entry in std::fs::read_dir(root.join(dir)).unwrap() {
                let p = entry.unwrap().path();
                if p.extension().is_some_and(|e| e == kind) {
                    let name = p.file_stem().unwrap().to_str().unwrap().to_string();
                    on_disk.insert(format!("pwm_actuator_msgs/{kind}/{name}"));
                }
            }
        }
        for pkg in std::fs::read_dir(root.join("interfaces")).unwrap() {
            let pkg = pkg.unwrap().path();
            if !pkg.is_dir() {
                continue;
            }
            for kind in ["msg", "srv"] {
                let Ok(files) = std::fs::read_dir(pkg.join(kind)) else {
                    continue;
                };
                for f in files {
                    let f = f.unwrap().path();
                    assert_eq!(f.extension().unwrap(), kind, "{}", f.display());
                    on_disk.insert(format!(
                        "{}/{kind}/{}",
                        pkg.file_name().unwrap().to_str().unwrap(),
                        f.file_stem().unwrap().to_str().unwrap()
                    ));
                }
            }
        }
        let compiled: BTreeSet<String> = DEFINITIONS
            .iter()
            .map(|d| format!("{}/{}/{}", d.package, d.kind, d.name))
            .collect();
        assert_eq!(compiled, on_disk);
    }

    #[test]
    fn every_type_has_a_hash_and_every_referenced_type_a_definition() {
        let hashes = type_hashes().unwrap();
        let expected: usize = DEFINITIONS
            .iter()
            .map(|d| types_per_definition(d.kind))
            .sum();
        assert_eq!(hashes.len(), expected);
        for (name, h) in &hashes {
            assert_eq!(h.len(), 7 + 64, "{name}: {h}");
            assert!(h.starts_with("RIHS01_"), "{name}: {h}");
            assert!(
                h[7..].chars().all(|c| matches!(c, '0'..='9' | 'a'..='f')),
                "{name}: {h}"
            );
        }
        // No two types hash alike.
        let distinct: BTreeSet<&String> = hashes.values().collect();
        assert_eq!(distinct.len(), hashes.len());
    }

    #[test]
    fn field_types_follow_field_type_msg() {
        let f = |t| field_type(t, "pkg").unwrap();
        assert_eq!(f("float64"), scalar(11));
        assert_eq!(f("char"), scalar(3));
        assert_eq!(f("byte"), scalar(16));
        assert_eq!(
            f("bool[]"),
            FieldType {
                type_id: 159,
                ..scalar(0)
            }
        );
        assert_eq!(
            f("char[16]"),
            FieldType {
                type_id: 51,
                capacity: 16,
                ..scalar(0)
            }
        );
        assert_eq!(
            f("float64[<=3]"),
            FieldType {
                type_id: 107,
                capacity: 3,
                ..scalar(0)
            }
        );
        assert_eq!(
            f("string<=256"),
            FieldType {
                type_id: 21,
                string_capacity: 256,
                ..scalar(0)
            }
        );
        assert_eq!(
            f("string<=8[<=2]"),
            FieldType {
                type_id: 117,
                capacity: 2,
                string_capacity: 8,
                ..scalar(0)
            }
        );
        assert_eq!(
            f("Gid[]"),
            FieldType {
                type_id: 145,
                ..nested("pkg/msg/Gid")
            }
        );
        assert_eq!(
            f("builtin_interfaces/Time"),
            nested("builtin_interfaces/msg/Time")
        );
        assert!(field_type("int8<=3", "pkg").is_err());
        assert!(field_type("a/b/c", "pkg").is_err());
        assert!(field_type("uint8[3", "pkg").is_err());
    }

    #[test]
    fn constants_defaults_and_comments_are_not_fields() {
        let body = "# comment\nuint8 A=1\nint32 B = -2  # c\nstring s \"x # y\"\n\nbool b true\n";
        let got = fields("p/msg/T", "p", body).unwrap();
        let names: Vec<&str> = got.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(names, ["s", "b"]);
        // Only constants: the placeholder IDL needs.
        let got = fields("p/msg/T", "p", "uint8 A=1\n").unwrap();
        assert_eq!(got, vec![placeholder_field()]);
    }

    /// The form rosidl hashes, checked on std_srvs/Trigger: an empty request, the event with
    /// its bounded sequences, the service with its three members.
    #[test]
    fn the_hashed_json_has_rosidls_form() {
        let all = individuals().unwrap();
        assert_eq!(
            hashed_json("std_srvs/srv/Trigger_Request", &all).unwrap(),
            "{\"type_description\": {\"type_name\": \"std_srvs/srv/Trigger_Request\", \
             \"fields\": [{\"name\": \"structure_needs_at_least_one_member\", \"type\": \
             {\"type_id\": 3, \"capacity\": 0, \"string_capacity\": 0, \"nested_type_name\": \
             \"\"}}]}, \"referenced_type_descriptions\": []}"
        );
        let service = hashed_json("std_srvs/srv/Trigger", &all).unwrap();
        let order: Vec<&str> = [
            "\"std_srvs/srv/Trigger\"",
            "\"builtin_interfaces/msg/Time\"",
            "\"service_msgs/msg/ServiceEventInfo\"",
            "\"std_srvs/srv/Trigger_Event\"",
            "\"std_srvs/srv/Trigger_Request\"",
            "\"std_srvs/srv/Trigger_Response\"",
        ]
        .into_iter()
        .filter(|n| service.contains(&format!("{{\"type_name\": {n}")))
        .collect();
        assert_eq!(order.len(), 6, "{service}");
        let at = |n: &str| service.find(&format!("{{\"type_name\": {n}")).unwrap();
        assert!(order.windows(2).all(|w| at(w[0]) < at(w[1])), "{service}");
        assert!(service.contains(
            "{\"name\": \"request\", \"type\": {\"type_id\": 97, \"capacity\": 1, \
             \"string_capacity\": 0, \"nested_type_name\": \"std_srvs/srv/Trigger_Request\"}}"
        ));
    }

    /// An action gives rosidl_parser's thirteen types, with its derived members, and every
    /// type of an action topic has the DDS name ros2-client uses (`Node::create_action_server`:
    /// `<Name>_SendGoal`, `<Name>_GetResult` services, `<Name>_FeedbackMessage` topic).
    #[test]
    fn an_action_expands_as_rosidl_parsers_action() {
        let all = individuals().unwrap();
        let base = "pwm_actuator_msgs/action/Autotune";
        let names: BTreeSet<&str> = all.keys().filter_map(|k| k.strip_prefix(base)).collect();
        let expected: BTreeSet<&str> = [
            "",
            "_Goal",
            "_Result",
            "_Feedback",
            "_SendGoal",
            "_SendGoal_Request",
            "_SendGoal_Response",
            "_SendGoal_Event",
            "_GetResult",
            "_GetResult_Request",
            "_GetResult_Response",
            "_GetResult_Event",
            "_FeedbackMessage",
        ]
        .into_iter()
        .collect();
        assert_eq!(names, expected);
        let fields = |t: &str| -> Vec<(String, u8, String)> {
            all[&format!("{base}{t}")]
                .fields
                .iter()
                .map(|f| (f.name.clone(), f.ty.type_id, f.ty.nested_type_name.clone()))
                .collect()
        };
        let f = |n: &str, id: u8, t: &str| (n.to_string(), id, t.to_string());
        let uuid = "unique_identifier_msgs/msg/UUID";
        assert_eq!(
            fields("_SendGoal_Request"),
            [f("goal_id", 1, uuid), f("goal", 1, &format!("{base}_Goal"))]
        );
        assert_eq!(
            fields("_SendGoal_Response"),
            [
                f("accepted", 15, ""),
                f("stamp", 1, "builtin_interfaces/msg/Time")
            ]
        );
        assert_eq!(fields("_GetResult_Request"), [f("goal_id", 1, uuid)]);
        assert_eq!(
            fields("_GetResult_Response"),
            [
                f("status", 2, ""),
                f("result", 1, &format!("{base}_Result"))
            ]
        );
        assert_eq!(
            fields("_FeedbackMessage"),
            [
                f("goal_id", 1, uuid),
                f("feedback", 1, &format!("{base}_Feedback"))
            ]
        );
        let members: Vec<String> = fields("").into_iter().map(|m| m.0).collect();
        assert_eq!(
            members,
            [
                "goal",
                "result",
                "feedback",
                "send_goal_service",
                "get_result_service",
                "feedback_message"
            ]
        );
        // The goal's fields are the first section of the file, the result's the second.
        assert_eq!(fields("_Goal")[0].0, "target_c");
        assert_eq!(fields("_Result")[0].0, "stop");
        assert_eq!(fields("_Feedback")[0].0, "phase");
    }

    #[test]
    fn sections_are_split_at_lines_of_three_dashes_only() {
        assert_eq!(
            sections("int8 a\n---\n# ---x\nint8 b\n --- \n"),
            ["int8 a\n", "# ---x\nint8 b\n", ""]
        );
        assert_eq!(sections("int8 a"), ["int8 a"]);
    }

    #[test]
    fn json_strings_escape_as_pythons_ensure_ascii() {
        let mut s = String::new();
        json_string(&mut s, "a\"b\\c\nd\u{e9}\u{1f600}");
        assert_eq!(s, "\"a\\\"b\\\\c\\nd\\u00e9\\ud83d\\ude00\"");
    }

    #[test]
    fn dds_type_names_are_ros2_clients() {
        assert_eq!(
            dds_type_name("std_msgs/msg/Float64").as_deref(),
            Some("std_msgs::msg::dds_::Float64_")
        );
        assert_eq!(
            dds_type_name("std_srvs/srv/Trigger_Request").as_deref(),
            Some("std_srvs::srv::dds_::Trigger_Request_")
        );
        assert_eq!(dds_type_name("std_srvs/srv/Trigger"), None);
        assert_eq!(
            dds_type_name("p/action/A_SendGoal_Request").as_deref(),
            Some("p::action::dds_::A_SendGoal_Request_")
        );
        assert_eq!(
            dds_type_name("p/action/A_GetResult_Response").as_deref(),
            Some("p::action::dds_::A_GetResult_Response_")
        );
        assert_eq!(
            dds_type_name("p/action/A_FeedbackMessage").as_deref(),
            Some("p::action::dds_::A_FeedbackMessage_")
        );
        for no_topic in [
            "A",
            "A_Goal",
            "A_Result",
            "A_Feedback",
            "A_SendGoal",
            "A_SendGoal_Event",
        ] {
            assert_eq!(
                dds_type_name(&format!("p/action/{no_topic}")),
                None,
                "{no_topic}"
            );
        }
        assert_eq!(dds_type_name("std_srvs/srv/Trigger_Event"), None);
        assert_eq!(user_data("RIHS01_00"), b"typehash=RIHS01_00;");
    }

    /// rmw_zenoh's type names (docs/design.md, "Topic and Service name mapping": the
    /// `std_msgs::msg::dds_::String_` and `example_interfaces::srv::dds_::AddTwoInts_`
    /// examples): a message as DDS names it, a service by its own name, an action by its two
    /// services and its feedback message.
    #[test]
    fn zenoh_type_names_are_rmw_zenohs() {
        let z = |t: &str| zenoh_type_name(t);
        assert_eq!(
            z("std_msgs/msg/String").as_deref(),
            Some("std_msgs::msg::dds_::String_")
        );
        assert_eq!(
            z("example_interfaces/srv/AddTwoInts").as_deref(),
            Some("example_interfaces::srv::dds_::AddTwoInts_")
        );
        assert_eq!(
            z("action_msgs/srv/CancelGoal").as_deref(),
            Some("action_msgs::srv::dds_::CancelGoal_")
        );
        for (part, name) in [
            ("_SendGoal", "p::action::dds_::A_SendGoal_"),
            ("_GetResult", "p::action::dds_::A_GetResult_"),
            ("_FeedbackMessage", "p::action::dds_::A_FeedbackMessage_"),
        ] {
            assert_eq!(z(&format!("p/action/A{part}")).as_deref(), Some(name));
        }
        for none in [
            "std_srvs/srv/Trigger_Request",
            "std_srvs/srv/Trigger_Response",
            "std_srvs/srv/Trigger_Event",
            "p/action/A",
            "p/action/A_Goal",
            "p/action/A_Result",
            "p/action/A_Feedback",
            "p/action/A_SendGoal_Request",
            "p/action/A_GetResult_Response",
            "p/action/A_SendGoal_Event",
            "p/other/A",
            "std_msgs/Float64",
            "/msg/A",
            "p/msg/",
        ] {
            assert_eq!(z(none), None, "{none}");
        }
    }
}
