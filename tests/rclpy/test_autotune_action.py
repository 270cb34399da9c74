"""The autotune action's server under many clients (docs/autotune.md, "Goals, results and what is
kept"): every request answered at once, none waiting behind another client, and nothing kept for
a request about a goal the server does not know.

- 100 goals sent during a run, from ten clients at once: every one answered within a second,
  rejected, the run going on; a goal with a kept id is rejected too;
- a goal sent 1 s after other goals ended whose clients never asked for their results (one
  refused, one canceled) is answered within a second, and its run starts within START_BY_S of
  the answer, seen on the trace; the unclaimed results are still there afterwards;
- get_result requests for unknown goals: answered at once with STATUS_UNKNOWN (a cancel of one:
  ERROR_UNKNOWN_GOAL_ID); 100,000 of them (PWM_RESULT_FLOOD; from PWM_RESULT_FLOOD_CLIENTS
  processes, 1 by default, about 5,000 a second here), after as many unmeasured, leave the
  node's resident memory within 1 MB of where it was before them.
"""

from __future__ import annotations

import os
import sys
import time
import uuid
from pathlib import Path

import pytest
from action_msgs.msg import GoalStatus, GoalStatusArray
from action_msgs.srv import CancelGoal
from rclpy.action import ActionClient
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from pwm_actuator_msgs.action import Autotune

from helpers_rules import MS, NODE, mono_ns
from result_flood import make_client
from test_autotune import TARGET, run
from test_channel_rules import close_trace, start
from test_heater import PARAMS

ACTION = f"{NODE}/pw01/autotune"
#: The latest a run starts after its goal was accepted (START_BY in src/ros/inbound/autotune.rs).
START_BY_S = 1.0
#: The period of the channel in these tests (test_heater.PARAMS), s.
PERIOD_S = 0.2
#: The status topic's QoS as rclpy's action clients ask for it.
STATUS_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
FLOOD = int(os.environ.get("PWM_RESULT_FLOOD", "100000"))
FLOOD_CLIENTS = int(os.environ.get("PWM_RESULT_FLOOD_CLIENTS", "1"))
FLOOD_SCRIPT = Path(__file__).with_name("result_flood.py")


def statuses(log) -> dict[bytes, int]:
    """The last GoalStatusArray of `log` as {goal id: status}."""
    if not log.messages:
        return {}
    return {bytes(s.goal_info.goal_id.uuid): s.status for s in log.messages[-1].status_list}


def uuid_of(handle) -> bytes:
    return bytes(handle.goal_id.uuid)


def send_goal(ros, client, goal, what: str):
    """Sends `goal`; returns the goal handle and how long its answer took, s."""
    t0 = time.monotonic()
    sent = client.send_goal_async(goal)
    ros.spin_until(sent.done, what, timeout=10)
    return sent.result(), time.monotonic() - t0


#: Requests a client has unanswered at most.
WINDOW = 10
#: The goal service's QoS for the clients that send many goals at once. With rclpy's default
#: (rmw_qos_profile_services_default, keep last 10) every client's reply reader takes in the
#: answers to all clients of the service, and keeps only the last 10 of a burst: an rclpy
#: client of an rclpy server loses the same answers (a burst of 20 from one client: 10 arrive).
DEEP = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=200,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


def send_windowed(ros, clients, count: int):
    """Sends `count` goals round-robin over `clients`, each client with at most WINDOW
    unanswered; returns the answers (goal handles) and how long each took, s."""
    pending: list[list] = [[] for _ in clients]
    answers, took = [], []
    sent = 0
    deadline = time.monotonic() + 60
    while len(answers) < count:
        for i, c in enumerate(clients):
            while sent < count and len(pending[i]) < WINDOW:
                goal = Autotune.Goal(target_c=TARGET)
                pending[i].append((time.monotonic(), c.send_goal_async(goal)))
                sent += 1
        ros.spin_once(0.01)
        for i in range(len(clients)):
            for t0, f in [p for p in pending[i] if p[1].done()]:
                answers.append(f.result())
                took.append(time.monotonic() - t0)
            pending[i] = [p for p in pending[i] if not p[1].done()]
        assert time.monotonic() < deadline, (
            f"{count - len(answers)} of {count} goals unanswered after 60 s"
        )
    return answers, took


def test_every_goal_sent_during_a_run_is_answered(
    node_process, process_launcher, node_binary, ros
):
    proc, ch, client = run(node_process, process_launcher, node_binary, ros)
    feedback: list = []
    sent = client.send_goal_async(
        Autotune.Goal(target_c=TARGET), feedback_callback=lambda m: feedback.append(m.feedback)
    )
    ros.spin_until(sent.done, "the first goal's answer", timeout=10)
    first = sent.result()
    assert first.accepted
    ros.spin_until(lambda: feedback, "the run's first feedback", timeout=10)

    # 100 goals from ten clients at once, each with up to WINDOW unanswered.
    others = [
        ActionClient(ros.node, Autotune, ACTION, goal_service_qos_profile=DEEP) for _ in range(10)
    ]
    for c in others:
        ros.spin_until(c.server_is_ready, "the action server", timeout=30)
    ros.spin_for(0.25)
    answers, took = send_windowed(ros, others, 100)
    print(
        f"100 goals during a run: {len(answers)} answered in {sum(took):.3f} s in all, the "
        f"slowest in {max(took) * 1000:.1f} ms, {sum(a.accepted for a in answers)} accepted"
    )
    assert len(answers) == 100 and not any(a.accepted for a in answers)
    assert max(took) < 1.0, max(took)
    # A goal whose id is kept (the run's): rejected, the run untouched.
    # rclpy's ActionClient picks the ids itself: the goal service's own client.
    request = Autotune.Impl.SendGoalService.Request()
    request.goal_id.uuid = first.goal_id.uuid
    request.goal = Autotune.Goal(target_c=TARGET)
    dup = ros.node.create_client(Autotune.Impl.SendGoalService, f"{ACTION}/_action/send_goal")
    ros.spin_until(dup.service_is_ready, "send_goal", timeout=10)
    answer = dup.call_async(request)
    ros.spin_until(answer.done, "the answer to a goal with a kept id", timeout=10)
    assert not answer.result().accepted

    # The run goes on, and its cancel and result are as without the flood.
    n = len(feedback)
    ros.spin_until(lambda: len(feedback) > n, "feedback after the 100 goals", timeout=30)
    canceled = first.cancel_goal_async()
    ros.spin_until(canceled.done, "the cancel's answer", timeout=10)
    assert [bytes(g.goal_id.uuid) for g in canceled.result().goals_canceling] == [uuid_of(first)]
    got = first.get_result_async()
    ros.spin_until(got.done, "the run's result", timeout=10)
    assert got.result().status == GoalStatus.STATUS_CANCELED, got.result()
    assert got.result().result.stop == "canceled", got.result().result
    close_trace(proc)


def test_a_goal_behind_unclaimed_results_is_answered_and_starts_at_once(
    node_process, process_launcher, node_binary, ros
):
    proc, ch, client = run(node_process, process_launcher, node_binary, ros)
    status_log = ros.subscribe(GoalStatusArray, f"{ACTION}/_action/status", STATUS_QOS)
    a = ActionClient(ros.node, Autotune, ACTION)
    ros.spin_until(a.server_is_ready, "the action server", timeout=30)

    # A's first goal is refused by the channel (a target above temp_max_c): accepted, then
    # aborted. A never asks for its result.
    refused, _ = send_goal(ros, a, Autotune.Goal(target_c=1000.0), "A's refused goal")
    assert refused.accepted
    ros.spin_until(
        lambda: statuses(status_log).get(uuid_of(refused)) == GoalStatus.STATUS_ABORTED,
        "A's refused goal aborted",
    )
    # A's second goal runs and is canceled; A never asks for its result either.
    feedback_a: list = []
    sent = a.send_goal_async(
        Autotune.Goal(target_c=TARGET), feedback_callback=lambda m: feedback_a.append(m)
    )
    ros.spin_until(sent.done, "A's second goal's answer", timeout=10)
    canceled = sent.result()
    assert canceled.accepted
    ros.spin_until(lambda: feedback_a, "A's run's feedback", timeout=10)
    c = canceled.cancel_goal_async()
    ros.spin_until(c.done, "A's cancel's answer", timeout=10)
    ros.spin_until(
        lambda: statuses(status_log).get(uuid_of(canceled)) == GoalStatus.STATUS_CANCELED,
        "A's second goal canceled",
    )
    ended_ns = mono_ns()

    # B, a second later: answered within a second, its run started within START_BY_S of the
    # answer (the relay's first rise on the trace, at most one period after the start).
    ros.spin_for(1.0)
    b = ActionClient(ros.node, Autotune, ACTION)
    ros.spin_until(b.server_is_ready, "the action server for B", timeout=30)
    feedback_b: list = []
    sent_ns = mono_ns()
    sent = b.send_goal_async(
        Autotune.Goal(target_c=TARGET), feedback_callback=lambda m: feedback_b.append(m)
    )
    ros.spin_until(sent.done, "B's goal's answer", timeout=10)
    answered_ns = mono_ns()
    handle_b = sent.result()
    assert handle_b.accepted
    ros.spin_until(lambda: feedback_b, "B's run's feedback", timeout=10)
    feedback_ns = mono_ns()
    print(
        f"B's goal answered in {(answered_ns - sent_ns) / MS:.1f} ms, its first feedback after "
        f"{(feedback_ns - sent_ns) / MS:.1f} ms"
    )
    assert answered_ns - sent_ns < 1000 * MS
    # A's results are still kept: ABORTED (refused) and CANCELED, whenever A asks.
    for handle, status, stop in (
        (refused, GoalStatus.STATUS_ABORTED, "refused"),
        (canceled, GoalStatus.STATUS_CANCELED, "canceled"),
    ):
        got = handle.get_result_async()
        ros.spin_until(got.done, "an unclaimed result", timeout=10)
        assert got.result().status == status, got.result()
        assert got.result().result.stop == stop, got.result().result
    ch.wait_status(lambda s: s.output, "B's relay switching the line on", timeout=10)
    got = handle_b.cancel_goal_async()
    ros.spin_until(got.done, "B's cancel's answer", timeout=10)
    got = handle_b.get_result_async()
    ros.spin_until(got.done, "B's result", timeout=10)
    assert got.result().status == GoalStatus.STATUS_CANCELED
    edges = close_trace(proc)
    # No rise between A's end and B's goal; B's run's first rise within START_BY_S of its answer
    # plus one period (the relay's duty starts with a period).
    between = [
        e
        for e in edges
        if e.level == 1 and ended_ns + PERIOD_S * 1e9 < e.scheduled_ns < sent_ns
    ]
    assert not between, [(e.scheduled_ns - ended_ns) / MS for e in between]
    rises = [e for e in edges if e.level == 1 and e.scheduled_ns >= sent_ns]
    assert rises, "B's run never switched the line on"
    first_rise_s = (rises[0].scheduled_ns - answered_ns) / 1e9
    print(f"B's first rise {(rises[0].scheduled_ns - sent_ns) / MS:.1f} ms after its goal")
    assert first_rise_s < START_BY_S + PERIOD_S, first_rise_s


def memory_kb(pid: int) -> dict[str, int]:
    """The memory figures of /proc/PID/status, kB: VmRSS, RssAnon, RssFile, VmHWM."""
    keys = ("VmRSS", "RssAnon", "RssFile", "VmHWM")
    got = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key = line.split(":")[0]
        if key in keys:
            got[key] = int(line.split()[1])
    assert set(got) == set(keys), got
    return got


def test_unknown_result_requests_are_answered_at_once(node_process, ros):
    start(node_process, ros, **PARAMS)
    # One request alone: answered at once with STATUS_UNKNOWN and an empty result.
    client = make_client(ros.node, ACTION)
    ros.spin_until(client.service_is_ready, "the get_result service", timeout=30)
    request = Autotune.Impl.GetResultService.Request()
    request.goal_id.uuid = list(uuid.uuid4().bytes)
    t0 = time.monotonic()
    answer = client.call_async(request)
    ros.spin_until(answer.done, "the answer for an unknown goal", timeout=10)
    took = time.monotonic() - t0
    assert answer.result().status == GoalStatus.STATUS_UNKNOWN
    assert answer.result().result == Autotune.Result()
    assert took < 1.0, took
    # A cancel of an unknown goal: ERROR_UNKNOWN_GOAL_ID, at once.
    cancel = ros.node.create_client(CancelGoal, f"{ACTION}/_action/cancel_goal")
    ros.spin_until(cancel.service_is_ready, "the cancel_goal service", timeout=10)
    req = CancelGoal.Request()
    req.goal_info.goal_id.uuid = list(uuid.uuid4().bytes)
    answer = cancel.call_async(req)
    ros.spin_until(answer.done, "the cancel of an unknown goal", timeout=10)
    assert answer.result().return_code == CancelGoal.Response.ERROR_UNKNOWN_GOAL_ID


# Two rounds of 100,000 requests: about 45 s here, twice that on a loaded machine. Untimed
# (pytest.ini): what the node's memory keeps, and every request answered (a client gives up
# only after 20 s without an answer); how soon one is answered is the test above's.
@pytest.mark.timeout(420)
@pytest.mark.untimed
def test_a_flood_of_unknown_result_requests_keeps_no_memory(
    node_process, process_launcher, ros, tmp_path
):
    proc, ch = start(node_process, ros, **PARAMS)
    # The flood, from processes of their own. Each first sends as many requests as it will
    # then, unmeasured: its participant is discovered, and the node's allocator reaches its
    # working set for this traffic (the DDS layer allocates and frees for each request on
    # several threads, and glibc keeps what was freed in per-thread arenas). Then it waits for
    # the start: what is measured is what the requests leave behind.
    go = tmp_path / "go"
    per = FLOOD // FLOOD_CLIENTS
    floods = [
        process_launcher.launch(
            [sys.executable, str(FLOOD_SCRIPT), ACTION, str(per), str(per), "8", str(go)],
            name=f"flood{i}",
        )
        for i in range(FLOOD_CLIENTS)
    ]
    for f in floods:
        f.wait_for_output("ready", timeout=max(120.0, per / 500.0), stream="stdout")
    ros.spin_for(1.0)
    before = memory_kb(proc.pid)
    t0 = time.monotonic()
    go.touch()
    for f in floods:
        f.wait_for_output("done", timeout=max(120.0, per / 500.0), stream="stdout")
    took = time.monotonic() - t0
    ros.spin_for(1.0)
    after = memory_kb(proc.pid)
    go.unlink()
    done = [
        line.split()
        for f in floods
        for line in f.stdout().splitlines()
        if line.startswith("done")
    ]
    for f in floods:
        assert f.wait_exit(timeout=30) == 0, f.output()
    answered = sum(int(d[1]) for d in done)
    unknown = sum(int(d[2]) for d in done)
    print(
        f"{answered} unknown get_result requests from {FLOOD_CLIENTS} clients in {took:.1f} s "
        f"({answered / took:.0f}/s): all STATUS_UNKNOWN: {unknown == answered}; node "
        + ", ".join(
            f"{k} {before[k]} -> {after[k]} kB ({after[k] - before[k]:+d})" for k in before
        )
    )
    assert answered == per * FLOOD_CLIENTS and unknown == answered
    assert after["VmRSS"] - before["VmRSS"] < 1024, (before, after)
    assert proc.is_running()
