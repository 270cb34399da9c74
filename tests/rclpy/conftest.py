"""Fixtures for the rclpy test suite: real ROS 2 clients talking to the built node over DDS.

Each test gets a ROS domain of its own (`ros_domain_id`), an rclpy node on that domain (`ros`),
optionally a second rclpy participant spinning in the background (`ros_peer`), and a launcher for
`pwm_actuator_node` (`node_process`) that puts the node on the same domain with a simulated output
and a trace file in the test's tmp_path. Every wait takes a timeout and fails the test with a
message naming what did not happen; nothing here waits forever or sleeps for a fixed time.

This module must not know the node's behaviour: it only starts processes and speaks ROS. What the
node does is asserted in the test modules.

Environment:
  PWM_ACTUATOR_NODE     path of the node binary (default: <repo>/target/release/pwm_actuator_node)
  PWM_TEST_TIMEOUT      default timeout of every wait, seconds (default 20: a loaded 2-core
                        machine can take several seconds for DDS discovery)
  PWM_TEST_DISCOVERY    ROS_AUTOMATIC_DISCOVERY_RANGE for the tests (default LOCALHOST, so test
                        traffic stays on this machine)
"""

from __future__ import annotations

import csv
import ctypes
import fcntl
import itertools
import os
import signal
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Optional, Sequence

import pytest
import rclpy
from rcl_interfaces.msg import ListParametersResult, ParameterValue, SetParametersResult
from rcl_interfaces.srv import (
    DescribeParameters,
    GetParameters,
    ListParameters,
    SetParameters,
    SetParametersAtomically,
)
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions
from rclpy.subscription import Subscription

REPO_ROOT = Path(__file__).resolve().parents[2]
MSG_DIR = REPO_ROOT / "msg"
DEFAULT_NODE_BINARY = REPO_ROOT / "target" / "release" / "pwm_actuator_node"

#: Default timeout of every wait, in seconds.
DEFAULT_TIMEOUT = float(os.environ.get("PWM_TEST_TIMEOUT", "20"))
#: How long a test waits for a process it started to be discovered (its publisher matched),
#: seconds: a lost discovery packet costs a period of announcements (RustDDS: 10 s), and the
#: test command loses some under its load.
DISCOVERY_S = 60.0
#: How long a node gets to exit after SIGTERM before it is killed and the test fails, seconds.
TERM_GRACE_S = 10.0
#: ROS domain ids handed to tests: 1..48. 0 is left to whatever else runs on the machine, 49..101
#: to the vendored RustDDS's tests, which take no lock (scripts/test.sh runs them beside this
#: suite), and above 101 Fast DDS's ports for the domain can collide with the ephemeral port
#: range.
DOMAIN_IDS = range(1, 49)
DISCOVERY_RANGE = os.environ.get("PWM_TEST_DISCOVERY", "LOCALHOST")

# rclpy writes its log files when a context is initialised; keep them inside the checkout
# (git-ignored) rather than in ~/.ros unless the user chose a place.
if "ROS_LOG_DIR" not in os.environ and "ROS_HOME" not in os.environ:
    os.environ["ROS_LOG_DIR"] = str(REPO_ROOT / ".ros-ws" / "ros_log")
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = DISCOVERY_RANGE


# ---------------------------------------------------------------------------------------------
# Waiting
# ---------------------------------------------------------------------------------------------


class WaitTimeout(AssertionError):
    """A wait ran out of time; the message says what was awaited."""


def udp_receive_buffer_errors() -> Optional[int]:
    """The host's count of UDP datagrams dropped because a socket's receive buffer was full
    (`Udp: RcvbufErrors` in /proc/net/snmp), or None where that file cannot be read."""
    try:
        lines = [l.split() for l in Path("/proc/net/snmp").read_text().splitlines()
                 if l.startswith("Udp:")]
        return int(lines[1][lines[0].index("RcvbufErrors")])
    except (OSError, IndexError, ValueError):
        return None


def wait_until(
    predicate: Callable[[], Any],
    what: str,
    timeout: Optional[float] = None,
    spin: Optional[Callable[[float], None]] = None,
    poll_s: float = 0.05,
) -> Any:
    """Calls `predicate` until it returns something truthy and returns that.

    `spin(seconds)` is called between tries (an executor's spin_once, say); without it the wait
    sleeps `poll_s`. Raises WaitTimeout naming `what` after `timeout` seconds (default
    DEFAULT_TIMEOUT).
    """
    timeout = DEFAULT_TIMEOUT if timeout is None else timeout
    deadline = time.monotonic() + timeout
    while True:
        result = predicate()
        if result:
            return result
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise WaitTimeout(f"timed out after {timeout:.1f} s waiting for {what}")
        if spin is not None:
            spin(min(poll_s, remaining))
        else:
            time.sleep(min(poll_s, remaining))


# ---------------------------------------------------------------------------------------------
# Timing groups
# ---------------------------------------------------------------------------------------------

#: The marker of a test whose result the load of tests run beside it cannot change
#: (pytest.ini): it times nothing the node does (no latency of an answer or a reaction, no rate,
#: lateness or length of anything on the line), and what it asserts over time is of seconds
#: with a second or a factor of two to spare (a simulated plant's temperature in a band, a check
#: named within its window's seconds, a peer seen within a look). scripts/test.sh runs these
#: (`--timing-group untimed`) in two pytest processes of their own beside all the others
#: (`--timing-group timed`), which run one at a time.
UNTIMED = "untimed"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--timing-group",
        choices=("all", "timed", "untimed"),
        default="all",
        help="run only the tests marked untimed, only the others (timed), or all (default)",
    )


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Deselects the tests outside the `--timing-group` asked for (reported as deselected)."""
    group = config.getoption("--timing-group")
    if group == "all":
        return
    keep, drop = [], []
    for item in items:
        untimed = item.get_closest_marker(UNTIMED) is not None
        (keep if untimed == (group == "untimed") else drop).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep


# ---------------------------------------------------------------------------------------------
# Figures shown, not asserted
# ---------------------------------------------------------------------------------------------

#: A directory where tests leave the tables of figures they show, so that tables of one group
#: measured in different pytest processes are printed together. scripts/test.sh points both of
#: its timing groups at one directory of the run's logs and empties it at the start of the run.
#: Unset, tables stay within the pytest process.
FIGURES_DIR = os.environ.get("PWM_TEST_FIGURES_DIR")

_FIGURES = pytest.StashKey[dict[str, dict[str, str]]]()


@pytest.fixture
def show_figures(request: pytest.FixtureRequest) -> Callable[[str, str, str], None]:
    """`show_figures(group, key, text)`: a table of figures the test shows (asserts nothing of).

    It is printed at the end of the pytest run with the other tables of `group`, in the order of
    their `key`s: those of this process, and with PWM_TEST_FIGURES_DIR those that any process
    wrote there so far. Each process that showed a table of a group prints the group, so the
    process that ends last prints all of it.
    """
    config = request.config

    def show(group: str, key: str, text: str) -> None:
        config.stash.setdefault(_FIGURES, {}).setdefault(group, {})[key] = text
        if FIGURES_DIR:
            directory = Path(FIGURES_DIR) / group
            directory.mkdir(parents=True, exist_ok=True)
            partial = directory / f".{key}.{os.getpid()}"
            partial.write_text(text)
            partial.replace(directory / f"{key}.txt")

    return show


def pytest_terminal_summary(terminalreporter: Any, config: pytest.Config) -> None:
    """Prints each group of tables shown through `show_figures` (above)."""
    for group, own in sorted(config.stash.get(_FIGURES, {}).items()):
        tables = dict(own)
        if FIGURES_DIR:
            for path in (Path(FIGURES_DIR) / group).glob("*.txt"):
                tables.setdefault(path.stem, path.read_text())
        terminalreporter.write_sep("=", f"{group}: {len(tables)} table(s) of this run")
        for key in sorted(tables):
            terminalreporter.write_line(tables[key])


# ---------------------------------------------------------------------------------------------
# ROS domains
# ---------------------------------------------------------------------------------------------


class DomainAllocator:
    """Hands out ROS domain ids that no other test, in this run or a parallel one, is using.

    Each id is held by an exclusive lock on a file in a machine-wide directory for as long as the
    test runs; the kernel drops the lock if the process dies. Ids are taken round-robin from a
    start that depends on the process id, so consecutive tests use different domains and a
    participant left over from one test is not seen by the next.
    """

    def __init__(self, lock_dir: Path) -> None:
        self._lock_dir = lock_dir
        self._lock_dir.mkdir(parents=True, exist_ok=True)
        self._counter = itertools.count(os.getpid() % len(DOMAIN_IDS))

    def acquire(self) -> tuple[int, int]:
        """Returns (domain id, lock fd); release with `release(fd)`."""
        for _ in range(len(DOMAIN_IDS)):
            domain_id = DOMAIN_IDS[next(self._counter) % len(DOMAIN_IDS)]
            fd = os.open(self._lock_dir / f"{domain_id}.lock", os.O_RDWR | os.O_CREAT, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                continue
            return domain_id, fd
        raise RuntimeError(f"all ROS domain ids {DOMAIN_IDS} are in use by other test runs")

    @staticmethod
    def release(fd: int) -> None:
        os.close(fd)


@pytest.fixture(scope="session")
def domain_allocator() -> DomainAllocator:
    """The run's DomainAllocator (locks in <tmp>/pwm_actuator-ros-domains, shared by all runs)."""
    return DomainAllocator(Path(tempfile.gettempdir()) / "pwm_actuator-ros-domains")


@pytest.fixture
def ros_domain_id(domain_allocator: DomainAllocator) -> Iterable[int]:
    """A ROS domain id (1..48) for this test alone."""
    domain_id, fd = domain_allocator.acquire()
    try:
        yield domain_id
    finally:
        domain_allocator.release(fd)


@pytest.fixture
def ros_env(ros_domain_id: int, tmp_path: Path) -> dict[str, str]:
    """Environment for processes that take part in this test's ROS domain."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(ros_domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = DISCOVERY_RANGE
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    env["ROS_LOG_DIR"] = str(tmp_path / "ros_log")
    env.setdefault("RUST_LOG", "info")
    env.setdefault("RUST_BACKTRACE", "1")
    return env


# ---------------------------------------------------------------------------------------------
# Processes
# ---------------------------------------------------------------------------------------------


@dataclass
class ManagedProcess:
    """A process started for a test, its output captured to files.

    The test may stop it (`terminate`, `wait_exit`); otherwise the fixture stops it at teardown
    with SIGTERM, kills it after TERM_GRACE_S and fails the test if it had to, and also fails the
    test if the process had exited by itself without the test waiting for that.
    """

    name: str
    argv: list[str]
    env: dict[str, str]
    stdout_path: Path
    stderr_path: Path
    popen: subprocess.Popen
    trace_path: Optional[Path] = None
    #: Set once the test has observed the exit (terminate / wait_exit / kill).
    exit_observed: bool = field(default=False)

    @property
    def pid(self) -> int:
        return self.popen.pid

    @property
    def returncode(self) -> Optional[int]:
        """Exit status (negative: killed by that signal), None while running."""
        return self.popen.poll()

    def is_running(self) -> bool:
        return self.popen.poll() is None

    def stdout(self) -> str:
        return self.stdout_path.read_text(errors="replace")

    def stderr(self) -> str:
        return self.stderr_path.read_text(errors="replace")

    def output(self) -> str:
        """stdout and stderr, labelled, for assertion messages."""
        return (
            f"--- {self.name} stdout ---\n{self.stdout()}"
            f"--- {self.name} stderr ---\n{self.stderr()}"
        )

    def send_signal(self, sig: int) -> None:
        self.popen.send_signal(sig)

    def wait_exit(self, timeout: Optional[float] = None) -> int:
        """Waits for the process to exit by itself and returns its status."""
        timeout = DEFAULT_TIMEOUT if timeout is None else timeout
        try:
            code = self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise WaitTimeout(
                f"{self.name} still running {timeout:.1f} s after it should have exited\n"
                + self.output()
            ) from None
        self.exit_observed = True
        return code

    def terminate(self, grace: float = TERM_GRACE_S) -> int:
        """SIGTERM, then waits up to `grace` seconds; returns the exit status.

        If the process is still running after `grace` it is killed and WaitTimeout is raised.
        """
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait()
                self.exit_observed = True
                raise WaitTimeout(
                    f"{self.name} did not exit within {grace:.0f} s of SIGTERM and was killed\n"
                    + self.output()
                ) from None
        self.exit_observed = True
        return self.popen.returncode

    def trace_text(self) -> str:
        """The trace file's content ('' if the node wrote none)."""
        if self.trace_path is None or not self.trace_path.exists():
            return ""
        return self.trace_path.read_text()

    def trace_rows(self) -> list[dict[str, str]]:
        """The CSV trace as rows keyed by its header line."""
        text = self.trace_text()
        if not text:
            return []
        return list(csv.DictReader(text.splitlines()))

    def wait_for_output(
        self, needle: str, timeout: Optional[float] = None, stream: str = "stderr"
    ) -> str:
        """Waits until `needle` appears in the process's `stream` ("stdout" or "stderr")."""
        read = self.stderr if stream == "stderr" else self.stdout

        def seen() -> bool:
            if needle in read():
                return True
            if not self.is_running():
                raise AssertionError(
                    f"{self.name} exited ({self.returncode}) before printing {needle!r}\n"
                    + self.output()
                )
            return False

        wait_until(seen, f"{needle!r} in {self.name}'s {stream}", timeout)
        return read()


class ProcessLauncher:
    """Starts processes for one test and stops them at its end (see ManagedProcess)."""

    def __init__(self, tmp_path: Path, env: Mapping[str, str]) -> None:
        self._tmp_path = tmp_path
        self._env = dict(env)
        self._procs: list[ManagedProcess] = []
        self._names = itertools.count(1)

    def launch(
        self,
        argv: Sequence[str],
        *,
        name: Optional[str] = None,
        env: Optional[Mapping[str, Optional[str]]] = None,
        trace_path: Optional[Path] = None,
        cwd: Optional[Path] = None,
    ) -> ManagedProcess:
        """Starts `argv` with the test's ROS environment, `env` entries added (None removes one).

        stdout and stderr go to <tmp_path>/<name>.stdout / .stderr; stdin is /dev/null.
        """
        name = name or f"proc{next(self._names)}"
        full_env = dict(self._env)
        for key, value in (env or {}).items():
            if value is None:
                full_env.pop(key, None)
            else:
                full_env[key] = value
        stdout_path = self._tmp_path / f"{name}.stdout"
        stderr_path = self._tmp_path / f"{name}.stderr"
        with open(stdout_path, "wb") as out, open(stderr_path, "wb") as err:
            popen = subprocess.Popen(
                [str(a) for a in argv],
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=err,
                env=full_env,
                cwd=str(cwd or self._tmp_path),
                # Its own session: a Ctrl-C at the terminal reaches pytest, which then stops
                # the process itself at teardown.
                start_new_session=True,
                preexec_fn=_die_with_parent,
            )
        proc = ManagedProcess(
            name=name,
            argv=[str(a) for a in argv],
            env=full_env,
            stdout_path=stdout_path,
            stderr_path=stderr_path,
            popen=popen,
            trace_path=trace_path,
        )
        self._procs.append(proc)
        return proc

    def stop_all(self) -> list[str]:
        """Stops every process still running; returns the problems found (empty: all well)."""
        problems = []
        for proc in reversed(self._procs):
            if proc.is_running():
                try:
                    proc.terminate()
                except WaitTimeout as exc:
                    problems.append(str(exc))
            elif not proc.exit_observed:
                problems.append(
                    f"{proc.name} exited by itself with status {proc.returncode} during the "
                    f"test\n{proc.output()}"
                )
            # Shown by pytest only when the test fails.
            print(f"{proc.name}: {' '.join(proc.argv)} -> status {proc.returncode}")
            print(_tail(proc.stderr(), 40, f"{proc.name} stderr"))
        return problems


_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    # Runs in the child between fork and exec: if the test run itself is killed, the kernel
    # sends the child SIGTERM instead of leaving it running without anyone to stop it.
    ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


def _tail(text: str, lines: int, label: str) -> str:
    kept = text.splitlines()[-lines:]
    return f"--- {label} (last {len(kept)} lines) ---\n" + "\n".join(kept)


@pytest.fixture
def process_launcher(tmp_path: Path, ros_env: dict[str, str]) -> Iterable[ProcessLauncher]:
    """Starts any program on this test's ROS domain; stops it at teardown (see ManagedProcess)."""
    launcher = ProcessLauncher(tmp_path, ros_env)
    yield launcher
    problems = launcher.stop_all()
    if problems:
        pytest.fail("\n\n".join(problems), pytrace=False)


@pytest.fixture(scope="session")
def node_binary() -> Path:
    """The pwm_actuator_node executable (PWM_ACTUATOR_NODE, or the release build)."""
    path = Path(os.environ.get("PWM_ACTUATOR_NODE", DEFAULT_NODE_BINARY))
    if not os.access(path, os.X_OK):
        pytest.fail(
            f"node binary {path} not found or not executable: run `cargo build --release` "
            "or set PWM_ACTUATOR_NODE",
            pytrace=False,
        )
    return path


NodeFactory = Callable[..., ManagedProcess]


@pytest.fixture
def node_process(
    node_binary: Path, process_launcher: ProcessLauncher, tmp_path: Path
) -> NodeFactory:
    """Factory starting pwm_actuator_node on this test's domain.

    node_process(args=(), *, output="sim", trace=True, name="node", env=None) -> ManagedProcess

    The command line is `pwm_actuator_node [--output OUTPUT] [--trace <tmp>/<name>-trace.csv]
    *args`: node options go in `args` before any `--ros-args ...`. `output=None` and
    `trace=False` leave those options out, for tests that pass their own.
    """

    def start(
        args: Sequence[str] = (),
        *,
        output: Optional[str] = "sim",
        trace: bool = True,
        name: str = "node",
        env: Optional[Mapping[str, Optional[str]]] = None,
    ) -> ManagedProcess:
        argv: list[str] = [str(node_binary)]
        if output is not None:
            argv += ["--output", output]
        trace_path = None
        if trace:
            trace_path = tmp_path / f"{name}-trace.csv"
            argv += ["--trace", str(trace_path)]
        argv += [str(a) for a in args]
        return process_launcher.launch(argv, name=name, env=env, trace_path=trace_path)

    return start


# ---------------------------------------------------------------------------------------------
# rclpy
# ---------------------------------------------------------------------------------------------


class MessageLog:
    """Messages received on one subscription, with their arrival times (time.monotonic())."""

    def __init__(self, ros: "RosClient", topic: str) -> None:
        self._ros = ros
        self.topic = topic
        self.messages: list[Any] = []
        self.arrivals: list[float] = []
        self.subscription: Optional[Subscription] = None

    def _on_message(self, msg: Any) -> None:
        self.messages.append(msg)
        self.arrivals.append(time.monotonic())

    def wait_for(
        self,
        predicate: Optional[Callable[[Any], bool]] = None,
        timeout: Optional[float] = None,
        start: int = 0,
        what: Optional[str] = None,
    ) -> Any:
        """Returns the first message (at index >= `start`) for which `predicate` holds."""

        def find() -> Any:
            for msg in self.messages[start:]:
                if predicate is None or predicate(msg):
                    return (msg,)
            return None

        found = self._ros.spin_until(
            find, what or f"a matching message on {self.topic}", timeout
        )
        return found[0]

    def wait_for_count(self, count: int, timeout: Optional[float] = None) -> list[Any]:
        """Waits until at least `count` messages have arrived; returns them all."""
        self._ros.spin_until(
            lambda: len(self.messages) >= count,
            f"{count} messages on {self.topic} (have {len(self.messages)})",
            timeout,
        )
        return list(self.messages)

    def wait_for_publishers(self, count: int = 1, timeout: Optional[float] = None) -> None:
        """Waits until this subscription is matched with `count` publishers.

        A timeout's message adds the host's UDP datagrams dropped for full receive buffers
        during the wait (/proc/net/snmp), which tells a discovery packet lost under load from
        a participant that never announced itself.
        """
        sub = self.subscription
        assert sub is not None
        drops = udp_receive_buffer_errors()
        try:
            self._ros.spin_until(
                lambda: sub.get_publisher_count() >= count,
                f"{count} publisher(s) matched on {self.topic}",
                timeout,
            )
        except WaitTimeout as e:
            after = udp_receive_buffer_errors()
            lost = "unknown" if drops is None or after is None else after - drops
            raise WaitTimeout(
                f"{e}; UDP datagrams dropped for full receive buffers meanwhile: {lost}"
            ) from None


class _OwnNode:
    """An rclpy node in a context of its own on a domain, with an executor of its own."""

    def __init__(self, domain_id: int, name: str) -> None:
        self.context = Context()
        rclpy.init(
            context=self.context,
            domain_id=domain_id,
            signal_handler_options=SignalHandlerOptions.NO,
        )
        self.node: Node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=5.0)
        self.node.destroy_node()
        self.context.try_shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RosClient(_OwnNode):
    """An rclpy node in a context of its own on the test's domain, spun by the calling thread.

    Every helper spins this node's executor while it waits, so callbacks run in the test's
    thread and need no locking.
    """

    def __init__(self, domain_id: int, name: str) -> None:
        super().__init__(domain_id, name)
        self.domain_id = domain_id
        self._clients: dict[tuple[Any, str], Any] = {}

    # -- spinning ---------------------------------------------------------------------------

    def spin_once(self, timeout_s: float = 0.05) -> None:
        self.executor.spin_once(timeout_sec=timeout_s)

    def spin_for(self, seconds: float) -> None:
        """Spins for `seconds` (for negative checks: "nothing arrives within ...")."""
        deadline = time.monotonic() + seconds
        while (remaining := deadline - time.monotonic()) > 0:
            self.spin_once(min(0.05, remaining))

    def spin_until(
        self, predicate: Callable[[], Any], what: str, timeout: Optional[float] = None
    ) -> Any:
        """Spins until `predicate()` is truthy and returns it (WaitTimeout naming `what`)."""
        return wait_until(predicate, what, timeout, spin=self.spin_once)

    # -- topics -----------------------------------------------------------------------------

    def subscribe(self, msg_type: Any, topic: str, qos: QoSProfile | int = 10) -> MessageLog:
        """Subscribes to `topic`; the returned log fills as this node spins."""
        log = MessageLog(self, topic)
        log.subscription = self.node.create_subscription(msg_type, topic, log._on_message, qos)
        return log

    def publisher(self, msg_type: Any, topic: str, qos: QoSProfile | int = 10) -> Publisher:
        return self.node.create_publisher(msg_type, topic, qos)

    def wait_for_subscribers(
        self, publisher: Publisher, count: int = 1, timeout: Optional[float] = None
    ) -> None:
        """Waits until `publisher` is matched with `count` subscriptions."""
        self.spin_until(
            lambda: publisher.get_subscription_count() >= count,
            f"{count} subscription(s) matched on {publisher.topic_name}",
            timeout,
        )

    def wait_for_message(
        self,
        msg_type: Any,
        topic: str,
        predicate: Optional[Callable[[Any], bool]] = None,
        timeout: Optional[float] = None,
        qos: QoSProfile | int = 10,
    ) -> Any:
        """Subscribes, waits for the first message satisfying `predicate`, unsubscribes."""
        log = self.subscribe(msg_type, topic, qos)
        try:
            return log.wait_for(predicate, timeout)
        finally:
            assert log.subscription is not None
            self.node.destroy_subscription(log.subscription)

    def publish_until(
        self,
        publisher: Publisher,
        msg: Any,
        done: Callable[[], Any],
        what: str,
        period_s: float = 0.5,
        timeout: Optional[float] = None,
    ) -> Any:
        """Publishes `msg` every `period_s` until `done()` is truthy (for volatile topics where
        the first message may precede matching on the other side)."""
        next_send = [0.0]

        def step() -> Any:
            result = done()
            if result:
                return result
            now = time.monotonic()
            if now >= next_send[0]:
                publisher.publish(msg)
                next_send[0] = now + period_s
            return None

        return self.spin_until(step, what, timeout)

    # -- graph ------------------------------------------------------------------------------

    def wait_for_node(
        self, name: str, namespace: str = "/", timeout: Optional[float] = None
    ) -> None:
        """Waits until the graph shows a node `name` in `namespace`."""
        self.spin_until(
            lambda: (name, namespace) in self.node.get_node_names_and_namespaces(),
            f"node {namespace.rstrip('/')}/{name} to appear",
            timeout,
        )

    def wait_for_topic(
        self,
        topic: str,
        publishers: int = 0,
        subscribers: int = 0,
        timeout: Optional[float] = None,
    ) -> None:
        """Waits until at least `publishers` publishers and `subscribers` subscribers of `topic`
        (fully qualified) are discovered."""
        self.spin_until(
            lambda: self.node.count_publishers(topic) >= publishers
            and self.node.count_subscribers(topic) >= subscribers,
            f"{publishers} publisher(s) and {subscribers} subscriber(s) of {topic}",
            timeout,
        )

    # -- services and parameters ------------------------------------------------------------

    def call(
        self, srv_type: Any, service: str, request: Any, timeout: Optional[float] = None
    ) -> Any:
        """Calls `service` and returns the response; waits `timeout` for the server to appear
        and again for the answer."""
        # One client per service, kept for the test: a new client per call is often not yet
        # matched on the server's side when the request goes out, and the request is then
        # resent only after Fast DDS's 3 s heartbeat.
        key = (srv_type, service)
        client = self._clients.get(key)
        if client is None:
            client = self.node.create_client(srv_type, service)
            self.spin_until(client.service_is_ready, f"service {service}", timeout)
            # Let the server's reader match ours before the first request.
            self.spin_for(0.25)
            self._clients[key] = client
        future = client.call_async(request)
        self.spin_until(future.done, f"a response from {service}", timeout)
        if future.exception() is not None:
            raise future.exception()
        return future.result()

    def get_parameters(
        self, node: str, names: Sequence[str], timeout: Optional[float] = None
    ) -> dict[str, Any]:
        """Values of `names` on `node` (fully qualified, e.g. "/pwm_actuator") as Python values;
        a parameter the node does not have maps to None."""
        values = self.get_parameter_values(node, names, timeout)
        if len(values) != len(names):
            raise AssertionError(
                f"{node}/get_parameters answered {len(values)} values for {len(names)} names"
            )
        return {n: parameter_value_to_python(v) for n, v in zip(names, values)}

    def get_parameter_values(
        self, node: str, names: Sequence[str], timeout: Optional[float] = None
    ) -> list[ParameterValue]:
        """Like get_parameters but the raw ParameterValue messages (to check the type field)."""
        request = GetParameters.Request(names=list(names))
        response = self.call(GetParameters, f"{node}/get_parameters", request, timeout)
        return list(response.values)

    def set_parameters(
        self, node: str, values: Mapping[str, Any], timeout: Optional[float] = None
    ) -> dict[str, SetParametersResult]:
        """Sets each parameter separately; returns each one's result (successful, reason).

        Values are Python values (bool, int, float, str, lists) typed as rclpy types them, or
        rclpy Parameter / ParameterValue objects for an explicit type.
        """
        request = SetParameters.Request(parameters=[_to_msg(n, v) for n, v in values.items()])
        response = self.call(SetParameters, f"{node}/set_parameters", request, timeout)
        return dict(zip(values.keys(), response.results))

    def set_parameters_atomically(
        self, node: str, values: Mapping[str, Any], timeout: Optional[float] = None
    ) -> SetParametersResult:
        """Sets all of `values` at once or none; returns the one result."""
        request = SetParametersAtomically.Request(
            parameters=[_to_msg(n, v) for n, v in values.items()]
        )
        response = self.call(
            SetParametersAtomically, f"{node}/set_parameters_atomically", request, timeout
        )
        return response.result

    def list_parameters(
        self,
        node: str,
        prefixes: Sequence[str] = (),
        depth: int = 0,
        timeout: Optional[float] = None,
    ) -> ListParametersResult:
        """The node's parameter names (`.names`) and prefixes (`.prefixes`); depth 0 = all."""
        request = ListParameters.Request(prefixes=list(prefixes), depth=depth)
        return self.call(ListParameters, f"{node}/list_parameters", request, timeout).result

    def describe_parameters(
        self, node: str, names: Sequence[str], timeout: Optional[float] = None
    ) -> dict[str, Any]:
        """Each parameter's ParameterDescriptor (ranges, read_only, description)."""
        request = DescribeParameters.Request(names=list(names))
        response = self.call(DescribeParameters, f"{node}/describe_parameters", request, timeout)
        return dict(zip(names, response.descriptors))


def _to_msg(name: str, value: Any):
    if isinstance(value, Parameter):
        return value.to_parameter_msg()
    if isinstance(value, ParameterValue):
        from rcl_interfaces.msg import Parameter as ParameterMsg

        return ParameterMsg(name=name, value=value)
    return Parameter(name, value=value).to_parameter_msg()


_client_names = itertools.count(1)


@pytest.fixture
def ros(ros_domain_id: int) -> Iterable[RosClient]:
    """An rclpy node ("pwm_test_client_N") on this test's domain; see RosClient."""
    with RosClient(ros_domain_id, f"pwm_test_client_{next(_client_names)}") as client:
        yield client


class RosPeer(_OwnNode):
    """A second rclpy participant on the test's domain whose executor spins in a thread of its
    own, for tests that need a counterpart that answers by itself (a publisher, a parameter
    server). Create its publishers and subscriptions before relying on them; its callbacks
    run in the background thread."""

    def __init__(self, domain_id: int, name: str) -> None:
        super().__init__(domain_id, name)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name=f"spin-{name}", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        super().close()


@pytest.fixture
def ros_peer(ros_domain_id: int) -> Iterable[RosPeer]:
    """A background-spun rclpy node ("pwm_test_peer_N") on this test's domain."""
    with RosPeer(ros_domain_id, f"pwm_test_peer_{next(_client_names)}") as peer:
        yield peer
