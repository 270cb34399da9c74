//! A managed (lifecycle) node, as the ROS 2 node lifecycle design defines it, with the state
//! machine rcl_lifecycle implements: the same states, transitions, ids and labels, so that
//! `ros2 lifecycle`, launch_ros' `LifecycleNode` and rclpy's lifecycle clients drive it.
//!
//! [`Machine`] is the state machine alone (sans-IO): a request for a transition runs the
//! node's [`Actions`] and yields the transition events. [`Lifecycle`] puts it on ROS:
//! `~/change_state`, `~/get_state`, `~/get_available_states`, `~/get_available_transitions`,
//! `~/get_transition_graph` and `~/transition_event`.
//!
//! What each state means for the lines is the node's business ([`Actions`]): unconfigured,
//! no line requested; inactive, lines requested and held inactive; active, lines follow their
//! channels; finalized, lines released.

use crate::error::chain;
use crate::output::panic_off::lock_ignore_poison as lock;
use crate::output::{GpioError, LineSlot};
use crate::output_thread::{Input, NotTaken};
use crate::ros::config::params::ParamError;
use crate::ros::inbound::inputs::Inputs;
pub use crate::ros::interface::lifecycle::{state, state_label, Edge, GRAPH, STATES};
use crate::ros::interface::msg::{
    ChangeStateRequest, ChangeStateResponse, EmptyRequest, GetAvailableStatesResponse,
    GetAvailableTransitionsResponse, GetStateResponse, LifecycleState, LifecycleTransition,
    TransitionDescription, TransitionEvent,
};
use crate::ros::interface::qos;
use crate::ros::wire::endpoints::ServiceMaker;
use crate::ros::wire::endpoints::{EndpointError, Endpoints};
use crate::ros::wire::mw::Publisher;
use log::{info, warn};
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use tokio::task::JoinHandle;

/// Why a transition's action failed (the machine then takes the failure edge).
#[derive(Debug, thiserror::Error)]
pub enum TransitionError {
    /// The parameters in force no longer give a valid configuration.
    #[error(transparent)]
    Params(#[from] ParamError),
    /// The GPIO lines cannot be requested (missing chip, busy line, no permission).
    #[error("cannot open the GPIO output: {}", chain(.0))]
    Lines(#[from] GpioError),
    /// The output thread did not take the release of the lines in time.
    #[error("the output thread did not let the lines follow: {0}")]
    NotLive(#[from] NotTaken),
    /// A refusal by other actions than the node's own (a test's, for instance).
    #[error("{0}")]
    Refused(&'static str),
}

/// A transition that cannot start from the current state.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("transition {asked} is not available from state {state}")]
pub struct Unavailable {
    /// The transition as asked for: its id, or its label (bounded, quoted).
    pub asked: String,
    /// The current state's label.
    pub state: &'static str,
}

/// What the node does in each transition. An `Err` is a failure: the machine takes the
/// transition's failure edge (configure: back to unconfigured) and the reason is logged.
pub trait Actions: Send + Sync {
    /// unconfigured → inactive: check the parameters, request the lines (held inactive).
    fn configure(&self) -> Result<(), TransitionError>;
    /// inactive → active: the lines follow their channels.
    fn activate(&self) -> Result<(), TransitionError>;
    /// active → inactive: every line inactive at once.
    fn deactivate(&self) -> Result<(), TransitionError>;
    /// inactive → unconfigured: release the lines (driven inactive first).
    fn cleanup(&self) -> Result<(), TransitionError>;
    /// any primary state → finalized: every line inactive and released.
    fn shutdown(&self) -> Result<(), TransitionError>;
}

/// What this node's transitions do to its lines (see [`Actions`]).
pub struct LineActions {
    /// The node's inputs, to the output thread.
    pub inputs: Arc<Inputs>,
    /// The GPIO lines, requested on configure; `None` for the sim output.
    pub lines: Option<LineSlot>,
}

impl Actions for LineActions {
    fn configure(&self) -> Result<(), TransitionError> {
        // The parameters in force must still give a valid configuration for every channel.
        self.inputs
            .with_params(|s| (0..s.channels()).try_for_each(|ch| s.channel_config(ch).map(drop)))?;
        if let Some(lines) = &self.lines {
            lines.attach()?;
        }
        Ok(())
    }

    fn activate(&self) -> Result<(), TransitionError> {
        self.live(true)
    }

    fn deactivate(&self) -> Result<(), TransitionError> {
        self.live(false)
    }

    fn cleanup(&self) -> Result<(), TransitionError> {
        if let Some(lines) = &self.lines {
            lines.detach();
        }
        Ok(())
    }

    fn shutdown(&self) -> Result<(), TransitionError> {
        // Released even when the hold could not be queued: dropping the lines drives them
        // inactive.
        let held = self.live(false);
        self.cleanup()?;
        held
    }
}

impl LineActions {
    /// Lets every line follow its channel, or holds every line inactive.
    ///
    /// Answered only once the output thread has taken it: the transitions run on tokio's
    /// blocking pool (`ServiceMaker::serve`), so this waits on that thread
    /// ([`SafetyPath::take`](crate::output_thread::SafetyPath::take), asleep on the
    /// acknowledgment eventfd, at most `SAFETY_TAKE_BOUND`, 250 ms). A hold it did not take in
    /// time has switched every output off through the emergency handle (so the lines are off and
    /// the transition stands); a release it did not take is withdrawn and the transition fails.
    fn live(&self, live: bool) -> Result<(), TransitionError> {
        let safety = self.inputs.safety();
        match safety.take(Input::Live(live)) {
            Ok(_) => Ok(()),
            Err(e) if !live => {
                log::error!(
                    "the hold of the lines was not taken: {e}; every output switched off by \
                     the emergency handle"
                );
                Ok(())
            }
            Err(e) => {
                safety.store(Input::Live(false));
                Err(e.into())
            }
        }
    }
}

/// A transition that took place: (transition id, label, start state, goal state).
pub type Step = Edge;

/// The state machine (sans-IO).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Machine {
    state: u8,
}

impl Default for Machine {
    fn default() -> Self {
        Machine {
            state: state::UNCONFIGURED,
        }
    }
}

impl Machine {
    /// The current state's id.
    pub fn state(&self) -> u8 {
        self.state
    }

    /// The transitions that can be requested now.
    pub fn available(&self) -> Vec<Step> {
        GRAPH
            .iter()
            .copied()
            .filter(|(id, _, start, _)| *id < 10 && *start == self.state)
            .collect()
    }

    /// Runs the transition `id` (or, when `id` is 0, the one labelled `label`) from the current
    /// state with `actions`. Returns whether it succeeded and the steps taken (none when it
    /// cannot start from here: then the reason).
    pub fn change(
        &mut self,
        id: u8,
        label: &str,
        actions: &dyn Actions,
    ) -> Result<(bool, Vec<Step>), Unavailable> {
        let requested = self.available().into_iter().find(|(tid, tlabel, _, _)| {
            if id != 0 {
                *tid == id
            } else {
                *tlabel == label
            }
        });
        let Some(first) = requested else {
            return Err(Unavailable {
                asked: if id != 0 {
                    id.to_string()
                } else {
                    format!("`{}`", crate::ros::config::logging::shown(label))
                },
                state: state_label(self.state),
            });
        };
        let mut steps = vec![first];
        let result = match first.1 {
            "configure" => actions.configure(),
            "activate" => actions.activate(),
            "deactivate" => actions.deactivate(),
            "cleanup" => actions.cleanup(),
            _ => actions.shutdown(),
        };
        let through = first.3;
        let outcome = if result.is_ok() {
            "transition_success"
        } else {
            "transition_failure"
        };
        if let Err(why) = &result {
            warn!("lifecycle: {} failed: {why}", first.1);
        }
        let second = GRAPH
            .iter()
            .copied()
            .find(|(_, l, start, _)| *start == through && *l == outcome)
            .expect("every transition state has a success and a failure edge");
        steps.push(second);
        self.state = second.3;
        Ok((result.is_ok(), steps))
    }
}

fn state_msg(id: u8) -> LifecycleState {
    LifecycleState {
        id,
        label: state_label(id).into(),
    }
}

fn description((id, label, start, goal): Step) -> TransitionDescription {
    TransitionDescription {
        transition: LifecycleTransition {
            id,
            label: label.into(),
        },
        start_state: state_msg(start),
        goal_state: state_msg(goal),
    }
}

/// The managed node on ROS: the machine, the node's actions and the transition events.
pub struct Lifecycle {
    machine: Mutex<Machine>,
    actions: Box<dyn Actions>,
    events: Publisher<TransitionEvent>,
    /// The current state's id, for readers that must not wait (diagnostics).
    current: Arc<AtomicU8>,
}

impl Lifecycle {
    /// Unconfigured, with `actions`; events go to `events` (`~/transition_event`); `current`
    /// follows the state.
    pub fn new(
        actions: Box<dyn Actions>,
        events: Publisher<TransitionEvent>,
        current: Arc<AtomicU8>,
    ) -> Lifecycle {
        current.store(state::UNCONFIGURED, Ordering::Release);
        Lifecycle {
            machine: Mutex::new(Machine::default()),
            actions,
            events,
            current,
        }
    }

    /// `~/change_state`.
    pub fn change_state(&self, req: ChangeStateRequest) -> ChangeStateResponse {
        let mut m = lock(&self.machine);
        let t = req.transition;
        match m.change(t.id, &t.label, self.actions.as_ref()) {
            Err(why) => {
                warn!("lifecycle: {why}");
                ChangeStateResponse { success: false }
            }
            Ok((success, steps)) => {
                self.current.store(m.state(), Ordering::Release);
                for step in steps {
                    let d = description(step);
                    let event = TransitionEvent {
                        timestamp: crate::clock::wall_ns().max(0) as u64,
                        transition: d.transition,
                        start_state: d.start_state,
                        goal_state: d.goal_state,
                    };
                    if let Err(e) = self.events.publish(event) {
                        warn!("lifecycle: cannot publish the transition event: {e}");
                    }
                }
                info!("lifecycle: {}", state_label(m.state()));
                ChangeStateResponse { success }
            }
        }
    }

    /// `~/get_state`.
    pub fn get_state(&self) -> GetStateResponse {
        GetStateResponse {
            current_state: state_msg(lock(&self.machine).state()),
        }
    }

    /// `~/get_available_states`.
    pub fn available_states(&self) -> GetAvailableStatesResponse {
        GetAvailableStatesResponse {
            available_states: STATES.iter().map(|(id, _)| state_msg(*id)).collect(),
        }
    }

    /// `~/get_available_transitions`.
    pub fn available_transitions(&self) -> GetAvailableTransitionsResponse {
        GetAvailableTransitionsResponse {
            available_transitions: lock(&self.machine)
                .available()
                .into_iter()
                .map(description)
                .collect(),
        }
    }

    /// `~/get_transition_graph`.
    pub fn transition_graph(&self) -> GetAvailableTransitionsResponse {
        GetAvailableTransitionsResponse {
            available_transitions: GRAPH.iter().copied().map(description).collect(),
        }
    }
}

/// Creates, with `m`, the five lifecycle services of `lifecycle` and the tasks serving them.
pub fn spawn(
    m: &mut ServiceMaker<'_>,
    lifecycle: &Arc<Lifecycle>,
) -> Result<Vec<JoinHandle<()>>, EndpointError> {
    let l = Arc::clone(lifecycle);
    let change = move |req: ChangeStateRequest| l.change_state(req);
    Ok(vec![
        m.serve("~/change_state", PKG, "ChangeState", change)?,
        m.serve(
            "~/get_state",
            PKG,
            "GetState",
            query(lifecycle, Lifecycle::get_state),
        )?,
        m.serve(
            "~/get_available_states",
            PKG,
            "GetAvailableStates",
            query(lifecycle, Lifecycle::available_states),
        )?,
        m.serve(
            "~/get_available_transitions",
            PKG,
            "GetAvailableTransitions",
            query(lifecycle, Lifecycle::available_transitions),
        )?,
        m.serve(
            "~/get_transition_graph",
            PKG,
            "GetAvailableTransitions",
            query(lifecycle, Lifecycle::transition_graph),
        )?,
    ])
}

/// The package of the lifecycle services' types.
const PKG: &str = "lifecycle_msgs";

/// A handler for a request without fields that answers with `answer`.
fn query<R: 'static>(
    lifecycle: &Arc<Lifecycle>,
    answer: fn(&Lifecycle) -> R,
) -> impl Fn(EmptyRequest) -> R + Send + 'static {
    let l = Arc::clone(lifecycle);
    move |_| answer(&l)
}

/// The managed node on ROS: `~/transition_event`, the lifecycle services, and the state
/// machine whose transitions hold or release the lines (`lines`: the GPIO lines requested on
/// configure; `None` for the sim output). `cell`: where the state is published for the
/// diagnostics.
pub fn serve(
    ep: &mut Endpoints<'_>,
    inputs: &Arc<Inputs>,
    lines: Option<LineSlot>,
    cell: Arc<AtomicU8>,
) -> Result<Vec<JoinHandle<()>>, EndpointError> {
    let events = ep.publisher("~/transition_event", qos::commands())?;
    let actions = LineActions {
        inputs: Arc::clone(inputs),
        lines,
    };
    let lifecycle = Arc::new(Lifecycle::new(Box::new(actions), events, cell));
    let tasks = spawn(&mut ep.services(), &lifecycle)?;
    info!("managed node: unconfigured; every line held inactive until configure and activate");
    Ok(tasks)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicBool;

    #[derive(Default)]
    struct Recorder {
        calls: Mutex<Vec<&'static str>>,
        fail_configure: AtomicBool,
    }

    impl Recorder {
        fn call(&self, what: &'static str) -> Result<(), TransitionError> {
            lock(&self.calls).push(what);
            let fail = what == "configure" && self.fail_configure.load(Ordering::SeqCst);
            if fail {
                Err(TransitionError::Refused("line busy"))
            } else {
                Ok(())
            }
        }
    }

    impl Actions for Recorder {
        fn configure(&self) -> Result<(), TransitionError> {
            self.call("configure")
        }
        fn activate(&self) -> Result<(), TransitionError> {
            self.call("activate")
        }
        fn deactivate(&self) -> Result<(), TransitionError> {
            self.call("deactivate")
        }
        fn cleanup(&self) -> Result<(), TransitionError> {
            self.call("cleanup")
        }
        fn shutdown(&self) -> Result<(), TransitionError> {
            self.call("shutdown")
        }
    }

    #[test]
    fn the_whole_walk_takes_the_designs_edges() {
        let a = Recorder::default();
        let mut m = Machine::default();
        assert_eq!(
            m.available(),
            [(1, "configure", 1, 10), (5, "shutdown", 1, 12)]
        );
        let walk = [
            (1, state::INACTIVE, (1, 10)),
            (3, state::ACTIVE, (3, 30)),
            (4, state::INACTIVE, (4, 40)),
            (2, state::UNCONFIGURED, (2, 20)),
            (1, state::INACTIVE, (1, 10)),
            (6, state::FINALIZED, (6, 50)),
        ];
        for (id, goal, (t1, t2)) in walk {
            let (ok, steps) = m.change(id, "", &a).unwrap();
            assert!(ok);
            assert_eq!(m.state(), goal);
            assert_eq!((steps[0].0, steps[1].0), (t1, t2));
        }
        assert_eq!(
            *lock(&a.calls),
            [
                "configure",
                "activate",
                "deactivate",
                "cleanup",
                "configure",
                "shutdown"
            ]
        );
        assert!(m.available().is_empty(), "nothing leaves finalized");
    }

    #[test]
    fn a_failing_configure_lands_in_unconfigured_and_labels_work() {
        let a = Recorder::default();
        a.fail_configure.store(true, Ordering::SeqCst);
        let mut m = Machine::default();
        let (ok, steps) = m.change(0, "configure", &a).unwrap();
        assert!(!ok);
        assert_eq!(steps[1], (11, "transition_failure", 10, 1));
        assert_eq!(m.state(), state::UNCONFIGURED);
        // Not available from unconfigured: refused, nothing runs.
        assert!(m
            .change(3, "", &a)
            .unwrap_err()
            .to_string()
            .contains("not available"));
        assert!(m.change(0, "activate", &a).is_err());
        assert_eq!(*lock(&a.calls), ["configure"]);
        // Shutdown by label from unconfigured takes transition 5.
        let (ok, steps) = m.change(0, "shutdown", &a).unwrap();
        assert!(ok && steps[0].0 == 5 && m.state() == state::FINALIZED);
    }
}
