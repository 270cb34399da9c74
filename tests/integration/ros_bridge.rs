//! The ROS side in-process, on an output that fails: an output fault is reported as ERROR on
//! /diagnostics, asks the node to stop, and a parameter change the output thread can no longer
//! take is refused with nothing changed. (The sim and GPIO outputs cannot be made to fail from
//! outside, so this drives the bridge directly with a failing output.)

use crate::ros_harness::*;
use pwm_actuator::core::Command;
use pwm_actuator::output::{EmergencyOff, ErrorKind, LineChange, Output, OutputError};
use pwm_actuator::output_thread::{self, OutputThreadError, OutputThreadOptions};
use pwm_actuator::ros::config::names::to_ros_name;
use pwm_actuator::ros::config::params::{ParamStore, Stage};
use pwm_actuator::ros::inbound::inputs::{ChangeError, Inputs, NOTE_QUEUE};
use pwm_actuator::ros::inbound::node_state::NodeState;
use pwm_actuator::ros::interface::msg::{DiagnosticArray, DiagnosticStatus, RosMessage};
use pwm_actuator::ros::outbound::diagnostics::ChannelHealth;
use pwm_actuator::ros::outbound::reporter::{ChannelPubs, Reporter, StopSignal};
use ros2_client::{Context, ContextOptions, Node, NodeName, NodeOptions, ParameterValue};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

#[derive(Debug, thiserror::Error)]
#[error("simulated write failure")]
struct WriteFailed;

impl OutputError for WriteFailed {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Write
    }
}

/// Accepts `ok_writes` writes, then fails every one.
struct FailingOutput {
    ok_writes: usize,
}

struct NoOff;

impl EmergencyOff for NoOff {
    fn all_inactive(&self) {}
}

impl Output for FailingOutput {
    type Error = WriteFailed;

    fn line_count(&self) -> usize {
        1
    }

    fn set_levels(&mut self, _: &[LineChange]) -> Result<(), WriteFailed> {
        if self.ok_writes == 0 {
            return Err(WriteFailed);
        }
        self.ok_writes -= 1;
        Ok(())
    }

    fn set_all_inactive(&mut self) -> Result<(), WriteFailed> {
        Ok(())
    }

    fn emergency_off(&self) -> Arc<dyn EmergencyOff> {
        Arc::new(NoOff)
    }
}

fn publisher<M: RosMessage>(
    node: &mut Node,
    topic: &str,
    qos: ros2_client::QosProfile,
) -> pwm_actuator::ros::wire::mw::Publisher<M> {
    let t = node
        .create_topic(&to_ros_name(topic).unwrap(), M::type_name(), &qos)
        .unwrap();
    pwm_actuator::ros::wire::mw::Publisher::Dds(node.create_publisher(&t, Some(qos)).unwrap())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_output_fault_is_an_error_and_stops_the_node() {
    let dom = Domain::acquire();
    let ctx = Context::with_options(ContextOptions::new().domain_id(dom.id)).unwrap();
    let mut node = ctx
        .new_node(
            NodeName::new("/", "bridge_test").unwrap(),
            NodeOptions::new().start_parameter_services(false),
        )
        .unwrap();
    let spinner = node.spinner().unwrap();
    tokio::spawn(spinner.spin());

    let mut store = ParamStore::new(1);
    let a = store
        .check(
            &[("pw01.period_ms".into(), ParameterValue::Integer(50))],
            Stage::StartUp,
        )
        .unwrap();
    store.commit(&a);
    let started = output_thread::spawn(
        vec![store.channel_config(0).unwrap()],
        FailingOutput { ok_writes: 2 },
        OutputThreadOptions::default(),
    )
    .unwrap();
    let pubs = vec![ChannelPubs {
        edges: publisher(&mut node, "/bridge_test/pw01/edges", default_qos()),
        e1: publisher(&mut node, "/bridge_test/pw01/e1", latched_qos()),
        status: publisher(&mut node, "/bridge_test/pw01/status", default_qos()),
    }];
    let diagnostics = publisher::<DiagnosticArray>(&mut node, "/diagnostics", default_qos());
    let events = node
        .create_publisher(&ctx.get_parameter_events_topic(), None)
        .unwrap();
    let (notes_tx, notes_rx) = std::sync::mpsc::sync_channel(NOTE_QUEUE);
    let signal = Arc::new(StopSignal::default());
    let state = Arc::new(NodeState::from_store(&store));
    let reporter = Reporter::new(
        "bridge_test".into(),
        vec![ChannelHealth::new("pw01", "test:0")],
        pubs,
        diagnostics,
        notes_rx,
        10.0,
        10,
        Arc::clone(&signal),
        Arc::clone(&state),
    );
    let bridge = Arc::new(Inputs::new(
        "/bridge_test".into(),
        store,
        started.requests,
        pwm_actuator::ros::wire::mw::Publisher::Dds(events),
        notes_tx,
        state,
    ));

    let mut ros = Ros::new(dom.id);
    let diag = ros.sub::<DiagnosticArray>("/diagnostics", default_qos());

    // The report thread, as the node runs it: it owns the reporter.
    let mut reports = started.reports;
    // It hands the reporter back: its publishers must outlive the ERROR they were given, as
    // in the node (a DDS writer dropped at once can take its last sample with it).
    let pump = std::thread::spawn(move || {
        let reporter = std::cell::RefCell::new(reporter);
        let ended = reports.serve(
            || false,
            |r| reporter.borrow_mut().handle(r),
            |r| reporter.borrow_mut().after_batch(r.dropped()),
        );
        (ended, reporter.into_inner())
    });

    // Make sure the observer hears /diagnostics (1 Hz) before the fault: the node publishes
    // the ERROR once, at the fault, and then stops.
    assert!(
        next(&diag, Duration::from_secs(15)).await.is_some(),
        "the observer receives /diagnostics"
    );

    bridge.command(0, Command::Percent(50.0));
    bridge.enable(0, true);
    // Two edges are written, the third write fails.
    tokio::time::timeout(LONG, signal.stop.notified())
        .await
        .expect("the reporter asks the node to stop");
    assert!(signal.fault.load(Ordering::SeqCst));
    let a = wait_for(&diag, LONG, |a: &DiagnosticArray| {
        a.status
            .iter()
            .any(|s| s.name == "bridge_test: pw01" && s.level == DiagnosticStatus::ERROR)
    })
    .await
    .expect("ERROR on /diagnostics");
    let d = &a.status[0];
    assert!(d.message.starts_with("output fault"), "{}", d.message);
    assert_eq!(kv(d, "output_fault"), "true");
    assert_eq!(d.hardware_id, "test:0");

    // The output thread ends with the fault (the stop is asked for when the fault is
    // reported, a moment before the thread is gone).
    let result = started.handle.shutdown();
    assert!(
        matches!(
            result,
            Err(OutputThreadError::OutputFault { channel: 0, .. })
        ),
        "{result:?}"
    );
    // The output thread is gone: a parameter change cannot reach it and changes nothing.
    let r = bridge
        .set_params(
            vec![("pw01.period_ms".into(), ParameterValue::Integer(200))],
            "test",
        )
        .await;
    assert!(matches!(r, Err(ChangeError::OutputThread { .. })), "{r:?}");
    assert_eq!(
        bridge.with_params(|s| s.channel(0).map(|c| c.period_ms)),
        Some(50),
        "the store keeps the old value"
    );
    let (ended, reporter) = pump.join().unwrap();
    assert!(ended, "the report thread saw the output thread end");
    drop(reporter);
}

/// Two parameter changes at once reach the output thread in the order the store took them:
/// here the first change's planner is awaited only after the second change is done whole (as
/// when the first's task is descheduled as soon as it has released the store), and the output
/// thread still ends with the store's planner, the second's.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_planner_changes_reach_the_output_thread_in_the_stores_order() {
    let dom = Domain::acquire();
    let ctx = Context::with_options(ContextOptions::new().domain_id(dom.id)).unwrap();
    let mut node = ctx
        .new_node(
            NodeName::new("/", "order_test").unwrap(),
            NodeOptions::new().start_parameter_services(false),
        )
        .unwrap();
    let events = node
        .create_publisher(&ctx.get_parameter_events_topic(), None)
        .unwrap();
    let store = ParamStore::new(1);
    let started = output_thread::spawn(
        vec![store.channel_config(0).unwrap()],
        FailingOutput {
            ok_writes: usize::MAX,
        },
        OutputThreadOptions {
            bank: store.node_settings().bank,
            ..OutputThreadOptions::default()
        },
    )
    .unwrap();
    let (notes_tx, _notes_rx) = std::sync::mpsc::sync_channel(NOTE_QUEUE);
    let state = Arc::new(NodeState::from_store(&store));
    let inputs = Inputs::new(
        "/order_test".into(),
        store,
        started.requests,
        pwm_actuator::ros::wire::mw::Publisher::Dds(events),
        notes_tx,
        state,
    );
    let limit = |n| {
        vec![(
            "max_simultaneous_on".to_string(),
            ParameterValue::Integer(n),
        )]
    };

    let first = inputs.apply_params(&limit(2), "first").unwrap();
    let second = inputs.apply_params(&limit(1), "second").unwrap();
    inputs.announce(second).await;
    inputs.announce(first).await;

    let stored = inputs.with_params(|s| s.node_settings().bank);
    assert_eq!(stored.max_on, 1, "the store holds the later change");
    // Both acknowledgments came (none late: no emergency handle, no error), so the output
    // thread has read the slot since the last store: it runs with what the slot holds.
    assert_eq!(
        inputs.safety().bank(),
        stored,
        "the output thread ends with the store's planner"
    );
    started.handle.shutdown().unwrap();
}
