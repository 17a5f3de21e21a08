"""Faults on the running graph: a killed driver, nano-hand, recorder or launcher never hangs the
rest; every node stops within 2 s on SIGINT/SIGTERM, even mid-action."""

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from conftest import wait_for
from std_msgs.msg import Header
from test_driver import scan_goal

from afm_bringup.commander import AfmCommander, AfmError
from afm_core.imaging.landmarks import Landmark
from afm_core.recording import RecordingReader, recover
from afm_msgs.action import ScanImage
from afm_msgs.msg import LandmarkArray, TipCommand
from afm_ros import topics
from afm_ros.action_client import SERVER_SILENCE_S, SafeActionClient
from afm_ros.action_instrument import DriverUnavailable, call_action
from afm_ros.conversions import landmarks_to_msg
from afm_ros.qos_profiles import LATCHED

pytestmark = pytest.mark.ros

AFM = [sys.executable, "-m", "afm_bringup.cli"]
# How soon a dead server must be noticed: the heartbeat's silence plus a probe period and
# scheduling on a loaded two-core machine (the bound: "within a few seconds").
NOTICE_S = SERVER_SILENCE_S + 2.0
STOP_S = 2.0  # every node honours SIGINT/SIGTERM within this, even mid-action
GOODBYE_S = 3.0  # s: how soon a peer drops a node that stopped (the goodbye is one UDP packet)


def stop_time(node, sig) -> float:
    t0 = time.monotonic()
    node.process.send_signal(sig)
    node.process.wait(timeout=15)
    return time.monotonic() - t0


def test_a_killed_driver_ends_every_wait_for_it_within_seconds(nodes, ros_node):
    """The CLI's commander and the graph's call_action, each waiting on a driver goal."""
    driver = nodes("driver", seed=2, real_time_factor=1.0)
    client = SafeActionClient(ros_node, ScanImage, topics.ACTION_SCAN_IMAGE)
    outcome = {}

    def graph_helper():
        try:
            call_action(client, scan_goal(pixels=(16, 16), line_rate=4.0), 30.0, 600.0)
            outcome["error"] = "returned a result"
        except DriverUnavailable as exc:
            outcome["error"], outcome["at"] = str(exc), time.monotonic()

    with AfmCommander(server_timeout=30) as afm:
        scan = afm.send("scan_image", scan_goal(pixels=(64, 256), line_rate=1.0), wait=False)
        wait_for(lambda: scan.feedback is not None, 60, what="the scan started")
        helper = threading.Thread(target=graph_helper)
        helper.start()  # its goal queues behind the scan
        # the driver killed before it had answered this new client would be "did not answer",
        # not "gone": on a loaded machine matching a new client took more than a second
        wait_for(lambda: client._answered_at > 0, 30, what="the driver answering call_action")
        time.sleep(1.0)
        killed = time.monotonic()
        driver.process.kill()
        with pytest.raises(AfmError, match="aborted: server gone"):
            scan.result(60)
        commander_s = time.monotonic() - killed
        helper.join(60)
    assert "aborted: driver gone" in outcome["error"], outcome
    helper_s = outcome["at"] - killed
    print(f"driver killed: commander {commander_s:.1f} s, call_action {helper_s:.1f} s")
    assert commander_s < NOTICE_S and helper_s < NOTICE_S, (commander_s, helper_s)


def test_a_driver_with_a_full_queue_still_answers_the_heartbeat(nodes):
    """Queued goals hold executor threads; the probe (a cancel) must still be served, or a
    busy driver would be taken for a dead one."""
    from test_driver import move_goal

    nodes("driver", seed=2, real_time_factor=1.0, max_queued_goals=5)
    with (
        AfmCommander(server_timeout=30) as afm,
        AfmCommander("second_commander", server_timeout=30) as other,
    ):
        scan = afm.send("scan_image", scan_goal(pixels=(64, 256), line_rate=1.0), wait=False)
        moves = [
            afm.send("move_tip", move_goal(20e-6, 20e-6 + i * 1e-6, speed=10e-6), wait=False)
            for i in range(5)
        ]
        wait_for(lambda: scan.feedback is not None, 60, what="the scan started")
        time.sleep(0.5)
        t0 = time.monotonic()
        assert other.clients["move_tip"].wait_until_answering(SERVER_SILENCE_S)
        answered_s = time.monotonic() - t0
        with pytest.raises(AfmError, match="no result after"):
            moves[-1].result(SERVER_SILENCE_S + 1.0)  # waited past the silence: not "gone"
        for job in [*moves, scan]:
            job.cancel()
    print(f"full queue: the driver answered a probe in {answered_s:.3f} s")


def fake_map(ros_node, position=(55e-6, 55e-6)):
    """One sphere where the simulator has one, as the imaging node would publish it."""
    mark = Landmark(
        id=1,
        kind="sphere",
        x=position[0],
        y=position[1],
        covariance=np.eye(2) * 25e-18,
        radius=100e-9,
        height=200e-9,
        length=0.0,
        orientation=0.0,
    )
    publisher = ros_node.create_publisher(LandmarkArray, topics.LANDMARKS, LATCHED)
    publisher.publish(landmarks_to_msg([mark], Header(frame_id="afm_task")))
    return publisher


def start_push(afm, phases):
    return afm.push(
        (55e-6, 55.3e-6),
        particle_position=(55e-6, 55e-6),
        feedback=lambda f: phases.append(f.phase),
        wait=False,
    )


def test_a_driver_killed_mid_push_frees_the_nano_hand(nodes, ros_node):
    driver = nodes("driver", seed=2, real_time_factor=1.0)
    hand = nodes("nano_hand")
    _keep = fake_map(ros_node)
    phases = []
    with AfmCommander(server_timeout=30) as afm:
        job = start_push(afm, phases)
        wait_for(lambda: "scanning" in phases, 60, what="the push's first scan")
        time.sleep(1.0)  # the driver is mid-action (pits, then the before-scan)
        killed = time.monotonic()
        driver.process.kill()
        result = job.result(60)
        noticed = time.monotonic() - killed
        print(f"driver killed mid-push: the push ended {noticed:.1f} s later: {result.message}")
        assert not result.success and "aborted: driver gone" in result.message, result.message
        assert noticed < NOTICE_S + 1.0, noticed  # + the goal's result reaching us
        # not "busy" forever: the next push is accepted and fails with the reason
        again = afm.push((55e-6, 55.3e-6), particle_position=(55e-6, 55e-6), timeout=60)
        assert not again.success and "is its node running" in again.message, again.message
    assert stop_time(hand, signal.SIGTERM) < STOP_S


def push_ending(job) -> str:
    """How a client learns that the nano-hand stopped mid-push: its own aborted result (the
    node ends its goal within its stop grace when the reply leaves before the process does),
    or, when the process went first, the heartbeat's "server gone". Which one comes depends on
    the scheduling of the stopping node's last milliseconds; both name the cause."""
    try:
        result = job.result(60)
    except AfmError as exc:
        return str(exc)
    assert not result.success, result.message
    return result.message


def test_nodes_stop_within_two_seconds_mid_action(nodes, ros_node):
    driver = nodes("driver", seed=2, real_time_factor=1.0)
    hand = nodes("nano_hand")
    _keep = fake_map(ros_node)
    phases = []
    with AfmCommander(server_timeout=30) as afm:
        job = start_push(afm, phases)
        wait_for(lambda: "scanning" in phases, 60, what="the push's first scan")
        time.sleep(1.0)  # the nano-hand waits on the driver
        hand_s = stop_time(hand, signal.SIGTERM)
        ending = push_ending(job)
        assert "aborted: server gone" in ending or "this node is stopping" in ending, ending
        scan = afm.send("scan_image", scan_goal(pixels=(64, 256), line_rate=1.0), wait=False)
        wait_for(lambda: scan.feedback is not None, 60, what="a scan started")
        driver_s = stop_time(driver, signal.SIGINT)
    print(f"mid-action stop: nano-hand (SIGTERM) {hand_s:.2f} s ({ending}),", end=" ")
    print(f"driver (SIGINT) {driver_s:.2f} s")
    assert hand_s < STOP_S and driver_s < STOP_S, (hand_s, driver_s)


def test_a_node_stopped_after_its_work_says_nothing_of_unread_errors(nodes):
    """Callbacks handed to the pool as the stop came used to fail on the destroyed executor
    and rclpy printed "The following exception was never retrieved" at every stop."""
    driver = nodes("driver", seed=2, real_time_factor=0.0)
    with AfmCommander(server_timeout=60) as afm:
        afm.scan(origin=(54.6e-6, 54.6e-6), size=(0.5e-6, 0.5e-6), pixels=(32, 32))
    status, output = driver.stop(signal.SIGINT)
    assert status == 0, output
    assert "never retrieved" not in output and "failed while stopping" not in output, output


def test_a_stopped_node_leaves_the_graph_at_once_a_killed_one_stays_listed(nodes, ros_node):
    """A node stopped by a signal says goodbye: `ros2 node list` and every peer drop it at
    once. A killed one cannot: its participant stays listed, its endpoints matched, until its
    lease runs out (Fast DDS: 20 s). The test fixtures stop nodes by signal for this reason."""

    def listed(name):
        return name in ros_node.get_node_names()

    for sig, name in ((signal.SIGINT, "planner"), (signal.SIGKILL, "planner")):
        node = nodes(name)
        wait_for(lambda: listed("afm_planner"), 30, what="the planner listed")
        node.stop(sig)
        time.sleep(GOODBYE_S)
        if sig == signal.SIGINT:
            assert not listed("afm_planner"), f"listed {GOODBYE_S} s after a clean stop"
        else:  # its lease has not run out
            assert listed("afm_planner"), f"not listed {GOODBYE_S} s after it was killed"


def test_afm_push_ends_soon_after_the_nano_hand_is_killed(nodes, ros_node):
    """The CLI without --timeout: the nano-hand killed mid-push ends it with the reason."""
    nodes("driver", seed=2, real_time_factor=1.0)
    hand = nodes("nano_hand")
    _keep = fake_map(ros_node)
    push = subprocess.Popen(
        AFM + ["push", "--at", "55um", "55um", "--goal", "55um", "55.3um"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines = []
    threading.Thread(target=lambda: lines.extend(push.stdout), daemon=True).start()
    try:
        wait_for(lambda: any("[scanning]" in line for line in lines), 60, what="push feedback")
        killed = time.monotonic()
        hand.process.kill()
        push.wait(30)
        ended_s = time.monotonic() - killed
    finally:
        if push.poll() is None:
            push.kill()
    print(f"nano-hand killed: afm push ended {ended_s:.1f} s later")
    assert push.returncode != 0 and "aborted: server gone" in "".join(lines), lines
    assert ended_s < NOTICE_S + 1.0, ended_s


def test_a_killed_recorder_loses_at_most_about_a_second(tmp_path, nodes, ros_node):
    output = tmp_path / "r.mcap"
    recorder = nodes(
        "recorder",
        output=str(output),
        topics="['/afm/tip_command']",
        discovery_period=0.1,
        log_time="receive",  # the stamps below count messages (from 0, unset), not time
    )
    publisher = ros_node.create_publisher(TipCommand, topics.TIP_COMMAND, 100)
    wait_for(lambda: publisher.get_subscription_count() > 0, 30, what="the recorder")
    time.sleep(0.5)
    sent = []  # wall time of each message, indexed by its header stamp
    for i in range(80):  # 4 s at 20 Hz
        msg = TipCommand()
        msg.header.stamp.sec = i
        publisher.publish(msg)
        sent.append(time.monotonic())
        time.sleep(0.05)
    recorder.process.kill()
    killed = time.monotonic()
    recorder.process.wait(10)
    assert not output.exists()
    recovery = recover(tmp_path / "r.mcap.part")
    with RecordingReader(recovery.path) as reader:
        stamps = [m.header.stamp.sec for _, _, m in reader.messages()]
    assert stamps == list(range(len(stamps))), stamps  # a gap-free prefix
    lost_s = killed - sent[stamps[-1]]
    print(f"recorder killed: {len(sent) - len(stamps)} messages, the last {lost_s:.2f} s, lost")
    assert lost_s <= 1.0 + 0.3, lost_s  # flush_interval + delivery and scheduling


def children_of(pid) -> dict[int, str]:
    found = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = open(f"/proc/{entry}/stat").read()
            cmdline = open(f"/proc/{entry}/cmdline").read().replace("\0", " ")
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            found[int(entry)] = cmdline
    return found


def alive(pid) -> bool:
    try:
        state = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_a_killed_launcher_takes_its_nodes_and_a_killed_recorder_is_restarted(tmp_path):
    record = tmp_path / "g.mcap"
    log = open(tmp_path / "launch.log", "wb")
    launch = subprocess.Popen(
        AFM + ["launch", "--nodes", "driver", "--record", str(record)],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    text = lambda: (tmp_path / "launch.log").read_text()  # noqa: E731
    try:
        wait_for(lambda: "afm launch: ready" in text(), 60, what="launch ready")
        children = children_of(launch.pid)
        recorder = next(pid for pid, cmd in children.items() if "recorder_node" in cmd)
        os.kill(recorder, signal.SIGKILL)
        wait_for(lambda: "recorder restarted" in text(), 20, what="the recorder's restart")
        assert "exited with status -9" in text()
        restarted = tmp_path / "g.restart1.mcap"
        wait_for(lambda: restarted.with_name(restarted.name + ".part").exists(), 20)
        survivors = children_of(launch.pid)
        assert len(survivors) == 2 and recorder not in survivors  # driver and a new recorder
        launch.kill()
        launch.wait(10)
        wait_for(lambda: not any(alive(p) for p in survivors), 10, what="the nodes to die with it")
    finally:
        if launch.poll() is None:
            launch.kill()
        for pid in children_of(launch.pid):
            os.kill(pid, signal.SIGKILL)
    assert restarted.exists()  # the restarted recorder stopped cleanly: summary, final name
    assert (tmp_path / "g.mcap.part").exists()  # the killed one's, for `afm recover`


def test_replay_of_a_damaged_recording_exits_with_the_reason(tmp_path):
    from test_recording_durability import chunk_messages, flip_bit, write_chunked

    path = tmp_path / "d.mcap"
    write_chunked(path)
    victim, _ = chunk_messages(path)[1]
    flip_bit(path, victim.chunk_start_offset + victim.chunk_length // 2)
    result = subprocess.run(
        AFM + ["replay", str(path), "--rate", "50", "--no-clock"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode != 0 and "chunks damaged" in result.stderr, result.stderr
