//! Building the node's output from its description: [`open`] turns an [`OutputSpec`] (which
//! backend, which lines, which trace files, an injected fault for tests) into one
//! [`AnyOutput`], whatever the backend. The node and the tests start the output thread on
//! that one type.
//!
//! Order of the checks, so that a refused configuration touches nothing: trace file names,
//! then the line bindings (no line bound to two channels), then the trace files are created,
//! then the chips are opened.

use super::fault::{FailingOutput, Fault, HangingOutput, FAULT_ENV};
use super::gpio::{plan_requests, GpioError, GpioLine, GpioOutput};
use super::slot::{slot, LineSlot};
use super::trace::{TraceError, TraceSpec};
use super::trace_files::{TraceHealth, TraceLimit};
use super::{EmergencyOff, ErrorKind, LineChange, Output, OutputError, SimOutput, Traced};
use std::path::PathBuf;
use std::sync::Arc;

/// Which backend drives the lines.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Backend {
    /// The simulated sink: no hardware.
    Sim {
        /// Channel names, one line each, in order.
        names: Vec<String>,
    },
    /// GPIO character-device lines, one per channel, in channel order.
    Gpio {
        /// The lines.
        lines: Vec<GpioLine>,
    },
}

/// Everything needed to build the node's output.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OutputSpec {
    /// The backend and its lines.
    pub backend: Backend,
    /// Trace files (`.vcd`, `.csv`; `.mcap` ones are accepted and left to the ROS side) of
    /// what is written to the lines; may be empty.
    pub trace: Vec<PathBuf>,
    /// What the files of each trace may hold together (`trace_max_mb`).
    pub trace_limit: TraceLimit,
    /// A write fault to inject (`PWM_ACTUATOR_FAULT`, exit-path tests): writes that fail after
    /// a count, or that hang after a time. `None` in normal operation; other faults are not
    /// the output's and are ignored here.
    pub fault: Option<Fault>,
}

impl OutputSpec {
    /// The channel names, one per line, in order.
    pub fn names(&self) -> Vec<String> {
        match &self.backend {
            Backend::Sim { names } => names.clone(),
            Backend::Gpio { lines } => lines.iter().map(|l| l.name.clone()).collect(),
        }
    }

    /// Each line's hardware id as diagnostics show it: `sim`, or `CHIP:OFFSET`.
    pub fn hardware_ids(&self) -> Vec<String> {
        match &self.backend {
            Backend::Sim { names } => vec!["sim".to_string(); names.len()],
            Backend::Gpio { lines } => lines
                .iter()
                .map(|l| format!("{}:{}", l.chip.display(), l.offset))
                .collect(),
        }
    }
}

/// Why the output cannot be built. Every variant is a configuration problem (a bad trace
/// path, a line bound twice, a missing chip, a busy line): nothing has been driven.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// The trace files cannot be written.
    #[error("trace: {0}")]
    Trace(#[source] TraceError),
    /// The GPIO lines cannot be opened.
    #[error("cannot open the GPIO output: {0}")]
    Gpio(#[source] GpioError),
    /// An end switch's input line cannot be requested.
    #[error("cannot open an end switch line: {0}")]
    Switch(#[source] super::gpio_input::InputError),
}

/// The error of an [`AnyOutput`]: the backend's own error, with its kind and line kept.
/// Displays as the backend's error and has the same source.
#[derive(Debug)]
pub struct AnyError {
    kind: ErrorKind,
    line: Option<usize>,
    inner: Box<dyn std::error::Error + Send + Sync>,
}

impl AnyError {
    fn new<E: OutputError>(e: E) -> AnyError {
        AnyError {
            kind: e.kind(),
            line: e.line(),
            inner: Box::new(e),
        }
    }
}

impl std::fmt::Display for AnyError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.inner.fmt(f)
    }
}

impl std::error::Error for AnyError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        self.inner.source()
    }
}

impl OutputError for AnyError {
    fn kind(&self) -> ErrorKind {
        self.kind
    }
    fn line(&self) -> Option<usize> {
        self.line
    }
}

/// Any backend behind one type: what [`open`] returns.
pub struct AnyOutput(Box<dyn Output<Error = AnyError>>, TraceHealth);

impl AnyOutput {
    /// Wraps a backend.
    pub fn new<O: Output>(output: O) -> AnyOutput {
        AnyOutput(Box::new(Erased(output)), TraceHealth::new())
    }

    /// The state of the VCD and CSV traces [`open`] created (none for other outputs): the
    /// ROS side adds its MCAP traces and reports them all.
    pub fn trace_health(&self) -> TraceHealth {
        self.1.clone()
    }
}

/// Maps a backend's error to [`AnyError`].
struct Erased<O>(O);

impl<O: Output> Output for Erased<O> {
    type Error = AnyError;
    fn line_count(&self) -> usize {
        self.0.line_count()
    }
    fn set_levels(&mut self, changes: &[LineChange]) -> Result<(), AnyError> {
        self.0.set_levels(changes).map_err(AnyError::new)
    }
    fn set_all_inactive(&mut self) -> Result<(), AnyError> {
        self.0.set_all_inactive().map_err(AnyError::new)
    }
    fn emergency_off(&self) -> Arc<dyn EmergencyOff> {
        self.0.emergency_off()
    }
}

impl Output for AnyOutput {
    type Error = AnyError;
    fn line_count(&self) -> usize {
        self.0.line_count()
    }
    fn set_levels(&mut self, changes: &[LineChange]) -> Result<(), AnyError> {
        self.0.set_levels(changes)
    }
    fn set_all_inactive(&mut self) -> Result<(), AnyError> {
        self.0.set_all_inactive()
    }
    fn emergency_off(&self) -> Arc<dyn EmergencyOff> {
        self.0.emergency_off()
    }
}

/// Builds the output `spec` describes (see the module documentation for the order of the
/// checks). The lines start inactive.
pub fn open(spec: &OutputSpec) -> Result<AnyOutput, OpenError> {
    Ok(build(spec, false)?.0)
}

/// Builds the output as [`open`] does, except that GPIO lines are not requested yet: they are
/// requested and released through the returned [`LineSlot`] (a managed node's `configure` and
/// `cleanup`). The checks that need no hardware (trace files, line bindings) are made now. The
/// sim output has nothing to request: no slot.
pub fn open_deferred(spec: &OutputSpec) -> Result<(AnyOutput, Option<LineSlot>), OpenError> {
    build(spec, true)
}

fn build(spec: &OutputSpec, deferred: bool) -> Result<(AnyOutput, Option<LineSlot>), OpenError> {
    // MCAP files are checked here with the others but written by the ROS side.
    let trace = TraceSpec::from_paths(&spec.trace)
        .map_err(OpenError::Trace)?
        .line_traces();
    let health = TraceHealth::new();
    let recorder = |names: Vec<String>| {
        for f in trace.files() {
            log::info!(
                "tracing what is written to the lines to {}",
                f.path.display()
            );
        }
        SimOutput::traced(names, Some(trace.clone()), spec.trace_limit, &health)
            .map_err(OpenError::Trace)
    };
    let mut line_slot = None;
    let output = match &spec.backend {
        Backend::Sim { names } => AnyOutput::new(recorder(names.clone())?),
        Backend::Gpio { lines } => {
            // The binding check before any trace file is created; the chips last.
            let plans = plan_requests(lines).map_err(OpenError::Gpio)?;
            let recorder = match trace.is_empty() {
                true => None,
                false => Some(recorder(spec.names())?),
            };
            if deferred {
                let (out, lines) = slot(plans, lines.len());
                line_slot = Some(lines);
                AnyOutput::new(Traced::new(out, recorder))
            } else {
                let gpio =
                    GpioOutput::open_planned(&plans, lines.len()).map_err(OpenError::Gpio)?;
                AnyOutput::new(Traced::new(gpio, recorder))
            }
        }
    };
    let output = match spec.fault {
        Some(Fault::FailWriteAfter(n)) => {
            log::warn!("{FAULT_ENV}: output writes fail after {n}");
            AnyOutput::new(FailingOutput::new(output, n))
        }
        Some(Fault::HangWriteAfterMs(ms)) => {
            log::warn!("{FAULT_ENV}: output writes hang after {ms} ms");
            AnyOutput::new(HangingOutput::new(output, ms))
        }
        Some(Fault::PanicAfterMs(_)) | None => output,
    };
    Ok((AnyOutput(output.0, health), line_slot))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::Level;
    use crate::output::fault::InjectedFailure;

    fn sim(names: &[&str]) -> OutputSpec {
        OutputSpec {
            backend: Backend::Sim {
                names: names.iter().map(|n| n.to_string()).collect(),
            },
            trace: vec![],
            trace_limit: TraceLimit::default(),
            fault: None,
        }
    }

    fn on(line: usize) -> [LineChange; 1] {
        [LineChange {
            line,
            level: Level::High,
            scheduled_ns: 0,
        }]
    }

    #[test]
    fn a_sim_spec_opens_one_line_per_channel() {
        let spec = sim(&["pw01", "pw02"]);
        let mut out = open(&spec).unwrap();
        assert_eq!(out.line_count(), 2);
        out.set_levels(&on(1)).unwrap();
        out.set_all_inactive().unwrap();
        assert_eq!(spec.hardware_ids(), ["sim", "sim"]);
    }

    #[test]
    fn an_injected_failure_keeps_its_kind_line_and_text() {
        let mut spec = sim(&["pw01"]);
        spec.fault = Some(Fault::FailWriteAfter(1));
        let mut out = open(&spec).unwrap();
        out.set_levels(&on(0)).unwrap();
        let e = out.set_levels(&on(0)).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Injected);
        assert_eq!(e.line(), None);
        let expected = InjectedFailure {
            after: 1,
            line: None,
        };
        assert_eq!(e.to_string(), expected.to_string());
        // Switching off keeps working after the failure.
        out.set_all_inactive().unwrap();
    }

    #[test]
    fn a_line_bound_twice_is_refused_before_any_trace_file_is_created() {
        let dir = tempfile::tempdir().unwrap();
        let vcd = dir.path().join("t.vcd");
        let line = |name: &str| GpioLine {
            name: name.into(),
            chip: "/dev/gpiochip-missing".into(),
            offset: 3,
            active_low: false,
        };
        let spec = OutputSpec {
            backend: Backend::Gpio {
                lines: vec![line("pw01"), line("pw02")],
            },
            trace: vec![vcd.clone()],
            trace_limit: TraceLimit::default(),
            fault: None,
        };
        let e = open(&spec).err().unwrap();
        assert!(matches!(e, OpenError::Gpio(GpioError::Binding(_))), "{e:?}");
        assert!(!vcd.exists());
        // A managed node's deferred lines are checked the same way, before anything else.
        let e = open_deferred(&spec).err().unwrap();
        assert!(matches!(e, OpenError::Gpio(GpioError::Binding(_))), "{e:?}");
        assert!(!vcd.exists());
        assert_eq!(spec.hardware_ids(), ["/dev/gpiochip-missing:3"; 2]);
    }

    #[test]
    fn a_missing_chip_is_refused_after_the_binding_check() {
        let spec = OutputSpec {
            backend: Backend::Gpio {
                lines: vec![GpioLine {
                    name: "pw01".into(),
                    chip: "/dev/gpiochip-missing".into(),
                    offset: 3,
                    active_low: true,
                }],
            },
            trace: vec![],
            trace_limit: TraceLimit::default(),
            fault: None,
        };
        let e = open(&spec).err().unwrap();
        assert!(
            matches!(e, OpenError::Gpio(GpioError::ChipNotFound { .. })),
            "{e:?}"
        );
    }
}
