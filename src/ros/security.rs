//! The ROS 2 security environment (SROS2) read as rcl reads it, and what this node does with
//! it: it cannot secure its DDS participant, so it refuses to start when security is enforced
//! and says once that it runs unsecured when it is only permitted.
//!
//! rcl's rules (`rcl/src/rcl/security.c`): security is on only when `ROS_SECURITY_ENABLE` is
//! exactly `true`; the strategy is `Enforce` only when `ROS_SECURITY_STRATEGY` is exactly
//! `Enforce`, anything else is permissive. Under `Enforce` rcl refuses to start when it cannot
//! find or load the enclave's security files; under permissive it then starts unsecured. The
//! enclave is `--enclave` (`-e`) of `--ros-args`, overridden by `ROS_SECURITY_ENCLAVE_OVERRIDE`,
//! and is looked up under `ROS_SECURITY_KEYSTORE/enclaves`.
//!
//! This node is built on ros2-client and RustDDS without their `security` feature, so it can
//! never load those files: `Enforce` is always a refusal here, whatever the keystore holds.
//! This module only reads variables and decides; it must not touch the network.

use crate::ros::logging::shown;

/// `ROS_SECURITY_ENABLE`: `true` (exactly) turns security on.
pub const ENABLE_ENV: &str = "ROS_SECURITY_ENABLE";
/// `ROS_SECURITY_STRATEGY`: `Enforce` (exactly) or anything else (permissive).
pub const STRATEGY_ENV: &str = "ROS_SECURITY_STRATEGY";
/// `ROS_SECURITY_KEYSTORE`: the keystore directory.
pub const KEYSTORE_ENV: &str = "ROS_SECURITY_KEYSTORE";
/// `ROS_SECURITY_ENCLAVE_OVERRIDE`: an enclave that replaces `--enclave`.
pub const ENCLAVE_OVERRIDE_ENV: &str = "ROS_SECURITY_ENCLAVE_OVERRIDE";

/// What the environment and the command line ask for, as rcl reads them.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct SecurityRequest {
    /// `ROS_SECURITY_ENABLE` is exactly `true`.
    pub enabled: bool,
    /// `ROS_SECURITY_STRATEGY` is exactly `Enforce`.
    pub enforce: bool,
    /// `ROS_SECURITY_KEYSTORE`, if set and not empty.
    pub keystore: Option<String>,
    /// The enclave: `ROS_SECURITY_ENCLAVE_OVERRIDE` if set and not empty, else `--enclave`.
    pub enclave: Option<String>,
}

impl SecurityRequest {
    /// Reads the request from variables looked up with `var` and the `--enclave` argument.
    pub fn read(var: impl Fn(&str) -> Option<String>, enclave_arg: Option<&str>) -> Self {
        let non_empty = |k: &str| var(k).filter(|v| !v.is_empty());
        SecurityRequest {
            enabled: var(ENABLE_ENV).as_deref() == Some("true"),
            enforce: var(STRATEGY_ENV).as_deref() == Some("Enforce"),
            keystore: non_empty(KEYSTORE_ENV),
            enclave: non_empty(ENCLAVE_OVERRIDE_ENV)
                .or_else(|| enclave_arg.filter(|e| !e.is_empty()).map(str::to_string)),
        }
    }

    /// What was asked, for a message: `ROS_SECURITY_ENABLE=true, ROS_SECURITY_STRATEGY=Enforce,
    /// keystore `/k`, enclave `/e``.
    fn describe(&self) -> String {
        let quoted = |v: &Option<String>| match v {
            Some(v) => format!("`{}`", shown(v)),
            None => "(none)".to_string(),
        };
        format!(
            "{ENABLE_ENV}=true, {STRATEGY_ENV}={}, keystore {}, enclave {}",
            if self.enforce {
                "Enforce"
            } else {
                "Permissive"
            },
            quoted(&self.keystore),
            quoted(&self.enclave)
        )
    }
}

/// Why the node cannot start with the security it was asked for.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SecurityError {
    /// `Enforce` was asked for; this node cannot secure its participant.
    #[error(
        "DDS security is enforced ({asked}) but this node cannot provide it: it is built on \
         ros2-client/RustDDS without DDS Security, so it can neither authenticate itself nor \
         refuse unauthenticated participants. Refusing to start rather than run unsecured. To run \
         unsecured on purpose, unset {ENABLE_ENV} or set {STRATEGY_ENV}=Permissive, and isolate \
         the ROS domain (see the README, \"Security and trust\")"
    )]
    EnforceUnsupported {
        /// What was asked, as [`SecurityRequest`] describes it.
        asked: String,
    },
}

/// What to do at start-up.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SecurityDecision {
    /// Nothing was asked for: start, no message.
    Unsecured,
    /// Start unsecured, and log this warning once.
    Warn(String),
}

/// Decides from `req`: `Enforce` with security enabled is refused; permissive security and an
/// enclave given without security each give one warning.
pub fn decide(req: &SecurityRequest) -> Result<SecurityDecision, SecurityError> {
    if req.enabled && req.enforce {
        return Err(SecurityError::EnforceUnsupported {
            asked: req.describe(),
        });
    }
    if req.enabled {
        return Ok(SecurityDecision::Warn(format!(
            "DDS security is asked for under the permissive strategy ({}) but this node cannot \
             provide it (ros2-client/RustDDS without DDS Security): running UNSECURED, as rcl \
             does when permissive security cannot be loaded",
            req.describe()
        )));
    }
    if let Some(e) = &req.enclave {
        return Ok(SecurityDecision::Warn(format!(
            "enclave `{}` given but {ENABLE_ENV} is not `true`: running unsecured (this node \
             cannot provide DDS security in any case)",
            shown(e)
        )));
    }
    Ok(SecurityDecision::Unsecured)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn req(vars: &[(&str, &str)], enclave: Option<&str>) -> SecurityRequest {
        let vars: Vec<(String, String)> = vars
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        SecurityRequest::read(
            |k| vars.iter().find(|(n, _)| n == k).map(|(_, v)| v.clone()),
            enclave,
        )
    }

    #[test]
    fn nothing_asked_starts_silently() {
        assert_eq!(decide(&req(&[], None)), Ok(SecurityDecision::Unsecured));
        // rcl: only the exact string `true` enables security.
        for v in ["1", "TRUE", "True", "yes", ""] {
            let r = req(&[(ENABLE_ENV, v), (STRATEGY_ENV, "Enforce")], None);
            assert_eq!(decide(&r), Ok(SecurityDecision::Unsecured), "{v}");
        }
    }

    #[test]
    fn enforce_is_refused_with_what_was_asked() {
        let r = req(
            &[
                (ENABLE_ENV, "true"),
                (STRATEGY_ENV, "Enforce"),
                (KEYSTORE_ENV, "/no/such/keystore"),
            ],
            Some("/pwm"),
        );
        let e = decide(&r).unwrap_err();
        let m = e.to_string();
        for s in [
            "ROS_SECURITY_STRATEGY=Enforce",
            "`/no/such/keystore`",
            "enclave `/pwm`",
            "Refusing to start",
        ] {
            assert!(m.contains(s), "{s} missing from {m}");
        }
        // Without a keystore, too: rcl refuses as well (no security files).
        let r = req(&[(ENABLE_ENV, "true"), (STRATEGY_ENV, "Enforce")], None);
        assert!(decide(&r).is_err());
    }

    #[test]
    fn the_override_replaces_the_enclave_argument() {
        let r = req(&[(ENCLAVE_OVERRIDE_ENV, "/other")], Some("/pwm"));
        assert_eq!(r.enclave.as_deref(), Some("/other"));
        let r = req(&[(ENCLAVE_OVERRIDE_ENV, "")], Some("/pwm"));
        assert_eq!(r.enclave.as_deref(), Some("/pwm"));
    }

    #[test]
    fn permissive_and_a_bare_enclave_warn() {
        for strategy in [None, Some("Permissive"), Some("enforce")] {
            let mut v = vec![(ENABLE_ENV, "true")];
            if let Some(s) = strategy {
                v.push((STRATEGY_ENV, s));
            }
            match decide(&req(&v, None)) {
                Ok(SecurityDecision::Warn(w)) => assert!(w.contains("UNSECURED"), "{w}"),
                other => panic!("{strategy:?}: {other:?}"),
            }
        }
        match decide(&req(&[], Some("/pwm"))) {
            Ok(SecurityDecision::Warn(w)) => assert!(w.contains("enclave `/pwm`"), "{w}"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn echoed_values_are_escaped() {
        let r = req(
            &[
                (ENABLE_ENV, "true"),
                (STRATEGY_ENV, "Enforce"),
                (KEYSTORE_ENV, "/k\n[INFO] forged"),
            ],
            None,
        );
        let m = decide(&r).unwrap_err().to_string();
        assert!(!m.contains('\n'), "{m}");
    }
}
