//! Shared helpers of the ROS integration tests: start the built node as a process on its own
//! ROS domain, capture its log, and talk to it over ROS with a ros2-client node. Every wait
//! has a timeout; nothing here asserts timing.
#![allow(dead_code)]

use futures::StreamExt;
use ros2_client::parameters::raw;
use ros2_client::qos::{Durability, History};
use ros2_client::rcl_interfaces::*;
use ros2_client::{
    Client, Context, ContextOptions, Message, MessageTypeName, Name, Node, NodeName, NodeOptions,
    ParameterValue, Publisher, QosProfile, ServiceMapping, ServiceTypeName, Subscription,
};
use rustdds::Topic;
use serde::de::DeserializeOwned;
use serde::Serialize;
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// One channel's topics, as a ROS user sees them: its inputs to publish on and its outputs.
pub struct ChannelTopics {
    /// `~/<ch>/duty`.
    pub duty: Publisher<pwm_actuator::ros::interface::msg::Float64>,
    /// `~/<ch>/sv`.
    pub sv: Publisher<pwm_actuator::ros::interface::msg::UInt16>,
    /// `~/<ch>/enable`.
    pub enable: Publisher<pwm_actuator::ros::interface::msg::Bool>,
    /// `~/<ch>/edges`.
    pub edges: Subscription<pwm_actuator::ros::interface::msg::OutputEdge>,
    /// `~/<ch>/status`.
    pub status: Subscription<pwm_actuator::ros::interface::msg::ChannelStatus>,
    /// `~/<ch>/e1` (transient local).
    pub e1: Subscription<pwm_actuator::ros::interface::msg::Bool>,
}

/// A message type with its ROS type name, for typed subscriptions and publishers.
pub trait TopicType {
    /// ROS package, e.g. `std_msgs`.
    const PKG: &'static str;
    /// Type name inside the package, e.g. `Float64`.
    const NAME: &'static str;

    /// The ros2-client type name.
    fn type_name() -> MessageTypeName {
        MessageTypeName::new(Self::PKG, Self::NAME)
    }
}

/// The node's own message types take their names from `RosMessage`.
macro_rules! node_topic_types {
    ($($ty:ident),+) => {
        $(impl TopicType for pwm_actuator::ros::interface::msg::$ty {
            const PKG: &'static str =
                <pwm_actuator::ros::interface::msg::$ty as pwm_actuator::ros::interface::msg::RosMessage>::PACKAGE;
            const NAME: &'static str =
                <pwm_actuator::ros::interface::msg::$ty as pwm_actuator::ros::interface::msg::RosMessage>::NAME;
        })+
    };
}
node_topic_types!(
    Float64,
    UInt16,
    Bool,
    DiagnosticArray,
    OutputEdge,
    ChannelStatus,
    ChannelParams
);

impl TopicType for raw::ParameterEvent {
    const PKG: &'static str = "rcl_interfaces";
    const NAME: &'static str = "ParameterEvent";
}

impl TopicType for ros2_client::Log {
    const PKG: &'static str = "rcl_interfaces";
    const NAME: &'static str = "Log";
}

/// Generous upper bound for anything that involves DDS discovery on a loaded machine.
pub const LONG: Duration = Duration::from_secs(15);

/// `--ros-args -p P1 -p P2 ...`: the command line that sets each of `params` (`NAME:=VALUE`).
pub fn ros_params<'a>(params: &[&'a str]) -> Vec<&'a str> {
    let mut args = vec!["--ros-args"];
    for p in params {
        args.extend(["-p", p]);
    }
    args
}

/// ROS domain ids handed to tests, shared with the rclpy suite (tests/rclpy/conftest.py): 1..48.
/// 49..101 are the vendored RustDDS tests' (they take no lock; scripts/test.sh runs them beside
/// the other suites), and above 101 the DDS ports of a domain fall into Linux's ephemeral port
/// range.
const DOMAIN_IDS: std::ops::RangeInclusive<u16> = 1..=48;

/// A ROS domain id held for one test: an exclusive `flock` on
/// `<tmp>/pwm_actuator-ros-domains/<id>.lock`, the same lock files the rclpy suite takes, so
/// concurrent test runs of either suite never share a domain. Released on drop (or by the
/// kernel if the process dies).
pub struct Domain {
    /// The domain id.
    pub id: u16,
    _lock: std::fs::File,
}

impl Domain {
    /// Takes the next free domain id, round-robin from a start that depends on the process id.
    pub fn acquire() -> Domain {
        use std::os::fd::AsRawFd;
        use std::sync::atomic::{AtomicUsize, Ordering};
        static NEXT: AtomicUsize = AtomicUsize::new(usize::MAX);
        let dir = std::env::temp_dir().join("pwm_actuator-ros-domains");
        let _ = std::fs::create_dir_all(&dir);
        let ids: Vec<u16> = DOMAIN_IDS.collect();
        let _ = NEXT.compare_exchange(
            usize::MAX,
            std::process::id() as usize % ids.len(),
            Ordering::SeqCst,
            Ordering::SeqCst,
        );
        for _ in 0..ids.len() {
            let id = ids[NEXT.fetch_add(1, Ordering::SeqCst) % ids.len()];
            let Ok(file) = std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .create(true)
                .truncate(false)
                .open(dir.join(format!("{id}.lock")))
            else {
                continue;
            };
            // SAFETY: flock on a file descriptor this function owns; no memory is involved.
            let rc = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
            if rc == 0 {
                return Domain { id, _lock: file };
            }
        }
        panic!("every ROS domain id in {DOMAIN_IDS:?} is held by another test run");
    }
}

/// The node as a child process with its stderr captured, on a ROS domain of its own.
pub struct NodeProc {
    child: Option<Child>,
    log: Arc<Mutex<String>>,
    reader: Option<std::thread::JoinHandle<()>>,
    /// The ROS domain the node runs on.
    pub domain: u16,
    /// Held as long as the node: released after it is gone.
    _domain_lock: Domain,
}

impl NodeProc {
    /// Starts `pwm_actuator_node ARGS` on a free ROS domain.
    pub fn start(args: &[&str]) -> NodeProc {
        Self::start_with(args, &[])
    }

    /// Starts the node on a free ROS domain and waits until it says it is running.
    pub fn launch(args: &[&str]) -> NodeProc {
        let node = Self::start(args);
        node.wait_running();
        node
    }

    /// Starts the node on a free ROS domain with extra environment variables.
    pub fn start_with(args: &[&str], env: &[(&str, &str)]) -> NodeProc {
        let dom = Domain::acquire();
        let mut child = Command::new(env!("CARGO_BIN_EXE_pwm_actuator_node"))
            .args(args)
            .envs(env.iter().copied())
            .env("ROS_DOMAIN_ID", dom.id.to_string())
            .env_remove("ROS_DISTRO")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("the node binary starts");
        let log = Arc::new(Mutex::new(String::new()));
        let stderr = child.stderr.take().expect("stderr is piped");
        let sink = Arc::clone(&log);
        let reader = std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                let mut l = sink.lock().unwrap();
                l.push_str(&line);
                l.push('\n');
            }
        });
        NodeProc {
            child: Some(child),
            log,
            reader: Some(reader),
            domain: dom.id,
            _domain_lock: dom,
        }
    }

    /// Everything the node has written to stderr so far.
    pub fn log(&self) -> String {
        self.log.lock().unwrap().clone()
    }

    /// Waits until the log contains `needle`.
    pub fn wait_log(&self, needle: &str, timeout: Duration) -> bool {
        let end = Instant::now() + timeout;
        while Instant::now() < end {
            if self.log().contains(needle) {
                return true;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        self.log().contains(needle)
    }

    /// As [`NodeProc::wait_log`] for async tests, whose runtime runs its other tasks meanwhile:
    /// waits until `done` holds for the log, up to `timeout`; whether it did.
    pub async fn log_until(&self, timeout: Duration, done: impl Fn(&str) -> bool) -> bool {
        let end = Instant::now() + timeout;
        while !done(&self.log()) {
            if Instant::now() >= end {
                return false;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        true
    }

    /// Waits until the node says it is running (or fails the test with its log).
    pub fn wait_running(&self) {
        assert!(
            self.wait_log(" running: ", LONG),
            "node did not start; log:\n{}",
            self.log()
        );
    }

    /// The node's process id (0 once it has been waited for).
    pub fn pid(&self) -> u32 {
        self.child.as_ref().map_or(0, Child::id)
    }

    /// Whether the process is still alive.
    pub fn running(&mut self) -> bool {
        match self.child.as_mut() {
            Some(c) => matches!(c.try_wait(), Ok(None)),
            None => false,
        }
    }

    /// Sends `sig` to the node.
    pub fn signal(&self, sig: nix::sys::signal::Signal) {
        if let Some(c) = &self.child {
            let _ = nix::sys::signal::kill(nix::unistd::Pid::from_raw(c.id() as i32), sig);
        }
    }

    /// Sends `sig` and waits for the exit (killing the node after `LONG`). Returns the exit
    /// status and the whole log.
    pub fn stop_with(mut self, sig: nix::sys::signal::Signal) -> (ExitStatus, String) {
        self.signal(sig);
        let status = self.wait_exit(LONG);
        if let Some(r) = self.reader.take() {
            let _ = r.join();
        }
        (status, self.log())
    }

    /// Waits for the process to exit by itself (killing it after `timeout`); the log then
    /// holds everything it wrote.
    pub fn wait_exit(&mut self, timeout: Duration) -> ExitStatus {
        let mut child = self.child.take().expect("the node was started");
        let end = Instant::now() + timeout;
        loop {
            if let Ok(Some(s)) = child.try_wait() {
                // The log is complete once the reader has seen stderr's end.
                if let Some(reader) = self.reader.take() {
                    let _ = reader.join();
                }
                return s;
            }
            if Instant::now() > end {
                let _ = child.kill();
                let s = child.wait().expect("wait after kill");
                panic!("node did not exit in time ({s:?}); log:\n{}", self.log());
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// SIGINT and wait; returns the exit status and the log.
    pub fn stop(self) -> (ExitStatus, String) {
        self.stop_with(nix::sys::signal::Signal::SIGINT)
    }

    /// SIGINT and wait; asserts a clean exit (0) and returns the log.
    pub fn stop_ok(self) -> String {
        let (status, log) = self.stop();
        assert!(status.success(), "{status:?}\n{log}");
        log
    }
}

impl Drop for NodeProc {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// The QoS rclpy uses by default (`create_publisher(T, topic, 10)`).
pub fn default_qos() -> QosProfile {
    QosProfile::publisher_default().history(History::KeepLast { depth: 10 })
}

/// A transient-local reader, to get a latched value.
pub fn latched_qos() -> QosProfile {
    default_qos()
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 })
}

/// A ros2-client node of the test, on the node's domain.
pub struct Ros {
    /// The test's node.
    pub node: Node,
    _context: Context,
    spin: tokio::task::JoinHandle<()>,
}

fn name(full: &str) -> Name {
    let (ns, base) = match full.rsplit_once('/') {
        Some(("", b)) => ("/", b),
        Some((ns, b)) => (ns, b),
        None => ("/", full),
    };
    Name::new(ns, base).expect("valid test topic name")
}

impl Ros {
    /// A test node on `domain` (needs a tokio runtime).
    pub fn new(domain: u16) -> Ros {
        Ros::on(
            Context::with_options(ContextOptions::new().domain_id(domain)).expect("DDS context"),
        )
    }

    /// A test node in `context` (needs a tokio runtime).
    pub fn on(context: Context) -> Ros {
        let mut node = context
            .new_node(
                NodeName::new("/", &format!("test_client_{}", std::process::id())).unwrap(),
                NodeOptions::new()
                    .enable_rosout(false)
                    .start_parameter_services(false),
            )
            .expect("test node");
        let spinner = node.spinner().expect("spinner");
        let spin = tokio::spawn(async move {
            let _ = spinner.spin().await;
        });
        Ros {
            node,
            _context: context,
            spin,
        }
    }

    /// The topic `topic` (absolute), typed by `M`.
    fn topic<M: TopicType>(&mut self, topic: &str, qos: &QosProfile) -> Topic {
        self.node
            .create_topic(&name(topic), M::type_name(), qos)
            .expect("topic")
    }

    /// Subscribes `topic` (absolute), typed by `M`.
    pub fn sub<M: TopicType + DeserializeOwned + 'static>(
        &mut self,
        topic: &str,
        qos: QosProfile,
    ) -> Subscription<M> {
        let t = self.topic::<M>(topic, &qos);
        self.node
            .create_subscription(&t, Some(qos))
            .expect("subscription")
    }

    /// Publishes on `topic` (absolute), typed by `M`.
    pub fn publisher<M: TopicType + Serialize>(&mut self, topic: &str) -> Publisher<M> {
        let qos = default_qos();
        let t = self.topic::<M>(topic, &qos);
        self.node
            .create_publisher(&t, Some(qos))
            .expect("publisher")
    }

    /// The topics of one channel of the node `/pwm_actuator` (`pw01`, ...).
    pub fn channel(&mut self, ch: &str) -> ChannelTopics {
        use pwm_actuator::ros::interface::msg::{Bool, ChannelStatus, Float64, OutputEdge, UInt16};
        let base = format!("/pwm_actuator/{ch}");
        ChannelTopics {
            duty: self.publisher::<Float64>(&format!("{base}/duty")),
            sv: self.publisher::<UInt16>(&format!("{base}/sv")),
            enable: self.publisher::<Bool>(&format!("{base}/enable")),
            edges: self.sub::<OutputEdge>(&format!("{base}/edges"), default_qos()),
            status: self.sub::<ChannelStatus>(&format!("{base}/status"), default_qos()),
            e1: self.sub::<Bool>(&format!("{base}/e1"), latched_qos()),
        }
    }

    /// Waits until `p` has a matched subscriber, then a little more so the other side has
    /// matched too.
    pub async fn matched<M: Serialize>(&self, p: &Publisher<M>) {
        let _ = tokio::time::timeout(LONG, p.wait_for_subscription(&self.node)).await;
        tokio::time::sleep(Duration::from_millis(300)).await;
    }

    /// A client of the parameter services of node `fqn`.
    pub fn params(&mut self, fqn: &str) -> Params {
        let n = &mut self.node;
        Params {
            get: client(n, fqn, "get_parameters", "GetParameters"),
            set: client(n, fqn, "set_parameters", "SetParameters"),
            set_atomically: client(
                n,
                fqn,
                "set_parameters_atomically",
                "SetParametersAtomically",
            ),
            list: client(n, fqn, "list_parameters", "ListParameters"),
            describe: client(n, fqn, "describe_parameters", "DescribeParameters"),
        }
    }
}

fn client<Req: Message + Clone + 'static, Resp: Message + 'static>(
    node: &mut Node,
    fqn: &str,
    service: &str,
    ty: &str,
) -> Client<Req, Resp> {
    let q = default_qos();
    node.create_client(
        ServiceMapping::Enhanced,
        &name(&format!("{fqn}/{service}")),
        &ServiceTypeName::new("rcl_interfaces", ty),
        q.clone(),
        q,
    )
    .expect("service client")
}

impl Drop for Ros {
    fn drop(&mut self) {
        self.spin.abort();
    }
}

/// The next message of `sub` within `timeout`.
pub async fn next<M: DeserializeOwned + 'static>(
    sub: &Subscription<M>,
    timeout: Duration,
) -> Option<M> {
    match tokio::time::timeout(timeout, sub.async_take()).await {
        Ok(Ok((m, _))) => Some(m),
        _ => None,
    }
}

/// The first message of `sub` within `timeout` for which `pred` holds.
pub async fn wait_for<M: DeserializeOwned + 'static>(
    sub: &Subscription<M>,
    timeout: Duration,
    mut pred: impl FnMut(&M) -> bool,
) -> Option<M> {
    let stream = sub.async_stream();
    futures::pin_mut!(stream);
    let fut = async {
        while let Some(r) = stream.next().await {
            if let Ok((m, _)) = r {
                if pred(&m) {
                    return Some(m);
                }
            }
        }
        None
    };
    tokio::time::timeout(timeout, fut).await.ok().flatten()
}

/// Publishes `msg` every 300 ms until a message of `sub` satisfies `pred` (commands are
/// idempotent, so a repeat does no harm); gives up after `LONG`.
pub async fn command_until<C: Serialize + Clone, M: DeserializeOwned + 'static>(
    p: &Publisher<C>,
    msg: C,
    sub: &Subscription<M>,
    mut pred: impl FnMut(&M) -> bool,
) -> Option<M> {
    let end = Instant::now() + LONG;
    while Instant::now() < end {
        let _ = p.publish(msg.clone());
        if let Some(m) = wait_for(sub, Duration::from_millis(300), &mut pred).await {
            return Some(m);
        }
    }
    None
}

/// Clients of the standard parameter services of one node.
pub struct Params {
    get: Client<GetParametersRequest, GetParametersResponse>,
    set: Client<SetParametersRequest, SetParametersResponse>,
    set_atomically: Client<SetParametersRequest, SetParametersAtomicallyResponse>,
    list: Client<ListParametersRequest, ListParametersResponse>,
    describe: Client<DescribeParametersRequest, DescribeParametersResponse>,
}

/// Calls a service, retrying (a response can be lost while discovery completes); every
/// request used in the tests may be repeated without changing the outcome.
async fn call<Req: Message + Clone + 'static, Resp: Message + 'static>(
    c: &Client<Req, Resp>,
    req: Req,
) -> Resp {
    let end = Instant::now() + LONG;
    while Instant::now() < end {
        if let Ok(Ok(r)) =
            tokio::time::timeout(Duration::from_secs(2), c.async_call_service(req.clone())).await
        {
            return r;
        }
    }
    panic!("no response from the parameter service");
}

fn raw_params(items: &[(&str, ParameterValue)]) -> SetParametersRequest {
    SetParametersRequest {
        parameter: items
            .iter()
            .map(|(n, v)| raw::Parameter {
                name: n.to_string(),
                value: v.clone().into(),
            })
            .collect(),
    }
}

impl Params {
    /// Waits until the services are matched.
    pub async fn ready(&self, ros: &Ros) {
        let _ = tokio::time::timeout(LONG, self.get.wait_for_service(&ros.node)).await;
        let _ = tokio::time::timeout(LONG, self.set.wait_for_service(&ros.node)).await;
        tokio::time::sleep(Duration::from_millis(200)).await;
    }

    /// `get_parameters`.
    pub async fn get(&self, names: &[&str]) -> Vec<ParameterValue> {
        let r = call(
            &self.get,
            GetParametersRequest {
                names: names.iter().map(|s| s.to_string()).collect(),
            },
        )
        .await;
        r.values.into_iter().map(ParameterValue::from).collect()
    }

    /// Asserts the values `get_parameters` gives for the names in `expected`.
    pub async fn assert_values(&self, expected: &[(&str, ParameterValue)]) {
        let names: Vec<&str> = expected.iter().map(|(n, _)| *n).collect();
        let want: Vec<ParameterValue> = expected.iter().map(|(_, v)| v.clone()).collect();
        assert_eq!(self.get(&names).await, want, "{names:?}");
    }

    /// `set_parameters`: (successful, reason) per parameter.
    pub async fn set(&self, items: &[(&str, ParameterValue)]) -> Vec<(bool, String)> {
        call(&self.set, raw_params(items))
            .await
            .results
            .into_iter()
            .map(|r| (r.successful, r.reason))
            .collect()
    }

    /// `set_parameters_atomically`.
    pub async fn set_atomically(&self, items: &[(&str, ParameterValue)]) -> (bool, String) {
        let r = call(&self.set_atomically, raw_params(items)).await.result;
        (r.successful, r.reason)
    }

    /// `list_parameters`.
    pub async fn list(&self, prefixes: &[&str], depth: u64) -> Vec<String> {
        call(
            &self.list,
            ListParametersRequest {
                prefixes: prefixes.iter().map(|s| s.to_string()).collect(),
                depth,
            },
        )
        .await
        .result
        .names
    }

    /// `describe_parameters`.
    pub async fn describe(&self, names: &[&str]) -> Vec<raw::ParameterDescriptor> {
        call(
            &self.describe,
            DescribeParametersRequest {
                names: names.iter().map(|s| s.to_string()).collect(),
            },
        )
        .await
        .values
    }
}

/// Asserts that `text` (a log, a help text) mentions every one of `needles`.
pub fn assert_mentions(text: &str, needles: &[&str]) {
    for s in needles {
        assert!(text.contains(s), "{s} missing from:\n{text}");
    }
}

/// The value of key `key` in a diagnostic status.
pub fn kv<'a>(d: &'a pwm_actuator::ros::interface::msg::DiagnosticStatus, key: &str) -> &'a str {
    d.values
        .iter()
        .find(|k| k.key == key)
        .map(|k| k.value.as_str())
        .unwrap_or("")
}
