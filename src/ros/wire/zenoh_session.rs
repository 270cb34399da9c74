//! The node's Zenoh session, as rmw_zenoh_cpp opens one for a context: the configuration from
//! the environment ([`config::zenoh`](crate::ros::config::zenoh)), the router check, and the
//! node's liveliness token (`@ros2_lv/<domain>/<zid>/0/0/NN/...`,
//! [`NodeToken`](super::zenoh_keys::NodeToken)), which is how every rmw_zenoh peer sees the node
//! in its graph. The node's token is declared when the session opens and withdrawn when it
//! closes; the endpoints' tokens and data keys are made from the same session.
//!
//! The calls here block (zenoh's `Wait`): they run at start-up, before the node's own runtime,
//! or on a thread that may block.

use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Subscriber;
use zenoh::sample::{Sample, SampleKind};
use zenoh::{Config, Session, Wait};

use crate::ros::config::logging::shown;
use crate::ros::config::zenoh::{
    check_router, RouterCheckOutcome, ZenohSettings, CONFIG_OVERRIDE_ENV,
};
use crate::ros::interface::qos::MAX_SAMPLE_BYTES;
use crate::ros::wire::zenoh_keys::{
    data_key, mangle, parse_token, EndpointType, EntityKind, EntityToken, KeyError, NodeToken,
    Token, ADMIN_SPACE,
};
use ros2_client::qos::History;
use ros2_client::QosProfile;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

/// How many other sessions holding a node of this name are warned about, each once; beyond
/// that one more line says the rest are not (a bound on what a hostile peer can make the node
/// remember or log).
pub const MAX_CLASHES_WARNED: usize = 16;

/// What stops the session from opening.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    /// The configuration's text is not a Zenoh configuration.
    #[error("the Zenoh session configuration is not valid: {0}")]
    Config(String),
    /// Zenoh could not open the session (e.g. a listen endpoint it cannot bind).
    #[error("cannot open the Zenoh session: {0}")]
    Open(String),
    /// The node's names make no valid liveliness token.
    #[error("the node's liveliness token: {0}")]
    Token(#[from] KeyError),
    /// Zenoh refused the node's liveliness token.
    #[error("cannot declare the node's liveliness token: {0}")]
    Declare(String),
    /// Zenoh refused the subscription to the graph's node tokens.
    #[error("cannot watch the graph for another node of this name: {0}")]
    Watch(String),
}

/// Where Zenoh's configuration keeps the largest message a link reassembles from fragments.
pub const MAX_MESSAGE_KEY: &str = "transport/link/rx/max_message_size";

/// The largest message the node's session reassembles, in bytes: the largest sample the node
/// accepts ([`MAX_SAMPLE_BYTES`]) and 16 KiB for what Zenoh's message carries beside it (key
/// expression, attachment, extensions). Zenoh's default is 1 GiB, per link and for each
/// priority and reliability (16 buffers); a larger message is dropped by Zenoh as it arrives,
/// before it is reassembled, and the link stays up.
pub const MAX_MESSAGE_BYTES: usize = MAX_SAMPLE_BYTES + 16 * 1024;

/// The session's configuration: `text` (JSON5) with the overrides of `settings` inserted in
/// order; an override the configuration refuses is `warn`ed about (escaped) and left out, as
/// rmw_zenoh does. The largest message reassembled ([`MAX_MESSAGE_KEY`]) is at most
/// [`MAX_MESSAGE_BYTES`]: a larger setting is lowered to it, with a warning, as the DDS side
/// bounds its samples; a smaller one is kept.
pub fn config(
    text: &str,
    settings: &ZenohSettings,
    mut warn: impl FnMut(String),
) -> Result<Config, SessionError> {
    let mut config =
        Config::from_json5(text).map_err(|e| SessionError::Config(shown(&e.to_string())))?;
    for (key, value) in &settings.overrides {
        if let Err(e) = config.insert_json5(key, value) {
            warn(format!(
                "{CONFIG_OVERRIDE_ENV}: ignored the invalid pair ({}, {}): {}",
                shown(key),
                shown(value),
                shown(&e.to_string())
            ));
        }
    }
    let set: Option<u64> = config
        .get_json(MAX_MESSAGE_KEY)
        .ok()
        .and_then(|v| v.trim().parse().ok());
    if set.is_none_or(|n| n > MAX_MESSAGE_BYTES as u64) {
        if let Some(n) = set.filter(|&n| n != ZENOH_DEFAULT_MAX_MESSAGE_BYTES) {
            warn(format!(
                "Zenoh: {MAX_MESSAGE_KEY} {n} lowered to {MAX_MESSAGE_BYTES}, the largest \
                 message the node takes"
            ));
        }
        config
            .insert_json5(MAX_MESSAGE_KEY, &MAX_MESSAGE_BYTES.to_string())
            .map_err(|e| SessionError::Config(shown(&e.to_string())))?;
    }
    Ok(config)
}

/// Zenoh's own default for [`MAX_MESSAGE_KEY`] (1 GiB), lowered without a warning: the user
/// did not choose it.
const ZENOH_DEFAULT_MAX_MESSAGE_BYTES: u64 = 1 << 30;

/// What the node's endpoints on Zenoh are made with: its session and the type hashes
/// ([`type_hashes`](crate::ros::interface::type_hash::type_hashes)) their keys carry.
pub struct ZenohNode {
    /// The session.
    pub session: NodeSession,
    /// The type hashes.
    pub hashes: std::collections::BTreeMap<String, String>,
}

/// An open session with the node's liveliness token declared.
pub struct NodeSession {
    session: Session,
    /// The node's token, withdrawn when this is dropped (before the session closes).
    token: Option<LivelinessToken>,
    /// The watch for another node of this name ([`NodeSession::watch_name_clash`]).
    clash: Option<Subscriber<()>>,
    /// The node's liveliness key.
    pub node_key: String,
    /// The node as its token tells it.
    node: NodeToken,
    /// The next endpoint's id: rmw_zenoh counts the node and its endpoints with one counter,
    /// the node 0.
    next_entity: AtomicU64,
    /// The session's id, lowercase hex.
    pub zid: String,
    /// What the router check found.
    pub router: RouterCheckOutcome,
}

/// The key expression of the node tokens of `namespace`/`name` in `domain`, from any session:
/// only those, so that what the name-clash watch is sent and keeps does not grow with the rest
/// of the domain's graph.
fn clash_key(domain: u32, namespace: &str, name: &str) -> String {
    format!(
        "{ADMIN_SPACE}/{domain}/*/*/*/NN/*/{}/{}",
        mangle(namespace),
        mangle(name)
    )
}

impl NodeSession {
    /// Opens a session with `config`, runs the router check of `settings` (warnings to
    /// `warn`), and declares the liveliness token of the node `namespace`/`name` in `domain`,
    /// with `enclave` (`/` for none).
    pub fn open(
        config: Config,
        settings: &ZenohSettings,
        domain: u32,
        enclave: &str,
        namespace: &str,
        name: &str,
        warn: impl FnMut(String),
    ) -> Result<NodeSession, SessionError> {
        let session = zenoh::open(config)
            .wait()
            .map_err(|e| SessionError::Open(shown(&e.to_string())))?;
        let router = check_router(
            settings.router_check,
            || session.info().routers_zid().wait().next().is_some(),
            std::thread::sleep,
            warn,
        );
        let zid = session.zid().to_string();
        let node = NodeToken {
            domain,
            zid: zid.clone(),
            node_id: 0,
            enclave: enclave.to_string(),
            namespace: namespace.to_string(),
            name: name.to_string(),
        };
        let node_key = node.key()?;
        let token = session
            .liveliness()
            .declare_token(node_key.as_str())
            .wait()
            .map_err(|e| SessionError::Declare(shown(&e.to_string())))?;
        Ok(NodeSession {
            session,
            token: Some(token),
            clash: None,
            node_key,
            node,
            next_entity: AtomicU64::new(1),
            zid,
            router,
        })
    }

    /// The session, for the endpoints.
    pub fn session(&self) -> &Session {
        &self.session
    }

    /// The ROS domain id.
    pub fn domain(&self) -> u32 {
        self.node.domain
    }

    /// The keys of a new endpoint of this node (the next entity id): `kind`, the fully
    /// qualified `name`, of ROS type `ros_type` (`std_msgs/msg/Float64`, its hash looked up in
    /// `hashes`), with `qos`. Returns (its data key, its liveliness token's key).
    pub fn endpoint_keys(
        &self,
        kind: EntityKind,
        name: &str,
        ros_type: &str,
        qos: QosProfile,
        hashes: &BTreeMap<String, String>,
    ) -> Result<(String, String), KeyError> {
        let ty = EndpointType::of(hashes, ros_type)?;
        let key = data_key(self.domain(), name, &ty)?;
        let token = EntityToken {
            node: self.node.clone(),
            entity_id: self.next_entity.fetch_add(1, Ordering::Relaxed),
            kind,
            name: name.to_string(),
            ty,
            qos,
            backends: None,
        };
        Ok((key, token.key()?))
    }

    /// Warns through `warn`, once for each, about every other session on this domain that
    /// holds a node with this node's namespace and name, now and whenever one appears, as
    /// ROS 2 does on DDS (both would receive the same commands and parameter requests and log
    /// under one name); until the session closes. rmw_zenoh's graph is its liveliness tokens,
    /// and a node's names its session. Only logs; what the node does is unchanged.
    pub fn watch_name_clash(
        &mut self,
        fqn: &str,
        warn: impl Fn(String) + Send + Sync + 'static,
    ) -> Result<(), SessionError> {
        let own = self.zid.clone();
        let (namespace, name) = (self.node.namespace.clone(), self.node.name.clone());
        let fqn = fqn.to_string();
        let warned: Mutex<BTreeSet<String>> = Mutex::new(BTreeSet::new());
        let key = clash_key(self.node.domain, &namespace, &name);
        let sub = self
            .session
            .liveliness()
            .declare_subscriber(key)
            .history(true)
            .callback(move |sample: Sample| {
                if sample.kind() != SampleKind::Put {
                    return;
                }
                let Ok(Token::Node(t)) = parse_token(sample.key_expr().as_str()) else {
                    return;
                };
                if t.zid == own || t.namespace != namespace || t.name != name {
                    return;
                }
                let Ok(mut w) = warned.lock() else { return };
                if w.len() > MAX_CLASHES_WARNED || w.contains(&t.zid) {
                    return;
                }
                if w.len() == MAX_CLASHES_WARNED {
                    w.insert(String::new());
                    warn(format!(
                        "more than {MAX_CLASHES_WARNED} other nodes named {fqn} on this ROS \
                         domain: no more are named"
                    ));
                    return;
                }
                w.insert(t.zid.clone());
                warn(format!(
                    "there are {} nodes with the name {fqn} on this ROS domain (another in \
                     Zenoh session {}): both receive the same commands and parameter requests \
                     and log under one name; give each a unique name (-r __node:=NAME or -r \
                     __ns:=/NS)",
                    w.len() + 1,
                    t.zid
                ));
            })
            .wait()
            .map_err(|e| SessionError::Watch(shown(&e.to_string())))?;
        self.clash = Some(sub);
        Ok(())
    }

    /// Withdraws the node's token and closes the session: every peer sees the node leave at
    /// once rather than when its lease runs out.
    pub fn close(mut self) {
        if let Some(clash) = self.clash.take() {
            let _ = clash.undeclare().wait();
        }
        if let Some(token) = self.token.take() {
            let _ = token.undeclare().wait();
        }
        let _ = self.session.close().wait();
    }
}

/// How many unread samples or requests an endpoint with `history` holds: its depth, from 1
/// to `max`; `max` for keep-all.
pub fn queue_depth(history: History, max: usize) -> usize {
    match history {
        History::KeepLast { depth } => depth.clamp(1, max),
        History::KeepAll => max,
    }
}

#[cfg(test)]
mod tests {
    use super::test_peers::{free_port, router, router_config};
    use super::*;
    use crate::ros::config::zenoh::{read, RouterCheck, DEFAULT_SESSION_CONFIG};
    use std::collections::HashMap;

    fn settings(pairs: &[(&str, &str)]) -> ZenohSettings {
        let map: HashMap<String, String> = pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        read(|k| map.get(k).cloned()).unwrap()
    }

    #[test]
    fn the_default_config_parses_and_holds_rmw_zenohs_ros_settings() {
        let c = config(DEFAULT_SESSION_CONFIG, &settings(&[]), |w| panic!("{w}")).unwrap();
        for (key, want) in [
            ("mode", r#""peer""#),
            ("connect/endpoints", r#"["tcp/localhost:7447"]"#),
            ("listen/endpoints", r#"["tcp/localhost:0"]"#),
            ("scouting/multicast/enabled", "false"),
            ("scouting/gossip/enabled", "true"),
            (
                "timestamping/enabled",
                r#"{"router":true,"peer":true,"client":true}"#,
            ),
            ("queries_default_timeout", "600000"),
            ("transport/unicast/open_timeout", "60000"),
            ("transport/shared_memory/enabled", "false"),
        ] {
            let got: String = c
                .get_json(key)
                .unwrap()
                .chars()
                .filter(|c| !c.is_whitespace())
                .collect();
            assert_eq!(got, want, "{key}");
        }
    }

    #[test]
    fn overrides_are_inserted_and_an_invalid_one_is_warned_about_and_left_out() {
        let s = settings(&[(
            CONFIG_OVERRIDE_ENV,
            r#"connect/endpoints=["tcp/127.0.0.1:7999"];mode="nonsense";no/such/key=1"#,
        )]);
        let mut warnings = Vec::new();
        let c = config(DEFAULT_SESSION_CONFIG, &s, |w| warnings.push(w)).unwrap();
        assert_eq!(
            c.get_json("connect/endpoints").unwrap(),
            r#"["tcp/127.0.0.1:7999"]"#
        );
        assert_eq!(c.get_json("mode").unwrap(), r#""peer""#);
        assert_eq!(warnings.len(), 2, "{warnings:?}");
        assert!(warnings[0].contains("(mode, \"nonsense\")"), "{warnings:?}");
        assert!(warnings[1].contains("(no/such/key, 1)"), "{warnings:?}");
    }

    #[test]
    fn the_largest_message_reassembled_is_the_nodes_bound_unless_set_lower() {
        let bound = MAX_MESSAGE_BYTES.to_string();
        let mut warnings = Vec::new();
        let c = config(DEFAULT_SESSION_CONFIG, &settings(&[]), |w| warnings.push(w)).unwrap();
        assert_eq!(c.get_json(MAX_MESSAGE_KEY).unwrap(), bound);
        assert!(warnings.is_empty(), "{warnings:?}");
        // Zenoh's own default, written out in a file, is lowered without a word.
        let c = config(
            "{ transport: { link: { rx: { max_message_size: 1073741824 } } } }",
            &settings(&[]),
            |w| warnings.push(w),
        )
        .unwrap();
        assert_eq!(c.get_json(MAX_MESSAGE_KEY).unwrap(), bound);
        assert!(warnings.is_empty(), "{warnings:?}");
        // A larger choice is lowered and said; a smaller one kept.
        let s = settings(&[(
            CONFIG_OVERRIDE_ENV,
            "transport/link/rx/max_message_size=10000000",
        )]);
        let c = config(DEFAULT_SESSION_CONFIG, &s, |w| warnings.push(w)).unwrap();
        assert_eq!(c.get_json(MAX_MESSAGE_KEY).unwrap(), bound);
        assert_eq!(warnings.len(), 1, "{warnings:?}");
        assert!(warnings[0].contains("10000000 lowered to"), "{warnings:?}");
        let s = settings(&[(
            CONFIG_OVERRIDE_ENV,
            "transport/link/rx/max_message_size=65536",
        )]);
        let c = config(DEFAULT_SESSION_CONFIG, &s, |w| panic!("{w}")).unwrap();
        assert_eq!(c.get_json(MAX_MESSAGE_KEY).unwrap(), "65536");
    }

    #[test]
    fn a_file_that_is_not_a_zenoh_config_is_an_error() {
        let e = config("{ mode: ", &settings(&[]), |_| {}).unwrap_err();
        assert!(matches!(e, SessionError::Config(_)), "{e}");
    }

    #[test]
    fn the_node_token_is_seen_through_a_router_and_withdrawn_when_the_node_closes() {
        let port = free_port();
        let router = router(port);
        let s = settings(&[(
            CONFIG_OVERRIDE_ENV,
            &format!(r#"connect/endpoints=["tcp/127.0.0.1:{port}"];listen/endpoints=[]"#),
        )]);
        let c = config(DEFAULT_SESSION_CONFIG, &s, |w| panic!("{w}")).unwrap();
        let mut warnings = Vec::new();
        let node = NodeSession::open(c, &s, 17, "/", "/lab", "pwm_actuator", |w| warnings.push(w))
            .unwrap();
        assert_eq!(node.router, RouterCheckOutcome::Seen(1), "{warnings:?}");
        assert!(warnings.is_empty(), "{warnings:?}");
        let keys = |router: &Session| -> Vec<String> {
            router
                .liveliness()
                .get("@ros2_lv/17/**")
                .wait()
                .unwrap()
                .iter()
                .filter_map(|r| r.into_result().ok())
                .map(|s| s.key_expr().to_string())
                .collect()
        };
        // The token reaches the router a moment after it is declared.
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        let mut seen = keys(&router);
        while seen.is_empty() && std::time::Instant::now() < deadline {
            std::thread::sleep(std::time::Duration::from_millis(20));
            seen = keys(&router);
        }
        assert_eq!(seen, vec![node.node_key.clone()]);
        match parse_token(&seen[0]).unwrap() {
            Token::Node(t) => {
                assert_eq!(
                    (t.domain, t.namespace.as_str(), t.name.as_str()),
                    (17, "/lab", "pwm_actuator")
                );
                assert_eq!(t.zid, node.zid);
            }
            other => panic!("{other:?}"),
        }
        node.close();
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        while !keys(&router).is_empty() {
            assert!(
                std::time::Instant::now() < deadline,
                "the node's token outlived it"
            );
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        router.close().wait().unwrap();
    }

    #[test]
    fn another_node_of_this_name_is_warned_about_once_and_other_names_not_at_all() {
        let port = free_port();
        let router = router(port);
        let s = settings(&[(
            CONFIG_OVERRIDE_ENV,
            // Each listens on loopback, as rmw_zenoh's peers do: they meet through the router
            // and then connect to each other.
            &format!(
                r#"connect/endpoints=["tcp/127.0.0.1:{port}"];listen/endpoints=["tcp/127.0.0.1:0"]"#
            ),
        )]);
        let open = |ns: &str, name: &str| {
            let c = config(DEFAULT_SESSION_CONFIG, &s, |w| panic!("{w}")).unwrap();
            NodeSession::open(c, &s, 18, "/", ns, name, |w| panic!("{w}")).unwrap()
        };
        // One of this name is there before the watch starts, one comes after; one of another
        // name and one in another namespace are not clashes.
        let before = open("/lab", "pwm_actuator");
        let mut node = open("/lab", "pwm_actuator");
        let warnings = std::sync::Arc::new(Mutex::new(Vec::<String>::new()));
        let w = warnings.clone();
        node.watch_name_clash("/lab/pwm_actuator", move |m| w.lock().unwrap().push(m))
            .unwrap();
        let other_name = open("/lab", "heater");
        let other_ns = open("/", "pwm_actuator");
        let after = open("/lab", "pwm_actuator");
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        while warnings.lock().unwrap().len() < 2 {
            assert!(
                std::time::Instant::now() < deadline,
                "{:?}",
                warnings.lock().unwrap()
            );
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        std::thread::sleep(std::time::Duration::from_millis(500));
        let got = warnings.lock().unwrap().clone();
        assert_eq!(got.len(), 2, "{got:?}");
        for zid in [&before.zid, &after.zid] {
            assert_eq!(
                got.iter().filter(|w| w.contains(zid.as_str())).count(),
                1,
                "{got:?}"
            );
        }
        assert!(
            got[0].contains("2 nodes with the name /lab/pwm_actuator"),
            "{got:?}"
        );
        assert!(
            got[1].contains("3 nodes with the name /lab/pwm_actuator"),
            "{got:?}"
        );
        for n in [before, node, other_name, other_ns, after] {
            n.close();
        }
        router.close().wait().unwrap();
    }

    #[test]
    fn the_name_clash_watch_takes_the_node_tokens_of_its_name_only() {
        use zenoh::key_expr::KeyExpr;
        let token = |ns: &str, name: &str, domain: u32| {
            NodeToken {
                domain,
                zid: "1f2e3d4c5b6a79880123456789abcdef".into(),
                node_id: 3,
                enclave: "/".into(),
                namespace: ns.into(),
                name: name.into(),
            }
            .key()
            .unwrap()
        };
        for ns in ["/", "/lab", "/site/lab"] {
            let watch = KeyExpr::try_from(clash_key(4, ns, "pwm_actuator")).unwrap();
            let has = |k: String| watch.includes(&KeyExpr::try_from(k).unwrap());
            assert!(has(token(ns, "pwm_actuator", 4)), "{ns}: {watch}");
            assert!(!has(token(ns, "heater", 4)), "{ns}");
            assert!(!has(token(ns, "pwm_actuator", 5)), "{ns}");
            assert!(!has(token("/other", "pwm_actuator", 4)), "{ns}");
        }
        // An endpoint's token of that node is not a node token.
        let watch = KeyExpr::try_from(clash_key(4, "/", "pwm_actuator")).unwrap();
        let endpoint = token("/", "pwm_actuator", 4).replace("/NN/", "/MP/") + "/%duty/x/y/z";
        assert!(!watch.intersects(&KeyExpr::try_from(endpoint).unwrap()));
    }

    #[test]
    fn a_router_that_asks_for_a_user_and_password_takes_the_node_only_with_them() {
        let dir = tempfile::tempdir().unwrap();
        let users = dir.path().join("users.txt");
        std::fs::write(&users, "ops:s3cret\n").unwrap();
        let port = free_port();
        let mut c = router_config(&format!("tcp/127.0.0.1:{port}"));
        c.insert_json5(
            "transport/auth/usrpwd/dictionary_file",
            &format!("{:?}", users.to_str().unwrap()),
        )
        .unwrap();
        let router = zenoh::open(c).wait().unwrap();
        let open = |password: &str| {
            open_with(
                &format!(
                    r#"connect/endpoints=["tcp/127.0.0.1:{port}"];listen/endpoints=[];transport/auth/usrpwd/user="ops";transport/auth/usrpwd/password="{password}""#
                ),
                19,
            )
        };
        assert_router_takes_only(router, open("s3cret"), open("guess"), "the wrong password");
    }

    /// The node's session opened with `ZENOH_CONFIG_OVERRIDE` set to `overrides` on `domain`,
    /// and the warnings it gave.
    fn open_with(overrides: &str, domain: u32) -> (Result<NodeSession, SessionError>, Vec<String>) {
        let s = settings(&[(CONFIG_OVERRIDE_ENV, overrides)]);
        let c = config(DEFAULT_SESSION_CONFIG, &s, |w| panic!("{w}")).unwrap();
        let mut warnings = Vec::new();
        let node = NodeSession::open(c, &s, domain, "/", "/", "pwm_actuator", |w| {
            warnings.push(w)
        });
        (node, warnings)
    }

    /// That `router` took the `good` node and refused the `bad` one, which has `lacks`: a
    /// refused link leaves the session open without a router, or not opened. Closes all three.
    fn assert_router_takes_only(
        router: Session,
        (good, warnings): (Result<NodeSession, SessionError>, Vec<String>),
        (bad, bad_warnings): (Result<NodeSession, SessionError>, Vec<String>),
        lacks: &str,
    ) {
        let held = |zid: &str| {
            let info = router.info();
            let mut zids = info.peers_zid().wait().chain(info.routers_zid().wait());
            zids.any(|z| z.to_string() == zid)
        };
        let good = good.unwrap();
        assert_eq!(good.router, RouterCheckOutcome::Seen(1), "{warnings:?}");
        assert!(held(&good.zid), "the router does not hold the node");
        if let Ok(bad) = bad {
            assert_eq!(
                bad.router,
                RouterCheckOutcome::NotSeen(1),
                "{bad_warnings:?}"
            );
            assert!(!held(&bad.zid), "the router took a node with {lacks}");
            bad.close();
        }
        good.close();
        router.close().wait().unwrap();
    }

    /// A certificate authority and, signed by it, a certificate for `127.0.0.1` and
    /// `localhost` per name in `leaves`, written to `dir` as PEM: the CA's file, then per leaf
    /// (certificate file, key file), each quoted for a JSON5 value.
    fn tls_files(dir: &std::path::Path, leaves: &[&str]) -> (String, Vec<(String, String)>) {
        use rcgen::{BasicConstraints, CertificateParams, CertifiedIssuer, IsCa, KeyPair};
        let write = |name: &str, pem: String| {
            let path = dir.join(name);
            std::fs::write(&path, pem).unwrap();
            format!("{:?}", path.to_str().unwrap())
        };
        let mut ca = CertificateParams::new(Vec::<String>::new()).unwrap();
        ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        let ca = CertifiedIssuer::self_signed(ca, KeyPair::generate().unwrap()).unwrap();
        let ca_file = write("ca.pem", ca.pem());
        let leaves = leaves
            .iter()
            .map(|name| {
                let key = KeyPair::generate().unwrap();
                let names = vec!["127.0.0.1".to_string(), "localhost".to_string()];
                let cert = CertificateParams::new(names)
                    .unwrap()
                    .signed_by(&key, &*ca)
                    .unwrap();
                (
                    write(&format!("{name}.pem"), cert.pem()),
                    write(&format!("{name}-key.pem"), key.serialize_pem()),
                )
            })
            .collect();
        (ca_file, leaves)
    }

    #[test]
    fn a_router_on_tls_that_asks_for_a_client_certificate_takes_the_node_only_with_one() {
        let dir = tempfile::tempdir().unwrap();
        let (ca, leaves) = tls_files(dir.path(), &["router", "node"]);
        let ((router_cert, router_key), (node_cert, node_key)) = (&leaves[0], &leaves[1]);
        let port = free_port();
        let mut c = router_config(&format!("tls/127.0.0.1:{port}"));
        for (key, value) in [
            ("root_ca_certificate", ca.as_str()),
            ("listen_certificate", router_cert),
            ("listen_private_key", router_key),
            ("enable_mtls", "true"),
        ] {
            c.insert_json5(&format!("transport/link/tls/{key}"), value)
                .unwrap();
        }
        let router = zenoh::open(c).wait().unwrap();
        let open = |client_certificate: bool| {
            let mut link = format!(
                r#"connect/endpoints=["tls/127.0.0.1:{port}"];listen/endpoints=[];transport/link/tls/root_ca_certificate={ca}"#
            );
            if client_certificate {
                link += &format!(
                    r#";transport/link/tls/enable_mtls=true;transport/link/tls/connect_certificate={node_cert};transport/link/tls/connect_private_key={node_key}"#
                );
            }
            open_with(&link, 18)
        };
        assert_router_takes_only(router, open(true), open(false), "no client certificate");
    }

    /// An RSA key pair for Zenoh's public-key authentication, written to `dir` as PKCS#1 PEM:
    /// (public key file, private key file), each quoted for a JSON5 value.
    fn rsa_files(dir: &std::path::Path, name: &str) -> (String, String) {
        use rsa::pkcs1::{EncodeRsaPrivateKey, EncodeRsaPublicKey, LineEnding};
        let key = rsa::RsaPrivateKey::new(&mut rsa::rand_core::OsRng, 2048).unwrap();
        let public = dir.join(format!("{name}-pub.pem"));
        let private = dir.join(format!("{name}-key.pem"));
        let public_pem = key.to_public_key().to_pkcs1_pem(LineEnding::LF).unwrap();
        std::fs::write(&public, public_pem).unwrap();
        std::fs::write(
            &private,
            key.to_pkcs1_pem(LineEnding::LF).unwrap().as_bytes(),
        )
        .unwrap();
        let quoted = |p: std::path::PathBuf| format!("{:?}", p.to_str().unwrap());
        (quoted(public), quoted(private))
    }

    #[test]
    fn a_configuration_asking_for_public_key_authentication_joins_no_router() {
        // Zenoh 1.10 reads no list of known keys from its configuration: a router asking for
        // public-key authentication refuses every key, and a node asking for it joins no
        // router. The node fails closed: its key settings are not ignored.
        let dir = tempfile::tempdir().unwrap();
        let (node_pub, node_key) = rsa_files(dir.path(), "node");
        let (router_pub, router_key) = rsa_files(dir.path(), "router");
        let router = |with_key: bool| {
            let port = free_port();
            let mut c = router_config(&format!("tcp/127.0.0.1:{port}"));
            if with_key {
                c.insert_json5("transport/auth/pubkey/public_key_file", &router_pub)
                    .unwrap();
                c.insert_json5("transport/auth/pubkey/private_key_file", &router_key)
                    .unwrap();
            }
            (zenoh::open(c).wait().unwrap(), port)
        };
        let open = |port: u16, with_key: bool| {
            let mut link =
                format!(r#"connect/endpoints=["tcp/127.0.0.1:{port}"];listen/endpoints=[]"#);
            if with_key {
                link += &format!(
                    r#";transport/auth/pubkey/public_key_file={node_pub};transport/auth/pubkey/private_key_file={node_key}"#
                );
            }
            open_with(&link, 16)
        };
        let (router_with_key, port) = router(true);
        let (node, warnings) = open(port, true);
        let node = node.unwrap();
        assert_eq!(node.router, RouterCheckOutcome::NotSeen(1), "{warnings:?}");
        node.close();
        router_with_key.close().wait().unwrap();
        // A router without authentication takes the node without key settings, not with them.
        let (router, port) = router(false);
        assert_router_takes_only(router, open(port, false), open(port, true), "key settings");
    }

    #[test]
    fn without_a_router_the_node_warns_at_each_attempt_and_opens() {
        let port = free_port();
        let s = settings(&[
            (
                CONFIG_OVERRIDE_ENV,
                &format!(r#"connect/endpoints=["tcp/127.0.0.1:{port}"];listen/endpoints=[]"#),
            ),
            ("ZENOH_ROUTER_CHECK_ATTEMPTS", "2"),
        ]);
        assert_eq!(s.router_check, RouterCheck::Attempts(2));
        let c = config(DEFAULT_SESSION_CONFIG, &s, |w| panic!("{w}")).unwrap();
        let mut warnings = Vec::new();
        let start = std::time::Instant::now();
        let node =
            NodeSession::open(c, &s, 3, "/", "/", "pwm_actuator", |w| warnings.push(w)).unwrap();
        assert_eq!(node.router, RouterCheckOutcome::NotSeen(2));
        assert_eq!(warnings.len(), 3, "{warnings:?}");
        assert!(
            warnings[0].contains("Unable to connect to a Zenoh router"),
            "{warnings:?}"
        );
        assert!(warnings[2].contains("after 2 attempt(s)"), "{warnings:?}");
        // One second between the two attempts.
        assert!(start.elapsed() >= std::time::Duration::from_secs(1));
        node.close();
    }
}

/// What the Zenoh modules' tests share: a free port, a router on it in the test process (as
/// `rmw_zenohd` would be), and the node's session connected to it.
#[cfg(test)]
pub(crate) mod test_peers {
    use super::{config, NodeSession};
    use crate::ros::config::zenoh::{read, DEFAULT_SESSION_CONFIG};
    use std::net::TcpListener;
    use zenoh::{Config, Session, Wait};

    /// A port nobody listens on now.
    pub(crate) fn free_port() -> u16 {
        TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port()
    }

    /// A router on `port` in this process, timestamping (publication caches need it).
    pub(crate) fn router(port: u16) -> Session {
        zenoh::open(router_config(&format!("tcp/127.0.0.1:{port}")))
            .wait()
            .unwrap()
    }

    /// The configuration of a router listening on `endpoint` alone (`tcp/127.0.0.1:7447`), as
    /// `rmw_zenohd`'s but for the endpoint and without multicast scouting.
    pub(crate) fn router_config(endpoint: &str) -> Config {
        let mut c = Config::default();
        c.insert_json5("mode", r#""router""#).unwrap();
        c.insert_json5("listen/endpoints", &format!(r#"["{endpoint}"]"#))
            .unwrap();
        c.insert_json5("scouting/multicast/enabled", "false")
            .unwrap();
        c.insert_json5("timestamping/enabled", "true").unwrap();
        c
    }

    /// The node's session in ROS domain `domain`, connected to the router on `port` alone.
    pub(crate) fn node(port: u16, domain: u32) -> NodeSession {
        let s = read(|k| {
            (k == "ZENOH_CONFIG_OVERRIDE").then(|| {
                format!(r#"connect/endpoints=["tcp/127.0.0.1:{port}"];listen/endpoints=[]"#)
            })
        })
        .unwrap();
        let c = config(DEFAULT_SESSION_CONFIG, &s, |w| panic!("{w}")).unwrap();
        NodeSession::open(c, &s, domain, "/", "/", "pwm_actuator", |w| panic!("{w}")).unwrap()
    }
}
