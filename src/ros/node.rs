//! Start-up, wiring and shutdown of the node: parse the command line, build the parameters,
//! open the output, create the ROS entities, start the output thread and the tasks that move
//! messages between ROS and it, then wait for SIGINT/SIGTERM or a fault and stop cleanly.
//!
//! Order matters for safety: duplicate GPIO lines are refused before any hardware is opened,
//! and the panic hook holds the output's emergency handle before the output thread starts. On
//! the way out the output thread drives every output inactive and the trace files are flushed
//! before the process exits.

use crate::clock;
use crate::core::config::ShortStr;
use crate::core::valve::ValveStart;
use crate::core::ChannelConfig;
use crate::core::ValveConfig;
use crate::error::chain;
use crate::output::fault::{Fault, FAULT_ENV};
use crate::output::{
    self, install_panic_hook, AnyOutput, Backend, LineSlot, OpenError, Output, TraceFormat,
    TraceHealth, TraceSpec,
};
use crate::output_thread::{
    self, Input, OutputThread, OutputThreadError, OutputThreadOptions, Reports, WriteFault,
};
use crate::ros::config::args::{self, ArgsError, RosArgs};
use crate::ros::config::cli::{self, CliError, DEMO_ORIGIN, EXIT_FAILURE, EXIT_USAGE};
use crate::ros::config::discovery::{self, Discovery, DiscoveryError};
use crate::ros::config::logging::{self, LogConfig};
use crate::ros::config::names::{NameError, NodeIdentity, NODE_NAME};
use crate::ros::config::params::{self, ParamError, ParamStore, StartupConfig};
use crate::ros::config::security::{self, SecurityError, SecurityRequest};
use crate::ros::config::split::{self, SplitError};
use crate::ros::config::start::{domain_id_from, start_values, FaultSpecError, StartupError};
use crate::ros::config::valve::{self, ValveError, ValveLimits, ValveSpec};
use crate::ros::config::valve_state::{self, StateRecord};
use crate::ros::inbound::autotune;
use crate::ros::inbound::estop::{self, EStop};
use crate::ros::inbound::heater::{self, HeaterChannel};
use crate::ros::inbound::inputs::{self, Inputs, NOTE_QUEUE};
use crate::ros::inbound::lifecycle;
use crate::ros::inbound::node_state::NodeState;
use crate::ros::inbound::param_services;
use crate::ros::inbound::valve::{self as valve_inputs, ValveAnswers, ValveRun};
use crate::ros::interface::msg::{self, RosMessage};
use crate::ros::interface::{qos, type_hash};
use crate::ros::outbound::diagnostics::ChannelHealth;
use crate::ros::outbound::mcap_trace::{self, McapTrace, TraceKey};
use crate::ros::outbound::reporter::{ChannelPubs, Reporter, StopSignal};
use crate::ros::outbound::traces::TraceReport;
use crate::ros::outbound::valve::ValveOut;
use crate::ros::wire::endpoints::{EndpointError, Endpoints, Mw};
use crate::ros::wire::name_clash::{self, NameClash};
use crate::service::WatchdogPinger;
use log::{debug, error, info, warn};
use ros2_client::{Context, NodeName, NodeOptions};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::task::JoinHandle;

/// Why the node could not start or stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    /// The configuration is refused (command line, names, parameters, discovery, security).
    #[error(transparent)]
    Config(#[from] StartupError),
    /// The output cannot be built (trace files, line bindings, chips, busy lines).
    #[error(transparent)]
    Output(#[from] OpenError),
    /// The output thread cannot start or failed.
    #[error("output thread: {0}")]
    OutputThread(#[source] OutputThreadError),
    /// A ROS entity cannot be created.
    #[error("ROS: cannot create {what}")]
    Ros {
        /// What.
        what: String,
        /// Why (ros2-client's error).
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// An endpoint (topic, publisher, subscription, service) cannot be created.
    #[error(transparent)]
    Endpoint(#[from] EndpointError),
    /// The async runtime cannot start.
    #[error("cannot start the async runtime: {0}")]
    Runtime(#[source] std::io::Error),
    /// The systemd watchdog thread cannot start.
    #[error("cannot start the systemd watchdog thread: {0}")]
    Watchdog(#[source] std::io::Error),
}

/// Each configuration error converts into a [`NodeError`] through [`StartupError`].
macro_rules! config_from {
    ($($t:ty),*) => {$(
        impl From<$t> for NodeError {
            fn from(e: $t) -> NodeError {
                NodeError::Config(StartupError::from(e))
            }
        }
    )*};
}
config_from!(
    ArgsError,
    CliError,
    NameError,
    ParamError,
    SplitError,
    ValveError,
    DiscoveryError,
    SecurityError,
    FaultSpecError
);

impl NodeError {
    /// The process exit code for this error.
    pub fn exit_code(&self) -> i32 {
        match self {
            // Opening the output fails only on configuration: a trace path, a line bound
            // twice, a missing chip, a busy line, an offset the chip lacks, no permission.
            // Write faults come later, as `OutputThread`.
            NodeError::Config(_) | NodeError::Output(_) => EXIT_USAGE,
            _ => EXIT_FAILURE,
        }
    }
}

/// Maps a creation error of ros2-client to [`NodeError::Ros`] naming `what`.
fn ros_err(what: impl Into<String>) -> impl FnOnce(ros2_client::CreateError) -> NodeError {
    let what = what.into();
    move |e| NodeError::Ros {
        what,
        source: Box::new(e),
    }
}

/// Runs the node with the command line `args` (without the program name) until SIGINT or
/// SIGTERM; returns the process exit code (0 after a clean stop).
pub fn run(args: &[String]) -> i32 {
    let mut logger_ready = false;
    match run_inner(args, &mut logger_ready) {
        Ok(code) => code,
        Err(e) => {
            if logger_ready {
                error!("{}", chain(&e));
            } else {
                eprintln!("[ERROR] [{NODE_NAME}]: {}", logging::for_log(&chain(&e)));
            }
            e.exit_code()
        }
    }
}

fn run_inner(args: &[String], logger_ready: &mut bool) -> Result<i32, NodeError> {
    let parsed = args::parse(args)?;
    let flags = cli::parse_flags(&parsed.app)?;
    if flags.help {
        println!("{}", cli::help().trim_end());
        return Ok(0);
    }
    if flags.version {
        println!("pwm_actuator_node {}", env!("CARGO_PKG_VERSION"));
        return Ok(0);
    }
    let id = NodeIdentity::from_remaps(NODE_NAME, "/", &parsed.ros.remaps)?;
    *logger_ready = logging::init(LogConfig::from_args(&parsed.ros, NODE_NAME, &id.name)).is_ok();
    if parsed.ros.log_config_file.is_some() {
        warn!("--log-config-file is not supported; use --log-level");
    }
    let domain = domain_id_from(std::env::var("ROS_DOMAIN_ID").ok().as_deref())?;
    let sec = SecurityRequest::read(|k| std::env::var(k).ok(), parsed.ros.enclave.as_deref());
    let secure = security::decide(&sec)?.log();
    let disc = discovery::read(|k| std::env::var(k).ok())?;
    let fqn = id.fully_qualified();
    let start = start_values(&flags, &parsed.ros, &id, &fqn)?;
    let su = params::start_up(&start)?;
    for n in &su.notes {
        info!("{n}");
    }
    for w in &su.warnings {
        warn!("{w}");
    }
    let (each, more) = ignored_warnings(&su.ignored);
    for w in each {
        warn!("{w}");
    }
    // A line of its own (and its own place for the log's rate limit).
    if let Some(more) = more {
        warn!("{more}");
    }
    let cfg = StartupConfig::from_store(&su.store)?;
    let channel_names: Vec<String> = cfg.channels.iter().map(|c| c.name.clone()).collect();
    let splits = split::parse(&cfg.settings.split, &channel_names)?;
    let valves = valve::parse(&cfg.settings.valve, &channel_names, &splits)?
        .into_iter()
        .map(|v| {
            let config = su
                .store
                .valve_params(&v.name)
                .validate()
                .map_err(|source| ValveError::Settings {
                    name: ShortStr::new(&v.name),
                    source,
                })?;
            Ok((v, config))
        })
        .collect::<Result<Vec<_>, ValveError>>()?;
    let limits = valve_limits(&su.store, &valves)?;
    let state_dir =
        (!cfg.settings.state_dir.is_empty()).then(|| PathBuf::from(&cfg.settings.state_dir));
    if let Some(dir) = &state_dir {
        valve_state::check_state_dir(dir).map_err(ValveError::StateDir)?;
    }
    let (runs, records) = valve_runs(&su.store, &valves, &limits, state_dir.as_deref());
    let gpio_lines = match &cfg.output.backend {
        Backend::Gpio { lines } => Some(lines.as_slice()),
        Backend::Sim { .. } => None,
    };
    let named: Vec<(&str, &ValveLimits)> = valves
        .iter()
        .zip(&limits)
        .map(|((v, _), l)| (v.name.as_str(), l))
        .collect();
    valve::check_limits(&named, gpio_lines)?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("pwm-ros")
        .enable_all()
        .build()
        .map_err(NodeError::Runtime)?;
    let result = rt.block_on(serve(
        id,
        parsed.ros,
        su.store,
        cfg,
        (splits, runs, limits, state_dir, records),
        (domain, disc, secure),
    ));
    // Dropping the runtime would wait for every blocking task, such as a Zenoh router check
    // a stop signal cut short, which may look for a router until one is there; the lines are
    // off by now.
    rt.shutdown_timeout(std::time::Duration::from_secs(1));
    result
}

/// What each valve starts with: its wired end switches, its feedback topic; and the record of
/// its state file (from `state_dir`; a file not used is logged with the reason).
fn valve_runs(
    store: &params::ParamStore,
    valves: &[(ValveSpec, ValveConfig)],
    limits: &[ValveLimits],
    state_dir: Option<&std::path::Path>,
) -> (Vec<ValveRun>, Vec<Option<StateRecord>>) {
    let mut records = Vec::new();
    let runs = valves
        .iter()
        .zip(limits)
        .map(|((v, config), l)| {
            let values = store.valve(&v.name).cloned().unwrap_or_default();
            let feedback_topic = values.feedback_topic.trim().to_string();
            // Read now, restored once the output holds the lines low (see `restore_valves`).
            let record = state_dir.and_then(|dir| match valve_state::read_state(dir, &v.name) {
                Ok(Some(r)) => Some(r),
                Ok(None) => {
                    info!("valve {}: no state file yet", v.name);
                    None
                }
                Err(e) => {
                    warn!(
                        "valve {}: state file not used: {e}; the position is unknown",
                        v.name
                    );
                    None
                }
            });
            records.push(record);
            ValveRun {
                spec: v.clone(),
                config: *config,
                start: ValveStart {
                    restored: None,
                    switches_wired: [l.open.is_some(), l.close.is_some()],
                    feedback: !feedback_topic.is_empty(),
                },
                feedback_topic,
                process_topic: values.process_topic.trim().to_string(),
                process_temperature: values.process_type != "float64",
            }
        })
        .collect();
    (runs, records)
}

/// The restored position of each valve from its record, its bounds grown up to now: called
/// once the output holds every line low, so no drive after it is missed (logged either way).
fn restore_valves(valves: &mut [ValveRun], records: &[Option<StateRecord>]) {
    for (run, record) in valves.iter_mut().zip(records) {
        let Some(r) = record else { continue };
        let name = &run.spec.name;
        match r.restore(&run.config, valve_state::Stamp::now()) {
            Ok(p) => {
                info!(
                    "valve {name}: position restored from its state file: motor {:.2} % within \
                     {:.2}..{:.2} %; reference_at_start {}",
                    p.position_pct,
                    p.low_pct,
                    p.high_pct,
                    run.config.reference_at_start.as_str()
                );
                run.start.restored = Some(p);
            }
            Err(e) => warn!("valve {name}: state file not used: {e}; the position is unknown"),
        }
    }
}

/// The end switches of each valve, from its parameters `NAME.open_limit_line`, ...
fn valve_limits(
    store: &params::ParamStore,
    valves: &[(ValveSpec, ValveConfig)],
) -> Result<Vec<ValveLimits>, ValveError> {
    valves
        .iter()
        .map(|(v, _)| {
            let values = store.valve(&v.name).cloned().unwrap_or_default();
            Ok(ValveLimits {
                open: valve::limit_line(&v.name, "open_limit_line", &values.open_limit_line)?,
                close: valve::limit_line(&v.name, "close_limit_line", &values.close_limit_line)?,
                active_low: values.limit_active_low,
                debounce_ms: values.limit_debounce_ms.max(0) as u64,
            })
        })
        .collect()
}

/// Most "no such parameter" warnings written at start-up; the rest are counted in one line.
const MAX_IGNORED_WARNINGS: usize = 10;

/// The warnings for start-up values of parameters this node does not have (`name (origin)`),
/// bounded: a parameter file with a million unknown keys gives [`MAX_IGNORED_WARNINGS`] lines
/// and a count, not a million lines. Values set by `--demo` for a channel that does not exist
/// are not worth a warning. Returns the lines for the first ones, and the count of the rest.
fn ignored_warnings(ignored: &[String]) -> (Vec<String>, Option<String>) {
    let demo = format!("({DEMO_ORIGIN})");
    let mut relevant = ignored.iter().filter(|i| !i.ends_with(&demo));
    let out: Vec<String> = relevant
        .by_ref()
        .take(MAX_IGNORED_WARNINGS)
        .map(|i| format!("ignoring a value for {i}: this node has no such parameter"))
        .collect();
    let more = relevant.count();
    let summary = (more > 0).then(|| {
        format!(
            "ignoring {more} more value{} for parameters this node does not have",
            if more == 1 { "" } else { "s" }
        )
    });
    (out, summary)
}

/// Opens the output (`PWM_ACTUATOR_FAULT=fail-write-after=N` or `hang-write-after-ms=N`
/// makes its writes fail or hang, for the exit-path tests) and installs the panic hook with its emergency handle.
///
/// A managed node's GPIO lines are not requested here but on `configure`, through the
/// returned slot.
fn open_output(cfg: &StartupConfig) -> Result<(AnyOutput, Option<LineSlot>), NodeError> {
    let mut spec = cfg.output.clone();
    spec.fault = Fault::from_env()?;
    let (out, lines) = match cfg.settings.managed {
        true => output::open_deferred(&spec)?,
        false => (output::open(&spec)?, None),
    };
    install_panic_hook(out.emergency_off());
    Ok((out, lines))
}

/// What the node runs, for its start-up line: channels, output, traces.
fn what_runs(cfg: &StartupConfig) -> String {
    let n = cfg.channels.len();
    let output = match (&cfg.output.backend, cfg.output.trace.len()) {
        (Backend::Sim { .. }, 0) => "sim output".to_string(),
        (Backend::Sim { .. }, n) => format!("sim output, {n} trace file(s)"),
        (Backend::Gpio { .. }, 0) => "gpio output".to_string(),
        (Backend::Gpio { .. }, n) => format!("gpio output, {n} trace file(s)"),
    };
    format!("{n} channel{} ({output})", if n == 1 { "" } else { "s" })
}

/// The channels' health for the diagnostics before the output thread reports: as the core
/// creates a channel (disabled, output off, duty 0), on its GPIO line or `sim`.
fn channel_health(cfg: &StartupConfig, hardware_ids: &[String]) -> Vec<ChannelHealth> {
    let hw = hardware_ids
        .iter()
        .map(String::as_str)
        .chain(std::iter::repeat("sim"));
    cfg.channels
        .iter()
        .zip(hw)
        .map(|(c, hw)| {
            let mut h = ChannelHealth::new(&c.name, hw);
            let now = clock::monotonic_ns();
            h.status = Some(crate::core::Channel::new(c.config, now).status(now));
            h
        })
        .collect()
}

/// The MCAP trace files of `--trace` / `trace`, if any: every channel's edges and status and
/// `/diagnostics`, under the names the node publishes them on, each with the key
/// [`Reporter`] records it under.
fn mcap_trace(
    cfg: &StartupConfig,
    ep: &Endpoints<'_>,
    names: &[String],
    health: &TraceHealth,
) -> Result<Option<McapTrace>, NodeError> {
    let trace_err = |e| NodeError::Output(OpenError::Trace(e));
    let paths = TraceSpec::from_paths(&cfg.output.trace)
        .map_err(trace_err)?
        .of_format(TraceFormat::Mcap);
    if paths.is_empty() {
        return Ok(None);
    }
    let mut topics = Vec::with_capacity(2 * names.len() + 1);
    for (ch, name) in names.iter().enumerate() {
        topics.push(mcap_trace::Topic {
            key: TraceKey::Edges(ch),
            name: ep.topic_name(&format!("~/{name}/edges"))?,
            package: msg::OutputEdge::PACKAGE,
            type_name: msg::OutputEdge::NAME,
        });
        topics.push(mcap_trace::Topic {
            key: TraceKey::Status(ch),
            name: ep.topic_name(&format!("~/{name}/status"))?,
            package: msg::ChannelStatus::PACKAGE,
            type_name: msg::ChannelStatus::NAME,
        });
    }
    topics.push(mcap_trace::Topic {
        key: TraceKey::Diagnostics,
        name: ep.topic_name("/diagnostics")?,
        package: msg::DiagnosticArray::PACKAGE,
        type_name: msg::DiagnosticArray::NAME,
    });
    for p in &paths {
        info!(
            "recording edges, status and /diagnostics as ROS messages to {}",
            p.display()
        );
    }
    McapTrace::create(&paths, topics, cfg.output.trace_limit, health)
        .map(Some)
        .map_err(trace_err)
}

/// Starts the output thread on the opened output.
fn start_output_thread(cfg: &StartupConfig, output: AnyOutput) -> Result<OutputThread, NodeError> {
    let configs: Vec<ChannelConfig> = cfg.channels.iter().map(|c| c.config).collect();
    let opts = OutputThreadOptions {
        rt_priority: cfg.settings.rt_priority,
        heartbeat_half_period_ns: cfg.heartbeat_hz().map(|hz| (5e8 / hz).round() as u64),
        // A managed node starts unconfigured: every line held inactive.
        start_held: cfg.settings.managed,
        bank: cfg.settings.bank,
        // The tick is for the systemd watchdog's pinger alone; without one the thread sleeps
        // until its next edge, request or status resend (a snapshot the full report queue
        // refused, e.g. the e-stop's after the thread was stopped behind a full queue:
        // test_an_estop_acts_while_the_output_thread_is_stopped_behind_a_full_queue).
        liveness_tick_ns: crate::service::watchdog_interval()
            .map(|_| output_thread::LIVENESS_TICK_NS),
        ..OutputThreadOptions::default()
    };
    let started = output_thread::spawn(configs, output, opts).map_err(NodeError::OutputThread)?;
    if let Some(Fault::PanicAfterMs(ms)) = Fault::from_env()? {
        warn!("{FAULT_ENV}: panicking in {ms} ms");
        std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(ms));
            panic!("{FAULT_ENV}: injected panic after {ms} ms");
        });
    }
    Ok(started)
}

/// Moves reports from the output thread to ROS until `quit` is set or the output thread ends.
/// A plain thread that owns the reporter: it sleeps on The output thread's eventfd ([`Reports::wait`])
/// or until the reporter's next periodic message, and publishes, which never waits for a
/// subscriber. It hands the reporter back when it ends: its publishers must outlive the last
/// messages they were given (a DDS writer dropped at once can take its last sample with it —
/// the ERROR of an output fault), so the caller drops it late in the shutdown.
fn pump(
    reporter: Reporter,
    mut reports: Reports,
    quit: Arc<AtomicBool>,
    sig: Arc<StopSignal>,
) -> Reporter {
    // Both callbacks act on the reporter, one after the other on this thread.
    let reporter = std::cell::RefCell::new(reporter);
    // What one batch publishes (an edge with its status, the two channels' rises, the periodic
    // status with /diagnostics) is handed to the DDS event loop with one wake-up at the end of
    // the batch, instead of one wake-up each: the loop's thread woke up to four times for one
    // batch. A message waits at most until its batch ends (a batch is the reports queued when
    // this thread woke, and its `after_batch`), and never more than the first write 1 ms
    // after it (`rustdds::hold_writer_wakes`).
    let hold = std::cell::RefCell::new(None);
    let ended = reports.serve(
        || quit.load(Ordering::SeqCst),
        |r| {
            hold.borrow_mut()
                .get_or_insert_with(rustdds::hold_writer_wakes);
            reporter.borrow_mut().handle(r)
        },
        |r| {
            let _batch = hold
                .borrow_mut()
                .take()
                .unwrap_or_else(rustdds::hold_writer_wakes);
            reporter.borrow_mut().after_batch(r.dropped())
        },
    );
    drop(hold);
    // What the output thread reported before the stop (the lines going off under the stop's
    // hold) is still published and traced.
    while let Some(r) = reports.try_recv() {
        reporter.borrow_mut().handle(r);
    }
    if ended {
        sig.stop.notify_one();
    }
    reporter.into_inner()
}

/// The split-range pairs, the valves, their end switches, the state directory and the valves'
/// state records, as the start-up made them.
type PairsAndValves = (
    Vec<split::SplitPair>,
    Vec<ValveRun>,
    Vec<ValveLimits>,
    Option<PathBuf>,
    Vec<Option<StateRecord>>,
);

async fn serve(
    id: NodeIdentity,
    ros: RosArgs,
    store: ParamStore,
    cfg: StartupConfig,
    (splits, mut valves, limits, state_dir, records): PairsAndValves,
    (domain, disc, secure): (u16, Discovery, Option<PathBuf>),
) -> Result<i32, NodeError> {
    let remaps = &ros.remaps;
    let fqn = id.fully_qualified();
    // Signals are caught before any output exists, so no stop request can ever kill the
    // process with a line left on.
    let mut signals = StopSignals::catch();
    // The output first: configuration and hardware errors stop the node before it joins ROS.
    let (output, line_slot) = open_output(&cfg)?;
    restore_valves(&mut valves, &records);
    let specs: Vec<ValveSpec> = valves.iter().map(|r| r.spec.clone()).collect();
    let switches = valve_inputs::open_switches(&specs, &limits)
        .map_err(|e| NodeError::Output(OpenError::Switch(e)))?;
    let hardware_ids = cfg.output.hardware_ids();

    // Before any reader exists: what the node keeps of an input is bounded by its size.
    rustdds::set_max_received_sample_size(qos::MAX_SAMPLE_BYTES);
    // Before any endpoint exists: each announces the type hash of its type (REP-2016).
    match type_hash::announce() {
        Ok(n) => debug!("type hashes announced for {n} endpoint types"),
        Err(e) => warn!("endpoints announce no type hash: {e}"),
    }
    let mut tasks: Vec<JoinHandle<()>> = Vec::new();
    let mut side = if disc.zenoh {
        for w in &disc.warnings {
            warn!("{w}");
        }
        // The router check may look for a router until one is there
        // (`ZENOH_ROUTER_CHECK_ATTEMPTS=0`): a stop signal meanwhile ends the node at once,
        // its lines never driven (the output, dropped, leaves them off).
        tokio::select! {
            side = RosSide::zenoh(&id, &ros, domain, secure.as_deref()) => side?,
            got = signals.any() => {
                info!("{got} while joining Zenoh: stopping; the lines were never driven");
                return Ok(0);
            }
        }
    } else {
        RosSide::dds(&id, &ros, domain, &disc, secure.as_deref(), &mut tasks)?
    };

    let names: Vec<String> = cfg.channels.iter().map(|c| c.name.clone()).collect();
    let mut ep = Endpoints {
        mw: side.mw(),
        id: &id,
        remaps,
    };
    let (pubs, diagnostics) = ChannelPubs::create(&mut ep, &names)?;
    let traces = output.trace_health();
    let mcap = mcap_trace(&cfg, &ep, &names, &traces)?;
    let valve_outs: Vec<(String, String, String)> = valves
        .iter()
        .map(|r| {
            (
                r.spec.name.clone(),
                names[r.spec.open].clone(),
                names[r.spec.close].clone(),
            )
        })
        .collect();
    let mut valve_pubs = ValveOut::create(&mut ep, &valve_outs)?;
    let valve_answers = Arc::new(ValveAnswers::new(valves.len()));
    for (k, (out, run)) in valve_pubs.iter_mut().zip(&valves).enumerate() {
        out.answer_to(k, Arc::clone(&valve_answers));
        if let Some(dir) = &state_dir {
            out.keep_state(dir.clone(), run.config);
        }
    }
    let param_events = side.parameter_events()?;

    let started = start_output_thread(&cfg, output)?;
    let OutputThread {
        requests,
        reports,
        handle,
    } = started;
    let (notes_tx, notes_rx) = std::sync::mpsc::sync_channel(NOTE_QUEUE);
    let health = channel_health(&cfg, &hardware_ids);
    let stop_signal = Arc::new(StopSignal::default());
    let node_state = Arc::new(NodeState::from_store(&store));
    let mut reporter = Reporter::new(
        id.name.clone(),
        health,
        pubs,
        diagnostics,
        notes_rx,
        cfg.settings.status_rate_hz,
        cfg.settings.edge_log_rate,
        Arc::clone(&stop_signal),
        Arc::clone(&node_state),
    );
    if let Some(mcap) = mcap {
        reporter.record_to(mcap);
    }
    reporter.watch_traces(TraceReport::new(traces.clone()));
    reporter.set_valves(valve_pubs);
    let estop = Arc::new(EStop::new(cfg.settings.estop_timeout_ms));
    let inputs = Arc::new(Inputs::new(
        fqn.clone(),
        store,
        requests,
        param_events,
        notes_tx,
        Arc::clone(&node_state),
    ));
    inputs.announce_declared();

    let mut ep = Endpoints {
        mw: side.mw(),
        id: &id,
        remaps,
    };
    tasks.extend(inputs::listen_channels(&mut ep, &inputs, &names)?);
    tasks.extend(inputs::listen_splits(&mut ep, &inputs, &splits)?);
    tasks.extend(valve_inputs::listen_valves(
        &mut ep,
        &inputs,
        &valves,
        &valve_answers,
    )?);
    valve_inputs::spawn_switch_readers(switches, &inputs);
    let heaters: Vec<HeaterChannel> = cfg
        .channels
        .iter()
        .enumerate()
        .filter(|(_, c)| !c.feedback_topic.is_empty())
        .map(|(channel, c)| HeaterChannel {
            channel,
            name: c.name.clone(),
            feedback_topic: c.feedback_topic.clone(),
            feedforward_topic: c.feedforward_topic.clone(),
            ambient_topic: c.ambient_topic.clone(),
        })
        .collect();
    tasks.extend(heater::listen_heaters(&mut ep, &inputs, &heaters)?);
    tasks.extend(autotune::serve_autotune(&mut ep, &inputs, &heaters)?);
    if cfg.settings.heater_fault_latches_estop {
        let _ = inputs.send(0, Input::HeaterEstop(true));
    }
    tasks.extend(param_services::spawn(&mut ep, &inputs)?);
    tasks.extend(estop::spawn(&mut ep, &inputs, &estop)?);
    if cfg.settings.managed {
        let cell = node_state.lifecycle_cell();
        tasks.extend(lifecycle::serve(&mut ep, &inputs, line_slot, cell)?);
    }
    let quit = Arc::new(AtomicBool::new(false));
    // The report thread sleeps until something is due: whatever it must see sooner wakes it.
    let wake_reports = reports.waker();
    node_state.set_reporter_waker(wake_reports.clone());
    {
        let w = wake_reports.clone();
        traces.on_change(move || w.wake());
    }
    let pump_thread = {
        let (q, sig) = (Arc::clone(&quit), Arc::clone(&stop_signal));
        std::thread::Builder::new()
            .name("pwm-reports".into())
            .spawn(move || pump(reporter, reports, q, sig))
            .map_err(NodeError::Runtime)?
    };

    inputs.start_up(&cfg.channels);
    info!("{fqn} running: {}, ROS domain {domain}", what_runs(&cfg));

    // Lines requested, output thread running, ROS side up: systemd's Type=notify start ends.
    crate::service::ready();
    let pinger = match crate::service::watchdog_interval() {
        Some(interval) => match WatchdogPinger::start(handle.liveness(), interval) {
            Ok(p) => Some(p),
            Err(e) => return Err(NodeError::Watchdog(e)),
        },
        None => None,
    };

    let reason = signals.wait(&stop_signal).await;
    info!("{reason}: stopping");
    logging::shutting_down();
    crate::service::stopping();
    // Every line off and held off now, not after the ROS side is torn down: no pulse starts
    // while the node stops. A thread that does not take it in time has the outputs switched
    // off by the emergency handle.
    if let Err(e) = inputs.safety().take_async(Input::Live(false)).await {
        warn!("the hold of the lines at stop was not taken: {e}");
    }
    drop(pinger);
    for t in &tasks {
        t.abort();
    }
    quit.store(true, Ordering::SeqCst);
    wake_reports.wake();
    // Joined on tokio's blocking pool, as the output thread below: no async worker waits.
    let reporter = match tokio::task::spawn_blocking(move || pump_thread.join()).await {
        Ok(Ok(r)) => Some(r),
        _ => {
            warn!("the report thread panicked");
            None
        }
    };
    // Drives every output inactive, flushes the traces, joins the output thread (up to
    // SHUTDOWN_WAIT, 2 s, for a thread stuck in a write).
    let fault = handle.fault();
    let result = handle.shutdown_async().await;
    for t in tasks {
        let _ = t.await;
    }
    drop(inputs);
    // The reporter's publishers go with the node, after the shutdown: their last samples (the
    // diagnostics of a fault) have had that long to leave.
    drop(reporter);
    side.close().await;
    let faulted = output_fault(fault.as_ref(), &result);
    match result {
        Ok(()) if !faulted => {
            info!("all outputs off; bye");
            Ok(0)
        }
        Ok(()) => Ok(EXIT_FAILURE),
        Err(e) => {
            let name = e.channel().and_then(|i| cfg.channels.get(i));
            match name {
                Some(c) => error!("output thread: {}: {}", c.name, chain(&e)),
                None => error!("output thread: {}", chain(&e)),
            }
            Ok(EXIT_FAILURE)
        }
    }
}

/// The node's ROS side on the middleware `RMW_IMPLEMENTATION` chose (config::discovery): its
/// DDS participant and node, or its Zenoh session. Everything else of the node is made on it
/// through [`Endpoints`] and knows no middleware. One value for the node's whole life: its
/// size does not matter.
#[allow(clippy::large_enum_variant)]
enum RosSide {
    /// DDS: the context, the node and the task that spins it.
    Dds {
        context: Context,
        node: ros2_client::Node,
        spin_task: JoinHandle<()>,
    },
    /// Zenoh: the session with the node's token.
    #[cfg(feature = "zenoh")]
    Zenoh(crate::ros::wire::zenoh_session::ZenohNode),
}

impl RosSide {
    /// The DDS participant for `domain` (discovery `disc`, secured with `secure`), the node
    /// with its `/rosout` (unless `--ros-args -p` turned it off) and spinner, and the watch for
    /// another node of this name, pushed to `tasks`.
    fn dds(
        id: &NodeIdentity,
        ros: &RosArgs,
        domain: u16,
        disc: &Discovery,
        secure: Option<&std::path::Path>,
        tasks: &mut Vec<JoinHandle<()>>,
    ) -> Result<RosSide, NodeError> {
        let fqn = id.fully_qualified();
        let participant = disc
            .participant(domain, secure)
            .map_err(|e| ros_err("the DDS participant")(e.into()))?;
        let context = Context::from_domain_participant(participant)
            .map_err(ros_err("the DDS participant"))?;
        disc.log(disc.confine()?);
        let node_name = NodeName::new(&id.namespace, &id.name).map_err(|e| NodeError::Ros {
            what: format!("node {fqn}"),
            source: Box::new(e),
        })?;
        let mut node = context
            .new_node(
                node_name,
                NodeOptions::new()
                    .enable_rosout(ros.rosout_logs != Some(false))
                    .start_parameter_services(false),
            )
            .map_err(|e| NodeError::Ros {
                what: format!("node {fqn}"),
                source: Box::new(e),
            })?;
        logging::attach_rosout(node.logging_handle());
        let spinner = node.spinner().map_err(ros_err("the node spinner"))?;
        let spin_task = tokio::spawn(async move {
            if let Err(e) = spinner.spin().await {
                warn!("ROS spinner stopped: {e}");
            }
        });
        if let Some(events) = node.status_receiver() {
            let clash = NameClash::new(&context.domain_participant(), fqn.clone());
            tasks.push(tokio::spawn(name_clash::watch(events, clash)));
        }
        Ok(RosSide::Dds {
            context,
            node,
            spin_task,
        })
    }

    /// The Zenoh session for `domain` with rmw_zenoh's configuration from the environment,
    /// its router check and the node's token. Security on Zenoh is the session
    /// configuration's (`ZENOH_SESSION_CONFIG_URI`, as zenoh_security_tools writes it): an
    /// SROS2 enclave asked for is refused.
    #[cfg(feature = "zenoh")]
    async fn zenoh(
        id: &NodeIdentity,
        ros: &RosArgs,
        domain: u16,
        secure: Option<&std::path::Path>,
    ) -> Result<RosSide, NodeError> {
        use crate::ros::config::zenoh as zcfg;
        use crate::ros::wire::zenoh_session::{config, NodeSession, ZenohNode};
        let failed = |e: String| NodeError::Ros {
            what: "the Zenoh session".into(),
            source: e.into(),
        };
        if let Some(enclave) = secure {
            return Err(failed(format!(
                "DDS security (enclave {}) does not apply on Zenoh: secure the session with \
                 its own configuration (ZENOH_SESSION_CONFIG_URI, e.g. from \
                 zenoh_security_tools) and run without ROS_SECURITY_ENABLE",
                enclave.display()
            )));
        }
        let settings = zcfg::read(|k| std::env::var(k).ok()).map_err(|e| failed(e.to_string()))?;
        for w in &settings.warnings {
            warn!("{w}");
        }
        let text = zcfg::config_text(&settings).map_err(|e| failed(e.to_string()))?;
        let cfg = config(&text, &settings, |w| warn!("{w}")).map_err(|e| failed(e.to_string()))?;
        let hashes = type_hash::type_hashes().map_err(|e| failed(e.to_string()))?;
        let (namespace, name) = (id.namespace.clone(), id.name.clone());
        let fqn = id.fully_qualified();
        // The session's calls block (the router check sleeps between attempts).
        let session = tokio::task::spawn_blocking(move || {
            let mut session = NodeSession::open(
                cfg,
                &settings,
                u32::from(domain),
                "/",
                &namespace,
                &name,
                |w| warn!("{w}"),
            )?;
            session.watch_name_clash(&fqn, |w| warn!("{w}"))?;
            Ok::<_, crate::ros::wire::zenoh_session::SessionError>(session)
        })
        .await
        .map_err(|e| failed(e.to_string()))?
        .map_err(|e| failed(e.to_string()))?;
        if ros.rosout_logs != Some(false) {
            use crate::ros::wire::zenoh_pub::ZenohPublisher;
            let rosout = ZenohPublisher::<ros2_client::log::Log>::of_type(
                &session,
                "/rosout",
                "rcl_interfaces/msg/Log",
                qos::rosout(),
                &hashes,
            )
            .map_err(|e| failed(e.to_string()))?;
            // Zenoh's put of a keep-last sample drops rather than waits (zenoh_pub), so a
            // record logged on any thread is sent without blocking it.
            logging::attach_rosout_sink(Box::new(move |r: logging::RosoutRecord<'_>| {
                let _ = rosout.publish(&ros2_client::log::Log {
                    stamp: ros2_client::builtin_interfaces::Time::now(),
                    level: logging::ros_level(r.level),
                    name: r.name.to_string(),
                    msg: r.text.to_string(),
                    file: r.file.to_string(),
                    function: r.function.to_string(),
                    line: r.line,
                });
            }));
        }
        info!(
            "on Zenoh: session {}, {}",
            session.zid,
            match session.router {
                zcfg::RouterCheckOutcome::Seen(_) => "connected to a router",
                zcfg::RouterCheckOutcome::NotSeen(_) => "no router seen",
                zcfg::RouterCheckOutcome::Skipped => "router check skipped",
            }
        );
        Ok(RosSide::Zenoh(ZenohNode { session, hashes }))
    }

    #[cfg(not(feature = "zenoh"))]
    async fn zenoh(
        _id: &NodeIdentity,
        _ros: &RosArgs,
        _domain: u16,
        _secure: Option<&std::path::Path>,
    ) -> Result<RosSide, NodeError> {
        unreachable!("config::discovery refuses Zenoh without the zenoh feature")
    }

    /// The middleware for [`Endpoints`].
    fn mw(&mut self) -> Mw<'_> {
        match self {
            RosSide::Dds { node, .. } => Mw::Dds(node),
            #[cfg(feature = "zenoh")]
            RosSide::Zenoh(z) => Mw::Zenoh(z),
        }
    }

    /// The publisher of `/parameter_events`.
    fn parameter_events(
        &mut self,
    ) -> Result<
        crate::ros::wire::mw::Publisher<ros2_client::parameters::raw::ParameterEvent>,
        NodeError,
    > {
        match self {
            RosSide::Dds { context, node, .. } => node
                .create_publisher(&context.get_parameter_events_topic(), None)
                .map(crate::ros::wire::mw::Publisher::Dds)
                .map_err(ros_err("publisher /parameter_events")),
            #[cfg(feature = "zenoh")]
            RosSide::Zenoh(z) => crate::ros::wire::zenoh_pub::ZenohPublisher::of_type(
                &z.session,
                "/parameter_events",
                "rcl_interfaces/msg/ParameterEvent",
                qos::parameter_events(),
                &z.hashes,
            )
            .map(crate::ros::wire::mw::Publisher::Zenoh)
            .map_err(|e| NodeError::Ros {
                what: "publisher /parameter_events".into(),
                source: Box::new(e),
            }),
        }
    }

    /// Leaves ROS: the node and its spinner (up to 1 s), then the participant; or the token
    /// and the session.
    async fn close(self) {
        match self {
            RosSide::Dds {
                context,
                node,
                spin_task,
            } => {
                // Dropping the node tells its spinner to stop.
                drop(node);
                let _ = tokio::time::timeout(Duration::from_secs(1), spin_task).await;
                drop(context);
            }
            #[cfg(feature = "zenoh")]
            RosSide::Zenoh(z) => {
                let _ = tokio::task::spawn_blocking(move || z.session.close()).await;
            }
        }
    }
}

fn output_fault(fault: Option<&WriteFault>, result: &Result<(), OutputThreadError>) -> bool {
    if let Some(f) = fault {
        error!("output fault: {}", f.error);
    }
    fault.is_some() || result.is_err()
}

/// The signals that stop the node cleanly. SIGHUP (a closed terminal or SSH session) and
/// SIGQUIT are caught too: their default action would end the process without switching the
/// outputs off.
struct StopSignals(Vec<(&'static str, tokio::signal::unix::Signal)>);

impl StopSignals {
    fn catch() -> StopSignals {
        use tokio::signal::unix::{signal, SignalKind};
        let kinds = [
            ("SIGINT", SignalKind::interrupt()),
            ("SIGTERM", SignalKind::terminate()),
            ("SIGHUP", SignalKind::hangup()),
            ("SIGQUIT", SignalKind::quit()),
        ];
        StopSignals(
            kinds
                .into_iter()
                .filter_map(|(name, kind)| match signal(kind) {
                    Ok(s) => Some((name, s)),
                    Err(e) => {
                        warn!("cannot catch {name}: {e}");
                        None
                    }
                })
                .collect(),
        )
    }

    /// Waits for a stop signal; says which. Never ends with no signal caught.
    async fn any(&mut self) -> String {
        let signals = &mut self.0;
        if signals.is_empty() {
            // select_all needs at least one future.
            return std::future::pending().await;
        }
        let recv = signals
            .iter_mut()
            .map(|(name, s)| Box::pin(async move { s.recv().await.map(|_| *name) }));
        futures::future::select_all(recv)
            .await
            .0
            .unwrap_or("signal stream closed")
            .to_string()
    }

    /// Waits for a stop signal or the reporter asking to stop; says which.
    async fn wait(&mut self, stop: &StopSignal) -> String {
        tokio::select! {
            got = self.any() => got,
            _ = stop.stop.notified() => {
                if stop.fault.load(Ordering::SeqCst) {
                    "output fault".to_string()
                } else {
                    "the output thread ended".to_string()
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::TraceError;

    #[test]
    fn domain_ids() {
        assert_eq!(domain_id_from(None).unwrap(), 0);
        assert_eq!(domain_id_from(Some("")).unwrap(), 0);
        assert_eq!(domain_id_from(Some("42")).unwrap(), 42);
        assert_eq!(domain_id_from(Some(" 7 ")).unwrap(), 7);
        for bad in ["233", "-1", "abc", "1.5", "70000"] {
            let e = domain_id_from(Some(bad)).unwrap_err();
            assert!(e.to_string().contains(bad), "{e}");
            assert_eq!(NodeError::from(e).exit_code(), EXIT_USAGE);
        }
    }

    #[test]
    fn unknown_start_up_values_give_a_bounded_warning() {
        let few: Vec<String> = vec!["a (-p)".into(), "pw03.duty (--demo)".into()];
        assert_eq!(
            ignored_warnings(&few),
            (
                vec!["ignoring a value for a (-p): this node has no such parameter".to_string()],
                None
            )
        );
        let many: Vec<String> = (0..1_500_000)
            .map(|i| format!("k{i} (--params-file big.yaml)"))
            .collect();
        let (each, more) = ignored_warnings(&many);
        assert_eq!(each.len(), MAX_IGNORED_WARNINGS);
        assert_eq!(
            more.as_deref(),
            Some("ignoring 1499990 more values for parameters this node does not have")
        );
    }

    #[test]
    fn error_chains_are_joined_once() {
        let e = NodeError::Output(OpenError::Trace(TraceError::UnknownExtension {
            path: "x.txt".into(),
        }));
        assert_eq!(
            chain(&e),
            "trace: trace file x.txt: unknown extension, expected .vcd, .csv or .mcap"
        );
    }
}
