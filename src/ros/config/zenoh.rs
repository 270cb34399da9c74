//! The Zenoh session's settings, read from the environment with rmw_zenoh_cpp's rules
//! (`rmw_zenoh_cpp/src/detail/zenoh_config.cpp` and `rmw_context_impl_s.cpp`, Kilted):
//!
//! - `ZENOH_SESSION_CONFIG_URI`: set and not empty, the JSON5 file it names is the session's
//!   configuration; a file that cannot be read (or is larger than [`MAX_CONFIG_FILE_BYTES`])
//!   stops the start, as rmw_zenoh's initialisation fails. Unset or empty: rmw_zenoh's default
//!   session configuration ([`DEFAULT_SESSION_CONFIG`]).
//! - `ZENOH_CONFIG_OVERRIDE`: `key=value` pairs separated by `;`, each split at its first `=`,
//!   the value inserted as JSON5 at the key's path after the file is read (zenoh's
//!   `insert_json5`, e.g. `connect/endpoints=["tcp/192.168.1.2:7447"]`). A pair the
//!   configuration refuses is warned about and ignored, as rmw_zenoh does. A pair without `=` or
//!   with nothing after it, which rmw_zenoh skips without a word, is skipped with a warning. More
//!   than [`MAX_OVERRIDES`] pairs, or a variable longer than [`MAX_OVERRIDE_BYTES`], is refused.
//! - `ZENOH_ROUTER_CHECK_ATTEMPTS`: how often the node looks for a Zenoh router, one second
//!   apart, before it goes on without one ([`RouterCheck`]): unset or empty, once; `N` > 0, N
//!   times; `0`, until one is seen; below 0, never. After the last attempt without a router the
//!   node warns and starts (rmw_zenoh since 2025 does the same; earlier ones failed to start).
//!   A value that is not a whole number, which rmw_zenoh's `strtoll` reads as 0 (wait forever),
//!   is warned about and taken as 1.
//!
//! Every value echoed in a warning or an error is escaped and cut ([`shown`]). This module reads
//! variables and files only; the session is opened elsewhere.

use std::path::PathBuf;

use crate::ros::config::args::read_at_most;
use crate::ros::config::logging::shown;

/// `ZENOH_SESSION_CONFIG_URI`.
pub const SESSION_CONFIG_URI_ENV: &str = "ZENOH_SESSION_CONFIG_URI";
/// `ZENOH_CONFIG_OVERRIDE`.
pub const CONFIG_OVERRIDE_ENV: &str = "ZENOH_CONFIG_OVERRIDE";
/// `ZENOH_ROUTER_CHECK_ATTEMPTS`.
pub const ROUTER_CHECK_ATTEMPTS_ENV: &str = "ZENOH_ROUTER_CHECK_ATTEMPTS";
/// Largest session configuration file read, bytes (rmw_zenoh's own default file is 43 kB).
pub const MAX_CONFIG_FILE_BYTES: u64 = 1024 * 1024;
/// Longest `ZENOH_CONFIG_OVERRIDE` taken, bytes.
pub const MAX_OVERRIDE_BYTES: usize = 64 * 1024;
/// Most `key=value` pairs of `ZENOH_CONFIG_OVERRIDE` taken.
pub const MAX_OVERRIDES: usize = 64;

/// rmw_zenoh's default session configuration: the entries its packaged
/// `DEFAULT_RMW_ZENOH_SESSION_CONFIG.json5` (rmw_zenoh_cpp/config/, Kilted) marks as "ROS
/// setting", each with the value it gives; every other entry is zenoh's own default, as in that
/// file. A peer that connects to the router on `tcp/localhost:7447`, listens on loopback only,
/// finds other nodes through the router's gossip instead of multicast, and timestamps its data
/// (the publication caches of transient-local topics need it).
pub const DEFAULT_SESSION_CONFIG: &str = r#"{
  mode: "peer",
  connect: {
    timeout_ms: { router: -1, peer: -1, client: 0 },
    endpoints: ["tcp/localhost:7447"],
    exit_on_failure: { router: false, peer: false, client: true },
  },
  listen: {
    timeout_ms: 0,
    endpoints: ["tcp/localhost:0"],
    exit_on_failure: true,
  },
  open: { return_conditions: { connect_scouted: true, declares: true } },
  scouting: {
    timeout: 3000,
    delay: 500,
    multicast: {
      enabled: false,
      autoconnect_strategy: { peer: { to_router: "always", to_peer: "greater-zid" } },
    },
    gossip: {
      enabled: true,
      multihop: false,
      target: { router: ["router", "peer"], peer: ["router"] },
      autoconnect: { router: [], peer: ["router", "peer"] },
      autoconnect_strategy: { peer: { to_router: "always", to_peer: "greater-zid" } },
    },
  },
  timestamping: { enabled: { router: true, peer: true, client: true }, drop_future_timestamp: false },
  queries_default_timeout: 600000,
  transport: {
    unicast: { open_timeout: 60000, accept_timeout: 60000, accept_pending: 10000, max_sessions: 10000 },
    link: {
      tx: { lease: 60000, keep_alive: 2, queue: { congestion_control: { block: { wait_before_close: 60000000 } } } },
    },
    shared_memory: { enabled: false },
  },
}"#;

/// How often the node looks for a Zenoh router before it goes on without one
/// (`ZENOH_ROUTER_CHECK_ATTEMPTS`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RouterCheck {
    /// Not at all (a value below 0).
    Skip,
    /// This many times, one second apart (at least 1).
    Attempts(u64),
    /// Until a router is seen (`0`).
    Forever,
}

/// The session's settings from the environment.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ZenohSettings {
    /// The configuration file of `ZENOH_SESSION_CONFIG_URI`; `None`: [`DEFAULT_SESSION_CONFIG`].
    pub config_file: Option<PathBuf>,
    /// The pairs of `ZENOH_CONFIG_OVERRIDE`, in order: (key path, JSON5 value).
    pub overrides: Vec<(String, String)>,
    /// The router check.
    pub router_check: RouterCheck,
    /// Warnings to log once at start-up.
    pub warnings: Vec<String>,
}

/// What the environment asks that the node will not do.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ZenohConfigError {
    /// `ZENOH_CONFIG_OVERRIDE` is longer than [`MAX_OVERRIDE_BYTES`].
    #[error(
        "{CONFIG_OVERRIDE_ENV} is {len} bytes long; the node takes at most {MAX_OVERRIDE_BYTES}. \
         Put the settings in a configuration file ({SESSION_CONFIG_URI_ENV}) instead"
    )]
    OverrideTooLong {
        /// Its length, bytes.
        len: usize,
    },
    /// `ZENOH_CONFIG_OVERRIDE` has more than [`MAX_OVERRIDES`] pairs.
    #[error(
        "{CONFIG_OVERRIDE_ENV} has {count} key=value pairs; the node takes at most \
         {MAX_OVERRIDES}. Put the settings in a configuration file ({SESSION_CONFIG_URI_ENV}) \
         instead"
    )]
    TooManyOverrides {
        /// How many it has.
        count: usize,
    },
    /// The configuration file cannot be read.
    #[error(
        "{SESSION_CONFIG_URI_ENV}={path}: cannot read the Zenoh session configuration: {reason}"
    )]
    ConfigFile {
        /// The path (escaped).
        path: String,
        /// Why.
        reason: String,
    },
}

/// Reads the session's settings from variables looked up with `var`.
pub fn read(var: impl Fn(&str) -> Option<String>) -> Result<ZenohSettings, ZenohConfigError> {
    let mut warnings = Vec::new();
    let config_file = var(SESSION_CONFIG_URI_ENV)
        .filter(|v| !v.is_empty())
        .map(PathBuf::from);
    let overrides = match var(CONFIG_OVERRIDE_ENV) {
        Some(text) => overrides(&text, &mut warnings)?,
        None => Vec::new(),
    };
    let router_check = router_check(var(ROUTER_CHECK_ATTEMPTS_ENV).as_deref(), &mut warnings);
    Ok(ZenohSettings {
        config_file,
        overrides,
        router_check,
        warnings,
    })
}

/// The pairs of `ZENOH_CONFIG_OVERRIDE`: split on `;`, then at the first `=`; empty items
/// skipped, a pair without a key or a value skipped with a warning.
fn overrides(
    text: &str,
    warnings: &mut Vec<String>,
) -> Result<Vec<(String, String)>, ZenohConfigError> {
    if text.len() > MAX_OVERRIDE_BYTES {
        return Err(ZenohConfigError::OverrideTooLong { len: text.len() });
    }
    let items: Vec<&str> = text.split(';').filter(|p| !p.trim().is_empty()).collect();
    if items.len() > MAX_OVERRIDES {
        return Err(ZenohConfigError::TooManyOverrides { count: items.len() });
    }
    let mut pairs = Vec::with_capacity(items.len());
    for item in items {
        match item.split_once('=') {
            Some((key, value)) if !key.trim().is_empty() && !value.trim().is_empty() => {
                pairs.push((key.trim().to_string(), value.trim().to_string()));
            }
            _ => warnings.push(format!(
                "{CONFIG_OVERRIDE_ENV}: `{}` is not a key=value pair; ignored",
                shown(item)
            )),
        }
    }
    Ok(pairs)
}

/// `ZENOH_ROUTER_CHECK_ATTEMPTS` with rmw_zenoh's rules; a value that is not a whole number is
/// warned about and taken as 1.
fn router_check(value: Option<&str>, warnings: &mut Vec<String>) -> RouterCheck {
    let Some(value) = value.map(str::trim).filter(|v| !v.is_empty()) else {
        return RouterCheck::Attempts(1);
    };
    match value.parse::<i64>() {
        Ok(n) if n > 0 => RouterCheck::Attempts(n as u64),
        Ok(0) => RouterCheck::Forever,
        Ok(_) => RouterCheck::Skip,
        Err(_) => {
            warnings.push(format!(
                "{ROUTER_CHECK_ATTEMPTS_ENV}=`{}` is not a whole number; the node looks for a \
                 Zenoh router once (a number > 0: that many times; 0: until one is seen; below \
                 0: never)",
                shown(value)
            ));
            RouterCheck::Attempts(1)
        }
    }
}

/// The session configuration's JSON5 text: the file of `settings` (at most
/// [`MAX_CONFIG_FILE_BYTES`]), or [`DEFAULT_SESSION_CONFIG`].
pub fn config_text(settings: &ZenohSettings) -> Result<String, ZenohConfigError> {
    let Some(path) = &settings.config_file else {
        return Ok(DEFAULT_SESSION_CONFIG.to_string());
    };
    let error = |reason: String| ZenohConfigError::ConfigFile {
        path: shown(&path.to_string_lossy()),
        reason,
    };
    let bytes = read_at_most(path, MAX_CONFIG_FILE_BYTES)
        .map_err(|e| error(e.to_string()))?
        .ok_or_else(|| error(format!("larger than {MAX_CONFIG_FILE_BYTES} bytes")))?;
    String::from_utf8(bytes).map_err(|_| error("not UTF-8 text".to_string()))
}

/// What the router check ends with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RouterCheckOutcome {
    /// Not checked ([`RouterCheck::Skip`]).
    Skipped,
    /// A router was seen at this attempt (from 1).
    Seen(u64),
    /// None was seen in this many attempts; the node goes on without one.
    NotSeen(u64),
}

/// The wait between two attempts of the router check.
pub const ROUTER_CHECK_PERIOD: std::time::Duration = std::time::Duration::from_secs(1);

/// Runs the router check: asks `has_router` up to as often as `check` says, `sleep`ing
/// [`ROUTER_CHECK_PERIOD`] after each attempt that saw none, and `warn`s at each such attempt
/// (rmw_zenoh's words) and once more after the last.
pub fn check_router(
    check: RouterCheck,
    mut has_router: impl FnMut() -> bool,
    mut sleep: impl FnMut(std::time::Duration),
    mut warn: impl FnMut(String),
) -> RouterCheckOutcome {
    let limit = match check {
        RouterCheck::Skip => return RouterCheckOutcome::Skipped,
        RouterCheck::Attempts(n) => n.max(1),
        RouterCheck::Forever => u64::MAX,
    };
    let mut attempt = 0u64;
    while attempt < limit {
        attempt += 1;
        if has_router() {
            return RouterCheckOutcome::Seen(attempt);
        }
        warn(format!(
            "Unable to connect to a Zenoh router (attempt {attempt}). Have you started a router \
             with `ros2 run rmw_zenoh_cpp rmw_zenohd`?"
        ));
        if attempt < limit {
            sleep(ROUTER_CHECK_PERIOD);
        }
    }
    warn(format!(
        "Unable to connect to a Zenoh router after {attempt} attempt(s); going on without one: \
         the node reaches only the Zenoh peers it connects to itself \
         ({ROUTER_CHECK_ATTEMPTS_ENV} sets how often it looks)"
    ));
    RouterCheckOutcome::NotSeen(attempt)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn env(pairs: &[(&str, &str)]) -> impl Fn(&str) -> Option<String> {
        let map: HashMap<String, String> = pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        move |k| map.get(k).cloned()
    }

    #[test]
    fn nothing_set_is_the_default_config_one_router_check_and_no_override() {
        let s = read(env(&[])).unwrap();
        assert_eq!(s.config_file, None);
        assert!(s.overrides.is_empty());
        assert_eq!(s.router_check, RouterCheck::Attempts(1));
        assert!(s.warnings.is_empty());
        assert_eq!(config_text(&s).unwrap(), DEFAULT_SESSION_CONFIG);
        // An empty URI is rmw_zenoh's default too.
        let s = read(env(&[(SESSION_CONFIG_URI_ENV, "")])).unwrap();
        assert_eq!(s.config_file, None);
    }

    #[test]
    fn router_check_attempts_follow_rmw_zenoh_and_a_non_number_is_warned_about() {
        let check = |v: &str| {
            let s = read(env(&[(ROUTER_CHECK_ATTEMPTS_ENV, v)])).unwrap();
            (s.router_check, s.warnings.len())
        };
        assert_eq!(check(""), (RouterCheck::Attempts(1), 0));
        assert_eq!(check("3"), (RouterCheck::Attempts(3), 0));
        assert_eq!(check(" 2 "), (RouterCheck::Attempts(2), 0));
        assert_eq!(check("0"), (RouterCheck::Forever, 0));
        assert_eq!(check("-1"), (RouterCheck::Skip, 0));
        assert_eq!(check("-99999"), (RouterCheck::Skip, 0));
        // strtoll reads these as 0 (forever): taken as once, with a warning.
        assert_eq!(check("abc"), (RouterCheck::Attempts(1), 1));
        assert_eq!(check("3x"), (RouterCheck::Attempts(1), 1));
        assert_eq!(
            check("99999999999999999999999"),
            (RouterCheck::Attempts(1), 1)
        );
        let s = read(env(&[(ROUTER_CHECK_ATTEMPTS_ENV, "a\x1b[2Jb")])).unwrap();
        assert!(!s.warnings[0].contains('\x1b'), "{}", s.warnings[0]);
    }

    #[test]
    fn overrides_split_on_semicolons_then_at_the_first_equals_sign() {
        let s = read(env(&[(
            CONFIG_OVERRIDE_ENV,
            r#"connect/endpoints=["tcp/127.0.0.1:7447"];;mode="client" ; a/b={x: "=;"}"#,
        )]))
        .unwrap();
        // `;` inside a value splits it, as in rmw_zenoh (its getline does the same).
        assert_eq!(
            s.overrides,
            vec![
                (
                    "connect/endpoints".into(),
                    r#"["tcp/127.0.0.1:7447"]"#.into()
                ),
                ("mode".into(), r#""client""#.into()),
                ("a/b".into(), r#"{x: "="#.into()),
            ]
        );
        assert_eq!(s.warnings.len(), 1, "{:?}", s.warnings);
        assert!(s.warnings[0].contains("`\"}`"), "{:?}", s.warnings);
    }

    #[test]
    fn an_override_without_key_or_value_is_skipped_with_a_warning() {
        let s = read(env(&[(CONFIG_OVERRIDE_ENV, "mode;=1;mode=;x=2")])).unwrap();
        assert_eq!(s.overrides, vec![("x".into(), "2".into())]);
        assert_eq!(s.warnings.len(), 3, "{:?}", s.warnings);
        for w in &s.warnings {
            assert!(w.contains("is not a key=value pair"), "{w}");
        }
    }

    #[test]
    fn overrides_beyond_their_bounds_are_refused() {
        let long = format!("a={}", "x".repeat(MAX_OVERRIDE_BYTES));
        assert_eq!(
            read(env(&[(CONFIG_OVERRIDE_ENV, &long)])).unwrap_err(),
            ZenohConfigError::OverrideTooLong { len: long.len() }
        );
        let many = vec!["a=1"; MAX_OVERRIDES + 1].join(";");
        assert_eq!(
            read(env(&[(CONFIG_OVERRIDE_ENV, &many)])).unwrap_err(),
            ZenohConfigError::TooManyOverrides {
                count: MAX_OVERRIDES + 1
            }
        );
        let most = vec!["a=1"; MAX_OVERRIDES].join(";");
        assert_eq!(
            read(env(&[(CONFIG_OVERRIDE_ENV, &most)]))
                .unwrap()
                .overrides
                .len(),
            MAX_OVERRIDES
        );
    }

    #[test]
    fn a_config_file_is_read_within_its_bound_or_the_start_stops() {
        let dir = std::env::temp_dir().join(format!("pwm-zenoh-cfg-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let good = dir.join("good.json5");
        std::fs::write(&good, "{ mode: \"client\" }").unwrap();
        let big = dir.join("big.json5");
        std::fs::write(&big, vec![b' '; MAX_CONFIG_FILE_BYTES as usize + 1]).unwrap();
        let text = |p: &std::path::Path| {
            let s = read(env(&[(SESSION_CONFIG_URI_ENV, p.to_str().unwrap())])).unwrap();
            config_text(&s)
        };
        assert_eq!(text(&good).unwrap(), "{ mode: \"client\" }");
        let e = text(&big).unwrap_err().to_string();
        assert!(e.contains("larger than 1048576 bytes"), "{e}");
        let e = text(&dir.join("missing.json5")).unwrap_err().to_string();
        assert!(
            e.starts_with(SESSION_CONFIG_URI_ENV) && e.contains("missing.json5"),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// The router check's attempts, sleeps and warnings, with a router that appears at attempt
    /// `appears_at` (never: `None`).
    fn run(check: RouterCheck, appears_at: Option<u64>) -> (RouterCheckOutcome, u64, usize) {
        let (mut asked, mut slept, mut warned) = (0u64, 0u64, 0usize);
        let outcome = check_router(
            check,
            || {
                asked += 1;
                appears_at.is_some_and(|a| asked >= a)
            },
            |d| {
                assert_eq!(d, ROUTER_CHECK_PERIOD);
                slept += 1;
            },
            |_| warned += 1,
        );
        (outcome, slept, warned)
    }

    #[test]
    fn the_router_check_warns_each_second_and_goes_on_after_the_last_attempt() {
        assert_eq!(
            run(RouterCheck::Skip, None),
            (RouterCheckOutcome::Skipped, 0, 0)
        );
        // Once (the default): one warning for the attempt, one for going on; no sleep.
        assert_eq!(
            run(RouterCheck::Attempts(1), None),
            (RouterCheckOutcome::NotSeen(1), 0, 2)
        );
        assert_eq!(
            run(RouterCheck::Attempts(2), None),
            (RouterCheckOutcome::NotSeen(2), 1, 3)
        );
        assert_eq!(
            run(RouterCheck::Attempts(5), Some(1)),
            (RouterCheckOutcome::Seen(1), 0, 0)
        );
        assert_eq!(
            run(RouterCheck::Attempts(5), Some(3)),
            (RouterCheckOutcome::Seen(3), 2, 2)
        );
        // Forever: until the router is there.
        assert_eq!(
            run(RouterCheck::Forever, Some(40)),
            (RouterCheckOutcome::Seen(40), 39, 39)
        );
    }
}
