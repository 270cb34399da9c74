//! How far the node's DDS participant discovers and can be reached: `ROS_AUTOMATIC_DISCOVERY_RANGE`,
//! `ROS_STATIC_PEERS` and the deprecated `ROS_LOCALHOST_ONLY`, read with rcl's Jazzy rules and
//! applied to the RustDDS participant, or refused when RustDDS cannot do what they ask.
//!
//! rcl's rules (Jazzy, `rcl/src/rcl/discovery_options.c` and `init.c`):
//! - `ROS_AUTOMATIC_DISCOVERY_RANGE`: `SUBNET` (also when unset or empty), `LOCALHOST`, `OFF`,
//!   `SYSTEM_DEFAULT`; any other value is warned about and taken as `LOCALHOST`.
//! - `ROS_STATIC_PEERS`: addresses separated by `;`, empty items skipped.
//! - `ROS_LOCALHOST_ONLY=1` is deprecated but honoured: the range becomes `LOCALHOST` and the
//!   two variables above are ignored, each with a warning.
//!
//! What RustDDS 0.15 allows and what this module does with it:
//! - `SUBNET`, `SYSTEM_DEFAULT`: RustDDS's defaults (multicast on every interface).
//! - `LOCALHOST`: only 127.0.0.1 is advertised and used for multicast, SPDP goes to the
//!   well-known localhost ports (RustDDS's `same_host_loopback`), and, because RustDDS binds
//!   its unicast sockets to the wildcard address, every UDP socket of the process is then
//!   bound to the loopback device (`SO_BINDTODEVICE lo`): the kernel delivers it nothing that
//!   arrived on another interface, and it sends nothing out of one.
//! - `OFF`: nothing is advertised, no multicast, no localhost announcements, and the sockets
//!   are confined to loopback as for `LOCALHOST`. The node then discovers no one.
//! - `ROS_STATIC_PEERS`: RustDDS has no initial-peer list, so a non-empty list is refused
//!   (under `OFF`, where rcl does not use static peers either, it is ignored with a warning).
//!
//! This module reads variables, builds the participant and sets socket options; it must not
//! send or receive anything itself.

use log::{info, warn};
use rustdds::dds::CreateResult;
use rustdds::{DomainParticipant, DomainParticipantBuilder};
use std::net::{IpAddr, Ipv4Addr};

use crate::ros::config::logging::shown;

/// `ROS_AUTOMATIC_DISCOVERY_RANGE`.
pub const RANGE_ENV: &str = "ROS_AUTOMATIC_DISCOVERY_RANGE";
/// `ROS_STATIC_PEERS`.
pub const PEERS_ENV: &str = "ROS_STATIC_PEERS";
/// `ROS_LOCALHOST_ONLY` (deprecated in Jazzy).
pub const LOCALHOST_ONLY_ENV: &str = "ROS_LOCALHOST_ONLY";

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
    /// Warnings to log once at start-up (deprecated or ignored variables).
    pub warnings: Vec<String>,
}

/// What cannot be honoured.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DiscoveryError {
    /// `ROS_STATIC_PEERS` names peers, and RustDDS cannot add initial peers.
    #[error(
        "{PEERS_ENV} asks for static peers ({peers}) but this node cannot honour it: RustDDS 0.15 \
         has no list of initial peers, so those peers would never be contacted. Unset \
         {PEERS_ENV}, or reach those machines by multicast ({RANGE_ENV}=SUBNET)"
    )]
    StaticPeers {
        /// The peers, escaped and bounded.
        peers: String,
    },
    /// The sockets could not be confined to the loopback device.
    #[error(
        "{RANGE_ENV}={range} cannot be honoured: binding the DDS sockets to the loopback device \
         failed ({reason}); refusing to stay reachable from other machines"
    )]
    Confine {
        /// The range asked for.
        range: &'static str,
        /// The OS error.
        reason: String,
    },
}

/// Reads the discovery settings from variables looked up with `var`, with rcl's Jazzy rules.
pub fn read(var: impl Fn(&str) -> Option<String>) -> Result<Discovery, DiscoveryError> {
    let mut warnings = Vec::new();
    let range_var = var(RANGE_ENV).filter(|v| !v.is_empty());
    let peers: Vec<String> = var(PEERS_ENV)
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
        if range_var.is_some() || !peers.is_empty() {
            warnings.push(format!(
                "{LOCALHOST_ONLY_ENV}=1: {RANGE_ENV} and {PEERS_ENV} are ignored"
            ));
        }
        return Ok(Discovery {
            range: Range::Localhost,
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
    if !peers.is_empty() {
        if range == Range::Off {
            warnings.push(format!(
                "{RANGE_ENV}=OFF: {PEERS_ENV} is ignored (no discovery at all)"
            ));
        } else {
            return Err(DiscoveryError::StaticPeers {
                peers: shown(&peers.join(";")),
            });
        }
    }
    Ok(Discovery { range, warnings })
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
        match self.range {
            Range::Subnet | Range::SystemDefault => b,
            Range::Localhost => b
                .with_only_networks([IpAddr::V4(Ipv4Addr::LOCALHOST)])
                .same_host_loopback(true),
            Range::Off => b
                .with_only_networks(Vec::<IpAddr>::new())
                .same_host_loopback(false),
        }
        .build()
    }

    /// For `LOCALHOST` and `OFF`, binds every UDP socket the process has to the loopback
    /// device; call it after the participant and every entity exist (RustDDS opens its
    /// sockets then). Returns how many sockets were newly confined; 0 for the other ranges.
    pub fn confine(&self) -> Result<usize, DiscoveryError> {
        match self.range {
            Range::Subnet | Range::SystemDefault => Ok(0),
            Range::Localhost | Range::Off => {
                confine_udp_sockets_to_loopback().map_err(|e| DiscoveryError::Confine {
                    range: self.range.as_str(),
                    reason: e.to_string(),
                })
            }
        }
    }

    /// Logs the warnings and, for a range other than the default, one line saying what it does.
    pub fn log(&self, confined: usize) {
        for w in &self.warnings {
            warn!("{w}");
        }
        match self.range {
            Range::Subnet | Range::SystemDefault => {}
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

    #[test]
    fn static_peers_are_refused_unless_discovery_is_off() {
        for r in ["", "SUBNET", "LOCALHOST", "SYSTEM_DEFAULT"] {
            let e =
                read_with(&[(RANGE_ENV, r), (PEERS_ENV, "192.168.0.1;remote.com")]).unwrap_err();
            assert!(e.to_string().contains("192.168.0.1;remote.com"), "{e}");
        }
        // Separators alone name no peer.
        assert!(read_with(&[(PEERS_ENV, " ; ;")]).is_ok());
        let d = read_with(&[(RANGE_ENV, "OFF"), (PEERS_ENV, "192.168.0.1")]).unwrap();
        assert_eq!(d.range, Range::Off);
        assert!(d.warnings[0].contains("ignored"));
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
