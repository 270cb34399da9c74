//! The node as a process under the ROS environment that concerns trust: SROS2 security
//! variables (refused when enforced, warned about when permissive), the discovery range
//! (`ROS_AUTOMATIC_DISCOVERY_RANGE`, `ROS_LOCALHOST_ONLY`, `ROS_STATIC_PEERS`), the middleware
//! asked for (`RMW_IMPLEMENTATION`) and two nodes with one name on a domain.

use crate::ros_harness::*;
use pwm_actuator::ros::interface::msg::DiagnosticArray;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Every variable these tests set, removed from the child's environment first so the
/// caller's shell cannot change a result.
const TRUST_VARS: [&str; 8] = [
    "ROS_SECURITY_ENABLE",
    "ROS_SECURITY_STRATEGY",
    "ROS_SECURITY_KEYSTORE",
    "ROS_SECURITY_ENCLAVE_OVERRIDE",
    "ROS_LOCALHOST_ONLY",
    "ROS_AUTOMATIC_DISCOVERY_RANGE",
    "ROS_STATIC_PEERS",
    "RMW_IMPLEMENTATION",
];

/// Runs the node with `env` and `args` until it exits by itself (or kills it after 20 s);
/// returns its exit code and stderr, and whether the trace file `csv` exists.
fn run_to_exit(env: &[(&str, &str)], args: &[&str]) -> (Option<i32>, String, bool) {
    let dom = Domain::acquire();
    let dir = std::env::temp_dir().join(format!("pwm_actuator_trust_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let csv = dir.join(format!("t{}.csv", dom.id));
    let _ = std::fs::remove_file(&csv);
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_pwm_actuator_node"));
    for v in TRUST_VARS {
        cmd.env_remove(v);
    }
    let mut all = vec!["--trace", csv.to_str().unwrap()];
    all.extend_from_slice(args);
    let out = cmd
        .args(&all)
        .envs(env.iter().copied())
        .env("ROS_DOMAIN_ID", dom.id.to_string())
        .env_remove("ROS_DISTRO")
        .output()
        .expect("the node binary runs");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
        csv.exists(),
    )
}

/// Starts the node with `env` (and nothing else of [`TRUST_VARS`] from the caller) and waits
/// until it runs.
fn start(env: &[(&str, &str)], args: &[&str]) -> NodeProc {
    let mut full: Vec<(&str, &str)> = TRUST_VARS
        .iter()
        .filter(|v| !env.iter().any(|(k, _)| k == *v))
        .map(|v| (*v, ""))
        .collect();
    full.extend_from_slice(env);
    let n = NodeProc::start_with(args, &full);
    n.wait_running();
    n
}

#[test]
fn enforced_security_is_refused_before_any_output_is_opened() {
    for (env, args) in [
        (
            vec![
                ("ROS_SECURITY_ENABLE", "true"),
                ("ROS_SECURITY_STRATEGY", "Enforce"),
                ("ROS_SECURITY_KEYSTORE", "/nonexistent/keystore"),
            ],
            vec!["--ros-args", "--enclave", "/pwm_actuator"],
        ),
        (
            vec![
                ("ROS_SECURITY_ENABLE", "true"),
                ("ROS_SECURITY_STRATEGY", "Enforce"),
            ],
            vec![],
        ),
    ] {
        let (code, err, traced) = run_to_exit(&env, &args);
        assert_eq!(code, Some(2), "{env:?}: {err}");
        assert!(err.contains("DDS security is enforced"), "{err}");
        assert!(err.contains("ROS_SECURITY_STRATEGY=Enforce"), "{err}");
        assert!(err.contains("Refusing to start"), "{err}");
        assert!(!traced, "the output was opened before the refusal");
        assert!(!err.contains(" running: "), "{err}");
    }
}

#[test]
fn permissive_security_and_a_bare_enclave_start_with_one_warning() {
    for (env, args, needle) in [
        (
            vec![
                ("ROS_SECURITY_ENABLE", "true"),
                ("ROS_SECURITY_STRATEGY", "Permissive"),
                ("ROS_SECURITY_KEYSTORE", "/nonexistent/keystore"),
            ],
            vec![],
            "running UNSECURED",
        ),
        (
            vec![],
            vec!["--ros-args", "-e", "/pwm_actuator"],
            "enclave `/pwm_actuator` given but ROS_SECURITY_ENABLE is not `true`",
        ),
    ] {
        let log = start(&env, &args).stop_ok();
        assert_eq!(log.matches(needle).count(), 1, "{needle}: {log}");
        assert!(log.contains("[WARN]"), "{log}");
    }
    // Nothing asked: nothing said.
    let n = start(&[], &[]);
    std::thread::sleep(Duration::from_millis(200));
    let (_, log) = n.stop();
    assert!(!log.contains("secur"), "{log}");
}

/// The node started directly (the harness keeps its pid to itself), stderr to a file.
struct Spawned {
    child: Child,
    log: std::path::PathBuf,
}

impl Spawned {
    fn start(dom: &Domain, env: &[(&str, &str)]) -> Spawned {
        let log = std::env::temp_dir().join(format!(
            "pwm_actuator_trust_{}_{}.log",
            std::process::id(),
            dom.id
        ));
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_pwm_actuator_node"));
        for v in TRUST_VARS {
            cmd.env_remove(v);
        }
        let child = cmd
            .envs(env.iter().copied())
            .env("ROS_DOMAIN_ID", dom.id.to_string())
            .env_remove("ROS_DISTRO")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .expect("the node binary starts");
        let s = Spawned { child, log };
        let end = Instant::now() + LONG;
        while !s.log().contains(" running: ") {
            assert!(Instant::now() < end, "node did not start:\n{}", s.log());
            std::thread::sleep(Duration::from_millis(20));
        }
        s
    }

    fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Asserts that the node's log so far contains `needle`.
    fn assert_logged(&self, needle: &str) {
        let log = self.log();
        assert!(log.contains(needle), "{needle:?} not in:\n{log}");
    }

    /// The node's UDP sockets as `ss` shows their local address (`0.0.0.0%lo:7400`: bound to
    /// the loopback device). Only `ss` (iproute2, over sock_diag) shows the device a socket is
    /// bound to, so a machine without it fails these tests, saying so, rather than skip them.
    fn udp_sockets(&self) -> Vec<String> {
        let out = Command::new("ss")
            .args(["-H", "-uanp"])
            .output()
            .unwrap_or_else(|e| panic!("`ss` (iproute2) is needed to see the node's sockets: {e}"));
        assert!(out.status.success(), "ss -H -uanp: {out:?}");
        let pid = format!("pid={},", self.child.id());
        String::from_utf8_lossy(&out.stdout)
            .lines()
            .filter(|l| l.contains(&pid))
            .filter_map(|l| l.split_whitespace().nth(3).map(str::to_string))
            .collect()
    }
}

impl Spawned {
    /// SIGINT, wait for the exit; returns the whole log.
    fn stop(mut self) -> String {
        self.interrupt();
        self.log()
    }
}

impl Drop for Spawned {
    fn drop(&mut self) {
        self.interrupt();
    }
}

impl Spawned {
    fn interrupt(&mut self) {
        let _ = nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(self.child.id() as i32),
            nix::sys::signal::Signal::SIGINT,
        );
        let end = Instant::now() + LONG;
        while Instant::now() < end {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Whether a test participant with RustDDS's defaults on `dom` hears the node's
/// `/diagnostics` (1 Hz) within `within`.
fn heard_from(dom: &Domain, within: Duration) -> bool {
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let mut ros = Ros::new(dom.id);
        let diag = ros.sub::<DiagnosticArray>("/diagnostics", default_qos());
        next(&diag, within).await.is_some()
    })
}

#[test]
fn localhost_binds_every_socket_to_loopback_and_still_talks_on_this_machine() {
    for env in [
        vec![("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")],
        vec![("ROS_LOCALHOST_ONLY", "1")],
    ] {
        let dom = Domain::acquire();
        let node = Spawned::start(&dom, &env);
        let socks = node.udp_sockets();
        assert!(socks.len() >= 4, "{env:?}: {socks:?}\n{}", node.log());
        for s in &socks {
            assert!(
                s.contains("%lo:") || s.starts_with("127."),
                "{env:?}: socket {s} is reachable from other interfaces: {socks:?}"
            );
        }
        node.assert_logged("discovery range LOCALHOST");
        // A participant on this machine still discovers it and hears it.
        assert!(heard_from(&dom, LONG), "{env:?}: {}", node.log());
        // Having matched a peer opened no socket outside loopback.
        let after = node.udp_sockets();
        assert!(
            !after.is_empty(),
            "{env:?}: no UDP socket after matching a peer"
        );
        assert!(
            after
                .iter()
                .all(|s| s.contains("%lo:") || s.starts_with("127.")),
            "{env:?}: after matching a peer: {after:?}"
        );
        // A clean stop is quiet: no rustdds error about multicast groups it never joined.
        let log = node.stop();
        assert!(log.contains("all outputs off"), "{log}");
        assert!(!log.contains("[ERROR]"), "{env:?}: {log}");
    }
    // ROS_LOCALHOST_ONLY says it is deprecated.
    let dom = Domain::acquire();
    let node = Spawned::start(&dom, &[("ROS_LOCALHOST_ONLY", "1")]);
    node.assert_logged("ROS_LOCALHOST_ONLY is deprecated");
}

#[test]
fn subnet_is_unchanged_and_off_discovers_no_one() {
    let dom = Domain::acquire();
    let node = Spawned::start(&dom, &[("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")]);
    let socks = node.udp_sockets();
    assert!(socks.iter().any(|s| s.starts_with("0.0.0.0:")), "{socks:?}");
    assert!(heard_from(&dom, LONG), "{}", node.log());
    drop(node);

    let dom = Domain::acquire();
    let node = Spawned::start(&dom, &[("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")]);
    let socks = node.udp_sockets();
    assert!(
        !socks.is_empty(),
        "OFF: the node has no UDP socket\n{}",
        node.log()
    );
    assert!(socks.iter().all(|s| s.contains("%lo:")), "{socks:?}");
    node.assert_logged("discovery range OFF");
    assert!(
        !heard_from(&dom, Duration::from_secs(4)),
        "OFF, yet heard: {}",
        node.log()
    );
}

#[test]
fn zenoh_asked_for_is_refused_before_any_output_and_a_dds_middleware_runs() {
    // A system on rmw_zenoh could neither command the node nor see its diagnostics: refused,
    // exit 2, before the output is opened, saying what to do.
    // (A build with the `zenoh` feature runs on Zenoh instead: tests/rclpy/test_zenoh.py.)
    if !cfg!(feature = "zenoh") {
        let (code, err, traced) = run_to_exit(&[("RMW_IMPLEMENTATION", "rmw_zenoh_cpp")], &[]);
        assert_eq!(code, Some(2), "{err}");
        assert!(
            err.contains(
                "RMW_IMPLEMENTATION=rmw_zenoh_cpp: this build of the node speaks DDS only"
            ),
            "{err}"
        );
        assert!(!traced, "the output was opened before the refusal");
    }
    // A DDS middleware is met on the wire: no word; an unknown one: a warning, and it runs.
    let dom = Domain::acquire();
    let node = Spawned::start(&dom, &[("RMW_IMPLEMENTATION", "rmw_cyclonedds_cpp")]);
    assert!(!node.log().contains("RMW_IMPLEMENTATION"), "{}", node.log());
    drop(node);
    let dom = Domain::acquire();
    let node = Spawned::start(&dom, &[("RMW_IMPLEMENTATION", "rmw_somethingelse")]);
    node.assert_logged("RMW_IMPLEMENTATION=rmw_somethingelse is not a middleware this node knows");
}

#[test]
fn static_peers_are_taken_bad_ones_warned_about_and_too_many_refused() {
    // Too many: refused before any output is opened, naming the count and the bound.
    let many: Vec<String> = (1..=33).map(|i| format!("127.0.1.{i}")).collect();
    let (code, err, traced) = run_to_exit(&[("ROS_STATIC_PEERS", &many.join(";"))], &[]);
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains("ROS_STATIC_PEERS names 33 peers; the node takes at most 32"),
        "{err}"
    );
    assert!(!traced, "the output was opened before the refusal");
    // Entries without an IPv4 address are skipped with a warning that echoes them escaped;
    // the others are used.
    let dom = Domain::acquire();
    let node = Spawned::start(
        &dom,
        &[(
            "ROS_STATIC_PEERS",
            "fe80::1; 127.0.0.1 ;bad\n[ERROR] forged",
        )],
    );
    node.assert_logged("ROS_STATIC_PEERS: peer `fe80::1` skipped: no IPv4 address");
    node.assert_logged("ROS_STATIC_PEERS: peer `bad\\n[ERROR] forged` skipped");
    node.assert_logged("static peers: discovery announcements also sent to 127.0.0.1");
    assert!(!node.log().contains("bad\n"), "{}", node.log());
    // Under OFF, rcl does not use them: a warning, and the node starts.
    let dom = Domain::acquire();
    let node = Spawned::start(
        &dom,
        &[
            ("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF"),
            ("ROS_STATIC_PEERS", "192.0.2.1"),
        ],
    );
    node.assert_logged("ROS_STATIC_PEERS is ignored");
    assert!(!node.log().contains("static peers:"), "{}", node.log());
}

#[test]
fn a_second_node_with_the_same_name_is_warned_about() {
    let dom = Domain::acquire();
    let first = Spawned::start(&dom, &[]);
    let second = Spawned::start(&dom, &[]);
    let needle = "there are 2 nodes with the name /pwm_actuator on this ROS domain";
    let end = Instant::now() + LONG;
    while !(first.log().contains(needle) && second.log().contains(needle)) {
        assert!(
            Instant::now() < end,
            "no warning\nfirst:\n{}\nsecond:\n{}",
            first.log(),
            second.log()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    // Once each, however often the other announces itself.
    std::thread::sleep(Duration::from_secs(1));
    assert_eq!(first.log().matches(needle).count(), 1, "{}", first.log());
    assert_eq!(second.log().matches(needle).count(), 1, "{}", second.log());
}

#[test]
fn a_node_alone_on_its_domain_says_nothing_about_names() {
    let dom = Domain::acquire();
    let node = Spawned::start(&dom, &[]);
    // Its own announcement comes back to it: that is not a second node.
    assert!(heard_from(&dom, LONG), "{}", node.log());
    assert!(
        !node.log().contains("nodes with the name"),
        "{}",
        node.log()
    );
}

#[cfg(feature = "zenoh")]
#[test]
fn a_stop_signal_while_the_node_looks_for_a_zenoh_router_ends_it_at_once() {
    use std::io::{BufRead, BufReader};
    // ZENOH_ROUTER_CHECK_ATTEMPTS=0: the node looks for a router until one is there, and
    // none ever is.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let dom = Domain::acquire();
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("lines.csv");
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_pwm_actuator_node"));
    for v in TRUST_VARS {
        cmd.env_remove(v);
    }
    let mut child = cmd
        .arg("--trace")
        .arg(&csv)
        .env("RMW_IMPLEMENTATION", "rmw_zenoh_cpp")
        .env("ZENOH_ROUTER_CHECK_ATTEMPTS", "0")
        .env(
            "ZENOH_CONFIG_OVERRIDE",
            format!(r#"connect/endpoints=["tcp/127.0.0.1:{port}"];listen/endpoints=[]"#),
        )
        .env("ROS_DOMAIN_ID", dom.id.to_string())
        .env_remove("ZENOH_SESSION_CONFIG_URI")
        .env_remove("ROS_DISTRO")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the node binary runs");
    let (tx, rx) = std::sync::mpsc::channel::<String>();
    let stderr = child.stderr.take().unwrap();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let mut log = String::new();
    let deadline = Instant::now() + Duration::from_secs(30);
    while !log.contains("Unable to connect to a Zenoh router (attempt 2)") {
        let left = deadline.saturating_duration_since(Instant::now());
        match rx.recv_timeout(left) {
            Ok(l) => log += &(l + "\n"),
            Err(_) => panic!("no second router check within 30 s:\n{log}"),
        }
    }
    let pid = nix::unistd::Pid::from_raw(child.id() as i32);
    nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM).unwrap();
    let sent = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if sent.elapsed() > Duration::from_secs(10) {
            let _ = child.kill();
            panic!("still running 10 s after SIGTERM:\n{log}");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    while let Ok(l) = rx.recv_timeout(Duration::from_millis(500)) {
        log += &(l + "\n");
    }
    assert_eq!(status.code(), Some(0), "{log}");
    assert!(
        log.contains("SIGTERM while joining Zenoh: stopping; the lines were never driven"),
        "{log}"
    );
    // What reached the lines: each set to off as the output opened and closed, never on.
    let text = std::fs::read_to_string(&csv).expect("the output's trace was written");
    let rows = pwm_actuator::output::read_csv(&text).expect("a CSV trace");
    assert!(!rows.is_empty(), "an empty trace:\n{text}");
    assert!(rows.iter().all(|r| !r.level.is_high()), "{rows:?}");
}
