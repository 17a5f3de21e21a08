"""Recorder and replay nodes across processes: record -> file -> replay, values compared."""

import signal
import threading
import time

import numpy as np
import pytest
from conftest import wait_for
from mcap_ros2.reader import read_ros2_messages
from rclpy.duration import Duration
from rclpy.qos import qos_profile_sensor_data
from rosgraph_msgs.msg import Clock
from sample_messages import force_trace, landmarks, raster_scan

from afm_core.recording import RecordingReader
from afm_msgs.msg import ForceTrace, LandmarkArray, RasterScan
from afm_ros.qos_profiles import LATCHED

pytestmark = pytest.mark.ros

TOPICS = "['/afm/scan','/afm/force_trace','/afm/landmarks']"


def publish_session(node, n_traces=20, period=0.02):
    """Latched scan + landmarks published before the recorder subscribes, then a stream."""
    scan_pub = node.create_publisher(RasterScan, "/afm/scan", LATCHED)
    marks_pub = node.create_publisher(LandmarkArray, "/afm/landmarks", LATCHED)
    # a history as deep as the stream: a reliable KEEP_LAST writer drops a sample it has not yet
    # repaired once `depth` newer ones follow (DDS's own rule), and with depth 10 at 50 Hz a
    # fresh clone's loaded run lost one that way (0, 1, 2, 4, ...); what the recorder is asked
    # to keep is what reached it, so the writer must not be the one losing messages
    trace_pub = node.create_publisher(ForceTrace, "/afm/force_trace", n_traces)
    scan_pub.publish(raster_scan(7))
    marks_pub.publish(landmarks(2))
    return scan_pub, marks_pub, trace_pub


def test_record_then_replay_round_trip(tmp_path, nodes, ros_node):
    path = tmp_path / "session.mcap"
    scan_pub, marks_pub, trace_pub = publish_session(ros_node)
    # arrival times: the replay is to reproduce the 20 ms pacing this test publishes with (the
    # sample messages' stamps are 1 s apart)
    recorder = nodes(
        "recorder", output=path, topics=TOPICS, discovery_period=0.1, log_time="receive"
    )
    wait_for(
        lambda: trace_pub.get_subscription_count() > 0 and scan_pub.get_subscription_count() > 0,
        15,
        what="recorder subscriptions",
    )
    sent = [force_trace(i) for i in range(20)]
    for msg in sent:
        trace_pub.publish(msg)
        time.sleep(0.02)
    time.sleep(0.5)
    code, output = recorder.stop(signal.SIGINT)
    assert code == 0, output
    assert path.exists() and not (tmp_path / "session.mcap.part").exists()

    # the independent decoder sees exactly what was published, latched messages included
    recorded = {"/afm/scan": [], "/afm/force_trace": [], "/afm/landmarks": []}
    log_times = []
    for item in read_ros2_messages(str(path)):
        recorded[item.channel.topic].append(item.ros_msg)
        if item.channel.topic == "/afm/force_trace":
            log_times.append(item.log_time_ns)
    assert [m.object_id for m in recorded["/afm/force_trace"]] == list(range(20))
    np.testing.assert_array_equal(
        recorded["/afm/force_trace"][5].vertical_deflection, sent[5].vertical_deflection
    )
    assert bytes(recorded["/afm/scan"][0].height.data) == bytes(raster_scan(7).height.data)
    assert [lm.id for lm in recorded["/afm/landmarks"][0].landmarks] == [20, 21, 22]
    gaps = np.diff(log_times) * 1e-9
    assert 0.01 < np.median(gaps) < 0.2  # the publisher's 20 ms pacing is what was recorded

    # replay into this process: same values, latched QoS kept, original pacing, /clock
    for publisher in (scan_pub, marks_pub, trace_pub):
        ros_node.destroy_publisher(publisher)
    wait_for(
        lambda: not ros_node.get_publishers_info_by_topic("/afm/scan"),
        5,
        what="test publishers gone",
    )
    received = {"scan": [], "trace": [], "clock": [], "landmarks": []}
    lock = threading.Lock()

    def keep(key):
        # the publisher's source timestamp: the replay's pacing, not when this process's
        # executor got round to the callback (late callbacks bunch up on a loaded machine)
        def callback(msg, info):
            with lock:
                received[key].append((info["source_timestamp"] * 1e-9, msg))

        return callback

    ros_node.create_subscription(RasterScan, "/afm/scan", keep("scan"), LATCHED)
    ros_node.create_subscription(ForceTrace, "/afm/force_trace", keep("trace"), 50)
    ros_node.create_subscription(Clock, "/clock", keep("clock"), 50)
    ros_node.create_subscription(LandmarkArray, "/afm/landmarks", keep("landmarks"), LATCHED)
    replay = nodes("replay", input=path, rate=1.0, start_delay=0.2, wait_for_subscribers=1)
    code, output = replay.wait(60)
    assert code == 0, output
    wait_for(lambda: len(received["trace"]) == 20, 5, what="20 replayed traces")
    assert [m.object_id for _, m in received["trace"]] == list(range(20))
    np.testing.assert_array_equal(
        received["trace"][13][1].lateral_torsion, sent[13].lateral_torsion
    )
    assert len(received["scan"]) == 1 and received["scan"][0][1].pair_id == raster_scan(7).pair_id
    assert received["landmarks"][0][1] == landmarks(2)
    # the recorded pacing: no trace goes out earlier after the first message than it was
    # recorded after it (an unpaced replay sends all within milliseconds); a stall on a shared
    # machine only delays, and the messages then due go out at once, as rosbag2 does
    with RecordingReader(path) as reader:
        recorded_at = {
            (topic, i): message.log_time
            for topic in ("/afm/scan", "/afm/landmarks")
            for i, (_, _, message) in enumerate(reader.raw_messages([topic]))
        }
    first_rec = min(recorded_at.values())
    first_sent = min(
        t
        for key, topic in (("scan", "/afm/scan"), ("landmarks", "/afm/landmarks"))
        for i, (t, _) in enumerate(received[key])
        if recorded_at[(topic, i)] == first_rec
    )
    replay_after_first = np.array([t for t, _ in received["trace"]]) - first_sent
    recorded_after_first = (np.array(log_times) - first_rec) * 1e-9
    assert np.all(replay_after_first > recorded_after_first - 0.002)
    assert replay_after_first[-1] < recorded_after_first[-1] + 10.0
    clock_ns = [m.clock.sec * 10**9 + m.clock.nanosec for _, m in received["clock"]]
    with RecordingReader(path) as reader:
        assert reader.start_time_ns <= min(clock_ns) and max(clock_ns) <= reader.end_time_ns
    assert np.all(np.diff(clock_ns) >= 0)


def test_replay_rate_and_topic_filter(tmp_path, nodes, ros_node):
    from sample_messages import cdr

    from afm_core.recording import QosDescription, RecordingWriter

    path = tmp_path / "paced.mcap"
    with RecordingWriter(path) as rec:
        trace = rec.add_channel("/afm/force_trace", "afm_msgs/msg/ForceTrace", [QosDescription()])
        scan = rec.add_channel("/afm/scan", "afm_msgs/msg/RasterScan", [QosDescription()])
        for i in range(11):  # 2 s of recording
            rec.write(trace, 10**9 + i * 2 * 10**8, cdr(force_trace(i)))
        rec.write(scan, 10**9, cdr(raster_scan(0)))
    arrivals, scans = [], []
    ros_node.create_subscription(
        ForceTrace,
        "/afm/force_trace",
        lambda m, info: arrivals.append(info["source_timestamp"] * 1e-9),
        50,
    )
    ros_node.create_subscription(RasterScan, "/afm/scan", scans.append, 50)
    code, output = nodes(
        "replay",
        input=path,
        rate=4.0,
        topics="['/afm/force_trace']",
        start_delay=0.2,
        wait_for_subscribers=1,
    ).wait(60)
    assert code == 0, output
    wait_for(lambda: len(arrivals) == 11, 5, what="11 traces")
    # 2 s at 4x is 0.5 s and never less; at 1x it would be 2 s (a shared machine can stall it)
    assert 0.495 < arrivals[-1] - arrivals[0] < 1.5
    assert scans == []


def test_replay_into_a_graph_whose_node_publishes_the_same_topic_warns(tmp_path, nodes, ros_node):
    """Replayed into a running graph, its nodes and recorder got both sessions mixed without a
    word."""
    from sample_messages import cdr

    from afm_core.recording import QosDescription, RecordingWriter

    path = tmp_path / "traces.mcap"
    with RecordingWriter(path) as rec:
        trace = rec.add_channel("/afm/force_trace", "afm_msgs/msg/ForceTrace", [QosDescription()])
        for i in range(3):
            rec.write(trace, 10**9 + i * 10**8, cdr(force_trace(i)))
    ros_node.create_publisher(ForceTrace, "/afm/force_trace", 10)  # a live driver's
    ros_node.create_subscription(ForceTrace, "/afm/force_trace", lambda _m: None, 10)
    code, output = nodes(
        "replay", input=path, start_delay=1.0, wait_for_subscribers=1, publish_clock=False
    ).wait(60)
    assert code == 0, output
    assert "other nodes publish what this replay publishes: /afm/force_trace (" in output
    assert ros_node.get_name() in output.split("/afm/force_trace (", 1)[1]


def test_replay_delivers_bursts_to_reliable_subscribers(tmp_path, nodes, ros_node):
    """Bursts larger than any publisher history, on topics recorded as our recorder records
    them (history depth unknown to the graph API) and one recorded best-effort: a reliable
    subscriber gets every message, in order. With one-message histories and the replay exiting
    right after its last message, a 40-message burst arrived with a third missing."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sample_messages import cdr

    from afm_core.recording import QosDescription, RecordingWriter

    path = tmp_path / "bursts.mcap"
    burst = 300
    as_recorded = dict(history="unknown", depth=0)
    with RecordingWriter(path) as rec:
        traces = rec.add_channel(
            "/afm/force_trace",
            "afm_msgs/msg/ForceTrace",
            [QosDescription(reliability="best_effort", **as_recorded)],
        )
        marks = rec.add_channel(
            "/afm/landmarks",
            "afm_msgs/msg/LandmarkArray",
            [QosDescription(durability="transient_local", **as_recorded)],
        )
        for i in range(burst):
            rec.write(traces, 10**9 + i * 10**4, cdr(force_trace(i)))
            rec.write(marks, 10**9 + i * 10**4, cdr(landmarks(i)))
    received = {"traces": [], "marks": []}
    reliable = QoSProfile(depth=10 * burst, reliability=ReliabilityPolicy.RELIABLE)
    latched = QoSProfile(
        depth=10 * burst,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    ros_node.create_subscription(
        ForceTrace, "/afm/force_trace", lambda m: received["traces"].append(m.object_id), reliable
    )
    ros_node.create_subscription(
        LandmarkArray,
        "/afm/landmarks",
        lambda m: received["marks"].append(m.landmarks[0].id),
        latched,
    )
    code, output = nodes(
        "replay",
        input=path,
        start_delay=0.0,
        wait_for_subscribers=1,
        wait_timeout=10.0,
        publish_clock="false",
    ).wait(60)
    assert code == 0, output
    wait_for(
        lambda: len(received["traces"]) >= burst and len(received["marks"]) >= burst,
        5,
        what=f"{burst} messages on each topic",
    )
    assert received["traces"] == list(range(burst))
    assert received["marks"] == [landmarks(i).landmarks[0].id for i in range(burst)]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signalled_recorder_leaves_a_readable_file(tmp_path, nodes, ros_node, sig):
    path = tmp_path / "killed.mcap"
    trace_pub = ros_node.create_publisher(ForceTrace, "/afm/force_trace", qos_profile_sensor_data)
    recorder = nodes("recorder", output=path, topics="['/afm/force_trace']", discovery_period=0.1)
    wait_for(lambda: trace_pub.get_subscription_count() > 0, 15, what="recorder subscription")
    stop_publishing = threading.Event()

    def stream():
        i = 0
        while not stop_publishing.is_set():
            trace_pub.publish(force_trace(i % 50))
            i += 1
            time.sleep(0.005)

    publisher = threading.Thread(target=stream)
    publisher.start()
    time.sleep(1.0)
    code, output = recorder.stop(sig)  # mid-stream
    stop_publishing.set()
    publisher.join()
    assert code == 0, output
    with RecordingReader(path) as reader:
        assert reader.topics()["/afm/force_trace"].message_count > 20
        assert reader.topics()["/afm/force_trace"].offered_qos[0].reliability == "best_effort"


def test_a_recording_named_with_yaml_characters_gets_that_name(tmp_path, nodes, ros_node):
    """ROS reads a -p value as YAML: "run #3: sphere's.mcap" was a comment, a mapping or a
    broken quote before the path parameters were passed quoted."""
    path = tmp_path / "run #3: sphere's [x].mcap"
    trace_pub = ros_node.create_publisher(ForceTrace, "/afm/force_trace", 10)
    recorder = nodes("recorder", output=path, topics="['/afm/force_trace']", discovery_period=0.1)
    wait_for(lambda: trace_pub.get_subscription_count() > 0, 15, what="recorder subscription")
    trace_pub.publish(force_trace(0))
    time.sleep(0.5)
    code, output = recorder.stop(signal.SIGINT)
    assert code == 0, output
    with RecordingReader(path) as reader:
        assert reader.topics()["/afm/force_trace"].message_count == 1


def test_hard_killed_recorder_is_recoverable(tmp_path, nodes, ros_node):
    from afm_core.recording import recover_recording

    path = tmp_path / "crash.mcap"
    # a deep reliable publisher queue and the recorder's keep-all: DDS delivers all 200 in
    # order even if the recorder stalls, so what reached the disk is exactly a prefix of what
    # was sent
    trace_pub = ros_node.create_publisher(ForceTrace, "/afm/force_trace", 1000)
    recorder = nodes(
        "recorder",
        output=path,
        topics="['/afm/force_trace']",
        discovery_period=0.1,
        chunk_size=16384,
    )
    wait_for(lambda: trace_pub.get_subscription_count() > 0, 15, what="recorder subscription")
    for i in range(200):
        trace_pub.publish(force_trace(i))
        time.sleep(0.002)
    time.sleep(0.5)
    recorder.stop(signal.SIGKILL)
    assert not path.exists()
    recovered, count = recover_recording(tmp_path / "crash.mcap.part")
    assert count > 100  # every chunk that reached the disk
    with RecordingReader(recovered) as reader:
        ids = reader.arrays("/afm/force_trace")["object_id"]
    np.testing.assert_array_equal(ids, np.arange(count))


def test_a_burst_larger_than_any_queue_reaches_the_recording_whole(tmp_path, nodes, ros_node):
    """6000 force traces published at once, reliably, to a recorder that compresses a chunk
    every few messages, stopped once it has written what it acknowledged: each one is
    recorded, in order. A keep-last-100 subscription lost 134 and 237 of them in two runs
    (the oldest, whenever the writer fell behind the burst)."""
    path = tmp_path / "burst.mcap"
    burst = 6000
    trace_pub = ros_node.create_publisher(ForceTrace, "/afm/force_trace", burst)
    recorder = nodes(
        "recorder",
        output=path,
        topics="['/afm/force_trace']",
        discovery_period=0.1,
        chunk_size=16384,
    )
    wait_for(lambda: trace_pub.get_subscription_count() > 0, 15, what="recorder subscription")
    for i in range(burst):
        trace_pub.publish(force_trace(i))
    assert trace_pub.wait_for_all_acked(Duration(seconds=60)), (
        "the recorder did not acknowledge the burst"
    )
    # acknowledged is in the recorder's queue, not yet written: it writes on (a stop drains
    # the queue for at most DRAIN_SECONDS, which a loaded machine needs more than for 6000)
    part = path.with_name(path.name + ".part")
    sizes = []
    wait_for(
        lambda: sizes.append(part.stat().st_size) or sizes[-12:] == [sizes[-1]] * 12,
        60,
        interval=0.25,
        what="the recorder's file to stop growing",
    )
    code, output = recorder.stop(signal.SIGINT)
    assert code == 0, output
    with RecordingReader(path) as reader:
        ids = reader.arrays("/afm/force_trace")["object_id"]
    np.testing.assert_array_equal(ids, np.arange(burst))


@pytest.mark.parametrize(
    "overrides, complaint",
    [
        ({}, "parameter output: required"),
        ({"output": "EXISTING"}, "already exists; recordings are never overwritten"),
        ({"output": "x.bag"}, "must end in .mcap"),
        ({"output": "/nonexistent_dir/x.mcap"}, "directory '/nonexistent_dir' does not exist"),
        ({"output": "OK", "compression": "gzip"}, "compression='gzip'"),
    ],
)
def test_bad_recorder_arguments_are_rejected_clearly(tmp_path, nodes, overrides, complaint):
    existing = tmp_path / "existing.mcap"
    existing.write_bytes(b"keep me")
    replace = {"EXISTING": str(existing), "OK": str(tmp_path / "ok.mcap")}
    overrides = {k: replace.get(v, v) for k, v in overrides.items()}
    code, output = nodes("recorder", **overrides).wait(30)
    assert code == 2 and complaint in output, output
    assert existing.read_bytes() == b"keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["existing.mcap"]


def test_replay_gives_up_when_nobody_listens(tmp_path, nodes):
    from test_recording_files import write_session

    path = tmp_path / "s.mcap"
    write_session(path, n=1)
    code, output = nodes(
        "replay", input=path, wait_for_subscribers=1, wait_timeout=1.0, topics="['/afm/landmarks']"
    ).wait(30)
    assert code == 1 and "wait_for_subscribers=1" in output and "/afm/landmarks" in output, output


@pytest.mark.parametrize(
    "overrides, complaint",
    [
        ({"input": "/nonexistent.mcap"}, "does not exist"),
        ({"input": "FILE", "rate": "0.0"}, "parameter rate=0.0: must be > 0"),
        ({"input": "FILE", "topics": "['/afm/nothing']"}, "['/afm/nothing'] not in"),
    ],
)
def test_bad_replay_arguments_are_rejected_clearly(tmp_path, nodes, overrides, complaint):
    path = tmp_path / "s.mcap"
    from test_recording_files import write_session

    write_session(path, n=1)
    overrides = {k: (str(path) if v == "FILE" else v) for k, v in overrides.items()}
    code, output = nodes("replay", **overrides).wait(30)
    assert code == 2 and complaint in output, output


def test_replay_loops_until_stopped(tmp_path, nodes, ros_node):
    from sample_messages import cdr

    from afm_core.recording import QosDescription, RecordingWriter

    path = tmp_path / "three.mcap"
    with RecordingWriter(path) as rec:
        trace = rec.add_channel("/afm/force_trace", "afm_msgs/msg/ForceTrace", [QosDescription()])
        for i in range(3):
            rec.write(trace, 10**9 + i * 10**8, cdr(force_trace(i)))
    ids = []
    ros_node.create_subscription(
        ForceTrace, "/afm/force_trace", lambda m: ids.append(m.object_id), 50
    )
    replay = nodes(
        "replay", input=path, rate=2.0, loop="true", start_delay=0.2, wait_for_subscribers=1
    )
    wait_for(lambda: len(ids) >= 9, 20, what="three passes of the recording")
    code, output = replay.stop(signal.SIGINT)
    assert code == 0, output
    assert ids[:9] == [0, 1, 2] * 3
