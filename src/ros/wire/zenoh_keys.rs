//! rmw_zenoh's wire format, as the Zenoh side of ROS 2 (`rmw_zenoh_cpp` on Zenoh 1.x, Jazzy
//! and later) writes and reads it: the key expression a topic's or service's data travels on,
//! the liveliness tokens that make up the ROS graph (a node's `NN`, an endpoint's `MP`, `MS`,
//! `SS` or `SC`), the QoS string inside them, the 33-byte attachment of every sample, request
//! and reply, and an endpoint's GID. Pure string and byte work: no Zenoh session, nothing
//! sent; always compiled, so the unit tests below pin the format whatever the build.
//!
//! The sources, which the tests quote:
//! - rmw_zenoh's `docs/design.md`: "Topic and Service name mapping to Zenoh key expressions"
//!   (data keys), "Graph Cache" (liveliness tokens and their examples), "Publishers",
//!   "Service Clients" and "Service Servers" (the attachment);
//! - `rmw_zenoh_cpp/src/detail/liveliness_utils.cpp`: `TopicInfo` (the data key, one leading
//!   and one trailing `/` of the name stripped), `Entity` (the token's chunks, the GID),
//!   `qos_to_keyexpr` / `keyexpr_to_qos` (the QoS string), `mangle_name`;
//! - `rmw_zenoh_cpp/src/detail/qos.cpp`: the default profile the QoS string leaves out
//!   (keep last, depth 42, reliable, volatile, infinite deadline, lifespan and lease,
//!   automatic liveliness);
//! - zenoh-ext's serializer, which writes the attachment (`i64`, `i64`, a 16-byte array
//!   with its length as one byte).
//!
//! Names here are fully qualified ROS names (`/pwm_actuator/pw01/e1`), after expansion and
//! remapping ([`crate::ros::config::names`]); types are the Zenoh type name and REP-2016
//! hash of a ROS type ([`EndpointType::of`]).

use crate::ros::interface::type_hash::zenoh_type_name;
use ros2_client::qos::{Durability, History, Liveliness, Reliability, WhenFull};
use ros2_client::QosProfile;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::time::Duration;

/// The first chunk of every liveliness token of ROS 2 on Zenoh: a hermetic chunk that `*` and
/// `**` never match.
pub const ADMIN_SPACE: &str = "@ros2_lv";

/// The depth rmw_zenoh gives a keep-last history asked for with depth 0, and which the QoS
/// string leaves out, in samples.
pub const DEFAULT_DEPTH: usize = 42;

/// The length of an attachment, in bytes: sequence number (8), source timestamp (8), the
/// GID's length (1), the GID (16).
pub const ATTACHMENT_BYTES: usize = 33;

/// The length of a GID, in bytes.
pub const GID_BYTES: usize = 16;

/// The longest liveliness token [`parse_token`] reads, in bytes. A token of the node's
/// longest endpoint (an action's feedback topic under a long namespace) is under 400 bytes;
/// ROS names are at most 255 characters.
pub const MAX_TOKEN_BYTES: usize = 4096;

/// The byte before the GID in an attachment: its length (zenoh-ext writes a byte array's
/// length as a LEB128 varint, one byte for 16).
const GID_LENGTH_BYTE: u8 = GID_BYTES as u8;

/// `RMW_DURATION_INFINITE` (rmw/time.h), in (seconds, nanoseconds): the default deadline,
/// lifespan and liveliness lease, which the QoS string leaves out.
const INFINITE: (u64, u64) = (9_223_372_036, 854_775_807);

/// The most chunks an endpoint's token has: 13, and the 14th that rmw_zenoh appends for the
/// buffer backends of an endpoint of a `rosidl::Buffer` type.
const MAX_CHUNKS: usize = 14;

/// A part of a key expression or a liveliness token, as [`KeyError`] names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Field {
    /// The whole key or token.
    Key,
    /// The first chunk, [`ADMIN_SPACE`].
    AdminSpace,
    /// The ROS domain id (decimal).
    Domain,
    /// The Zenoh session id (lowercase hex).
    Zid,
    /// The node's id within its session (decimal).
    NodeId,
    /// The endpoint's id within its session (decimal).
    EntityId,
    /// The kind of entity: `NN`, `MP`, `MS`, `SS` or `SC`.
    Kind,
    /// The SROS enclave (mangled).
    Enclave,
    /// The node's namespace (mangled).
    Namespace,
    /// The node's name.
    NodeName,
    /// The topic's or service's fully qualified name (mangled in a token).
    Name,
    /// The Zenoh type name, e.g. `std_msgs::msg::dds_::Bool_`.
    TypeName,
    /// The REP-2016 type hash, `RIHS01_` and 64 hex digits.
    TypeHash,
    /// The QoS string.
    Qos,
    /// The buffer backends chunk of a `rosidl::Buffer` endpoint.
    Backends,
}

/// Why a key or token cannot be made or read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum KeyError {
    /// A token longer than [`MAX_TOKEN_BYTES`].
    #[error("liveliness token of {bytes} bytes, more than {max}", max = MAX_TOKEN_BYTES)]
    TooLong {
        /// Its length, in bytes.
        bytes: usize,
    },
    /// A token with a number of `/`-separated chunks its kind does not have.
    #[error("liveliness token with {found} chunks: {expected}")]
    Chunks {
        /// How many it has (at most 15: the rest is not counted).
        found: usize,
        /// How many it must have.
        expected: &'static str,
    },
    /// A field that does not have its form.
    #[error("{field:?} {value:?}: {why}")]
    Field {
        /// Which field.
        field: Field,
        /// Its text (at most a token's, [`MAX_TOKEN_BYTES`]).
        value: String,
        /// What is wrong with it.
        why: &'static str,
    },
    /// A ROS type without a Zenoh type name (a service's request, an action's goal, ...).
    #[error("{ros_type} is not the type of a Zenoh topic or service")]
    NotAnEndpointType {
        /// The ROS type, e.g. `std_srvs/srv/Trigger_Request`.
        ros_type: String,
    },
    /// A ROS type without a hash: no definition compiled in.
    #[error("{ros_type} has no type hash")]
    NoHash {
        /// The ROS type.
        ros_type: String,
    },
}

fn field_error(field: Field, value: &str, why: &'static str) -> KeyError {
    KeyError::Field {
        field,
        value: value.to_string(),
        why,
    }
}

/// rmw_zenoh's `mangle_name`: every `/` replaced by `%`, so that a name is one chunk of a
/// token. An empty name gives `%` (a key has no empty chunk; the design document's "just `%`
/// if not set"); the root namespace `/` and the default enclave `/` give `%` too.
pub fn mangle(name: &str) -> String {
    if name.is_empty() {
        "%".to_string()
    } else {
        name.replace('/', "%")
    }
}

/// rmw_zenoh's `demangle_name`: every `%` back to `/`.
fn demangle(chunk: &str) -> String {
    chunk.replace('%', "/")
}

/// A token of a ROS name: letters, digits and `_`, not starting with a digit.
fn check_ros_token(t: &str) -> Result<(), &'static str> {
    let first = t.chars().next().ok_or("empty token")?;
    if !(first.is_ascii_alphabetic() || first == '_') {
        return Err("a token starts with a letter or `_`");
    }
    if !t.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
        return Err("a token is letters, digits and `_`");
    }
    Ok(())
}

/// An absolute ROS name (`/a/b`); `/` alone only where `root` allows it (a namespace, an
/// enclave).
fn check_absolute(name: &str, root: bool) -> Result<(), &'static str> {
    let rest = name.strip_prefix('/').ok_or("not absolute")?;
    if rest.is_empty() {
        return if root { Ok(()) } else { Err("`/` is no name") };
    }
    rest.split('/').try_for_each(check_ros_token)
}

/// A type name as rmw_zenoh writes it: letters, digits, `_` and `:`.
fn check_type_name(t: &str) -> Result<(), &'static str> {
    if t.is_empty() || t.len() > 256 {
        return Err("1 to 256 characters");
    }
    if !t
        .chars()
        .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == ':')
    {
        return Err("letters, digits, `_` and `:`");
    }
    Ok(())
}

/// A type hash as `rosidl_stringify_type_hash` writes it: `RIHS`, the version in two decimal
/// digits, `_`, the 32-byte hash in 64 lowercase hex digits.
fn check_type_hash(h: &str) -> Result<(), &'static str> {
    let b = h.as_bytes();
    let form = b.len() == 71
        && b.starts_with(b"RIHS")
        && b[4].is_ascii_digit()
        && b[5].is_ascii_digit()
        && b[6] == b'_'
        && b[7..]
            .iter()
            .all(|c| matches!(c, b'0'..=b'9' | b'a'..=b'f'));
    form.then_some(())
        .ok_or("`RIHS`, two digits, `_` and 64 lowercase hex digits")
}

/// A Zenoh session id as Zenoh prints it: 1 to 32 lowercase hex digits.
fn check_zid(z: &str) -> Result<(), &'static str> {
    let hex = z.bytes().all(|c| matches!(c, b'0'..=b'9' | b'a'..=b'f'));
    (hex && (1..=32).contains(&z.len()))
        .then_some(())
        .ok_or("1 to 32 lowercase hex digits")
}

/// A decimal number as `std::to_string` writes it: digits, no sign, no leading zero.
fn parse_decimal(s: &str) -> Option<u64> {
    let canonical = !s.is_empty()
        && s.len() <= 20
        && s.bytes().all(|c| c.is_ascii_digit())
        && (s == "0" || !s.starts_with('0'));
    if canonical {
        s.parse().ok()
    } else {
        None
    }
}

/// The Zenoh type name and type hash of a topic's or service's ROS type.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EndpointType {
    /// The Zenoh type name, e.g. `std_msgs::msg::dds_::Bool_`.
    pub name: String,
    /// The REP-2016 hash of the ROS type, `RIHS01_` and 64 lowercase hex digits.
    pub hash: String,
}

impl EndpointType {
    /// The endpoint type of `ros_type` (`std_msgs/msg/Bool`, `std_srvs/srv/Trigger`,
    /// `pkg/action/Autotune_SendGoal`), its hash looked up in `hashes`
    /// ([`type_hashes`](crate::ros::interface::type_hash::type_hashes)).
    pub fn of(hashes: &BTreeMap<String, String>, ros_type: &str) -> Result<Self, KeyError> {
        let name = zenoh_type_name(ros_type).ok_or_else(|| KeyError::NotAnEndpointType {
            ros_type: ros_type.to_string(),
        })?;
        let hash = hashes.get(ros_type).ok_or_else(|| KeyError::NoHash {
            ros_type: ros_type.to_string(),
        })?;
        check_type_hash(hash).map_err(|why| field_error(Field::TypeHash, hash, why))?;
        Ok(EndpointType {
            name,
            hash: hash.clone(),
        })
    }

    fn check(&self) -> Result<(), KeyError> {
        check_type_name(&self.name).map_err(|why| field_error(Field::TypeName, &self.name, why))?;
        check_type_hash(&self.hash).map_err(|why| field_error(Field::TypeHash, &self.hash, why))
    }
}

/// The key expression a topic's samples or a service's requests and replies travel on:
/// `<domain>/<name without its leading '/'>/<type name>/<type hash>`, e.g.
/// `0/pwm_actuator/pw01/e1/std_msgs::msg::dds_::Bool_/RIHS01_feb9...`. `domain` is the ROS
/// domain id; `name` a fully qualified topic or service name.
pub fn data_key(domain: u32, name: &str, ty: &EndpointType) -> Result<String, KeyError> {
    check_absolute(name, false).map_err(|why| field_error(Field::Name, name, why))?;
    ty.check()?;
    Ok(format!("{domain}/{}/{}/{}", &name[1..], ty.name, ty.hash))
}

/// The kind of endpoint a liveliness token stands for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EntityKind {
    /// A publisher (`MP`).
    Publisher,
    /// A subscription (`MS`).
    Subscription,
    /// A service server (`SS`).
    Service,
    /// A service client (`SC`).
    Client,
}

impl EntityKind {
    /// The token's chunk for this kind.
    pub fn code(self) -> &'static str {
        match self {
            EntityKind::Publisher => "MP",
            EntityKind::Subscription => "MS",
            EntityKind::Service => "SS",
            EntityKind::Client => "SC",
        }
    }

    fn from_code(code: &str) -> Option<Self> {
        Some(match code {
            "MP" => EntityKind::Publisher,
            "MS" => EntityKind::Subscription,
            "SS" => EntityKind::Service,
            "SC" => EntityKind::Client,
            _ => return None,
        })
    }
}

/// A node as its liveliness token tells it:
/// `@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<name>`, names
/// mangled.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NodeToken {
    /// The ROS domain id.
    pub domain: u32,
    /// The Zenoh session id, lowercase hex (Zenoh's `ZenohId` as it prints).
    pub zid: String,
    /// The node's id within its session (rmw_zenoh counts nodes and endpoints of a context
    /// with one counter from 0).
    pub node_id: u64,
    /// The SROS enclave, absolute; `/` when none is set.
    pub enclave: String,
    /// The node's namespace, absolute; `/` for the root.
    pub namespace: String,
    /// The node's name, e.g. `pwm_actuator`.
    pub name: String,
}

impl NodeToken {
    fn check(&self) -> Result<(), KeyError> {
        check_zid(&self.zid).map_err(|why| field_error(Field::Zid, &self.zid, why))?;
        check_absolute(&self.enclave, true)
            .map_err(|why| field_error(Field::Enclave, &self.enclave, why))?;
        check_absolute(&self.namespace, true)
            .map_err(|why| field_error(Field::Namespace, &self.namespace, why))?;
        check_ros_token(&self.name).map_err(|why| field_error(Field::NodeName, &self.name, why))
    }

    /// The chunks up to the entity id: `@ros2_lv/<domain>/<zid>/<node id>/<id>`.
    fn head(&self, id: u64) -> String {
        format!(
            "{ADMIN_SPACE}/{}/{}/{}/{id}",
            self.domain, self.zid, self.node_id
        )
    }

    /// The chunks after the kind: `<enclave>/<namespace>/<name>`, mangled.
    fn tail(&self) -> String {
        format!(
            "{}/{}/{}",
            mangle(&self.enclave),
            mangle(&self.namespace),
            mangle(&self.name)
        )
    }

    /// The node's liveliness token.
    pub fn key(&self) -> Result<String, KeyError> {
        self.check()?;
        Ok(format!("{}/NN/{}", self.head(self.node_id), self.tail()))
    }
}

/// An endpoint as its liveliness token tells it: `@ros2_lv/<domain>/<zid>/<node id>/<entity
/// id>/<MP|MS|SS|SC>/<enclave>/<namespace>/<node name>/<name>/<type name>/<type hash>/<qos>`,
/// names mangled, the QoS as [`qos_to_keyexpr`] writes it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EntityToken {
    /// The node the endpoint belongs to.
    pub node: NodeToken,
    /// The endpoint's id within its session.
    pub entity_id: u64,
    /// Publisher, subscription, service server or client.
    pub kind: EntityKind,
    /// The topic's or service's fully qualified name.
    pub name: String,
    /// Its type.
    pub ty: EndpointType,
    /// Its QoS. Read from a token, a reliable profile's `when_full` is
    /// [`WhenFull::DEFAULT`]: the token does not carry it.
    pub qos: QosProfile,
    /// The 14th chunk rmw_zenoh appends for an endpoint of a `rosidl::Buffer` type, as read,
    /// not interpreted; `None` for every other endpoint, and every endpoint of this node.
    pub backends: Option<String>,
}

impl EntityToken {
    /// The endpoint's liveliness token.
    pub fn key(&self) -> Result<String, KeyError> {
        self.node.check()?;
        check_absolute(&self.name, false)
            .map_err(|why| field_error(Field::Name, &self.name, why))?;
        self.ty.check()?;
        let mut key = format!(
            "{}/{}/{}/{}/{}/{}/{}",
            self.node.head(self.entity_id),
            self.kind.code(),
            self.node.tail(),
            mangle(&self.name),
            self.ty.name,
            self.ty.hash,
            qos_to_keyexpr(&self.qos)
        );
        if let Some(b) = &self.backends {
            check_backends(b)?;
            key.push('/');
            key.push_str(b);
        }
        Ok(key)
    }

    /// The endpoint's GID: [`Gid::of_token`] of its token.
    pub fn gid(&self) -> Result<Gid, KeyError> {
        Ok(Gid::of_token(&self.key()?))
    }
}

fn check_backends(b: &str) -> Result<(), KeyError> {
    let ok = !b.is_empty()
        && b.bytes()
            .all(|c| c.is_ascii_graphic() && !matches!(c, b'/' | b'*' | b'$' | b'?' | b'#'));
    ok.then_some(()).ok_or_else(|| {
        field_error(
            Field::Backends,
            b,
            "printable ASCII without `/`, `*`, `$`, `?` or `#`",
        )
    })
}

/// A liveliness token of the ROS graph, read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Token {
    /// A node (`NN`).
    Node(NodeToken),
    /// A publisher, subscription, service server or client.
    Entity(EntityToken),
}

/// Reads a liveliness token another participant declared (or this node, on its own graph
/// subscription). Strict: a token longer than [`MAX_TOKEN_BYTES`], with a chunk count its
/// kind does not have (9 for a node; 13, or 14 with a buffer backends chunk, for an
/// endpoint), or a field out of its form (numbers in canonical decimal, the zid in lowercase
/// hex, names that demangle to ROS names, a type hash as rosidl writes it, a QoS string as
/// [`keyexpr_to_qos`] reads it) is refused with a [`KeyError`]. Work bounded by the token's
/// length; never panics.
pub fn parse_token(key: &str) -> Result<Token, KeyError> {
    if key.len() > MAX_TOKEN_BYTES {
        return Err(KeyError::TooLong { bytes: key.len() });
    }
    let chunks: Vec<&str> = key.splitn(MAX_CHUNKS + 1, '/').collect();
    if chunks.len() < 9 {
        return Err(KeyError::Chunks {
            found: chunks.len(),
            expected: "9 for a node, 13 or 14 for an endpoint",
        });
    }
    if chunks[0] != ADMIN_SPACE {
        return Err(field_error(Field::AdminSpace, chunks[0], "not `@ros2_lv`"));
    }
    let number =
        |field, s: &str| parse_decimal(s).ok_or_else(|| field_error(field, s, "a decimal number"));
    let domain = u32::try_from(number(Field::Domain, chunks[1])?)
        .map_err(|_| field_error(Field::Domain, chunks[1], "more than 32 bits"))?;
    let node_id = number(Field::NodeId, chunks[3])?;
    let id = number(Field::EntityId, chunks[4])?;
    let name_chunk = |field, s: &str, root| {
        let name = demangle(s);
        check_absolute(&name, root)
            .map(|()| name)
            .map_err(|why| field_error(field, s, why))
    };
    let node = NodeToken {
        domain,
        zid: chunks[2].to_string(),
        node_id,
        enclave: name_chunk(Field::Enclave, chunks[6], true)?,
        namespace: name_chunk(Field::Namespace, chunks[7], true)?,
        name: chunks[8].to_string(),
    };
    node.check()?;
    if chunks[5] == "NN" {
        if chunks.len() != 9 {
            return Err(KeyError::Chunks {
                found: chunks.len(),
                expected: "9 for a node",
            });
        }
        if id != node_id {
            return Err(field_error(
                Field::EntityId,
                chunks[4],
                "a node's token repeats its node id",
            ));
        }
        return Ok(Token::Node(node));
    }
    let kind = EntityKind::from_code(chunks[5])
        .ok_or_else(|| field_error(Field::Kind, chunks[5], "not NN, MP, MS, SS or SC"))?;
    if !(13..=MAX_CHUNKS).contains(&chunks.len()) {
        return Err(KeyError::Chunks {
            found: chunks.len(),
            expected: "13 or 14 for an endpoint",
        });
    }
    let ty = EndpointType {
        name: chunks[10].to_string(),
        hash: chunks[11].to_string(),
    };
    ty.check()?;
    let backends = match chunks.get(13) {
        Some(b) => {
            check_backends(b)?;
            Some(b.to_string())
        }
        None => None,
    };
    Ok(Token::Entity(EntityToken {
        node,
        entity_id: id,
        kind,
        name: name_chunk(Field::Name, chunks[9], false)?,
        ty,
        qos: keyexpr_to_qos(chunks[12])?,
        backends,
    }))
}

/// A duration as rmw's `rmw_time_t` holds it, in (seconds, nanoseconds); `None` (infinite)
/// as [`INFINITE`].
fn rmw_time(d: Option<Duration>) -> (u64, u64) {
    d.map_or(INFINITE, |d| (d.as_secs(), u64::from(d.subsec_nanos())))
}

/// Writes `value` unless it is `default`.
fn push_unless(out: &mut String, value: u64, default: u64) {
    if value != default {
        let _ = write!(out, "{value}");
    }
}

/// rmw_zenoh's `qos_to_keyexpr`: the QoS string of a liveliness token,
/// `<reliability>:<durability>:<history>,<depth>:<deadline s>,<deadline ns>:<lifespan
/// s>,<lifespan ns>:<liveliness>,<lease s>,<lease ns>`, each field empty where it equals
/// rmw_zenoh's default (reliable, volatile, keep last, depth 42, infinite durations,
/// automatic liveliness), else the `rmw_qos_*_policy_e` number (reliable 1, best effort 2;
/// transient local 1, volatile 2; keep last 1, keep all 2; automatic 1, manual by topic 3)
/// or the decimal value. A keep-last depth of 0 is rmw_zenoh's 42; a keep-all history has
/// no depth here, so none is written (rmw_zenoh writes 42 for rclcpp's and rclpy's keep
/// all). `when_full` is not part of the string. E.g. reliable, volatile, keep last 10:
/// `::,10:,:,:,,`.
pub fn qos_to_keyexpr(q: &QosProfile) -> String {
    let mut s = String::with_capacity(16);
    if q.reliability == Reliability::BestEffort {
        s.push('2');
    }
    s.push(':');
    if q.durability == Durability::TransientLocal {
        s.push('1');
    }
    s.push(':');
    let depth = match q.history {
        History::KeepLast { depth: 0 } | History::KeepAll => DEFAULT_DEPTH,
        History::KeepLast { depth } => depth,
    };
    if q.history == History::KeepAll {
        s.push('2');
    }
    s.push(',');
    push_unless(&mut s, depth as u64, DEFAULT_DEPTH as u64);
    for d in [q.deadline, q.lifespan] {
        let (sec, nsec) = rmw_time(d);
        s.push(':');
        push_unless(&mut s, sec, INFINITE.0);
        s.push(',');
        push_unless(&mut s, nsec, INFINITE.1);
    }
    s.push(':');
    if q.liveliness == Liveliness::ManualByTopic {
        s.push('3');
    }
    let (sec, nsec) = rmw_time(q.liveliness_lease);
    s.push(',');
    push_unless(&mut s, sec, INFINITE.0);
    s.push(',');
    push_unless(&mut s, nsec, INFINITE.1);
    s
}

/// rmw_zenoh's `keyexpr_to_qos`: the profile a token's QoS string tells, an empty field
/// taken as rmw_zenoh's default. Strict where rmw_zenoh is lenient: exactly six
/// `:`-separated groups of 1, 1, 2, 2, 2 and 3 `,`-separated fields, numbers in canonical
/// decimal, and only the policy codes a profile here can hold (`0`, rmw's "system default",
/// read as rmw_zenoh's default; reliability 1 or 2, durability 1 or 2, history 1 or 2,
/// liveliness 1 or 3); a finite duration that overflows is refused too.
pub fn keyexpr_to_qos(s: &str) -> Result<QosProfile, KeyError> {
    let bad = |why| field_error(Field::Qos, s, why);
    let groups: Vec<&str> = s.splitn(7, ':').collect();
    if groups.len() != 6 {
        return Err(bad("six `:`-separated groups"));
    }
    let fields = |g: &'static str, group: &str, n: usize| -> Result<Vec<Option<u64>>, KeyError> {
        let parts: Vec<&str> = group.splitn(n + 1, ',').collect();
        if parts.len() != n {
            return Err(bad(g));
        }
        parts
            .iter()
            .map(|p| match *p {
                "" => Ok(None),
                p => parse_decimal(p)
                    .map(Some)
                    .ok_or_else(|| bad("fields are empty or decimal numbers")),
            })
            .collect()
    };
    let rel = fields("reliability: one field", groups[0], 1)?;
    let dur = fields("durability: one field", groups[1], 1)?;
    let hist = fields("history: kind and depth", groups[2], 2)?;
    let deadline = fields("deadline: seconds and nanoseconds", groups[3], 2)?;
    let lifespan = fields("lifespan: seconds and nanoseconds", groups[4], 2)?;
    let liv = fields(
        "liveliness: kind, lease seconds and nanoseconds",
        groups[5],
        3,
    )?;

    let reliability = match rel[0] {
        None | Some(0 | 1) => Reliability::Reliable {
            when_full: WhenFull::DEFAULT,
        },
        Some(2) => Reliability::BestEffort,
        Some(_) => return Err(bad("reliability is 1 (reliable) or 2 (best effort)")),
    };
    let durability = match dur[0] {
        None | Some(0 | 2) => Durability::Volatile,
        Some(1) => Durability::TransientLocal,
        Some(_) => return Err(bad("durability is 1 (transient local) or 2 (volatile)")),
    };
    let depth = usize::try_from(hist[1].unwrap_or(DEFAULT_DEPTH as u64))
        .map_err(|_| bad("depth too large"))?;
    let history = match hist[0] {
        None | Some(0 | 1) => History::KeepLast { depth },
        Some(2) => History::KeepAll,
        Some(_) => return Err(bad("history is 1 (keep last) or 2 (keep all)")),
    };
    let liveliness = match liv[0] {
        None | Some(0 | 1) => Liveliness::Automatic,
        Some(3) => Liveliness::ManualByTopic,
        Some(_) => return Err(bad("liveliness is 1 (automatic) or 3 (manual by topic)")),
    };
    let duration = |parts: &[Option<u64>]| -> Result<Option<Duration>, KeyError> {
        let t = (
            parts[0].unwrap_or(INFINITE.0),
            parts[1].unwrap_or(INFINITE.1),
        );
        if t == INFINITE {
            return Ok(None);
        }
        Duration::from_secs(t.0)
            .checked_add(Duration::from_nanos(t.1))
            .map(Some)
            .ok_or_else(|| bad("duration overflows"))
    };
    Ok(QosProfile {
        reliability,
        durability,
        history,
        deadline: duration(&deadline[..])?,
        lifespan: duration(&lifespan[..])?,
        liveliness,
        liveliness_lease: duration(&liv[1..])?,
    })
}

/// An endpoint's GID as rmw_zenoh makes it: 16 bytes, the XXH3-128 hash (seed 0) of the
/// endpoint's liveliness token, its low 64 bits little-endian, then its high 64 bits
/// little-endian.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Gid(pub [u8; GID_BYTES]);

impl Gid {
    /// The GID of the endpoint whose liveliness token is `token`.
    pub fn of_token(token: &str) -> Gid {
        let h = xxhash_rust::xxh3::xxh3_128(token.as_bytes());
        let mut gid = [0; GID_BYTES];
        gid[..8].copy_from_slice(&(h as u64).to_le_bytes());
        gid[8..].copy_from_slice(&((h >> 64) as u64).to_le_bytes());
        Gid(gid)
    }
}

/// The attachment of every sample a publisher puts, every request a client sends and every
/// reply a server gives (design.md "Publishers", "Service Clients", "Service Servers"):
/// `| sequence i64 LE | source timestamp i64 LE | 0x10 | GID, 16 bytes |`, 33 bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Attachment {
    /// The sequence number: a publisher's samples and a client's requests count from 1; a
    /// reply repeats its request's.
    pub sequence: i64,
    /// When the sample, request or reply was made, in nanoseconds since the UNIX epoch.
    pub source_timestamp_ns: i64,
    /// The publisher's or client's GID (a reply carries its client's).
    pub gid: Gid,
}

/// Why bytes are not an attachment.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum AttachmentError {
    /// Not [`ATTACHMENT_BYTES`] long.
    #[error("attachment of {bytes} bytes, not {n}", n = ATTACHMENT_BYTES)]
    Length {
        /// Its length, in bytes.
        bytes: usize,
    },
    /// The byte before the GID is not its length, 16.
    #[error("attachment's GID length byte is {found:#04x}, not 0x10")]
    GidLength {
        /// The byte found.
        found: u8,
    },
}

impl Attachment {
    /// The 33 bytes.
    pub fn encode(&self) -> [u8; ATTACHMENT_BYTES] {
        let mut b = [0; ATTACHMENT_BYTES];
        b[..8].copy_from_slice(&self.sequence.to_le_bytes());
        b[8..16].copy_from_slice(&self.source_timestamp_ns.to_le_bytes());
        b[16] = GID_LENGTH_BYTE;
        b[17..].copy_from_slice(&self.gid.0);
        b
    }

    /// Reads an attachment: exactly [`ATTACHMENT_BYTES`] bytes with the GID length byte
    /// 0x10, else an [`AttachmentError`]. Never panics.
    pub fn decode(bytes: &[u8]) -> Result<Attachment, AttachmentError> {
        let b: &[u8; ATTACHMENT_BYTES] = bytes
            .try_into()
            .map_err(|_| AttachmentError::Length { bytes: bytes.len() })?;
        if b[16] != GID_LENGTH_BYTE {
            return Err(AttachmentError::GidLength { found: b[16] });
        }
        let i64_at = |at: usize| {
            let mut x = [0; 8];
            x.copy_from_slice(&b[at..at + 8]);
            i64::from_le_bytes(x)
        };
        let mut gid = [0; GID_BYTES];
        gid.copy_from_slice(&b[17..]);
        Ok(Attachment {
            sequence: i64_at(0),
            source_timestamp_ns: i64_at(8),
            gid: Gid(gid),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros::interface::msg::{self, RosMessage};
    use crate::ros::interface::qos;
    use crate::ros::interface::type_hash::type_hashes;
    use proptest::prelude::*;

    /// The session ids of design.md's examples ("Graph Cache").
    const LISTENER_ZID: &str = "aac3178e146ba6f1fc6e6a4085e77f21";
    const TALKER_ZID: &str = "8b20917502ee955ac4476e0266340d5c";
    const SERVER_ZID: &str = "f9980ee0495eaafb3e38f0d19e2eae12";
    const CLIENT_ZID: &str = "e1dc8d1b45ae8717fce78689cc655685";
    /// `std_msgs/msg/String`'s hash as design.md gives it (and rosidl's
    /// `share/std_msgs/msg/String.json`).
    const STRING_HASH: &str =
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18";
    /// `example_interfaces/srv/AddTwoInts`' hash as design.md gives it (no definition here).
    const ADD_TWO_INTS_HASH: &str =
        "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a";

    fn hashes() -> BTreeMap<String, String> {
        type_hashes().unwrap()
    }

    fn ty(ros_type: &str) -> EndpointType {
        EndpointType::of(&hashes(), ros_type).unwrap()
    }

    fn add_two_ints() -> EndpointType {
        EndpointType {
            name: "example_interfaces::srv::dds_::AddTwoInts_".into(),
            hash: ADD_TWO_INTS_HASH.into(),
        }
    }

    fn node(domain: u32, zid: &str, name: &str) -> NodeToken {
        NodeToken {
            domain,
            zid: zid.into(),
            node_id: 0,
            enclave: "/".into(),
            namespace: "/".into(),
            name: name.into(),
        }
    }

    /// Reliable, volatile, keep last `depth`: rclcpp's and rclpy's default with that depth.
    fn keep_last(depth: usize) -> QosProfile {
        QosProfile::publisher_default().history(History::KeepLast { depth })
    }

    fn entity(
        node: NodeToken,
        id: u64,
        kind: EntityKind,
        name: &str,
        ty: EndpointType,
        qos: QosProfile,
    ) -> EntityToken {
        EntityToken {
            node,
            entity_id: id,
            kind,
            name: name.into(),
            ty,
            qos,
            backends: None,
        }
    }

    /// A profile as a token gives it back: `when_full` is not in the string.
    fn as_read(mut q: QosProfile) -> QosProfile {
        if let Reliability::Reliable { when_full } = &mut q.reliability {
            *when_full = WhenFull::DEFAULT;
        }
        q
    }

    fn hex(bytes: &[u8]) -> String {
        bytes.iter().map(|b| format!("{b:02x}")).collect()
    }

    #[test]
    fn mangling_replaces_every_slash_and_gives_nothing_a_percent() {
        assert_eq!(mangle("/"), "%");
        assert_eq!(mangle(""), "%");
        assert_eq!(mangle("/pwm_actuator/pw01/e1"), "%pwm_actuator%pw01%e1");
        assert_eq!(mangle("listener"), "listener");
        assert_eq!(demangle("%robot1%chatter"), "/robot1/chatter");
    }

    /// rosidl's hashes (`share/<pkg>/<kind>/<Name>.json` of the Jazzy packages, and of
    /// pwm_actuator_msgs as built): the types of the examples below and a service and
    /// action parts of the node, whose keys carry the service's own hash on Zenoh.
    #[test]
    fn the_hashes_the_keys_carry_are_rosidls() {
        let h = hashes();
        for (t, expected) in [
            (
                "std_msgs/msg/Bool",
                "RIHS01_feb91e995ff9ebd09c0cb3d2aed18b11077585839fb5db80193b62d74528f6c9",
            ),
            (
                "std_msgs/msg/Float64",
                "RIHS01_705ba9c3d1a09df43737eb67095534de36fd426c0587779bda2bc51fe790182a",
            ),
            ("std_msgs/msg/String", STRING_HASH),
            (
                "rcl_interfaces/srv/GetParameters",
                "RIHS01_bf9803d5c74cf989a5de3e0c2e99444599a627c7ff75f97b8c05b01003675cbc",
            ),
            (
                "action_msgs/srv/CancelGoal",
                "RIHS01_573d8b0a534451d7bc2ac8c5ffde8ac14b8593b7001175d0cd6516dcbeb8689a",
            ),
            (
                "action_msgs/msg/GoalStatusArray",
                "RIHS01_6c1684b00f177d37438febe6e709fc4e2b0d4248dca4854946f9ed8b30cda83e",
            ),
            (
                "pwm_actuator_msgs/action/Autotune_SendGoal",
                "RIHS01_17b4898c700077112c006395dd575c255e431aae205eafed2f43cc2a9283d49c",
            ),
            (
                "pwm_actuator_msgs/action/Autotune_GetResult",
                "RIHS01_1ee482204c3aa8124e98907370c208ae41858354606d54a9dc4f8fc116a2e385",
            ),
            (
                "pwm_actuator_msgs/action/Autotune_FeedbackMessage",
                "RIHS01_d7e501711a46cee3bb8d1dcdb824dc154709a626c8ca7076236ad71d099f4ab7",
            ),
        ] {
            assert_eq!(h[t], expected, "{t}");
            assert_eq!(ty(t).hash, expected, "{t}");
        }
    }

    /// design.md, "Topic and Service name mapping to Zenoh key expressions": the three
    /// examples; the first two from this node's own String hash and type name.
    #[test]
    fn data_keys_are_the_design_documents() {
        let string = ty("std_msgs/msg/String");
        assert_eq!(
            data_key(0, "/chatter", &string).unwrap(),
            "0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
        );
        assert_eq!(
            data_key(0, "/robot1/chatter", &string).unwrap(),
            "0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
        );
        assert_eq!(
            data_key(2, "/add_two_ints", &add_two_ints()).unwrap(),
            "2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
        );
    }

    /// The node's own keys: a channel's E1 and duty, a parameter service (the service's
    /// hash), the action's parts.
    #[test]
    fn the_nodes_data_keys() {
        let key = |d, name, t: &str| data_key(d, name, &ty(t)).unwrap();
        assert_eq!(
            key(0, "/pwm_actuator/pw01/e1", "std_msgs/msg/Bool"),
            "0/pwm_actuator/pw01/e1/std_msgs::msg::dds_::Bool_/RIHS01_feb91e995ff9ebd09c0cb3d2aed18b11077585839fb5db80193b62d74528f6c9"
        );
        assert_eq!(
            key(0, "/pwm_actuator/pw01/duty", "std_msgs/msg/Float64"),
            "0/pwm_actuator/pw01/duty/std_msgs::msg::dds_::Float64_/RIHS01_705ba9c3d1a09df43737eb67095534de36fd426c0587779bda2bc51fe790182a"
        );
        assert_eq!(
            key(7, "/pwm_actuator/get_parameters", "rcl_interfaces/srv/GetParameters"),
            "7/pwm_actuator/get_parameters/rcl_interfaces::srv::dds_::GetParameters_/RIHS01_bf9803d5c74cf989a5de3e0c2e99444599a627c7ff75f97b8c05b01003675cbc"
        );
        assert_eq!(
            key(
                0,
                "/pwm_actuator/pw03/autotune/_action/send_goal",
                "pwm_actuator_msgs/action/Autotune_SendGoal"
            ),
            "0/pwm_actuator/pw03/autotune/_action/send_goal/pwm_actuator_msgs::action::dds_::Autotune_SendGoal_/RIHS01_17b4898c700077112c006395dd575c255e431aae205eafed2f43cc2a9283d49c"
        );
    }

    #[test]
    fn data_keys_refuse_what_is_no_fully_qualified_name_or_type() {
        let t = ty("std_msgs/msg/Bool");
        for bad in [
            "", "/", "chatter", "/a//b", "/a/", "/a/*", "/a/$*", "/1a", "/a b", "/a/**",
        ] {
            assert!(
                matches!(
                    data_key(0, bad, &t),
                    Err(KeyError::Field {
                        field: Field::Name,
                        ..
                    })
                ),
                "{bad:?}"
            );
        }
        let mut wrong = t.clone();
        wrong.hash = "RIHS01_00".into();
        assert!(matches!(
            data_key(0, "/a", &wrong),
            Err(KeyError::Field {
                field: Field::TypeHash,
                ..
            })
        ));
        wrong = t.clone();
        wrong.name = "std_msgs/msg/Bool".into();
        assert!(matches!(
            data_key(0, "/a", &wrong),
            Err(KeyError::Field {
                field: Field::TypeName,
                ..
            })
        ));
        let h = hashes();
        assert_eq!(
            EndpointType::of(&h, "std_srvs/srv/Trigger_Request"),
            Err(KeyError::NotAnEndpointType {
                ros_type: "std_srvs/srv/Trigger_Request".into()
            })
        );
        assert_eq!(
            EndpointType::of(&h, "example_interfaces/srv/AddTwoInts"),
            Err(KeyError::NoHash {
                ros_type: "example_interfaces/srv/AddTwoInts".into()
            })
        );
    }

    /// design.md, "Graph Cache": the five example tokens, made from their parts, and read
    /// back into the same parts.
    #[test]
    fn liveliness_tokens_are_the_design_documents() {
        let string = ty("std_msgs/msg/String");
        let listener = node(2, LISTENER_ZID, "listener");
        assert_eq!(
            listener.key().unwrap(),
            "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
        );
        let cases = [
            (
                entity(
                    listener.clone(),
                    10,
                    EntityKind::Subscription,
                    "/chatter",
                    string.clone(),
                    keep_last(10),
                ),
                "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,10:,:,:,,",
            ),
            (
                entity(
                    node(2, TALKER_ZID, "talker"),
                    10,
                    EntityKind::Publisher,
                    "/chatter",
                    string,
                    keep_last(7),
                ),
                "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,",
            ),
            (
                entity(
                    node(2, SERVER_ZID, "add_two_ints_server"),
                    10,
                    EntityKind::Service,
                    "/add_two_ints",
                    add_two_ints(),
                    keep_last(10),
                ),
                "@ros2_lv/2/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/%add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a/::,10:,:,:,,",
            ),
            (
                entity(
                    node(2, CLIENT_ZID, "add_two_ints_client"),
                    10,
                    EntityKind::Client,
                    "/add_two_ints",
                    add_two_ints(),
                    keep_last(10),
                ),
                "@ros2_lv/2/e1dc8d1b45ae8717fce78689cc655685/0/10/SC/%/%/add_two_ints_client/%add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a/::,10:,:,:,,",
            ),
        ];
        assert_eq!(
            parse_token(&listener.key().unwrap()),
            Ok(Token::Node(listener.clone()))
        );
        for (token, expected) in cases {
            assert_eq!(token.key().unwrap(), expected);
            let mut read = token.clone();
            read.qos = as_read(read.qos);
            assert_eq!(parse_token(expected), Ok(Token::Entity(read)), "{expected}");
        }
    }

    /// The node's E1 publisher (reliable, transient local, keep last 1) as the plan of its
    /// Zenoh endpoints gives it, and an action's feedback under a namespace (a token of
    /// more than 240 bytes, XXH3's long-input path).
    #[test]
    fn the_nodes_tokens() {
        let pwm = NodeToken {
            domain: 0,
            zid: LISTENER_ZID.into(),
            node_id: 0,
            enclave: "/".into(),
            namespace: "/".into(),
            name: "pwm_actuator".into(),
        };
        let e1 = entity(
            pwm.clone(),
            7,
            EntityKind::Publisher,
            "/pwm_actuator/pw01/e1",
            ty("std_msgs/msg/Bool"),
            qos::e1(),
        );
        assert_eq!(
            e1.key().unwrap(),
            "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/7/MP/%/%/pwm_actuator/%pwm_actuator%pw01%e1/std_msgs::msg::dds_::Bool_/RIHS01_feb91e995ff9ebd09c0cb3d2aed18b11077585839fb5db80193b62d74528f6c9/:1:,1:,:,:,,"
        );
        let feedback = entity(
            NodeToken {
                namespace: "/plant/hall_2".into(),
                ..pwm
            },
            23,
            EntityKind::Publisher,
            "/plant/hall_2/pwm_actuator/pw03/autotune/_action/feedback",
            ty("pwm_actuator_msgs/action/Autotune_FeedbackMessage"),
            qos::action_server().feedback_publisher,
        );
        let key = feedback.key().unwrap();
        assert_eq!(
            key,
            "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/23/MP/%/%plant%hall_2/pwm_actuator/%plant%hall_2%pwm_actuator%pw03%autotune%_action%feedback/pwm_actuator_msgs::action::dds_::Autotune_FeedbackMessage_/RIHS01_d7e501711a46cee3bb8d1dcdb824dc154709a626c8ca7076236ad71d099f4ab7/::,10:,:,:,,"
        );
        assert!(key.len() > 240);
        let Ok(Token::Entity(read)) = parse_token(&key) else {
            panic!("{key}");
        };
        assert_eq!(read.node.namespace, "/plant/hall_2");
        assert_eq!(read.name, feedback.name);
        assert_eq!(read.key().unwrap(), key);
    }

    /// `qos_to_keyexpr` leaves out what equals rmw_zenoh's default profile (qos.cpp):
    /// design.md's `::,10:,:,:,,` and `::,7:,:,:,,`, and each of the node's profiles.
    #[test]
    fn qos_strings_leave_out_rmw_zenohs_defaults() {
        let s = |q: &QosProfile| qos_to_keyexpr(q);
        assert_eq!(s(&keep_last(10)), "::,10:,:,:,,");
        assert_eq!(s(&keep_last(7)), "::,7:,:,:,,");
        assert_eq!(s(&keep_last(42)), "::,:,:,:,,");
        assert_eq!(s(&keep_last(0)), "::,:,:,:,,");
        assert_eq!(s(&QosProfile::publisher_default()), "::,1:,:,:,,");
        assert_eq!(s(&qos::e1()), ":1:,1:,:,:,,");
        assert_eq!(s(&qos::edges()), "::,100:,:,:,,");
        assert_eq!(s(&qos::status()), "::,10:,:,:,,");
        assert_eq!(s(&qos::commands()), "::,10:,:,:,,");
        assert_eq!(s(&qos::diagnostics()), "::,10:,:,:,,");
        assert_eq!(s(&qos::services()), "::,10:,:,:,,");
        assert_eq!(s(&qos::sensor()), "2::,10:,:,:,,");
        let action = qos::action_server();
        assert_eq!(s(&action.status_publisher), ":1:,1:,:,:,,");
        assert_eq!(s(&action.feedback_publisher), "::,10:,:,:,,");
        assert_eq!(s(&action.goal_service), "::,10:,:,:,,");
        // Every field away from its default.
        let all = QosProfile {
            reliability: Reliability::BestEffort,
            durability: Durability::TransientLocal,
            history: History::KeepAll,
            deadline: Some(Duration::new(1, 500)),
            lifespan: Some(Duration::from_millis(2500)),
            liveliness: Liveliness::ManualByTopic,
            liveliness_lease: Some(Duration::ZERO),
        };
        assert_eq!(s(&all), "2:1:2,:1,500:2,500000000:3,0,0");
        // A component equal to the infinite duration's is left out on its own, as
        // rmw_zenoh compares seconds and nanoseconds one by one.
        let half = QosProfile {
            deadline: Some(Duration::new(5, 854_775_807)),
            lifespan: Some(Duration::new(9_223_372_036, 0)),
            ..keep_last(10)
        };
        assert_eq!(s(&half), "::,10:5,:,0:,,");
        let infinite = QosProfile {
            deadline: Some(Duration::new(INFINITE.0, INFINITE.1 as u32)),
            ..keep_last(10)
        };
        assert_eq!(s(&infinite), "::,10:,:,:,,");
    }

    #[test]
    fn qos_strings_read_back_into_their_profile() {
        for q in [
            qos::e1(),
            qos::edges(),
            qos::sensor(),
            qos::action_server().status_publisher,
            keep_last(42),
            QosProfile {
                reliability: Reliability::BestEffort,
                durability: Durability::TransientLocal,
                history: History::KeepAll,
                deadline: Some(Duration::new(1, 500)),
                lifespan: Some(Duration::from_millis(2500)),
                liveliness: Liveliness::ManualByTopic,
                liveliness_lease: Some(Duration::ZERO),
            },
        ] {
            let s = qos_to_keyexpr(&q);
            assert_eq!(keyexpr_to_qos(&s), Ok(as_read(q)), "{s}");
        }
        // rmw's "system default" (0) and explicit defaults read as the default.
        assert_eq!(keyexpr_to_qos("0:0:0,:,:,:0,,"), Ok(as_read(keep_last(42))));
        assert_eq!(
            keyexpr_to_qos("1:2:1,42:9223372036,854775807:,:1,,"),
            Ok(as_read(keep_last(42)))
        );
        // Keep all with a depth: the depth is not kept.
        assert_eq!(
            keyexpr_to_qos("::2,10:,:,:,,").map(|q| q.history),
            Ok(History::KeepAll)
        );
        // Half a duration: the other half is the infinite one's.
        assert_eq!(
            keyexpr_to_qos("::,:5,:,:,,").map(|q| q.deadline),
            Ok(Some(Duration::new(5, 854_775_807)))
        );
    }

    #[test]
    fn malformed_qos_strings_are_refused() {
        for bad in [
            "",
            "::,10:,:,:,",
            "::,10:,:,:,,,",
            "::,10:,:,:,,:",
            "::10:,:,:,,",
            "::,10,1:,:,:,,",
            "::,10:,:,,:,,",
            "3::,10:,:,:,,",
            ":3:,10:,:,:,,",
            "::3,10:,:,:,,",
            "::,10:,:,:2,,",
            "::,10:,:,:4,,",
            "::,-1:,:,:,,",
            "::,+1:,:,:,,",
            "::,010:,:,:,,",
            "::,1 :,:,:,,",
            "::,x:,:,:,,",
            "::,99999999999999999999999:,:,:,,",
            "::,:18446744073709551615,18446744073709551615:,:,,",
            "1,::,10:,:,:,,",
        ] {
            assert!(
                matches!(
                    keyexpr_to_qos(bad),
                    Err(KeyError::Field {
                        field: Field::Qos,
                        ..
                    })
                ),
                "{bad:?}: {:?}",
                keyexpr_to_qos(bad)
            );
        }
    }

    /// Every way a token can be malformed, each refused with the field it is wrong in.
    #[test]
    fn malformed_tokens_are_refused() {
        let good = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,10:,:,:,,";
        assert!(parse_token(good).is_ok());
        let chunks: Vec<&str> = good.split('/').collect();
        let with = |i: usize, v: &str| {
            let mut c = chunks.clone();
            c[i] = v;
            c.join("/")
        };
        let upper = STRING_HASH.to_uppercase();
        let version = STRING_HASH.replace("RIHS01", "RIHS1_");
        let field_of = |t: &str| match parse_token(t) {
            Err(KeyError::Field { field, .. }) => Some(field),
            _ => None,
        };
        for (i, v, field) in [
            (0, "@ros2", Field::AdminSpace),
            (0, "ros2_lv", Field::AdminSpace),
            (1, "", Field::Domain),
            (1, "-1", Field::Domain),
            (1, "02", Field::Domain),
            (1, "4294967296", Field::Domain),
            (1, "*", Field::Domain),
            (2, "", Field::Zid),
            (2, "AAC3178E146BA6F1FC6E6A4085E77F21", Field::Zid),
            (2, "aac3178e146ba6f1fc6e6a4085e77f21a", Field::Zid),
            (2, "g", Field::Zid),
            (3, "x", Field::NodeId),
            (3, "18446744073709551616", Field::NodeId),
            (4, "", Field::EntityId),
            (5, "XX", Field::Kind),
            (5, "mp", Field::Kind),
            (6, "", Field::Enclave),
            (6, "enclave", Field::Enclave),
            (6, "%%", Field::Enclave),
            (7, "ns", Field::Namespace),
            (7, "%a%", Field::Namespace),
            (7, "%a*", Field::Namespace),
            (8, "", Field::NodeName),
            (8, "%listener", Field::NodeName),
            (8, "1listener", Field::NodeName),
            (8, "**", Field::NodeName),
            (9, "%", Field::Name),
            (9, "chatter", Field::Name),
            (9, "%chat ter", Field::Name),
            (10, "", Field::TypeName),
            (10, "std_msgs%msg%String", Field::TypeName),
            (10, "$*", Field::TypeName),
            (11, "RIHS01_df668c", Field::TypeHash),
            (11, upper.as_str(), Field::TypeHash),
            (11, version.as_str(), Field::TypeHash),
            (12, "::,10:,:,:,", Field::Qos),
            (12, "", Field::Qos),
        ] {
            let t = with(i, v);
            assert_eq!(field_of(&t), Some(field), "{t}: {:?}", parse_token(&t));
        }
        // A node's token repeats its node id and has nothing after the node's name.
        let nn = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener";
        assert!(parse_token(nn).is_ok());
        assert_eq!(
            field_of(&nn.replace("/0/0/", "/0/1/")),
            Some(Field::EntityId)
        );
        assert!(matches!(
            parse_token(&format!("{nn}/%chatter")),
            Err(KeyError::Chunks { found: 10, .. })
        ));
        // Chunk counts.
        assert!(matches!(
            parse_token(""),
            Err(KeyError::Chunks { found: 1, .. })
        ));
        assert!(matches!(
            parse_token("@ros2_lv/2/aac3/0/0/NN/%/%"),
            Err(KeyError::Chunks { found: 8, .. })
        ));
        let short = chunks[..12].join("/");
        assert!(matches!(
            parse_token(&short),
            Err(KeyError::Chunks { found: 12, .. })
        ));
        let long = format!("{good}/cpu/more");
        assert!(matches!(
            parse_token(&long),
            Err(KeyError::Chunks { found: 15, .. })
        ));
        // A 14th chunk is the buffer backends', kept as read.
        let Ok(Token::Entity(e)) = parse_token(&format!("{good}/cpu")) else {
            panic!("backends chunk refused");
        };
        assert_eq!(e.backends.as_deref(), Some("cpu"));
        assert_eq!(e.key().unwrap(), format!("{good}/cpu"));
        assert_eq!(field_of(&format!("{good}/a*b")), Some(Field::Backends));
        assert_eq!(field_of(&format!("{good}/")), Some(Field::Backends));
        // Too long, refused before it is split.
        let huge = format!("{good}/{}", "x".repeat(MAX_TOKEN_BYTES));
        assert_eq!(
            parse_token(&huge),
            Err(KeyError::TooLong { bytes: huge.len() })
        );
    }

    /// Every endpoint type the node declares has a Zenoh type name and a hash: its topics
    /// (the messages of `msg.rs` it publishes and subscribes to, `/rosout`,
    /// `/parameter_events`), its services (`std_srvs/Trigger` for the resets, the
    /// lifecycle's and the parameters'), and its action's parts (two services, the cancel
    /// service, the feedback and status topics).
    #[test]
    fn every_endpoint_type_of_the_node_has_a_zenoh_type_and_hash() {
        fn topic<M: RosMessage>() -> String {
            format!("{}/msg/{}", M::PACKAGE, M::NAME)
        }
        let action = format!("{}/action/Autotune", msg::MSG_PACKAGE);
        let mut types = vec![
            topic::<msg::Float64>(),
            topic::<msg::UInt16>(),
            topic::<msg::Bool>(),
            topic::<msg::StringMsg>(),
            topic::<msg::OutputEdge>(),
            topic::<msg::ChannelStatus>(),
            topic::<msg::ChannelParams>(),
            topic::<msg::ValveState>(),
            topic::<msg::Temperature>(),
            topic::<msg::DiagnosticArray>(),
            topic::<msg::TransitionEvent>(),
            "rcl_interfaces/msg/Log".to_string(),
            "rcl_interfaces/msg/ParameterEvent".to_string(),
            "action_msgs/msg/GoalStatusArray".to_string(),
            format!("{action}_FeedbackMessage"),
            format!("{action}_SendGoal"),
            format!("{action}_GetResult"),
            "action_msgs/srv/CancelGoal".to_string(),
            "std_srvs/srv/Trigger".to_string(),
        ];
        for s in [
            "ChangeState",
            "GetState",
            "GetAvailableStates",
            "GetAvailableTransitions",
        ] {
            types.push(format!("lifecycle_msgs/srv/{s}"));
        }
        for s in [
            "GetParameters",
            "GetParameterTypes",
            "SetParameters",
            "SetParametersAtomically",
            "DescribeParameters",
            "ListParameters",
        ] {
            types.push(format!("rcl_interfaces/srv/{s}"));
        }
        let h = hashes();
        let zero = format!("RIHS01_{}", "0".repeat(64));
        let mut seen = std::collections::BTreeSet::new();
        for t in &types {
            let e = EndpointType::of(&h, t).unwrap_or_else(|e| panic!("{t}: {e}"));
            assert_ne!(e.hash, zero, "{t}");
            assert!(e.name.ends_with('_') && e.name.contains("::dds_::"), "{t}");
            assert!(seen.insert(e.hash.clone()), "{t}: hash twice");
            data_key(0, "/pwm_actuator/x", &e).unwrap();
        }
        assert_eq!(seen.len(), 29);
    }

    /// XXH3-128 of the token, low half first: the reference implementation's value for the
    /// empty input (xxHash's test vectors), and the Python `xxhash` package (the reference
    /// C library; `xxh3_128_intdigest(key).to_bytes(16, "little")`) for design.md's tokens
    /// and the node's E1 and feedback tokens above.
    #[test]
    fn gids_are_xxh3_128_of_the_token_low_half_first() {
        assert_eq!(
            hex(&Gid::of_token("").0),
            "7f498d4624c30160d8984701d306aa99"
        );
        for (token, gid) in [
            (
                "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener",
                "49877999dacb858702d11ac823785912",
            ),
            (
                "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,10:,:,:,,",
                "76148a538308fe55a6c5375462ca1de6",
            ),
            (
                "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,",
                "ac170f31eadcd9ff0cd86d7a17907d1c",
            ),
            (
                "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/7/MP/%/%/pwm_actuator/%pwm_actuator%pw01%e1/std_msgs::msg::dds_::Bool_/RIHS01_feb91e995ff9ebd09c0cb3d2aed18b11077585839fb5db80193b62d74528f6c9/:1:,1:,:,:,,",
                "2f5bf7c3a5646c12fc6459463b1a720a",
            ),
            (
                "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/23/MP/%/%plant%hall_2/pwm_actuator/%plant%hall_2%pwm_actuator%pw03%autotune%_action%feedback/pwm_actuator_msgs::action::dds_::Autotune_FeedbackMessage_/RIHS01_d7e501711a46cee3bb8d1dcdb824dc154709a626c8ca7076236ad71d099f4ab7/::,10:,:,:,,",
                "5b4286f2042f7d7741a2e10f4ddb5202",
            ),
        ] {
            assert_eq!(hex(&Gid::of_token(token).0), gid, "{token}");
        }
        let Ok(Token::Entity(e)) = parse_token(
            "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,",
        ) else {
            panic!("talker's token refused");
        };
        assert_eq!(hex(&e.gid().unwrap().0), "ac170f31eadcd9ff0cd86d7a17907d1c");
    }

    /// The bytes zenoh-ext's serializer writes for `(i64, i64, [u8; 16])` (Python
    /// `zenoh.ext.z_serialize((Int64(seq), Int64(ts), gid))`, eclipse-zenoh 1.10.2), which is
    /// what rmw_zenoh attaches.
    #[test]
    fn attachments_are_zenoh_exts_33_bytes() {
        let mut gid = [0; GID_BYTES];
        for (i, g) in gid.iter_mut().enumerate() {
            *g = i as u8;
        }
        let a = Attachment {
            sequence: 1,
            source_timestamp_ns: 0x18eb_f4c8_90e9_2806,
            gid: Gid(gid),
        };
        assert_eq!(
            hex(&a.encode()),
            "01000000000000000628e990c8f4eb1810000102030405060708090a0b0c0d0e0f"
        );
        assert_eq!(Attachment::decode(&a.encode()), Ok(a));
        for (i, g) in gid.iter_mut().enumerate() {
            *g = 0xf0 + i as u8;
        }
        let b = Attachment {
            sequence: 7,
            source_timestamp_ns: -2,
            gid: Gid(gid),
        };
        assert_eq!(
            hex(&b.encode()),
            "0700000000000000feffffffffffffff10f0f1f2f3f4f5f6f7f8f9fafbfcfdfeff"
        );
        assert_eq!(Attachment::decode(&b.encode()), Ok(b));
    }

    #[test]
    fn attachments_of_another_length_or_gid_length_are_refused() {
        let good = Attachment {
            sequence: 1,
            source_timestamp_ns: 2,
            gid: Gid([3; GID_BYTES]),
        }
        .encode();
        assert_eq!(
            Attachment::decode(&[]),
            Err(AttachmentError::Length { bytes: 0 })
        );
        assert_eq!(
            Attachment::decode(&good[..32]),
            Err(AttachmentError::Length { bytes: 32 })
        );
        let mut longer = good.to_vec();
        longer.push(0);
        assert_eq!(
            Attachment::decode(&longer),
            Err(AttachmentError::Length { bytes: 34 })
        );
        let mut wrong = good;
        wrong[16] = 0x0f;
        assert_eq!(
            Attachment::decode(&wrong),
            Err(AttachmentError::GidLength { found: 0x0f })
        );
    }

    /// A token made from valid parts.
    fn any_entity() -> impl Strategy<Value = EntityToken> {
        let name = "[a-z_][a-z0-9_]{0,6}";
        let fq = prop::collection::vec(name, 1..4).prop_map(|t| format!("/{}", t.join("/")));
        let ns = prop::collection::vec(name, 0..3).prop_map(|t| format!("/{}", t.join("/")));
        let duration = prop::option::of((0u64..20_000_000_000, 0u32..1_000_000_000))
            .prop_map(|d| d.map(|(s, n)| Duration::new(s, n)));
        let qos = (
            any::<bool>(),
            any::<bool>(),
            prop::option::of(0usize..200),
            duration.clone(),
            duration.clone(),
            any::<bool>(),
            duration,
        )
            .prop_map(
                |(best, tl, depth, deadline, lifespan, manual, lease)| QosProfile {
                    reliability: if best {
                        Reliability::BestEffort
                    } else {
                        Reliability::Reliable {
                            when_full: WhenFull::DEFAULT,
                        }
                    },
                    durability: if tl {
                        Durability::TransientLocal
                    } else {
                        Durability::Volatile
                    },
                    history: depth.map_or(History::KeepAll, |d| History::KeepLast {
                        depth: if d == 0 { DEFAULT_DEPTH } else { d },
                    }),
                    deadline,
                    lifespan,
                    liveliness: if manual {
                        Liveliness::ManualByTopic
                    } else {
                        Liveliness::Automatic
                    },
                    liveliness_lease: lease,
                },
            );
        (
            (any::<u32>(), "[0-9a-f]{1,32}", any::<u64>(), ns, name),
            any::<u64>(),
            0..4usize,
            fq,
            ("[a-z_]{1,8}::msg::dds_::[A-Z][a-z]{0,6}_", "[0-9a-f]{64}"),
            qos,
            prop::option::of("[a-z]{1,5}"),
        )
            .prop_map(
                |((domain, zid, node_id, namespace, node_name), id, kind, name, t, qos, b)| {
                    EntityToken {
                        node: NodeToken {
                            domain,
                            zid,
                            node_id,
                            enclave: "/".into(),
                            namespace,
                            name: node_name,
                        },
                        entity_id: id,
                        kind: [
                            EntityKind::Publisher,
                            EntityKind::Subscription,
                            EntityKind::Service,
                            EntityKind::Client,
                        ][kind],
                        name,
                        ty: EndpointType {
                            name: t.0,
                            hash: format!("RIHS01_{}", t.1),
                        },
                        qos,
                        backends: b,
                    }
                },
            )
    }

    proptest! {
        #[test]
        fn attachment_decoding_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..80)) {
            match Attachment::decode(&bytes) {
                Ok(a) => {
                    prop_assert_eq!(bytes.len(), ATTACHMENT_BYTES);
                    prop_assert_eq!(&a.encode()[..], &bytes[..]);
                }
                Err(AttachmentError::Length { bytes: n }) => {
                    prop_assert_eq!(n, bytes.len());
                    prop_assert_ne!(n, ATTACHMENT_BYTES);
                }
                Err(AttachmentError::GidLength { found }) => prop_assert_ne!(found, 0x10),
            }
        }

        #[test]
        fn attachments_round_trip(
            sequence in any::<i64>(),
            source_timestamp_ns in any::<i64>(),
            gid in any::<[u8; GID_BYTES]>(),
        ) {
            let a = Attachment { sequence, source_timestamp_ns, gid: Gid(gid) };
            let bytes = a.encode();
            prop_assert_eq!(bytes[16], 0x10);
            prop_assert_eq!(Attachment::decode(&bytes), Ok(a));
        }

        /// A token made from valid parts reads back into them, and writes back the same
        /// string (so its GID is the same whether hashed as sent or as rewritten).
        #[test]
        fn tokens_round_trip(e in any_entity()) {
            let key = e.key().unwrap();
            prop_assert!(key.len() <= MAX_TOKEN_BYTES);
            let read = parse_token(&key).unwrap();
            prop_assert_eq!(&read, &Token::Entity(e.clone()));
            let Token::Entity(read) = read else { unreachable!() };
            prop_assert_eq!(read.key().unwrap(), key.clone());
            prop_assert_eq!(read.gid().unwrap(), Gid::of_token(&key));
            let nn = e.node.key().unwrap();
            prop_assert_eq!(parse_token(&nn), Ok(Token::Node(e.node.clone())));
        }

        /// Arbitrary text never panics the parser, and anything it accepts writes back
        /// unchanged or as a token that reads the same.
        #[test]
        fn token_parsing_never_panics(s in "\\PC{0,300}") {
            if let Ok(t) = parse_token(&s) {
                let key = match &t {
                    Token::Node(n) => n.key().unwrap(),
                    Token::Entity(e) => e.key().unwrap(),
                };
                prop_assert_eq!(parse_token(&key), Ok(t));
            }
        }

        /// A valid token with one byte changed, cut or doubled: read or refused, never a
        /// panic.
        #[test]
        fn mutated_tokens_never_panic(
            e in any_entity(),
            at in any::<prop::sample::Index>(),
            byte in any::<u8>(),
            how in 0..3u8,
        ) {
            let mut bytes = e.key().unwrap().into_bytes();
            let i = at.index(bytes.len());
            match how {
                0 => bytes[i] = byte,
                1 => bytes.truncate(i),
                _ => {
                    let tail = bytes[i..].to_vec();
                    bytes.extend_from_slice(&tail);
                }
            }
            let s = String::from_utf8_lossy(&bytes);
            let _ = parse_token(&s);
            let qos = s.rsplit('/').next().unwrap_or("");
            let _ = keyexpr_to_qos(qos);
        }
    }
}
