//! `pwm_actuator_node sim-valve`: a simulated three-point valve actuator as its own process and
//! ROS participant (part of the binary only).
//!
//! It listens to the `~/<ch>/edges` of a valve's two channels (the node's real edges, stamped
//! with the time each write returned) and moves a true position ([`TrueValve`]) with its own
//! travel times — which may differ from the ones the node is configured with —, a start lag, a
//! coast after each fall and play between motor and stem, between hard end stops, and
//! publishes it as `std_msgs/Float64` (percent, 0 = closed) at a fixed rate. It can be made
//! faulty: a stalled motor, an end switch stuck active. Beside the truth it publishes what
//! sensors would tell the node: an analog position feedback with noise (`--feedback-topic`,
//! for `NAME.feedback_topic`) and its two end switches (`std_msgs/Bool`, closed within
//! `--switch-at-pct` of their end). With `--record` it writes every edge and every published
//! position to a CSV file (`t_s,kind,value`, wall-clock seconds; kind `open`, `close` or
//! `true`) for the picture of docs/valve.md.
//!
//! With `--mix` the valve is a mixing valve in front of a temperature sensor: the core's
//! [`Mixing`] plant (hot and cold supply, dead time, first-order lag, seeded noise) runs on
//! the valve's true position — not the node's estimate — every 100 ms, and its sensor is
//! published as `sensor_msgs/Temperature` on `--mix-topic` at `--mix-rate-hz`, for a valve
//! under `NAME.control` `pid`. The hot supply steps at `--hot-step-after` (to `--hot-step-to`)
//! or whenever a `std_msgs/Float64` arrives on `--hot-topic`. `--setpoint` makes it act as the
//! user too (the setpoint once a second on `~/valve/NAME/setpoint`), and `--print-every` prints
//! the temperature and the true position. The record then also holds kinds `reading` (°C
//! published), `mixed` (°C, the true mixed water) and `hot` (°C, each supply change).

use crate::sim_ros::{self, make_topic, within, OptionOutOfRange, SimError};
use clap::{ArgAction, Args, FromArgMatches};
use futures::StreamExt;
use pwm_actuator::clock;
use pwm_actuator::core::valve::mixing::{Mixing, MixingParams};
use pwm_actuator::core::valve::truth::{TrueValve, TruthParams};
use pwm_actuator::ros::interface::msg::{self, Header, RosMessage};
use ros2_client::builtin_interfaces::Time;
use ros2_client::qos::{History, Reliability};
use ros2_client::QosProfile;
use std::io::Write;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Options of `pwm_actuator_node sim-valve`.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct SimValveOptions {
    /// The node whose channels drive the valve
    #[arg(long, value_name = "NODE", default_value = "/pwm_actuator")]
    pub node: String,
    /// The channel whose line drives the valve open
    #[arg(long, value_name = "CH", default_value = "pw01")]
    pub open: String,
    /// The channel whose line drives the valve closed
    #[arg(long, value_name = "CH", default_value = "pw02")]
    pub close: String,
    /// The true travel time from closed to open, ms, 100..3600000
    #[arg(long, value_name = "MS", default_value_t = 60_000.0)]
    pub travel_open_ms: f64,
    /// The true travel time from open to closed, ms, 100..3600000
    #[arg(long, value_name = "MS", default_value_t = 60_000.0)]
    pub travel_close_ms: f64,
    /// Where the valve starts, percent 0..100 (unknown to the node)
    #[arg(long, value_name = "PCT", default_value_t = 37.0)]
    pub start_pct: f64,
    /// From a line's rise until the motor moves, ms, 0..10000
    #[arg(long, value_name = "MS", default_value_t = 0.0)]
    pub start_lag_ms: f64,
    /// The motor runs on this long after a fall, ms, 0..10000
    #[arg(long, value_name = "MS", default_value_t = 0.0)]
    pub coast_ms: f64,
    /// Play between motor and stem, percent of the stroke, 0..10
    #[arg(long, value_name = "PCT", default_value_t = 0.0)]
    pub backlash_pct: f64,
    /// The motor does not turn (a dead motor, a blown fuse), after --stall-after-s
    #[arg(long)]
    pub stalled: bool,
    /// With --stalled: the motor stops turning this many seconds after the start
    #[arg(long, value_name = "S", default_value_t = 0.0)]
    pub stall_after_s: f64,
    /// The open end switch is stuck active
    #[arg(long)]
    pub stuck_open_switch: bool,
    /// The close end switch is stuck active
    #[arg(long)]
    pub stuck_close_switch: bool,
    /// An end switch closes this close to its end, percent, 0..10
    #[arg(long, value_name = "PCT", default_value_t = 0.5)]
    pub switch_at_pct: f64,
    /// Publish the position with noise here (std_msgs/Float64, percent), as an analog feedback
    #[arg(long, value_name = "TOPIC")]
    pub feedback_topic: Option<String>,
    /// Uniform noise of the feedback, ± percent, 0..10
    #[arg(long, value_name = "PCT", default_value_t = 0.0)]
    pub feedback_noise_pct: f64,
    /// The end switches are published on TOPIC/open and TOPIC/close (std_msgs/Bool)
    #[arg(long, value_name = "TOPIC", default_value = "/sim_valve/switch")]
    pub switch_topic: String,
    /// The topic the true position is published on (std_msgs/Float64, percent)
    #[arg(long, value_name = "TOPIC", default_value = "/sim_valve/position")]
    pub topic: String,
    /// Positions published per second, 0.1..1000
    #[arg(long, value_name = "HZ", default_value_t = 20.0)]
    pub rate_hz: f64,
    /// Write every edge and published position to this CSV file
    #[arg(long, value_name = "FILE.csv")]
    pub record: Option<PathBuf>,
    /// Stop after this many seconds (0: run until interrupted)
    #[arg(long, value_name = "S", default_value_t = 0.0)]
    pub duration: f64,
    /// A mixing valve: publish the mixed water's temperature behind the true position
    #[arg(long)]
    pub mix: bool,
    /// With --mix: the topic of the mixed water's temperature (sensor_msgs/Temperature, best
    /// effort)
    #[arg(long, value_name = "TOPIC", default_value = "/mixing/temperature")]
    pub mix_topic: String,
    /// With --mix: readings per second, 0.1..10 (the plant itself advances every 100 ms)
    #[arg(long, value_name = "HZ", default_value_t = 2.0)]
    pub mix_rate_hz: f64,
    /// With --mix: the hot supply, °C, -50..200
    #[arg(
        long,
        value_name = "C",
        default_value_t = 70.0,
        allow_negative_numbers = true
    )]
    pub hot: f64,
    /// With --mix: the cold supply (or the return), °C, -50..200
    #[arg(
        long,
        value_name = "C",
        default_value_t = 15.0,
        allow_negative_numbers = true
    )]
    pub cold: f64,
    /// With --mix: the time constant of the mixed water at the sensor, s, 0.1..10000
    #[arg(long, value_name = "S", default_value_t = 120.0)]
    pub tau: f64,
    /// With --mix: the dead time from the valve to the sensor, s, 0..600
    #[arg(long, value_name = "S", default_value_t = 20.0)]
    pub dead_time: f64,
    /// With --mix: the sensor's peak noise, °C (uniform), 0..10
    #[arg(long, value_name = "C", default_value_t = 0.5)]
    pub noise: f64,
    /// With --mix: the noise generator's seed (a run repeats exactly)
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub seed: u64,
    /// With --mix: the hot supply steps to this temperature at --hot-step-after, °C, -50..200
    #[arg(long, value_name = "C", allow_negative_numbers = true)]
    pub hot_step_to: Option<f64>,
    /// With --hot-step-to: this many seconds after the start, 0..10000000
    #[arg(long, value_name = "S", default_value_t = 0.0)]
    pub hot_step_after: f64,
    /// With --mix: a std_msgs/Float64 here sets the hot supply at run time, °C, -50..200
    /// (others are refused and counted)
    #[arg(long, value_name = "TOPIC", default_value = "/mixing/hot")]
    pub hot_topic: String,
    /// With --mix: also act as the user, publishing this setpoint (°C) on
    /// NODE/valve/VALVE/setpoint once a second
    #[arg(long, value_name = "C", allow_negative_numbers = true)]
    pub setpoint: Option<f64>,
    /// The valve's name, for --setpoint
    #[arg(long, value_name = "NAME", default_value = "mix")]
    pub valve: String,
    /// With --mix: print the temperature and the true position this often, s (0: never)
    #[arg(long, value_name = "S", default_value_t = 0.0)]
    pub print_every: f64,
}

/// The `sim-valve` subcommand, for the whole command line.
pub fn command() -> clap::Command {
    SimValveOptions::augment_args(clap::Command::new("sim-valve"))
        .about(
            "A simulated three-point valve actuator driven by two channels' ~/<ch>/edges, with \
             its own travel times and hard end stops, publishing its true position \
             (std_msgs/Float64, %). Its own ROS participant (node sim_valve).",
        )
        .disable_help_flag(true)
        .arg(
            clap::Arg::new("help")
                .short('h')
                .long("help")
                .action(ArgAction::Help)
                .help("Print help"),
        )
}

/// Parses the subcommand's matches.
pub fn options(m: &clap::ArgMatches) -> Result<SimValveOptions, clap::Error> {
    SimValveOptions::from_arg_matches(m)
}

/// Why the simulated valve's options are refused (exit status 2).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OptionError {
    /// A value outside its range.
    #[error(transparent)]
    OutOfRange(#[from] OptionOutOfRange),
    /// A supply temperature outside [`SUPPLY_C`].
    #[error("--{option} {source}")]
    Supply {
        /// The option, without its dashes.
        option: &'static str,
        /// The value and the range.
        #[source]
        source: SupplyOutOfRange,
    },
    /// An option that only the mixing plant uses, without `--mix`.
    #[error("--{option} needs --mix")]
    NeedsMix {
        /// The option, without its dashes.
        option: &'static str,
    },
}

/// Why the options are refused.
fn check(o: &SimValveOptions) -> Result<(), OptionError> {
    let within_supply = |option: &'static str, c: f64| {
        supply(c).map_err(|source| OptionError::Supply { option, source })
    };
    within("travel-open-ms", o.travel_open_ms, 100.0, 3_600_000.0)?;
    within("travel-close-ms", o.travel_close_ms, 100.0, 3_600_000.0)?;
    within("start-pct", o.start_pct, 0.0, 100.0)?;
    within("start-lag-ms", o.start_lag_ms, 0.0, 10_000.0)?;
    within("coast-ms", o.coast_ms, 0.0, 10_000.0)?;
    within("backlash-pct", o.backlash_pct, 0.0, 10.0)?;
    within("stall-after-s", o.stall_after_s, 0.0, 1e7)?;
    within("switch-at-pct", o.switch_at_pct, 0.0, 10.0)?;
    within("feedback-noise-pct", o.feedback_noise_pct, 0.0, 10.0)?;
    within("rate-hz", o.rate_hz, 0.1, 1000.0)?;
    within("duration", o.duration, 0.0, 1e7)?;
    within("mix-rate-hz", o.mix_rate_hz, 0.1, MIX_TICKS_PER_S)?;
    within_supply("hot", o.hot)?;
    within_supply("cold", o.cold)?;
    within("tau", o.tau, 0.1, 10_000.0)?;
    within("dead-time", o.dead_time, 0.0, 600.0)?;
    within("noise", o.noise, 0.0, 10.0)?;
    if let Some(c) = o.hot_step_to {
        within_supply("hot-step-to", c)?;
    }
    within("hot-step-after", o.hot_step_after, 0.0, 1e7)?;
    within("print-every", o.print_every, 0.0, 1e7)?;
    if let Some(c) = o.setpoint {
        within("setpoint", c, SUPPLY_C.0, SUPPLY_C.1)?;
    }
    let needs_mix = [
        (o.hot_step_to.is_some(), "hot-step-to"),
        (o.setpoint.is_some(), "setpoint"),
        (o.print_every > 0.0, "print-every"),
    ];
    match needs_mix.iter().find(|(set, _)| *set && !o.mix) {
        Some(&(_, option)) => Err(OptionError::NeedsMix { option }),
        None => Ok(()),
    }
}

/// The supply temperatures accepted (options and `--hot-topic`), °C: water and brine, with
/// room for a test.
const SUPPLY_C: (f64, f64) = (-50.0, 200.0);

/// A supply temperature outside [`SUPPLY_C`] (or not a number).
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[error("{value} is outside {}..{}", SUPPLY_C.0, SUPPLY_C.1)]
pub struct SupplyOutOfRange {
    /// The value given, °C.
    pub value: f64,
}

/// A supply temperature, °C, or why it is refused.
fn supply(c: f64) -> Result<f64, SupplyOutOfRange> {
    if (SUPPLY_C.0..=SUPPLY_C.1).contains(&c) {
        Ok(c)
    } else {
        Err(SupplyOutOfRange { value: c })
    }
}

/// A hot supply value refused on `--hot-topic`, as printed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{topic} {source}: refused ({count} so far)")]
struct HotRefused {
    /// The topic it came on.
    topic: String,
    /// The value and the range.
    #[source]
    source: SupplyOutOfRange,
    /// Values refused since the start, this one included.
    count: u64,
}

/// The mixing plant advances this often a second (the plant's model asks for at least every
/// 100 ms while the valve moves); readings are published at most this often.
const MIX_TICKS_PER_S: f64 = 10.0;

/// The mixing plant these options describe, settled at valve position `pct` at `now` (ns).
pub fn mixing(o: &SimValveOptions, pct: f64, now: u64) -> Mixing {
    Mixing::new(
        MixingParams {
            hot_c: o.hot,
            cold_c: o.cold,
            tau_s: o.tau,
            dead_time_s: o.dead_time,
            noise_c: o.noise,
        },
        pct,
        now,
        o.seed,
    )
}

/// The true valve these options describe.
pub fn true_valve(o: &SimValveOptions) -> TrueValve {
    let mut v = TrueValve::new(
        TruthParams {
            travel_ns: [o.travel_open_ms * 1e6, o.travel_close_ms * 1e6],
            lag_ns: o.start_lag_ms * 1e6,
            coast_ns: o.coast_ms * 1e6,
            backlash_pct: o.backlash_pct,
            switch_at_pct: o.switch_at_pct,
        },
        o.start_pct,
    );
    v.stuck = [o.stuck_open_switch, o.stuck_close_switch];
    v
}

/// A small xorshift generator for the feedback's noise (no crate needed for a test sensor).
struct Noise(u64);

impl Noise {
    /// Uniform in `-a..=a`.
    fn next(&mut self, a: f64) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64 * 2.0 * a - a
    }
}

/// Runs the simulated valve; returns the exit status (0 done, 1 ROS error, 2 bad options).
pub fn run(o: SimValveOptions) -> i32 {
    if let Err(e) = check(&o) {
        eprintln!("sim-valve: {e}");
        return 2;
    }
    sim_ros::block_on("sim-valve", serve(o))
}

/// The CSV record, if asked for.
struct Record(Option<std::io::BufWriter<std::fs::File>>);

impl Record {
    fn line(&mut self, t: f64, kind: &str, value: f64) {
        if let Some(w) = self.0.as_mut() {
            let _ = writeln!(w, "{t:.6},{kind},{value:.4}");
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

async fn serve(o: SimValveOptions) -> Result<(), SimError> {
    let mut node = sim_ros::start_node("sim_valve")?;
    let reliable = QosProfile::publisher_default().history(History::KeepLast { depth: 100 });
    let valve = Arc::new(Mutex::new(true_valve(&o)));
    let start_wall = clock::wall_ns();
    // Wall-clock seconds, as the node's messages are stamped, so a record and a ROS recording
    // line up.
    let secs = |t: i64| t as f64 / 1e9;
    let record = Arc::new(Mutex::new(Record(match &o.record {
        Some(p) => Some(std::io::BufWriter::new(
            std::fs::File::create(p).map_err(SimError::record(p))?,
        )),
        None => None,
    })));
    for (i, ch) in [&o.open, &o.close].into_iter().enumerate() {
        let topic = format!("{}/{}/edges", o.node.trim_end_matches('/'), ch);
        let t = make_topic(&node, &topic, msg::OutputEdge::type_name(), &reliable)?;
        let edges = node
            .create_subscription::<msg::OutputEdge>(&t, Some(reliable.clone()))
            .map_err(SimError::endpoint("subscription", &topic))?;
        let (valve, record) = (Arc::clone(&valve), Arc::clone(&record));
        tokio::spawn(async move {
            let stream = edges.async_stream();
            futures::pin_mut!(stream);
            while let Some(Ok((e, _))) = stream.next().await {
                let t = e.stamp.to_nanos();
                lock(&valve).edge(i, e.level, t);
                let kind = if i == 0 { "open" } else { "close" };
                lock(&record).line(secs(t), kind, f64::from(u8::from(e.level)));
            }
        });
    }
    let out_t = make_topic(&node, &o.topic, msg::Float64::type_name(), &reliable)?;
    let publisher = node
        .create_publisher::<msg::Float64>(&out_t, Some(reliable.clone()))
        .map_err(SimError::endpoint("publisher", &o.topic))?;
    let feedback = match &o.feedback_topic {
        Some(topic) => {
            let t = make_topic(&node, topic, msg::Float64::type_name(), &reliable)?;
            Some(
                node.create_publisher::<msg::Float64>(&t, Some(reliable.clone()))
                    .map_err(SimError::endpoint("publisher", topic))?,
            )
        }
        None => None,
    };
    let mut switches = Vec::new();
    for end in ["open", "close"] {
        let topic = format!("{}/{end}", o.switch_topic.trim_end_matches('/'));
        let t = make_topic(&node, &topic, msg::Bool::type_name(), &reliable)?;
        switches.push(
            node.create_publisher::<msg::Bool>(&t, Some(reliable.clone()))
                .map_err(SimError::endpoint("publisher", &topic))?,
        );
    }
    let mut noise = Noise(start_wall as u64 | 1);
    let stall_at = o
        .stalled
        .then(|| start_wall + (o.stall_after_s * 1e9) as i64);
    eprintln!(
        "sim-valve: true travel {} ms open, {} ms close, from {} %; edges from {}/{{{},{}}}/edges, \
         position on {} at {} Hz",
        o.travel_open_ms, o.travel_close_ms, o.start_pct, o.node, o.open, o.close, o.topic, o.rate_hz
    );
    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / o.rate_hz));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut mix = match o.mix {
        true => Some(MixRun::start(&mut node, &o, &valve, &record, start_wall)?),
        false => None,
    };
    let mut mix_tick = tokio::time::interval(Duration::from_secs_f64(1.0 / MIX_TICKS_PER_S));
    mix_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let end = (o.duration > 0.0).then(|| start_wall + (o.duration * 1e9) as i64);
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(SimError::Signal)?;
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = mix_tick.tick(), if mix.is_some() => {
                let now = clock::wall_ns();
                if end.is_some_and(|e| now >= e) {
                    break;
                }
                if let Some(m) = mix.as_mut() {
                    m.tick(&o, &valve, &record, now);
                }
                continue;
            }
            _ = tokio::signal::ctrl_c() => break,
            _ = term.recv() => break,
        }
        let now = clock::wall_ns();
        if end.is_some_and(|e| now >= e) {
            break;
        }
        let (pos, sw) = {
            let mut v = lock(&valve);
            if stall_at.is_some_and(|t| now >= t) && !v.stalled {
                // The motor stops where it is: the drive so far counted first.
                let moved = v.position(now);
                let (p, stuck) = (*v.params(), v.stuck);
                *v = TrueValve::new(p, moved);
                v.stuck = stuck;
                v.stalled = true;
                eprintln!("sim-valve: the motor stalls at {moved:.2} %");
            }
            (v.position(now), v.switches(now))
        };
        lock(&record).line(secs(now), "true", pos);
        let _ = publisher.publish(msg::Float64 { data: pos });
        if let Some(f) = &feedback {
            let _ = f.publish(msg::Float64 {
                data: pos + noise.next(o.feedback_noise_pct),
            });
        }
        for (p, on) in switches.iter().zip(sw) {
            let _ = p.publish(msg::Bool { data: on });
        }
    }
    if let Some(m) = &mix {
        let refused = lock(&m.hot).refused;
        if refused > 0 {
            eprintln!(
                "sim-valve: {refused} hot supply values refused on {}",
                o.hot_topic
            );
        }
    }
    if let Some(w) = lock(&record).0.as_mut() {
        let _ = w.flush();
    }
    Ok(())
}

/// The hot supply set on `--hot-topic`, waiting for the plant's next tick.
#[derive(Debug, Default)]
struct HotSupply {
    /// The newest accepted value not yet applied, °C.
    pending: Option<f64>,
    /// Values refused (outside the supply range, NaN, infinite).
    refused: u64,
}

impl HotSupply {
    /// Takes a value from the topic; a refused one is counted, and its reason returned for the
    /// first ten and every thousandth (a flood cannot flood the log).
    fn offer(&mut self, c: f64, topic: &str) -> Result<(), Option<HotRefused>> {
        match supply(c) {
            Ok(c) => {
                self.pending = Some(c);
                Ok(())
            }
            Err(source) => {
                self.refused += 1;
                let count = self.refused;
                Err(
                    (count <= 10 || count.is_multiple_of(1000)).then(|| HotRefused {
                        topic: topic.to_string(),
                        source,
                        count,
                    }),
                )
            }
        }
    }
}

/// The mixing plant at run time (`--mix`).
struct MixRun {
    plant: Mixing,
    start_wall: i64,
    /// The plant's own time, ns since the start; never goes back (a wall-clock step back
    /// holds it).
    at: u64,
    publisher: ros2_client::Publisher<msg::Temperature>,
    setpoints: Option<ros2_client::Publisher<msg::Float64>>,
    hot: Arc<Mutex<HotSupply>>,
    /// Plant ticks between readings.
    every: u64,
    ticks: u64,
    step_at: Option<(u64, f64)>,
    next_setpoint: u64,
    next_print: u64,
    /// `sensor_msgs/Temperature`'s variance of the noise, °C² (uniform in ±a: a²/3).
    variance: f64,
}

impl MixRun {
    fn start(
        node: &mut ros2_client::Node,
        o: &SimValveOptions,
        valve: &Arc<Mutex<TrueValve>>,
        record: &Arc<Mutex<Record>>,
        start_wall: i64,
    ) -> Result<MixRun, SimError> {
        let reliable = QosProfile::publisher_default().history(History::KeepLast { depth: 100 });
        // A sensor publishes best effort (the node's reader matches both).
        let sensor = QosProfile::publisher_default()
            .history(History::KeepLast { depth: 10 })
            .reliability(Reliability::BestEffort);
        let t = make_topic(node, &o.mix_topic, msg::Temperature::type_name(), &sensor)?;
        let publisher = node
            .create_publisher::<msg::Temperature>(&t, Some(sensor))
            .map_err(SimError::endpoint("publisher", &o.mix_topic))?;
        let setpoints = match o.setpoint {
            Some(_) => {
                let topic = format!(
                    "{}/valve/{}/setpoint",
                    o.node.trim_end_matches('/'),
                    o.valve
                );
                let t = make_topic(node, &topic, msg::Float64::type_name(), &reliable)?;
                Some(
                    node.create_publisher::<msg::Float64>(&t, Some(reliable.clone()))
                        .map_err(SimError::endpoint("publisher", &topic))?,
                )
            }
            None => None,
        };
        let t = make_topic(node, &o.hot_topic, msg::Float64::type_name(), &reliable)?;
        let hots = node
            .create_subscription::<msg::Float64>(&t, Some(reliable))
            .map_err(SimError::endpoint("subscription", &o.hot_topic))?;
        let hot = Arc::new(Mutex::new(HotSupply::default()));
        {
            let (hot, topic) = (Arc::clone(&hot), o.hot_topic.clone());
            tokio::spawn(async move {
                let stream = hots.async_stream();
                futures::pin_mut!(stream);
                while let Some(Ok((m, _))) = stream.next().await {
                    if let Err(Some(why)) = lock(&hot).offer(m.data, &topic) {
                        eprintln!("sim-valve: {why}");
                    }
                }
            });
        }
        let pos = lock(valve).position(start_wall);
        let plant = mixing(o, pos, 0);
        lock(record).line(start_wall as f64 / 1e9, "hot", o.hot);
        eprintln!(
            "sim-valve: mixing {} °C hot, {} °C cold, tau {} s, dead time {} s, noise ±{} °C; \
             {:.2} °C at {:.1} %, on {} at {} Hz; hot supply set on {}",
            o.hot,
            o.cold,
            o.tau,
            o.dead_time,
            o.noise,
            plant.temperature(),
            pos,
            o.mix_topic,
            o.mix_rate_hz,
            o.hot_topic
        );
        Ok(MixRun {
            plant,
            start_wall,
            at: 0,
            publisher,
            setpoints,
            hot,
            every: ((MIX_TICKS_PER_S / o.mix_rate_hz).round() as u64).max(1),
            ticks: 0,
            step_at: o.hot_step_to.map(|c| ((o.hot_step_after * 1e9) as u64, c)),
            next_setpoint: 0,
            next_print: (o.print_every * 1e9) as u64,
            variance: o.noise * o.noise / 3.0,
        })
    }

    /// One plant tick at wall time `now`: the supply, the plant on the true position, and a
    /// reading when one is due.
    fn tick(
        &mut self,
        o: &SimValveOptions,
        valve: &Arc<Mutex<TrueValve>>,
        record: &Arc<Mutex<Record>>,
        now: i64,
    ) {
        self.at = self
            .at
            .max(now.saturating_sub(self.start_wall).max(0) as u64);
        let t = self.at;
        let secs = now as f64 / 1e9;
        let mut hot = None;
        if let Some((at, c)) = self.step_at {
            if t >= at {
                self.step_at = None;
                hot = Some(c);
            }
        }
        if let Some(c) = lock(&self.hot).pending.take() {
            hot = Some(c);
        }
        if let Some(c) = hot {
            self.plant.set_hot(c);
            eprintln!("sim-valve: hot supply {c} °C");
            lock(record).line(secs, "hot", c);
        }
        let pos = lock(valve).position(now);
        self.plant.advance(t, pos);
        self.ticks += 1;
        if !(self.ticks - 1).is_multiple_of(self.every) {
            return;
        }
        let reading = self.plant.reading();
        let mixed = self.plant.temperature();
        {
            let mut r = lock(record);
            r.line(secs, "reading", reading);
            r.line(secs, "mixed", mixed);
        }
        let _ = self.publisher.publish(msg::Temperature {
            header: Header {
                stamp: Time::from_nanos(clock::wall_ns()),
                frame_id: "sim_valve".into(),
            },
            temperature: reading,
            variance: self.variance,
        });
        if let (Some(sp), Some(p)) = (o.setpoint, self.setpoints.as_ref()) {
            if t >= self.next_setpoint {
                self.next_setpoint = t + 1_000_000_000;
                let _ = p.publish(msg::Float64 { data: sp });
            }
        }
        if o.print_every > 0.0 && t >= self.next_print {
            // Every --print-every from the start, whatever the readings' phase; after a stall
            // (the runtime starved) from now on.
            let every = (o.print_every * 1e9) as u64;
            self.next_print += every;
            if self.next_print <= t {
                self.next_print = t + every;
            }
            println!(
                "t={:7.1} s  temperature {:6.2} °C  valve {:5.1} %  hot {:5.1} °C",
                t as f64 / 1e9,
                reading,
                pos,
                self.plant.params().hot_c
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_options_make_the_true_valve_and_bad_ones_are_refused() {
        let m = command()
            .try_get_matches_from([
                "sim-valve",
                "--travel-open-ms",
                "1000",
                "--start-pct",
                "50",
                "--start-lag-ms",
                "100",
                "--stuck-close-switch",
            ])
            .unwrap();
        let o = options(&m).unwrap();
        assert_eq!(check(&o), Ok(()));
        let mut v = true_valve(&o);
        assert_eq!(v.switches(0), [false, true], "stuck");
        v.edge(0, true, 0);
        v.edge(0, false, 350_000_000);
        assert!(
            (v.position(1_000_000_000) - 75.0).abs() < 1e-9,
            "250 ms after the lag"
        );
        let m = command()
            .try_get_matches_from(["sim-valve", "--travel-open-ms", "10"])
            .unwrap();
        assert_eq!(
            check(&options(&m).unwrap()),
            Err(OptionError::OutOfRange(OptionOutOfRange {
                option: "travel-open-ms",
                value: 10.0,
                lo: 100.0,
                hi: 3_600_000.0
            }))
        );
        let mut n = Noise(7);
        assert!((0..1000).map(|_| n.next(0.5)).all(|x| x.abs() <= 0.5));
    }

    fn mix_options(args: &[&str]) -> SimValveOptions {
        let m = command()
            .try_get_matches_from(["sim-valve", "--mix"].iter().chain(args))
            .expect("parses");
        options(&m).expect("options")
    }

    #[test]
    fn the_mixing_options_make_the_plant_and_bad_ones_are_refused() {
        let o = mix_options(&["--hot", "60", "--cold", "20", "--tau", "25", "--noise", "0"]);
        assert_eq!(check(&o), Ok(()));
        assert_eq!(o.mix_topic, "/mixing/temperature");
        let m = mixing(&o, 25.0, 0);
        assert!((m.temperature() - 30.0).abs() < 1e-9, "{}", m.temperature());
        assert_eq!(m.params().tau_s, 25.0);
        for (args, why) in [
            (&["--tau", "0"][..], "--tau 0 is outside 0.1..10000"),
            (&["--dead-time", "601"], "--dead-time 601 is outside 0..600"),
            (&["--noise", "NaN"], "--noise NaN is outside 0..10"),
            (&["--hot", "inf"], "--hot inf is outside -50..200"),
            (&["--cold", "-60"], "--cold -60 is outside -50..200"),
            (
                &["--mix-rate-hz", "20"],
                "--mix-rate-hz 20 is outside 0.1..10",
            ),
            (
                &["--hot-step-to", "300"],
                "--hot-step-to 300 is outside -50..200",
            ),
        ] {
            let e = check(&mix_options(args)).unwrap_err();
            assert_eq!(e.to_string(), why, "{args:?}");
        }
        let m = command()
            .try_get_matches_from(["sim-valve", "--hot-step-to", "60"])
            .expect("parses");
        assert_eq!(
            check(&options(&m).expect("options"))
                .unwrap_err()
                .to_string(),
            "--hot-step-to needs --mix"
        );
    }

    #[test]
    fn a_hot_supply_from_the_topic_is_bounded_and_refusals_are_counted() {
        let mut h = HotSupply::default();
        assert_eq!(h.offer(60.0, "/mixing/hot"), Ok(()));
        assert_eq!(h.pending, Some(60.0));
        let why = h.offer(f64::NAN, "/mixing/hot").unwrap_err();
        assert_eq!(
            why.map(|w| w.to_string()).as_deref(),
            Some("/mixing/hot NaN is outside -50..200: refused (1 so far)")
        );
        assert_eq!(h.pending, Some(60.0), "the last good value stays");
        let mut told = 1;
        for _ in 1..3000 {
            if h.offer(1e300, "/mixing/hot").unwrap_err().is_some() {
                told += 1;
            }
        }
        assert_eq!((h.refused, told), (3000, 10 + 3));
    }
}
