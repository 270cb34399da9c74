//! Output backends: where the logical levels decided by the core become electrical levels.
//!
//! The trait is shaped like embedded-hal's `OutputPin`: small, fallible, with a [`Level`] type
//! rather than a bare bool. A backend owns every line of the node (one request for the process
//! lifetime on real hardware) and sets several lines in one call when edges coincide.
//! Backends never decide timing; they write what they are told, when they are told.

pub use crate::core::{Level, Nanos};

/// One line change handed to a backend.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LineChange {
    /// Index of the line among the node's bound lines (= channel index, 0 = pw01).
    pub line: usize,
    /// The new logical level (High = on); the backend applies `active_low`.
    pub level: Level,
    /// When the core scheduled this edge, monotonic ns (recorded by tracing backends).
    pub scheduled_ns: Nanos,
}

/// A set of output lines driven together.
///
/// Implementations must leave every line inactive when dropped, and must make
/// [`Output::set_all_inactive`] work even after a failed write.
pub trait Output: Send + 'static {
    /// The backend's error: its own type, with a [`ErrorKind`] the output thread can act on.
    type Error: OutputError;

    /// Number of lines this backend drives.
    fn line_count(&self) -> usize;

    /// Writes the given logical levels, in one call where the hardware allows.
    fn set_levels(&mut self, changes: &[LineChange]) -> Result<(), Self::Error>;

    /// Drives every line inactive (logical low), as on shutdown or after a fault.
    fn set_all_inactive(&mut self) -> Result<(), Self::Error>;

    /// A handle that drives every line inactive from any thread (panic hook, signal path),
    /// without going through the thread that owns the backend.
    fn emergency_off(&self) -> std::sync::Arc<dyn EmergencyOff>;
}

/// What went wrong in a backend, as a small comparable value (embedded-hal's `ErrorKind`
/// style): the output thread and the node act on the kind and keep the backend's own error as the
/// source for the message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum ErrorKind {
    /// The hardware or the kernel refused a write.
    Write,
    /// The emergency handle switched every line off; writes are refused from then on.
    Tripped,
    /// A change named a line the backend does not have.
    UnknownLine,
    /// A failure injected for a test (`PWM_ACTUATOR_FAULT`).
    Injected,
}

impl std::fmt::Display for ErrorKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ErrorKind::Write => "write refused",
            ErrorKind::Tripped => "outputs switched off by the emergency handle",
            ErrorKind::UnknownLine => "no such line",
            ErrorKind::Injected => "injected failure",
        })
    }
}

/// The error of an [`Output`]: any error type that says its [`ErrorKind`] and, where it
/// concerns one line, which.
pub trait OutputError: std::error::Error + Send + Sync + 'static {
    /// What kind of failure this is.
    fn kind(&self) -> ErrorKind;
    /// The line (index among the output's lines) the failure concerns, when it concerns one.
    fn line(&self) -> Option<usize> {
        None
    }
}

/// A backend that cannot fail (the simulated sink).
impl OutputError for std::convert::Infallible {
    fn kind(&self) -> ErrorKind {
        match *self {}
    }
}

/// Drives every line of a backend inactive from any thread. Must not block for long and must
/// not panic: it runs inside the panic hook.
pub trait EmergencyOff: Send + Sync {
    /// Drives every line inactive; best effort, errors are swallowed after being printed.
    fn all_inactive(&self);
}

pub mod bindings;
pub mod fault;
pub mod gpio;
pub mod gpio_input;
pub mod open;
pub mod panic_off;
pub mod sim;
pub mod slot;
pub mod trace;
pub mod trace_files;
pub mod traced;

pub use bindings::{check_unique, BindingError, LineAddr};
pub use gpio::{GpioError, GpioLine, GpioOutput};
pub use open::{open, open_deferred, AnyError, AnyOutput, Backend, OpenError, OutputSpec};
pub use panic_off::{install_panic_hook, EmergencyRegistry, PANIC_EXIT_CODE};
pub use sim::{SimOutput, SimProbe};
pub use slot::LineSlot;
pub use trace::{read_csv, CsvReadError, CsvRow, EdgeRecord, TraceError, TraceFormat, TraceSpec};
pub use trace_files::{TraceHealth, TraceLimit, TraceState};
pub use traced::Traced;
