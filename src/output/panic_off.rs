//! Fail-safe on panic: a panic in any thread drives every output inactive, prints the usual
//! panic message and exits the process with [`PANIC_EXIT_CODE`] (SPEC §2: "On ... a panic ...
//! every output is driven inactive before exit").
//!
//! Everything here runs inside the panic hook, possibly on a thread that holds a lock or is in
//! the middle of an output write: it must never panic (a panic in the hook aborts the process
//! before the outputs are safe), never take a lock without a time bound, and never wait
//! indefinitely.

use super::EmergencyOff;
use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, Once, PoisonError, TryLockError};
use std::time::{Duration, Instant};

/// Exit code of the process after a panic (the code Rust itself uses for a panicking `main`).
pub const PANIC_EXIT_CODE: i32 = 101;

/// How long emergency code tries to take each lock before going on without it. Bounded
/// because the lock may be held by the panicking thread itself (a blocking `lock()` would then
/// deadlock).
pub const EMERGENCY_LOCK_BUDGET: Duration = Duration::from_millis(100);

/// How long a thread that panics while another panic is being handled waits for that handling
/// to exit the process before exiting itself.
pub const CONCURRENT_PANIC_WAIT: Duration = Duration::from_secs(5);

/// Tries to take a lock for at most `budget`, ignoring poisoning (the data guarded by the
/// output locks stay consistent whatever point a holder panicked at). Never blocks in the
/// kernel, so it cannot deadlock on a lock held by the calling thread.
pub(crate) fn lock_bounded<T>(m: &Mutex<T>, budget: Duration) -> Option<MutexGuard<'_, T>> {
    let deadline = Instant::now() + budget;
    loop {
        match m.try_lock() {
            Ok(g) => return Some(g),
            Err(TryLockError::Poisoned(p)) => return Some(p.into_inner()),
            Err(TryLockError::WouldBlock) => {
                if Instant::now() >= deadline {
                    return None;
                }
                std::thread::sleep(Duration::from_millis(1));
            }
        }
    }
}

/// Takes a lock, ignoring poisoning. For paths that are not the panic hook.
pub(crate) fn lock_ignore_poison<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Writes one line to stderr without panicking (`eprintln!` panics when stderr is closed).
pub(crate) fn warn(args: std::fmt::Arguments<'_>) {
    let _ = writeln!(std::io::stderr(), "pwm_actuator: {args}");
}

/// Remembers that a panic is being handled, so that a second panic does not run the handling
/// again (and cannot loop).
#[derive(Debug, Default)]
pub struct PanicLatch(AtomicBool);

impl PanicLatch {
    /// A latch not yet set.
    pub const fn new() -> PanicLatch {
        PanicLatch(AtomicBool::new(false))
    }

    /// `true` once a panic has been handled (or is being handled).
    pub fn is_set(&self) -> bool {
        self.0.load(Ordering::SeqCst)
    }
}

/// What [`on_panic`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PanicRole {
    /// This was the first panic: outputs were driven inactive, the message printed; the caller
    /// must now exit the process.
    First,
    /// Another panic is already being handled: only the message was printed.
    Concurrent,
}

/// The body of the panic hook, without the exit: on the first panic drives every output
/// inactive through `off` and then runs `report` (the previous hook, which prints the panic
/// message); on any later panic only runs `report`.
pub fn on_panic(latch: &PanicLatch, off: &dyn EmergencyOff, report: impl FnOnce()) -> PanicRole {
    if latch.0.swap(true, Ordering::SeqCst) {
        report();
        return PanicRole::Concurrent;
    }
    // Outputs first: printing can block (a full pipe on stderr) and must not delay them.
    off.all_inactive();
    report();
    PanicRole::First
}

/// A set of emergency handles driven together, so the panic hook can be installed once at
/// start-up and outputs register their handle when they exist.
#[derive(Default)]
pub struct EmergencyRegistry {
    handles: Mutex<Vec<Arc<dyn EmergencyOff>>>,
}

impl EmergencyRegistry {
    /// An empty registry.
    pub const fn new() -> EmergencyRegistry {
        EmergencyRegistry {
            handles: Mutex::new(Vec::new()),
        }
    }

    /// Adds a handle; every registered handle is driven by [`EmergencyOff::all_inactive`].
    pub fn register(&self, handle: Arc<dyn EmergencyOff>) {
        lock_ignore_poison(&self.handles).push(handle);
    }

    /// Number of registered handles.
    pub fn len(&self) -> usize {
        lock_ignore_poison(&self.handles).len()
    }

    /// `true` when no handle is registered.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl EmergencyOff for EmergencyRegistry {
    /// Drives every registered handle, in registration order. Bounded: the registry lock is
    /// only tried for [`EMERGENCY_LOCK_BUDGET`].
    fn all_inactive(&self) {
        match lock_bounded(&self.handles, EMERGENCY_LOCK_BUDGET) {
            Some(handles) => {
                for h in handles.iter() {
                    h.all_inactive();
                }
            }
            None => warn(format_args!(
                "emergency off: handle registry busy, outputs not driven inactive"
            )),
        }
    }
}

static REGISTRY: EmergencyRegistry = EmergencyRegistry::new();
static LATCH: PanicLatch = PanicLatch::new();
static INSTALL: Once = Once::new();

/// The process-wide registry the panic hook drives. Also usable from the signal path:
/// `registry().all_inactive()`.
pub fn registry() -> &'static EmergencyRegistry {
    &REGISTRY
}

/// Registers `off` in the process-wide [`registry`] and installs the panic hook (once per
/// process; later calls only register). See [`install_global_panic_hook`].
pub fn install_panic_hook(off: Arc<dyn EmergencyOff>) {
    REGISTRY.register(off);
    install_global_panic_hook();
}

/// Installs, once per process, a panic hook that on a panic in any thread drives every handle
/// of [`registry`] inactive, then runs the previous hook (the default one prints the usual
/// message), then exits the process with [`PANIC_EXIT_CODE`]. A panic in another thread while
/// this runs only prints its message and waits for the exit (at most
/// [`CONCURRENT_PANIC_WAIT`], then exits with the same code). Destructors do not run after a
/// panic: the outputs are already inactive and the trace files flushed by their handles.
pub fn install_global_panic_hook() {
    INSTALL.call_once(|| {
        let prev = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            match on_panic(&LATCH, &REGISTRY, || prev(info)) {
                PanicRole::First => std::process::exit(PANIC_EXIT_CODE),
                PanicRole::Concurrent => {
                    std::thread::sleep(CONCURRENT_PANIC_WAIT);
                    // SAFETY: _exit ends the process at once; it is async-signal-safe and, unlike
                    // exit(), safe to call while another thread may be running exit handlers.
                    unsafe { libc::_exit(PANIC_EXIT_CODE) }
                }
            }
        }));
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::Level;
    use crate::output::sim::SimOutput;
    use crate::output::trace::TraceSpec;
    use crate::output::{LineChange, Output};
    use std::sync::atomic::AtomicUsize;

    /// Counts calls and logs their order.
    struct Probe {
        calls: AtomicUsize,
        log: Arc<Mutex<Vec<&'static str>>>,
    }

    impl EmergencyOff for Probe {
        fn all_inactive(&self) {
            self.calls.fetch_add(1, Ordering::SeqCst);
            self.log.lock().unwrap().push("off");
        }
    }

    fn probe() -> (Arc<Probe>, Arc<Mutex<Vec<&'static str>>>) {
        let log = Arc::new(Mutex::new(Vec::new()));
        (
            Arc::new(Probe {
                calls: AtomicUsize::new(0),
                log: Arc::clone(&log),
            }),
            log,
        )
    }

    #[test]
    fn first_panic_switches_off_then_reports() {
        let latch = PanicLatch::new();
        let (off, log) = probe();
        let role = on_panic(&latch, &*off, || log.lock().unwrap().push("report"));
        assert_eq!(role, PanicRole::First);
        assert_eq!(*log.lock().unwrap(), ["off", "report"]);
        assert!(latch.is_set());
    }

    #[test]
    fn second_panic_only_reports() {
        let latch = PanicLatch::new();
        let (off, log) = probe();
        on_panic(&latch, &*off, || {});
        let role = on_panic(&latch, &*off, || log.lock().unwrap().push("report 2"));
        assert_eq!(role, PanicRole::Concurrent);
        assert_eq!(off.calls.load(Ordering::SeqCst), 1);
        assert_eq!(*log.lock().unwrap(), ["off", "report 2"]);
    }

    #[test]
    fn registry_drives_every_handle() {
        let reg = EmergencyRegistry::new();
        assert!(reg.is_empty());
        let (a, _) = probe();
        let (b, _) = probe();
        reg.register(a.clone());
        reg.register(b.clone());
        assert_eq!(reg.len(), 2);
        reg.all_inactive();
        assert_eq!(a.calls.load(Ordering::SeqCst), 1);
        assert_eq!(b.calls.load(Ordering::SeqCst), 1);
    }

    #[test]
    fn registry_does_not_block_on_a_held_lock() {
        let reg = EmergencyRegistry::new();
        let (a, _) = probe();
        reg.register(a.clone());
        let guard = reg.handles.lock().unwrap();
        let t0 = Instant::now();
        reg.all_inactive();
        // Returns after the bounded budget (generous upper margin for a loaded machine).
        assert!(t0.elapsed() < Duration::from_secs(30));
        drop(guard);
        assert_eq!(a.calls.load(Ordering::SeqCst), 0);
    }

    #[test]
    fn lock_bounded_takes_free_and_poisoned_locks() {
        let m = Arc::new(Mutex::new(5));
        assert_eq!(lock_bounded(&m, Duration::ZERO).map(|g| *g), Some(5));
        let m2 = Arc::clone(&m);
        let _ = std::thread::spawn(move || {
            let _g = m2.lock();
            panic!("poison the lock (expected in this test)");
        })
        .join();
        assert!(m.is_poisoned());
        assert_eq!(lock_bounded(&m, Duration::ZERO).map(|g| *g), Some(5));
        let held = m.lock().unwrap_or_else(PoisonError::into_inner);
        assert!(lock_bounded(&m, Duration::from_millis(5)).is_none());
        drop(held);
    }

    const CHILD_ENV: &str = "PWM_ACTUATOR_PANIC_CHILD_DIR";

    /// Run as a child process by `panic_in_a_thread_exits_101_with_outputs_inactive`: drives
    /// both sim lines active, installs the hook and panics in a worker thread.
    #[test]
    #[ignore = "helper process of panic_in_a_thread_exits_101_with_outputs_inactive"]
    fn panic_child() {
        let Some(dir) = std::env::var_os(CHILD_ENV) else {
            println!(
                "SKIPPED: helper process, run by panic_in_a_thread_exits_101_with_outputs_inactive"
            );
            return;
        };
        let csv = std::path::Path::new(&dir).join("panic.csv");
        let spec = TraceSpec::from_paths(&[csv]).unwrap();
        let mut out = SimOutput::new(vec!["pw01".into(), "pw02".into()], Some(spec)).unwrap();
        let on = |line| LineChange {
            line,
            level: Level::High,
            scheduled_ns: 0,
        };
        out.set_levels(&[on(0), on(1)]).unwrap();
        install_panic_hook(out.emergency_off());
        let worker = std::thread::spawn(|| panic!("deliberate panic in a worker thread"));
        let _ = worker.join();
        // Only reached if the hook did not end the process.
        std::process::exit(3);
    }

    #[test]
    fn panic_in_a_thread_exits_101_with_outputs_inactive() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let exe = std::env::current_exe().unwrap();
        let child = std::process::Command::new(exe)
            .args([
                "--exact",
                "output::panic_off::tests::panic_child",
                "--ignored",
                "--nocapture",
                "--test-threads=1",
            ])
            .env(CHILD_ENV, dir)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let out = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(PANIC_EXIT_CODE), "stderr: {stderr}");
        assert!(
            stderr.contains("deliberate panic in a worker thread"),
            "the usual panic message is printed: {stderr}"
        );
        let text = std::fs::read_to_string(dir.join("panic.csv")).unwrap();
        // Initial 0 rows, the two 1 edges, then both driven to 0 by the hook.
        let levels: Vec<(String, Level)> = crate::output::read_csv(&text)
            .unwrap()
            .into_iter()
            .map(|r| (r.channel, r.level))
            .collect();
        let (p1, p2) = (String::from("pw01"), String::from("pw02"));
        assert_eq!(
            levels,
            [
                (p1.clone(), Level::Low),
                (p2.clone(), Level::Low),
                (p1.clone(), Level::High),
                (p2.clone(), Level::High),
                (p1, Level::Low),
                (p2, Level::Low)
            ]
        );
    }
}
