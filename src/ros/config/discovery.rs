//! How far the node's DDS participant discovers and can be reached: `ROS_AUTOMATIC_DISCOVERY_RANGE`,
//! `ROS_STATIC_PEERS` and the deprecated `ROS_LOCALHOST_ONLY`, read with rcl's Jazzy rules and
//! applied to the RustDDS participant.
//!
//! rcl's rules (Jazzy, `rcl/src/rcl/discovery_options.c` and `init.c`):
//! - `ROS_AUTOMATIC_DISCOVERY_RANGE`: `SUBNET` (also when unset or empty), `LOCALHOST`, `OFF`,
//!   `SYSTEM_DEFAULT`; any other value is warned about and taken as `LOCALHOST`.
//! - `ROS_STATIC_PEERS`: addresses or host names separated by `;`, empty items skipped; used
//!   with every range but `OFF`.
//! - `ROS_LOCALHOST_ONLY=1` is deprecated but honoured: the range becomes `LOCALHOST` and the
//!   two variables above are ignored, each with a warning.
//!
//! What this module does with them on RustDDS (with the vendored patch's static peers and
//! discovery without multicast, vendor/rustdds/README.pwm_actuator.md):
//! - `SUBNET`, `SYSTEM_DEFAULT`: RustDDS's defaults (multicast on every interface).
//! - `LOCALHOST`: only 127.0.0.1 is advertised and used for multicast, SPDP goes to the
//!   well-known localhost ports (RustDDS's `same_host_loopback`), and, because RustDDS binds
//!   its unicast sockets to the wildcard address, every UDP socket of the process is then
//!   bound to the loopback device (`SO_BINDTODEVICE lo`): the kernel delivers it nothing that
//!   arrived on another interface, and it sends nothing out of one.
//! - `OFF`: nothing is advertised, no multicast, no localhost announcements, and the sockets
//!   are confined to loopback as for `LOCALHOST`. The node then discovers no one.
//! - `ROS_STATIC_PEERS`: each peer is resolved to its IPv4 addresses at start-up, and every SPDP
//!   announcement is also sent unicast to the well-known SPDP ports of participant ids 0..9 of
//!   the domain on each, as Fast DDS's and Cyclone DDS's initial peers are. With `SUBNET` and
//!   `SYSTEM_DEFAULT` that is beside multicast; with `LOCALHOST` multicast is off, SPDP goes to
//!   the localhost ports and the peers, the node advertises its addresses on every interface
//!   (the peers must reach them), and its sockets are not confined to loopback; under `OFF` the
//!   peers are ignored with a warning, as rcl ignores them. An entry that is neither an address
//!   nor spelled as a host name, is longer than [`MAX_PEER_LEN`], or names no IPv4 address (an
//!   unknown name, an IPv6 address) is skipped with a warning that echoes it escaped; more than
//!   [`MAX_STATIC_PEERS`] entries are refused.
//!
//! `RMW_IMPLEMENTATION` names the middleware the rest of a ROS 2 system loads. The node speaks
//! DDS (RTPS) itself and loads none, so it meets every DDS-based one (`rmw_fastrtps_cpp`,
//! `rmw_fastrtps_dynamic_cpp`, `rmw_cyclonedds_cpp`, `rmw_connextdds`, `rmw_gurumdds_cpp`) on the
//! wire. `rmw_zenoh_cpp` (or any `rmw_zenoh*`) puts the node on Zenoh (`zenoh` in
//! [`Discovery`]); a build without the `zenoh` feature refuses to start instead, rather than run
//! where no Zenoh peer can command it or see its diagnostics. Any other value is warned about
//! (echoed escaped) and the node runs on DDS.
//!
//! This module reads variables, resolves peer names (the system's resolver may ask a DNS
//! server), builds the participant and sets socket options; it must not send or receive
//! anything else itself.

use log::{info, warn};
use rustdds::dds::CreateResult;
use rustdds::{DomainParticipant, DomainParticipantBuilder};
use std::net::{IpAddr, Ipv4Addr, ToSocketAddrs};

use crate::ros::config::logging::shown;

/// `ROS_AUTOMATIC_DISCOVERY_RANGE`.
pub const RANGE_ENV: &str = "ROS_AUTOMATIC_DISCOVERY_RANGE";
/// `ROS_STATIC_PEERS`.
pub const PEERS_ENV: &str = "ROS_STATIC_PEERS";
/// `ROS_LOCALHOST_ONLY` (deprecated in Jazzy).
pub const LOCALHOST_ONLY_ENV: &str = "ROS_LOCALHOST_ONLY";
/// `RMW_IMPLEMENTATION`.
pub const RMW_ENV: &str = "RMW_IMPLEMENTATION";
/// The middlewares of `RMW_IMPLEMENTATION` the node meets on the wire: the DDS-based ones.
pub const DDS_RMWS: [&str; 5] = [
    "rmw_fastrtps_cpp",
    "rmw_fastrtps_dynamic_cpp",
    "rmw_cyclonedds_cpp",
    "rmw_connextdds",
    "rmw_gurumdds_cpp",
];
/// Most entries `ROS_STATIC_PEERS` may name, and most addresses the node sends to (a name
/// may resolve to several): each address costs ten datagrams per SPDP announcement.
pub const MAX_STATIC_PEERS: usize = 32;
/// Longest entry of `ROS_STATIC_PEERS`, in bytes: a DNS name's limit.
pub const MAX_PEER_LEN: usize = 253;

/// How far automatic discovery goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Range {
    /// Everything reachable by multicast (the default).
    Subnet,
    /// This machine only.
    Localhost,
    /// No automatic discovery, not even on this machine.
    Off,
    /// The middleware's own defaults (here: as `Subnet`).
    SystemDefault,
}

impl Range {
    /// The variable's spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Range::Subnet => "SUBNET",
            Range::Localhost => "LOCALHOST",
            Range::Off => "OFF",
            Range::SystemDefault => "SYSTEM_DEFAULT",
        }
    }
}

/// The discovery settings the node runs with, and what to say about them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Discovery {
    /// The range.
    pub range: Range,
    /// The static peers' IPv4 addresses, each with the entry of `ROS_STATIC_PEERS` it came
    /// from; empty under `OFF`.
    pub peers: Vec<(String, Ipv4Addr)>,
    /// The node runs on Zenoh (`RMW_IMPLEMENTATION=rmw_zenoh*`, built with the `zenoh`
    /// feature) instead of DDS; the range and peers then do not apply.
    pub zenoh: bool,
    /// Warnings to log once at start-up (deprecated or ignored variables).
    pub warnings: Vec<String>,
}

/// What cannot be honoured.
#[derive(Debug, thiserror::Error)]
pub enum DiscoveryError {
    /// `RMW_IMPLEMENTATION` asks for a middleware the node cannot speak.
    #[error(
        "{RMW_ENV}={value}: this build of the node speaks DDS only (RTPS through RustDDS; it was \
         built without the `zenoh` cargo feature) and cannot join a Zenoh network, where no \
         peer could command it or see its diagnostics. Run a build with the default features, or \
         run it without {RMW_ENV} (or with a DDS one: {dds}) and the nodes that talk to it on \
         a DDS-based middleware (docs/deployment.md)",
        dds = DDS_RMWS.join(", ")
    )]
    Middleware {
        /// The variable's value (escaped).
        value: String,
    },
    /// `ROS_STATIC_PEERS` names more peers than the node sends to.
    #[error(
        "{PEERS_ENV} names {count} peers; the node takes at most {MAX_STATIC_PEERS} (each is \
         sent every discovery announcement ten times). List fewer hosts, or reach them by \
         multicast ({RANGE_ENV}=SUBNET)"
    )]
    TooManyPeers {
        /// How many it names.
        count: usize,
    },
    /// The sockets could not be confined to the loopback device.
    #[error(
        "{RANGE_ENV}={range} cannot be honoured: binding the DDS sockets to the loopback device \
         failed ({source}); refusing to stay reachable from other machines"
    )]
    Confine {
        /// The range asked for.
        range: &'static str,
        /// The OS error.
        source: std::io::Error,
    },
}

/// Reads the discovery settings from variables looked up with `var`, with rcl's Jazzy rules,
/// resolving peer names with the system's resolver.
pub fn read(var: impl Fn(&str) -> Option<String>) -> Result<Discovery, DiscoveryError> {
    read_resolving(var, system_resolve)
}

/// The IPv4 and IPv6 addresses of `host` from the system's resolver.
fn system_resolve(host: &str) -> std::io::Result<Vec<IpAddr>> {
    Ok((host, 0u16).to_socket_addrs()?.map(|a| a.ip()).collect())
}

/// [`read`], resolving peer names with `resolve`.
pub fn read_resolving(
    var: impl Fn(&str) -> Option<String>,
    resolve: impl Fn(&str) -> std::io::Result<Vec<IpAddr>>,
) -> Result<Discovery, DiscoveryError> {
    read_in_build(var, resolve, cfg!(feature = "zenoh"))
}

/// [`read_resolving`] in a build with (`zenoh_built`) or without the `zenoh` feature: a
/// parameter, so that the tests of either build check both.
fn read_in_build(
    var: impl Fn(&str) -> Option<String>,
    resolve: impl Fn(&str) -> std::io::Result<Vec<IpAddr>>,
    zenoh_built: bool,
) -> Result<Discovery, DiscoveryError> {
    let mut warnings = Vec::new();
    if let Some(rmw) = var(RMW_ENV).filter(|v| !v.is_empty()) {
        if rmw.starts_with("rmw_zenoh") {
            if zenoh_built {
                // Zenoh's own settings are read where its session opens (config::zenoh).
                // The DDS discovery variables do not apply there: a value that would narrow
                // or widen discovery on DDS is said to be ignored, so that a site that counts
                // on one to keep the node on this host knows it does not. The defaults
                // (`SUBNET`, `ROS_LOCALHOST_ONLY=0`, no peers) pass without a word.
                for v in [RANGE_ENV, PEERS_ENV, LOCALHOST_ONLY_ENV] {
                    let value = var(v).unwrap_or_default();
                    let value = value.trim();
                    let matters = match v {
                        RANGE_ENV => !matches!(value, "" | "SUBNET" | "SYSTEM_DEFAULT"),
                        LOCALHOST_ONLY_ENV => !matches!(value, "" | "0"),
                        _ => value.split(';').any(|p| !p.trim().is_empty()),
                    };
                    if matters {
                        warnings.push(format!(
                            "{v} is ignored on Zenoh: what the node reaches is the session \
                             configuration's (connect/endpoints, listen/endpoints; \
                             ZENOH_CONFIG_OVERRIDE)"
                        ));
                    }
                }
                return Ok(Discovery {
                    range: Range::Subnet,
                    peers: Vec::new(),
                    zenoh: true,
                    warnings,
                });
            }
            return Err(DiscoveryError::Middleware { value: shown(&rmw) });
        }
        if !DDS_RMWS.contains(&rmw.as_str()) {
            warnings.push(format!(
                "{RMW_ENV}={} is not a middleware this node knows; it speaks DDS (RTPS) and \
                 meets only DDS-based ones ({})",
                shown(&rmw),
                DDS_RMWS.join(", ")
            ));
        }
    }
    let range_var = var(RANGE_ENV).filter(|v| !v.is_empty());
    let names: Vec<String> = var(PEERS_ENV)
        .unwrap_or_default()
        .split(';')
        .map(str::trim)
        .filter(|p| !p.is_empty())
        .map(str::to_string)
        .collect();
    if var(LOCALHOST_ONLY_ENV).as_deref() == Some("1") {
        warnings.push(format!(
            "{LOCALHOST_ONLY_ENV} is deprecated but still honored if it is enabled. Use \
             {RANGE_ENV} and {PEERS_ENV} instead"
        ));
        if range_var.is_some() || !names.is_empty() {
            warnings.push(format!(
                "{LOCALHOST_ONLY_ENV}=1: {RANGE_ENV} and {PEERS_ENV} are ignored"
            ));
        }
        return Ok(Discovery {
            range: Range::Localhost,
            peers: Vec::new(),
            zenoh: false,
            warnings,
        });
    }
    let range = match range_var.as_deref() {
        None | Some("SUBNET") => Range::Subnet,
        Some("LOCALHOST") => Range::Localhost,
        Some("OFF") => Range::Off,
        Some("SYSTEM_DEFAULT") => Range::SystemDefault,
        Some(other) => {
            warnings.push(format!(
                "invalid value `{}` for {RANGE_ENV} (SUBNET, LOCALHOST, OFF or SYSTEM_DEFAULT): \
                 assuming LOCALHOST, as rcl does",
                shown(other)
            ));
            Range::Localhost
        }
    };
    let mut peers = Vec::new();
    if !names.is_empty() {
        if range == Range::Off {
            warnings.push(format!(
                "{RANGE_ENV}=OFF: {PEERS_ENV} is ignored (no discovery at all)"
            ));
        } else if names.len() > MAX_STATIC_PEERS {
            return Err(DiscoveryError::TooManyPeers { count: names.len() });
        } else {
            for name in &names {
                match peer_addresses(name, &resolve) {
                    Ok(addrs) => {
                        let mut dropped = 0usize;
                        for a in addrs {
                            if peers.iter().any(|(_, p)| *p == a) {
                                continue;
                            }
                            if peers.len() < MAX_STATIC_PEERS {
                                peers.push((shown(name), a));
                            } else {
                                dropped += 1;
                            }
                        }
                        if dropped > 0 {
                            warnings.push(format!(
                                "{PEERS_ENV}: {dropped} address(es) of peer `{}` skipped: the \
                                 node sends to at most {MAX_STATIC_PEERS} addresses",
                                shown(name)
                            ));
                        }
                    }
                    Err(why) => warnings.push(format!(
                        "{PEERS_ENV}: peer `{}` skipped: {why}",
                        shown(name)
                    )),
                }
            }
        }
    }
    Ok(Discovery {
        range,
        peers,
        zenoh: false,
        warnings,
    })
}

/// Whether `name` is spelled as a host name: labels of ASCII letters, digits, `-` and `_`
/// separated by dots.
fn is_host_name(name: &str) -> bool {
    !name.is_empty()
        && name.split('.').all(|l| {
            !l.is_empty()
                && l.bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_')
        })
}

/// Why an entry of `ROS_STATIC_PEERS` is skipped (a warning at start-up, not a refusal).
#[derive(Debug, thiserror::Error)]
enum PeerSkipped {
    /// The entry is longer than a host name can be.
    #[error("longer than {MAX_PEER_LEN} bytes")]
    TooLong,
    /// Neither an address nor spelled as a host name.
    #[error("not an address or a host name")]
    NotAName,
    /// The resolver gave no answer.
    #[error("cannot be resolved ({0})")]
    Unresolved(#[source] std::io::Error),
    /// The resolver answered with no address.
    #[error("no address")]
    NoAddress,
    /// The name has IPv6 addresses only.
    #[error("no IPv4 address (the node's DDS transport is IPv4 only)")]
    NoIpv4,
}

/// The IPv4 addresses of one entry of `ROS_STATIC_PEERS`: an address, or a name `resolve`
/// knows; why none, if none.
fn peer_addresses(
    name: &str,
    resolve: impl Fn(&str) -> std::io::Result<Vec<IpAddr>>,
) -> Result<Vec<Ipv4Addr>, PeerSkipped> {
    if name.len() > MAX_PEER_LEN {
        return Err(PeerSkipped::TooLong);
    }
    let addrs = match name.parse::<IpAddr>() {
        Ok(a) => vec![a],
        // Only what can be a host name goes to the resolver (and so to a DNS server).
        Err(_) if !is_host_name(name) => return Err(PeerSkipped::NotAName),
        Err(_) => resolve(name).map_err(PeerSkipped::Unresolved)?,
    };
    let v4: Vec<Ipv4Addr> = addrs
        .iter()
        .filter_map(|a| match a {
            IpAddr::V4(a) => Some(*a),
            IpAddr::V6(_) => None,
        })
        .collect();
    if v4.is_empty() {
        return Err(if addrs.is_empty() {
            PeerSkipped::NoAddress
        } else {
            PeerSkipped::NoIpv4
        });
    }
    Ok(v4)
}

impl Discovery {
    /// Builds the DDS participant for `domain` with this range, secured with the enclave in
    /// `secure` (see [`crate::ros::config::security`]; only with the cargo feature `dds-security`, else
    /// `secure` is never `Some`).
    pub fn participant(
        &self,
        domain: u16,
        secure: Option<&std::path::Path>,
    ) -> CreateResult<DomainParticipant> {
        let b = DomainParticipantBuilder::new(domain);
        #[cfg(feature = "dds-security")]
        let b = match secure {
            // ROS keystores hold unencrypted keys: no pass phrase.
            Some(dir) => b.builtin_security(
                rustdds::DomainParticipantSecurityConfigFiles::with_ros_default_names(
                    dir,
                    String::new(),
                ),
            ),
            None => b,
        };
        #[cfg(not(feature = "dds-security"))]
        let _ = secure;
        let peers = self.peers.iter().map(|(_, a)| *a);
        match self.range {
            Range::Subnet | Range::SystemDefault => b.with_static_peers(peers),
            // This host and the static peers: no multicast, SPDP to the localhost ports and
            // the peers, the addresses of every interface advertised so the peers can answer.
            Range::Localhost if self.reaches_peers() => b
                .multicast_discovery(false)
                .same_host_loopback(true)
                .with_static_peers(peers),
            Range::Localhost => b
                .with_only_networks([IpAddr::V4(Ipv4Addr::LOCALHOST)])
                .same_host_loopback(true),
            Range::Off => b
                .with_only_networks(Vec::<IpAddr>::new())
                .same_host_loopback(false),
        }
        .build()
    }

    /// Whether SPDP also goes to static peers (there are some, and the range is not `OFF`).
    pub fn reaches_peers(&self) -> bool {
        !self.peers.is_empty() && self.range != Range::Off
    }

    /// For `LOCALHOST` without static peers and `OFF`, binds every UDP socket the process has
    /// to the loopback device; call it after the participant and every entity exist (RustDDS
    /// opens its sockets then). Returns how many sockets were newly confined; 0 for the other
    /// ranges, and for `LOCALHOST` with static peers (they must reach the node).
    pub fn confine(&self) -> Result<usize, DiscoveryError> {
        match self.range {
            Range::Subnet | Range::SystemDefault => Ok(0),
            Range::Localhost if self.reaches_peers() => Ok(0),
            Range::Localhost | Range::Off => {
                confine_udp_sockets_to_loopback().map_err(|e| DiscoveryError::Confine {
                    range: self.range.as_str(),
                    source: e,
                })
            }
        }
    }

    /// Logs the warnings and, for a range other than the default, one line saying what it does.
    pub fn log(&self, confined: usize) {
        for w in &self.warnings {
            warn!("{w}");
        }
        if self.reaches_peers() {
            let list: Vec<String> = self
                .peers
                .iter()
                .map(|(name, a)| match name.parse::<Ipv4Addr>() {
                    Ok(_) => a.to_string(),
                    Err(_) => format!("{a} ({name})"),
                })
                .collect();
            info!(
                "static peers: discovery announcements also sent to {}{}",
                list.join(", "),
                match self.range {
                    Range::Localhost => "; no multicast, sockets not confined to loopback",
                    _ => "",
                }
            );
        }
        match self.range {
            Range::Subnet | Range::SystemDefault => {}
            Range::Localhost if self.reaches_peers() => {}
            Range::Localhost => info!(
                "discovery range LOCALHOST: advertising 127.0.0.1 only, {confined} UDP sockets \
                 bound to the loopback device"
            ),
            Range::Off => info!(
                "discovery range OFF: no discovery; {confined} UDP sockets bound to the loopback \
                 device"
            ),
        }
    }
}

/// The loopback device's name.
const LOOPBACK: &[u8] = b"lo";

/// Binds every IPv4/IPv6 UDP socket of this process that is not yet bound to a device to the
/// loopback device. Returns how many it bound.
fn confine_udp_sockets_to_loopback() -> std::io::Result<usize> {
    let mut n = 0;
    for entry in std::fs::read_dir("/proc/self/fd")? {
        let Ok(entry) = entry else { continue };
        let Some(fd) = entry
            .file_name()
            .to_str()
            .and_then(|s| s.parse::<i32>().ok())
        else {
            continue;
        };
        let is_socket = std::fs::read_link(entry.path())
            .map(|l| l.to_string_lossy().starts_with("socket:"))
            .unwrap_or(false);
        if !is_socket || !is_inet_udp(fd) || bound_to_device(fd) {
            continue;
        }
        // SAFETY: setsockopt on a descriptor of this process with a valid buffer and length;
        // on a descriptor closed or reused meanwhile it fails or acts on a socket we checked.
        let rc = unsafe {
            libc::setsockopt(
                fd,
                libc::SOL_SOCKET,
                libc::SO_BINDTODEVICE,
                LOOPBACK.as_ptr().cast(),
                LOOPBACK.len() as libc::socklen_t,
            )
        };
        if rc != 0 {
            return Err(std::io::Error::last_os_error());
        }
        n += 1;
    }
    Ok(n)
}

/// Reads the socket option `name` of `level` into `buf`; how many bytes it wrote, or `None` if
/// the option cannot be read.
fn sockopt(fd: i32, level: i32, name: i32, buf: &mut [u8]) -> Option<usize> {
    let mut len = buf.len() as libc::socklen_t;
    // SAFETY: getsockopt with a buffer of the size it is told.
    let rc = unsafe { libc::getsockopt(fd, level, name, buf.as_mut_ptr().cast(), &mut len) };
    (rc == 0).then_some(len as usize)
}

/// Reads an integer socket option.
fn int_opt(fd: i32, level: i32, name: i32) -> Option<i32> {
    let mut buf = [0u8; std::mem::size_of::<libc::c_int>()];
    sockopt(fd, level, name, &mut buf)?;
    Some(libc::c_int::from_ne_bytes(buf))
}

/// Whether `fd` is an IPv4 or IPv6 datagram socket.
fn is_inet_udp(fd: i32) -> bool {
    int_opt(fd, libc::SOL_SOCKET, libc::SO_TYPE) == Some(libc::SOCK_DGRAM)
        && matches!(
            int_opt(fd, libc::SOL_SOCKET, libc::SO_DOMAIN),
            Some(libc::AF_INET) | Some(libc::AF_INET6)
        )
}

/// Whether `fd` is already bound to a device (an unprivileged process cannot rebind it).
fn bound_to_device(fd: i32) -> bool {
    let mut buf = [0u8; libc::IFNAMSIZ];
    sockopt(fd, libc::SOL_SOCKET, libc::SO_BINDTODEVICE, &mut buf).is_some_and(|len| len > 0)
        && buf[0] != 0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read_with(vars: &[(&str, &str)]) -> Result<Discovery, DiscoveryError> {
        read(|k| {
            vars.iter()
                .find(|(n, _)| *n == k)
                .map(|(_, v)| v.to_string())
        })
    }

    #[test]
    fn the_default_is_subnet_without_a_word() {
        for v in [
            vec![],
            vec![(RANGE_ENV, "")],
            vec![(LOCALHOST_ONLY_ENV, "0")],
        ] {
            let d = read_with(&v).unwrap();
            assert_eq!(d.range, Range::Subnet, "{v:?}");
            assert!(d.warnings.is_empty(), "{v:?}");
        }
    }

    #[test]
    fn a_dds_middleware_is_met_zenoh_is_refused_and_an_unknown_one_warned_about() {
        for rmw in DDS_RMWS {
            let d = read_with(&[(RMW_ENV, rmw)]).unwrap();
            assert!(d.warnings.is_empty(), "{rmw}: {:?}", d.warnings);
        }
        // Both builds, whichever this one is: with the `zenoh` feature Zenoh is taken,
        // without it refused.
        let in_build = |vars: &[(&str, &str)], zenoh_built: bool| {
            read_in_build(
                |k| {
                    vars.iter()
                        .find(|(n, _)| *n == k)
                        .map(|(_, v)| v.to_string())
                },
                |_| Ok(Vec::new()),
                zenoh_built,
            )
        };
        assert_eq!(
            read_with(&[(RMW_ENV, "rmw_zenoh_cpp")]).is_ok(),
            cfg!(feature = "zenoh")
        );
        for rmw in ["rmw_zenoh_cpp", "rmw_zenoh"] {
            let d = in_build(&[(RMW_ENV, rmw)], true).unwrap();
            assert!(d.zenoh && d.warnings.is_empty(), "{rmw}: {d:?}");
            // Their defaults are no news.
            let d = in_build(
                &[
                    (RMW_ENV, rmw),
                    (RANGE_ENV, "SUBNET"),
                    (PEERS_ENV, " ; "),
                    (LOCALHOST_ONLY_ENV, "0"),
                ],
                true,
            )
            .unwrap();
            assert!(d.warnings.is_empty(), "{rmw}: {:?}", d.warnings);
            // The DDS discovery variables are said to be ignored, each by name.
            let d = in_build(
                &[
                    (RMW_ENV, rmw),
                    (RANGE_ENV, "LOCALHOST"),
                    (PEERS_ENV, "10.0.0.2"),
                    (LOCALHOST_ONLY_ENV, "1"),
                ],
                true,
            )
            .unwrap();
            assert!(d.zenoh, "{rmw}");
            assert_eq!(d.warnings.len(), 3, "{:?}", d.warnings);
            for (w, v) in d
                .warnings
                .iter()
                .zip([RANGE_ENV, PEERS_ENV, LOCALHOST_ONLY_ENV])
            {
                assert!(w.starts_with(&format!("{v} is ignored on Zenoh")), "{w}");
            }
            let e = in_build(&[(RMW_ENV, rmw)], false).unwrap_err();
            assert!(
                matches!(&e, DiscoveryError::Middleware { value } if value == rmw),
                "{e:?}"
            );
            let text = e.to_string();
            assert!(
                text.starts_with(&format!(
                    "{RMW_ENV}={rmw}: this build of the node speaks DDS only"
                )) && text.contains("rmw_cyclonedds_cpp"),
                "{text}"
            );
        }
        let d = read_with(&[(RMW_ENV, "rmw_other\u{1b}[2J")]).unwrap();
        assert_eq!(d.warnings.len(), 1);
        assert!(
            d.warnings[0].contains("is not a middleware this node knows")
                && !d.warnings[0].contains('\u{1b}'),
            "{:?}",
            d.warnings
        );
    }

    #[test]
    fn each_range_as_spelled() {
        for (v, r) in [
            ("SUBNET", Range::Subnet),
            ("LOCALHOST", Range::Localhost),
            ("OFF", Range::Off),
            ("SYSTEM_DEFAULT", Range::SystemDefault),
        ] {
            let d = read_with(&[(RANGE_ENV, v)]).unwrap();
            assert_eq!(d.range, r);
            assert_eq!(r.as_str(), v);
        }
    }

    #[test]
    fn an_unknown_range_is_localhost_with_a_warning() {
        let d = read_with(&[(RANGE_ENV, "localhost\n[ERROR] x")]).unwrap();
        assert_eq!(d.range, Range::Localhost);
        assert_eq!(d.warnings.len(), 1);
        assert!(d.warnings[0].contains("assuming LOCALHOST"));
        assert!(!d.warnings[0].contains('\n'));
    }

    #[test]
    fn localhost_only_wins_and_is_deprecated() {
        let d = read_with(&[
            (LOCALHOST_ONLY_ENV, "1"),
            (RANGE_ENV, "SUBNET"),
            (PEERS_ENV, "10.0.0.1"),
        ])
        .unwrap();
        assert_eq!(d.range, Range::Localhost);
        assert!(d.warnings[0].contains("deprecated"));
        assert!(d.warnings[1].contains("ignored"));
    }

    /// A resolver that knows `robot.local` (IPv4 and IPv6) and `v6only.local`.
    fn resolve(host: &str) -> std::io::Result<Vec<IpAddr>> {
        match host {
            "robot.local" => Ok(vec![
                "10.0.0.7".parse().unwrap(),
                "fe80::1".parse().unwrap(),
                "10.0.0.8".parse().unwrap(),
            ]),
            "v6only.local" => Ok(vec!["fe80::2".parse().unwrap()]),
            "farm.local" => Ok((1..=40)
                .map(|i| IpAddr::V4(Ipv4Addr::new(10, 9, 0, i)))
                .collect()),
            _ => Err(std::io::Error::other("unknown host")),
        }
    }

    fn read_peers(vars: &[(&str, &str)]) -> Result<Discovery, DiscoveryError> {
        read_resolving(
            |k| {
                vars.iter()
                    .find(|(n, _)| *n == k)
                    .map(|(_, v)| v.to_string())
            },
            resolve,
        )
    }

    #[test]
    fn static_peers_are_addresses_and_resolved_names() {
        for r in ["", "SUBNET", "LOCALHOST", "SYSTEM_DEFAULT"] {
            let d = read_peers(&[
                (RANGE_ENV, r),
                (PEERS_ENV, " 192.168.0.1;robot.local;;10.0.0.7 "),
            ])
            .unwrap();
            let addrs: Vec<String> = d.peers.iter().map(|(_, a)| a.to_string()).collect();
            // In order, each address once, IPv4 only.
            assert_eq!(addrs, ["192.168.0.1", "10.0.0.7", "10.0.0.8"], "{r}");
            assert_eq!(d.peers[1].0, "robot.local");
            assert!(d.reaches_peers());
            assert!(d.warnings.is_empty(), "{:?}", d.warnings);
        }
        // Separators alone name no peer.
        let d = read_peers(&[(PEERS_ENV, " ; ;")]).unwrap();
        assert!(d.peers.is_empty() && !d.reaches_peers());
    }

    #[test]
    fn peers_without_an_ipv4_address_are_skipped_with_a_warning() {
        let d = read_peers(&[(
            PEERS_ENV,
            "nowhere.invalid;v6only.local;fe80::3;10.1.1.1;x\n[ERROR] y",
        )])
        .unwrap();
        assert_eq!(
            d.peers,
            [("10.1.1.1".to_string(), Ipv4Addr::new(10, 1, 1, 1))]
        );
        assert_eq!(d.warnings.len(), 4, "{:?}", d.warnings);
        assert!(d.warnings[0].contains("nowhere.invalid") && d.warnings[0].contains("resolved"));
        assert!(d.warnings[1].contains("IPv4"));
        assert!(d.warnings[2].contains("fe80::3"));
        // Not a host name: never given to the resolver, echoed escaped.
        assert!(
            d.warnings[3].contains("`x\\n[ERROR] y` skipped: not an address or a host name"),
            "{:?}",
            d.warnings
        );
        assert!(d.warnings.iter().all(|w| !w.contains('\n')));
        for name in ["a..b", ".a", "a b", "a/b", "", "a\0b"] {
            assert!(!is_host_name(name), "{name:?}");
        }
        assert!(is_host_name("robot-1.lab_net.local"));
        let long = "a".repeat(MAX_PEER_LEN + 1);
        let d = read_peers(&[(PEERS_ENV, &long)]).unwrap();
        assert!(d.peers.is_empty());
        assert!(d.warnings[0].contains("longer than"), "{:?}", d.warnings);
    }

    #[test]
    fn static_peers_are_bounded_and_ignored_when_discovery_is_off() {
        let many: Vec<String> = (0..=MAX_STATIC_PEERS)
            .map(|i| format!("10.0.1.{i}"))
            .collect();
        let e = read_peers(&[(PEERS_ENV, &many.join(";"))]).unwrap_err();
        assert!(
            e.to_string().contains(&format!("{}", MAX_STATIC_PEERS + 1)),
            "{e}"
        );
        let d = read_peers(&[(RANGE_ENV, "OFF"), (PEERS_ENV, "192.168.0.1")]).unwrap();
        assert_eq!(d.range, Range::Off);
        assert!(d.peers.is_empty() && !d.reaches_peers());
        assert!(d.warnings[0].contains("ignored"));
        // As many entries as allowed are all taken.
        let d = read_peers(&[(PEERS_ENV, &many[..MAX_STATIC_PEERS].join(";"))]).unwrap();
        assert_eq!(d.peers.len(), MAX_STATIC_PEERS);
        // A name with more addresses than fit: the first ones are taken, the rest warned about.
        let d = read_peers(&[(PEERS_ENV, "10.0.0.1;farm.local")]).unwrap();
        assert_eq!(d.peers.len(), MAX_STATIC_PEERS);
        assert_eq!(
            d.peers[1],
            ("farm.local".to_string(), Ipv4Addr::new(10, 9, 0, 1))
        );
        assert_eq!(d.warnings.len(), 1, "{:?}", d.warnings);
        assert!(d.warnings[0].contains("9 address(es) of peer `farm.local` skipped"));
    }

    #[test]
    fn hostile_peer_lists_are_warned_about_bounded_and_never_panic() {
        // Control characters, a NUL, a very long entry, a huge list of separators: with the
        // system's resolver (no name here reaches a DNS server: each is refused before).
        let long = format!("{}\n[ERROR] forged", "h".repeat(100_000));
        let list = format!("a\0b;{long};10.0.0.5;{}", ";".repeat(1_000_000));
        let d = read(|k| (k == PEERS_ENV).then(|| list.clone())).unwrap();
        assert_eq!(
            d.peers,
            [("10.0.0.5".to_string(), Ipv4Addr::new(10, 0, 0, 5))]
        );
        assert_eq!(d.warnings.len(), 2, "{:?}", d.warnings);
        for w in &d.warnings {
            assert!(!w.contains('\n') && !w.contains('\0'), "{w:?}");
            assert!(w.len() < 400, "{} bytes", w.len());
        }
    }

    #[test]
    fn localhost_with_static_peers_leaves_the_sockets_reachable() {
        let d = read_peers(&[(RANGE_ENV, "LOCALHOST"), (PEERS_ENV, "10.0.0.9")]).unwrap();
        assert_eq!(d.range, Range::Localhost);
        // Nothing is confined: the peers must reach the node's unicast sockets.
        let udp = std::net::UdpSocket::bind("0.0.0.0:0").unwrap();
        use std::os::fd::AsRawFd;
        assert_eq!(d.confine().unwrap(), 0);
        assert!(!bound_to_device(udp.as_raw_fd()));
    }

    /// Whether the running kernel is older than 5.7 (from /proc/sys/kernel/osrelease).
    fn kernel_before_5_7() -> bool {
        let release = std::fs::read_to_string("/proc/sys/kernel/osrelease").unwrap_or_default();
        let mut parts = release
            .trim()
            .split(['.', '-'])
            .map(|p| p.parse::<u32>().ok());
        match (parts.next().flatten(), parts.next().flatten()) {
            (Some(major), Some(minor)) => (major, minor) < (5, 7),
            _ => false,
        }
    }

    #[test]
    fn confining_binds_udp_sockets_to_lo_and_leaves_others() {
        let udp = std::net::UdpSocket::bind("0.0.0.0:0").unwrap();
        let tcp = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        use std::os::fd::AsRawFd;
        assert!(!bound_to_device(udp.as_raw_fd()));
        let d = Discovery {
            range: Range::Localhost,
            peers: vec![],
            zenoh: false,
            warnings: vec![],
        };
        match d.confine() {
            Ok(n) => {
                assert!(n >= 1);
                assert!(bound_to_device(udp.as_raw_fd()));
                assert!(!bound_to_device(tcp.as_raw_fd()));
            }
            // Kernels before 5.7 need CAP_NET_RAW for it: there, and only for that refusal,
            // the check cannot run. Any other error is a failure.
            Err(e) if kernel_before_5_7() && e.to_string().contains("Operation not permitted") => {
                eprintln!("skipped: SO_BINDTODEVICE needs CAP_NET_RAW before Linux 5.7: {e}")
            }
            Err(e) => panic!("confining the sockets failed: {e}"),
        }
    }
}
