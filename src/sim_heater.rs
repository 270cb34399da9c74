//! `pwm_actuator_node sim-heater`: a simulated heater as its own process and ROS participant,
//! so the whole loop can be tried without hardware (part of the binary only).
//!
//! It listens to a channel's `~/<ch>/edges` (the node's real edges, as they reached the line)
//! and runs the core's first-order-plus-dead-time [`Plant`] on them in real time, each edge
//! from the instant its stamp says the line was written (not its arrival), its sensor
//! lagging the block by `--sensor-tau`, publishing the sensor as `sensor_msgs/Temperature` at
//! a fixed rate. Faults are injected from the command line (`--fault`, `--fault-after`) or at
//! run time on `/sim_heater/fault` (`std_msgs/String`: `none`, `heater_disconnected`,
//! `heater_stuck_on`, `heater_half_power`, `sensor_stuck`, `sensor_silent`, `sensor_shorted`,
//! `sensor_fallen_off`). A fan that takes a share of the heater's full power away is set from
//! the command line (`--fan`, `--fan-after`) or at run time on `/sim_heater/fan`
//! (`std_msgs/Float64`, 0..1). With `--record` it writes every reading, every edge and every
//! fan change to a CSV file (`t_s,kind,value,true_c`), for the pictures of docs/heater.md.

use crate::sim_ros::{self, make_topic, within, OptionOutOfRange, SimError};
use clap::{ArgAction, Args, FromArgMatches};
use futures::StreamExt;
use pwm_actuator::clock;
use pwm_actuator::core::heater::{Plant, PlantFault, PlantParams};
use pwm_actuator::ros::interface::msg::{self, Header, RosMessage};
use ros2_client::builtin_interfaces::Time;
use ros2_client::qos::{History, Reliability};
use ros2_client::QosProfile;
use std::io::Write;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Options of `pwm_actuator_node sim-heater`.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct SimHeaterOptions {
    /// The node whose channel drives the heater
    #[arg(long, value_name = "NODE", default_value = "/pwm_actuator")]
    pub node: String,
    /// The channel whose edges drive the heater
    #[arg(long, value_name = "CH", default_value = "pw01")]
    pub channel: String,
    /// The topic the temperature is published on (sensor_msgs/Temperature)
    #[arg(long, value_name = "TOPIC", default_value = "/heater/temperature")]
    pub topic: String,
    /// Readings per second, 0.1..1000
    #[arg(long, value_name = "HZ", default_value_t = 10.0)]
    pub rate_hz: f64,
    /// Rise at 100 % from ambient, °C/s, 0.001..1000
    #[arg(long, value_name = "C_PER_S", default_value_t = 2.0)]
    pub heat_rate: f64,
    /// Time constant, s, 0.1..100000
    #[arg(long, value_name = "S", default_value_t = 60.0)]
    pub tau: f64,
    /// Dead time between the line and the sensor, s, 0..600
    #[arg(long, value_name = "S", default_value_t = 2.0)]
    pub dead_time: f64,
    /// Ambient and start temperature, °C, -100..1000
    #[arg(long, value_name = "C", default_value_t = 20.0)]
    pub ambient: f64,
    /// Peak sensor noise, °C (uniform), 0..100
    #[arg(long, value_name = "C", default_value_t = 0.05)]
    pub noise: f64,
    /// The sensor's own time constant behind its block, s (0: it reads the block), 0..10000
    #[arg(long, value_name = "S", default_value_t = 0.0)]
    pub sensor_tau: f64,
    /// A fan (or an open door) that takes this share of the heater's full power away, 0..1;
    /// at run time on /sim_heater/fan (std_msgs/Float64)
    #[arg(long, value_name = "SHARE", default_value_t = 0.0)]
    pub fan: f64,
    /// Switch --fan on this many seconds after start (0: from the start)
    #[arg(long, value_name = "S", default_value_t = 0.0)]
    pub fan_after: f64,
    /// A fault to inject: none, heater_disconnected, heater_stuck_on, heater_half_power,
    /// sensor_stuck, sensor_silent, sensor_shorted (reads ambient), sensor_fallen_off (cools
    /// toward ambient with a 20 s time constant)
    #[arg(long, value_name = "FAULT", default_value = "none")]
    pub fault: String,
    /// The sensor's resolution, °C (0.25 for a MAX6675 board, 0.0625 for a DS18B20); 0: none,
    /// 0..10
    #[arg(long, value_name = "C", default_value_t = 0.0)]
    pub quantum: f64,
    /// Inject --fault this many seconds after start (0: from the start)
    #[arg(long, value_name = "S", default_value_t = 0.0)]
    pub fault_after: f64,
    /// Publish reliable instead of best effort (the node's reader matches both)
    #[arg(long, action = ArgAction::SetTrue)]
    pub reliable: bool,
    /// Write every reading and edge to this CSV file
    #[arg(long, value_name = "FILE.csv")]
    pub record: Option<PathBuf>,
    /// Also act as the user: publish this setpoint (°C) on the channel's ~/<ch>/setpoint once
    /// a second
    // The text is `--help`'s, where `<ch>` is no HTML tag.
    #[allow(rustdoc::invalid_html_tags)]
    #[arg(long, value_name = "C")]
    pub setpoint: Option<f64>,
    /// Print the temperature and the line's share of on time this often, s (0: never)
    #[arg(long, value_name = "S", default_value_t = 0.0)]
    pub print_every: f64,
    /// Stop after this many seconds (0: run until interrupted)
    #[arg(long, value_name = "S", default_value_t = 0.0)]
    pub duration: f64,
}

/// The `sim-heater` subcommand, for the whole command line.
pub fn command() -> clap::Command {
    SimHeaterOptions::augment_args(clap::Command::new("sim-heater"))
        .about(
            "A simulated heater (first order plus dead time) driven by a channel's ~/<ch>/edges, \
             publishing sensor_msgs/Temperature; faults injected with --fault or on \
             /sim_heater/fault (std_msgs/String), a fan with --fan or on /sim_heater/fan \
             (std_msgs/Float64, share of full power). Its own ROS participant (node \
             sim_heater).",
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
pub fn options(m: &clap::ArgMatches) -> Result<SimHeaterOptions, clap::Error> {
    SimHeaterOptions::from_arg_matches(m)
}

/// Why the simulated heater's options are refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OptionError {
    /// A value outside its range.
    #[error(transparent)]
    OutOfRange(#[from] OptionOutOfRange),
    /// `--fault` names no fault.
    #[error(
        "--fault {0}: expected none, heater_disconnected, heater_stuck_on, heater_half_power, \
         sensor_stuck, sensor_silent, sensor_shorted or sensor_fallen_off"
    )]
    UnknownFault(String),
}

/// The plant and the fault the options describe, or why they are refused.
fn check(o: &SimHeaterOptions) -> Result<(PlantParams, PlantFault), OptionError> {
    within("rate-hz", o.rate_hz, 0.1, 1000.0)?;
    within("heat-rate", o.heat_rate, 0.001, 1000.0)?;
    within("tau", o.tau, 0.1, 100_000.0)?;
    within("dead-time", o.dead_time, 0.0, 600.0)?;
    within("ambient", o.ambient, -100.0, 1000.0)?;
    within("noise", o.noise, 0.0, 100.0)?;
    within("sensor-tau", o.sensor_tau, 0.0, 10_000.0)?;
    within("fan", o.fan, 0.0, 1.0)?;
    within("fan-after", o.fan_after, 0.0, 1e6)?;
    within("quantum", o.quantum, 0.0, 10.0)?;
    within("fault-after", o.fault_after, 0.0, 1e6)?;
    within("duration", o.duration, 0.0, 1e7)?;
    within("print-every", o.print_every, 0.0, 1e6)?;
    if let Some(sp) = o.setpoint {
        within("setpoint", sp, -273.15, 3000.0)?;
    }
    let fault =
        PlantFault::parse(&o.fault).ok_or_else(|| OptionError::UnknownFault(o.fault.clone()))?;
    Ok((
        PlantParams {
            rate_c_per_s: o.heat_rate,
            tau_s: o.tau,
            dead_time_s: o.dead_time,
            ambient_c: o.ambient,
            noise_c: o.noise,
            sensor_tau_s: o.sensor_tau,
        },
        fault,
    ))
}

/// Runs the simulated heater; returns the exit status (0 done, 1 ROS error, 2 bad options).
pub fn run(o: SimHeaterOptions) -> i32 {
    let (params, fault) = match check(&o) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("sim-heater: {e}");
            return 2;
        }
    };
    sim_ros::block_on("sim-heater", serve(o, params, fault))
}

/// The plant's line as last told and since when (monotonic ns).
fn plant_line(plant: &Mutex<Plant>) -> (bool, u64) {
    plant.lock().unwrap_or_else(|p| p.into_inner()).line_state()
}

/// The CSV record, if asked for, and the instant its times count from (monotonic ns).
struct Record(Option<std::io::BufWriter<std::fs::File>>, u64);

impl Record {
    fn line(&mut self, t: f64, kind: &str, value: f64, true_c: f64) {
        if let Some(w) = self.0.as_mut() {
            let _ = writeln!(w, "{t:.3},{kind},{value:.4},{true_c:.4}");
        }
    }
}

/// Sets the fan's share at `now` (the plant advanced to it first) and records the change.
fn fan(p: &mut Plant, record: &mut Record, now: u64, share: f64) {
    p.advance(now);
    p.set_disturbance(share);
    let t = p.temperature();
    record.line(secs_since(record.1, now), "fan", share, t);
}

/// The oldest an edge is taken to be on arrival, ns: a stamp from further back (a clock set
/// back, another host's skewed clock) counts as this old.
const MAX_EDGE_AGE_NS: i64 = 2_000_000_000;

/// When an edge reached the line, on this process's monotonic clock (ns): its wall-clock
/// stamp's age on arrival (`wall_now`, ns since the epoch) taken back from `mono_now`, within
/// 0..[`MAX_EDGE_AGE_NS`]. The plant then heats for the time the line was on, not for the time
/// the edge took to arrive: a message delayed on the way (a loaded host, a lost packet sent
/// again) by less than the plant's dead time moves the edge's arrival, not the heater; a longer
/// delay moves the heater by what exceeds the dead time (the plant is not run backwards).
fn edge_at(stamp_ns: i64, wall_now: i64, mono_now: u64) -> u64 {
    let age = wall_now.saturating_sub(stamp_ns).clamp(0, MAX_EDGE_AGE_NS);
    mono_now.saturating_sub(age as u64)
}

fn secs_since(start: u64, t: u64) -> f64 {
    t.saturating_sub(start) as f64 / 1e9
}

async fn serve(
    o: SimHeaterOptions,
    params: PlantParams,
    fault: PlantFault,
) -> Result<(), SimError> {
    let mut node = sim_ros::start_node("sim_heater")?;
    let reliable = QosProfile::publisher_default().history(History::KeepLast { depth: 100 });
    let edges_topic = format!("{}/{}/edges", o.node.trim_end_matches('/'), o.channel);
    let edges_t = make_topic(&node, &edges_topic, msg::OutputEdge::type_name(), &reliable)?;
    let fault_t = make_topic(
        &node,
        "/sim_heater/fault",
        msg::StringMsg::type_name(),
        &reliable,
    )?;
    let fan_t = make_topic(
        &node,
        "/sim_heater/fan",
        msg::Float64::type_name(),
        &reliable,
    )?;
    let out_qos = if o.reliable {
        reliable.clone()
    } else {
        QosProfile::publisher_default()
            .history(History::KeepLast { depth: 10 })
            .reliability(Reliability::BestEffort)
    };
    let temp_t = make_topic(&node, &o.topic, msg::Temperature::type_name(), &out_qos)?;
    let edges = node
        .create_subscription::<msg::OutputEdge>(&edges_t, Some(reliable.clone()))
        .map_err(SimError::endpoint("subscription", &edges_topic))?;
    let faults = node
        .create_subscription::<msg::StringMsg>(&fault_t, Some(reliable.clone()))
        .map_err(SimError::endpoint("subscription", "/sim_heater/fault"))?;
    let fans = node
        .create_subscription::<msg::Float64>(&fan_t, Some(reliable.clone()))
        .map_err(SimError::endpoint("subscription", "/sim_heater/fan"))?;
    let publisher = node
        .create_publisher::<msg::Temperature>(&temp_t, Some(out_qos))
        .map_err(SimError::endpoint("publisher", &o.topic))?;
    let setpoint_topic = format!("{}/{}/setpoint", o.node.trim_end_matches('/'), o.channel);
    let setpoints = match o.setpoint {
        Some(_) => {
            let t = make_topic(&node, &setpoint_topic, msg::Float64::type_name(), &reliable)?;
            Some(
                node.create_publisher::<msg::Float64>(&t, Some(reliable.clone()))
                    .map_err(SimError::endpoint("publisher", &setpoint_topic))?,
            )
        }
        None => None,
    };

    let start = clock::monotonic_ns();
    let mut plant = Plant::new(params, start, 0x5eed);
    plant.set_quantum(o.quantum);
    let plant = Arc::new(Mutex::new(plant));
    let record = Arc::new(Mutex::new(Record(
        match &o.record {
            Some(p) => Some(std::io::BufWriter::new(
                std::fs::File::create(p).map_err(SimError::record(p))?,
            )),
            None => None,
        },
        start,
    )));
    let secs = move |t: u64| t.saturating_sub(start) as f64 / 1e9;
    eprintln!(
        "sim-heater: {} °C/s at 100 %, tau {} s, dead time {} s, sensor tau {} s, ambient {} \
         °C; edges from {edges_topic}, temperature on {} at {} Hz",
        params.rate_c_per_s,
        params.tau_s,
        params.dead_time_s,
        params.sensor_tau_s,
        params.ambient_c,
        o.topic,
        o.rate_hz
    );
    {
        let (plant, record) = (Arc::clone(&plant), Arc::clone(&record));
        tokio::spawn(async move {
            let stream = edges.async_stream();
            futures::pin_mut!(stream);
            while let Some(Ok((e, _))) = stream.next().await {
                let (mono, wall) = (clock::monotonic_ns(), clock::wall_ns());
                let mut p = plant.lock().unwrap_or_else(|p| p.into_inner());
                let at = edge_at(e.stamp.to_nanos(), wall, mono).max(p.line_state().1);
                p.line(at, e.level);
                let t = p.temperature();
                drop(p);
                record.lock().unwrap_or_else(|p| p.into_inner()).line(
                    secs(at),
                    "line",
                    f64::from(u8::from(e.level)),
                    t,
                );
            }
        });
    }
    {
        let plant = Arc::clone(&plant);
        tokio::spawn(async move {
            let stream = faults.async_stream();
            futures::pin_mut!(stream);
            while let Some(Ok((m, _))) = stream.next().await {
                match PlantFault::parse(m.data.trim()) {
                    Some(f) => {
                        eprintln!("sim-heater: fault {}", m.data.trim());
                        plant.lock().unwrap_or_else(|p| p.into_inner()).set_fault(f);
                    }
                    None => eprintln!("sim-heater: unknown fault {:?} ignored", m.data),
                }
            }
        });
    }
    {
        let (plant, record) = (Arc::clone(&plant), Arc::clone(&record));
        tokio::spawn(async move {
            let stream = fans.async_stream();
            futures::pin_mut!(stream);
            while let Some(Ok((m, _))) = stream.next().await {
                if !(0.0..=1.0).contains(&m.data) {
                    eprintln!("sim-heater: fan share {} outside 0..1 ignored", m.data);
                    continue;
                }
                let now = clock::monotonic_ns();
                eprintln!("sim-heater: fan {}", m.data);
                let mut p = plant.lock().unwrap_or_else(|p| p.into_inner());
                fan(
                    &mut p,
                    &mut record.lock().unwrap_or_else(|r| r.into_inner()),
                    now,
                    m.data,
                );
            }
        });
    }
    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / o.rate_hz));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let fault_at = start + (o.fault_after * 1e9) as u64;
    let end = (o.duration > 0.0).then(|| start + (o.duration * 1e9) as u64);
    let mut injected = fault == PlantFault::None;
    let fan_at = start + (o.fan_after * 1e9) as u64;
    let mut fan_on = o.fan == 0.0;
    let mut next_setpoint = start;
    let every = (o.print_every * 1e9) as u64;
    let mut next_print = start + every;
    let mut last_print = start;
    let mut on_since: Option<u64> = None;
    let mut on_ns = 0u64;
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(SimError::Signal)?;
    loop {
        // SIGINT and SIGTERM end the run with the record flushed.
        tokio::select! {
            _ = tick.tick() => {}
            _ = tokio::signal::ctrl_c() => break,
            _ = term.recv() => break,
        }
        let now = clock::monotonic_ns();
        if end.is_some_and(|e| now >= e) {
            break;
        }
        let mut p = plant.lock().unwrap_or_else(|p| p.into_inner());
        if !injected && now >= fault_at {
            injected = true;
            eprintln!("sim-heater: fault {}", o.fault);
            p.set_fault(fault);
        }
        if !fan_on && now >= fan_at {
            fan_on = true;
            eprintln!("sim-heater: fan {}", o.fan);
            fan(
                &mut p,
                &mut record.lock().unwrap_or_else(|r| r.into_inner()),
                now,
                o.fan,
            );
        }
        let reading = p.reading(now);
        let true_c = p.temperature();
        drop(p);
        if let (Some(sp), Some(pubr)) = (o.setpoint, setpoints.as_ref()) {
            if now >= next_setpoint {
                next_setpoint = now + 1_000_000_000;
                let _ = pubr.publish(msg::Float64 { data: sp });
            }
        }
        if every > 0 {
            // The line's on time since the last line printed, from the edges recorded.
            let (level, since) = plant_line(&plant);
            match (level, on_since) {
                (true, None) => on_since = Some(since.max(last_print)),
                (false, Some(s)) => {
                    on_ns += since.saturating_sub(s);
                    on_since = None;
                }
                _ => {}
            }
            if now >= next_print {
                if let Some(s) = on_since {
                    on_ns += now.saturating_sub(s);
                    on_since = Some(now);
                }
                println!(
                    "t={:7.1} s  temperature {:7.2} °C  line on {:5.1} %",
                    secs(now),
                    reading.unwrap_or(f64::NAN),
                    on_ns as f64 / now.saturating_sub(last_print).max(1) as f64 * 100.0
                );
                on_ns = 0;
                last_print = now;
                next_print = now + every;
            }
        }
        if let Some(c) = reading {
            record
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .line(secs(now), "reading", c, true_c);
            let m = msg::Temperature {
                header: Header {
                    stamp: Time::from_nanos(clock::wall_ns()),
                    frame_id: "sim_heater".into(),
                },
                temperature: c,
                variance: (o.noise * o.noise) / 3.0,
            };
            let _ = publisher.publish(m);
        }
    }
    if let Some(w) = record.lock().unwrap_or_else(|p| p.into_inner()).0.as_mut() {
        let _ = w.flush();
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn opts() -> SimHeaterOptions {
        let m = command()
            .try_get_matches_from(["sim-heater"])
            .expect("defaults parse");
        options(&m).expect("defaults are options")
    }

    #[test]
    fn an_edge_counts_from_its_stamp_not_its_arrival() {
        let (wall, mono) = (1_800_000_000_000_000_000, 5_000_000_000);
        // Written 300 ms before it arrived: 300 ms back on the monotonic clock.
        assert_eq!(edge_at(wall - 300_000_000, wall, mono), 4_700_000_000);
        // A stamp from the future (a skewed clock) is now; one from long ago is 2 s old.
        assert_eq!(edge_at(wall + 1_000_000_000, wall, mono), mono);
        assert_eq!(edge_at(0, wall, mono), 3_000_000_000);
        assert_eq!(edge_at(wall - 300_000_000, wall, 100), 0);
    }

    #[test]
    fn a_late_edge_heats_the_plant_as_if_it_had_arrived_at_once() {
        // Dead time 0.5 s: an edge that arrives 300 ms after its stamp is still in time.
        let p = PlantParams {
            rate_c_per_s: 5.0,
            tau_s: 20.0,
            dead_time_s: 0.5,
            ambient_c: 20.0,
            noise_c: 0.0,
            ..PlantParams::default()
        };
        let (mut on_time, mut late) = (Plant::new(p, 0, 1), Plant::new(p, 0, 1));
        let s = 1_000_000_000;
        on_time.line(s, true);
        late.advance(s + 300_000_000);
        late.line(edge_at(-300_000_000, 0, s + 300_000_000), true);
        for t in [s, 2 * s, 5 * s] {
            assert_eq!(on_time.reading(t), late.reading(t), "at {t} ns");
        }
        assert!(on_time.temperature() > 30.0, "{}", on_time.temperature());
    }

    #[test]
    fn bad_options_are_refused_with_the_reason() {
        assert!(check(&opts()).is_ok());
        let bad = SimHeaterOptions { tau: 0.0, ..opts() };
        assert_eq!(
            check(&bad).unwrap_err().to_string(),
            "--tau 0 is outside 0.1..100000"
        );
        let bad = SimHeaterOptions {
            noise: f64::NAN,
            ..opts()
        };
        assert!(check(&bad)
            .unwrap_err()
            .to_string()
            .starts_with("--noise NaN"));
        let bad = SimHeaterOptions { fan: 1.5, ..opts() };
        assert_eq!(
            check(&bad).unwrap_err().to_string(),
            "--fan 1.5 is outside 0..1"
        );
        let lag = SimHeaterOptions {
            sensor_tau: 3.0,
            ..opts()
        };
        assert_eq!(check(&lag).unwrap().0.sensor_tau_s, 3.0);
        let bad = SimHeaterOptions {
            fault: "melted".into(),
            ..opts()
        };
        assert!(check(&bad)
            .unwrap_err()
            .to_string()
            .starts_with("--fault melted"));
    }
}
