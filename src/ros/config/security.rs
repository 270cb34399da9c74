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
//! Built with the cargo feature `dds-security`, the node secures its participant with RustDDS's
//! built-in plugins from the enclave's six files (rmw_dds_common's names, [`ENCLAVE_FILES`]);
//! when they cannot be found `Enforce` is refused (exit 2) and a permissive strategy starts
//! unsecured with a warning, as rcl does. Built without it (the default), the node can never
//! load those files: `Enforce` is always a refusal, whatever the keystore holds.
//! This module only reads variables and files' existence and decides; it must not touch the
//! network.

use crate::ros::config::logging::shown;
use log::{info, warn};
use std::path::{Path, PathBuf};

/// Whether this build can secure its participant (cargo feature `dds-security`).
pub const SUPPORTED: bool = cfg!(feature = "dds-security");

/// The files of an enclave, as rmw_dds_common names them; all are needed.
pub const ENCLAVE_FILES: [&str; 6] = [
    "identity_ca.cert.pem",
    "cert.pem",
    "key.pem",
    "permissions_ca.cert.pem",
    "governance.p7s",
    "permissions.p7s",
];

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

    /// The enclave's directory, as rcl finds the secure root: `<keystore>/enclaves/<enclave>`,
    /// the enclave `/` when none is given. `None` without a keystore.
    pub fn enclave_dir(&self) -> Option<PathBuf> {
        let keystore = self.keystore.as_ref()?;
        let enclave = self
            .enclave
            .as_deref()
            .unwrap_or("/")
            .trim_start_matches('/');
        let mut dir = Path::new(keystore).join("enclaves");
        if !enclave.is_empty() {
            dir.push(enclave);
        }
        Some(dir)
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
         ros2-client/RustDDS without DDS Security (cargo feature `dds-security`), so it can \
         neither authenticate itself nor refuse unauthenticated participants. Refusing to start \
         rather than run unsecured. To run \
         unsecured on purpose, unset {ENABLE_ENV} or set {STRATEGY_ENV}=Permissive, and isolate \
         the ROS domain (see docs/security.md)"
    )]
    EnforceUnsupported {
        /// What was asked, as [`SecurityRequest`] describes it.
        asked: String,
    },
    /// `Enforce` was asked for and the enclave's files cannot be found.
    #[error(
        "DDS security is enforced ({asked}) but the enclave cannot be loaded: {reason}. Refusing \
         to start rather than run unsecured"
    )]
    EnclaveUnusable {
        /// What was asked, as [`SecurityRequest`] describes it.
        asked: String,
        /// What is missing.
        reason: EnclaveMissing,
    },
}

/// Why the enclave cannot be loaded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EnclaveMissing {
    /// The keystore variable is not set.
    #[error("{KEYSTORE_ENV} is not set")]
    NoKeystore,
    /// The enclave's directory lacks these files.
    #[error("{} lacks {}", shown(&.dir.to_string_lossy()), .files.join(", "))]
    Files {
        /// The enclave's directory.
        dir: PathBuf,
        /// The files it lacks, by name.
        files: Vec<&'static str>,
    },
}

/// What to do at start-up.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SecurityDecision {
    /// Nothing was asked for: start, no message.
    Unsecured,
    /// Start unsecured, and log this warning once.
    Warn(String),
    /// Secure the participant with the enclave in this directory.
    Secure(PathBuf),
}

impl SecurityDecision {
    /// Logs the decision (a warning, or which enclave secures the participant) and returns
    /// the enclave's directory when the participant is to be secured.
    pub fn log(self) -> Option<PathBuf> {
        match self {
            SecurityDecision::Unsecured => None,
            SecurityDecision::Warn(w) => {
                warn!("{w}");
                None
            }
            SecurityDecision::Secure(dir) => {
                info!("DDS security on: enclave {}", shown(&dir.to_string_lossy()));
                Some(dir)
            }
        }
    }
}

/// Decides from `req` for this build ([`SUPPORTED`]), looking for the enclave's files.
pub fn decide(req: &SecurityRequest) -> Result<SecurityDecision, SecurityError> {
    decide_with(req, SUPPORTED, |p| p.is_file())
}

/// The enclave's directory for `req` when all its files are there; what is missing otherwise.
fn find_enclave(
    req: &SecurityRequest,
    exists: impl Fn(&Path) -> bool,
) -> Result<PathBuf, EnclaveMissing> {
    let Some(dir) = req.enclave_dir() else {
        return Err(EnclaveMissing::NoKeystore);
    };
    let missing: Vec<&'static str> = ENCLAVE_FILES
        .iter()
        .copied()
        .filter(|f| !exists(&dir.join(f)))
        .collect();
    if missing.is_empty() {
        Ok(dir)
    } else {
        Err(EnclaveMissing::Files {
            dir,
            files: missing,
        })
    }
}

/// As [`decide`], for a build that can (`supported`) or cannot secure its participant, with
/// `exists` telling whether a file exists. Without support, `Enforce` is refused; with it, the
/// enclave's files decide. A permissive strategy that cannot be honoured, and an enclave given
/// without security, each give one warning.
pub fn decide_with(
    req: &SecurityRequest,
    supported: bool,
    exists: impl Fn(&Path) -> bool,
) -> Result<SecurityDecision, SecurityError> {
    if req.enabled && supported {
        return match (find_enclave(req, exists), req.enforce) {
            (Ok(dir), _) => Ok(SecurityDecision::Secure(dir)),
            (Err(reason), true) => Err(SecurityError::EnclaveUnusable {
                asked: req.describe(),
                reason,
            }),
            (Err(reason), false) => Ok(SecurityDecision::Warn(format!(
                "DDS security is asked for under the permissive strategy ({}) but the enclave \
                 cannot be loaded ({reason}): running UNSECURED, as rcl does",
                req.describe()
            ))),
        };
    }
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
            "enclave `{}` given but {ENABLE_ENV} is not `true`: running unsecured",
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

    fn unsupported(r: &SecurityRequest) -> Result<SecurityDecision, SecurityError> {
        decide_with(r, false, |_| true)
    }

    #[test]
    fn with_support_the_enclave_files_decide() {
        let asked = |strategy: &str| {
            req(
                &[
                    (ENABLE_ENV, "true"),
                    (STRATEGY_ENV, strategy),
                    (KEYSTORE_ENV, "/ks"),
                ],
                Some("/pwm/a"),
            )
        };
        let r = asked("Enforce");
        assert_eq!(r.enclave_dir(), Some(PathBuf::from("/ks/enclaves/pwm/a")));
        assert_eq!(
            decide_with(&r, true, |_| true),
            Ok(SecurityDecision::Secure(PathBuf::from(
                "/ks/enclaves/pwm/a"
            )))
        );
        let missing_key = |p: &Path| !p.ends_with("key.pem");
        let e = decide_with(&r, true, missing_key).unwrap_err().to_string();
        assert!(e.contains("/ks/enclaves/pwm/a lacks key.pem"), "{e}");
        match decide_with(&asked("Permissive"), true, missing_key) {
            Ok(SecurityDecision::Warn(w)) => assert!(w.contains("UNSECURED"), "{w}"),
            other => panic!("{other:?}"),
        }
        // No keystore at all.
        let r = req(&[(ENABLE_ENV, "true"), (STRATEGY_ENV, "Enforce")], None);
        let e = decide_with(&r, true, |_| true).unwrap_err().to_string();
        assert!(e.contains("ROS_SECURITY_KEYSTORE is not set"), "{e}");
        // The enclave `/` is the keystore's `enclaves` directory itself.
        let r = req(&[(KEYSTORE_ENV, "/ks")], None);
        assert_eq!(r.enclave_dir(), Some(PathBuf::from("/ks/enclaves")));
    }

    #[test]
    fn nothing_asked_starts_silently() {
        assert_eq!(
            unsupported(&req(&[], None)),
            Ok(SecurityDecision::Unsecured)
        );
        assert_eq!(decide(&req(&[], None)), Ok(SecurityDecision::Unsecured));
        // rcl: only the exact string `true` enables security.
        for v in ["1", "TRUE", "True", "yes", ""] {
            let r = req(&[(ENABLE_ENV, v), (STRATEGY_ENV, "Enforce")], None);
            assert_eq!(unsupported(&r), Ok(SecurityDecision::Unsecured), "{v}");
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
        let e = unsupported(&r).unwrap_err();
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
        assert!(unsupported(&r).is_err());
        assert!(decide_with(&r, true, |_| true).is_err());
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
            match unsupported(&req(&v, None)) {
                Ok(SecurityDecision::Warn(w)) => assert!(w.contains("UNSECURED"), "{w}"),
                other => panic!("{strategy:?}: {other:?}"),
            }
        }
        match unsupported(&req(&[], Some("/pwm"))) {
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
        let m = unsupported(&r).unwrap_err().to_string();
        assert!(!m.contains('\n'), "{m}");
    }
}
