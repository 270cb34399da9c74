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

use crate::sim_ros::{self, make_topic};
use clap::{ArgAction, Args, FromArgMatches};
use futures::StreamExt;
use pwm_actuator::clock;
use pwm_actuator::core::valve::truth::{TrueValve, TruthParams};
use pwm_actuator::ros::interface::msg::{self, RosMessage};
use ros2_client::qos::History;
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

/// Why the options are refused.
fn check(o: &SimValveOptions) -> Result<(), String> {
    let within = |name: &str, v: f64, lo: f64, hi: f64| {
        if (lo..=hi).contains(&v) {
            Ok(())
        } else {
            Err(format!("--{name} {v} is outside {lo}..{hi}"))
        }
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
    within("duration", o.duration, 0.0, 1e7)
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

async fn serve(o: SimValveOptions) -> Result<(), String> {
    let mut node = sim_ros::start_node("sim_valve")?;
    let reliable = QosProfile::publisher_default().history(History::KeepLast { depth: 100 });
    let valve = Arc::new(Mutex::new(true_valve(&o)));
    let start_wall = clock::wall_ns();
    // Wall-clock seconds, as the node's messages are stamped, so a record and a ROS recording
    // line up.
    let secs = |t: i64| t as f64 / 1e9;
    let record = Arc::new(Mutex::new(Record(match &o.record {
        Some(p) => Some(std::io::BufWriter::new(
            std::fs::File::create(p).map_err(|e| format!("{}: {e}", p.display()))?,
        )),
        None => None,
    })));
    for (i, ch) in [&o.open, &o.close].into_iter().enumerate() {
        let topic = format!("{}/{}/edges", o.node.trim_end_matches('/'), ch);
        let t = make_topic(&node, &topic, msg::OutputEdge::type_name(), &reliable)?;
        let edges = node
            .create_subscription::<msg::OutputEdge>(&t, Some(reliable.clone()))
            .map_err(|e| format!("subscription {topic}: {e}"))?;
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
        .map_err(|e| format!("publisher {}: {e}", o.topic))?;
    let feedback = match &o.feedback_topic {
        Some(topic) => {
            let t = make_topic(&node, topic, msg::Float64::type_name(), &reliable)?;
            Some(
                node.create_publisher::<msg::Float64>(&t, Some(reliable.clone()))
                    .map_err(|e| format!("publisher {topic}: {e}"))?,
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
                .map_err(|e| format!("publisher {topic}: {e}"))?,
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
    let end = (o.duration > 0.0).then(|| start_wall + (o.duration * 1e9) as i64);
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(|e| format!("SIGTERM: {e}"))?;
    loop {
        tokio::select! {
            _ = tick.tick() => {}
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
    if let Some(w) = lock(&record).0.as_mut() {
        let _ = w.flush();
    }
    Ok(())
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
        assert!(check(&options(&m).unwrap())
            .unwrap_err()
            .contains("travel-open-ms"));
        let mut n = Noise(7);
        assert!((0..1000).map(|_| n.next(0.5)).all(|x| x.abs() <= 0.5));
    }
}
