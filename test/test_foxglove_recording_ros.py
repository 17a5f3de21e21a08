"""A recorded session that Foxglove and `ros2 bag play` show as it is: the frame tree on
/tf_static and /tf, every scan and map also as an rgb8 Image, the planner's markers, all
recorded by default, and one time base (log time = header stamp, the instrument's clock)."""

import signal
import time

import numpy as np
import pytest
from conftest import wait_for
from test_driver import scan_goal
from test_planner_node import call, start_pose

from afm_core.imaging.colour_map import height_to_rgb
from afm_core.recording import RecordingReader
from afm_core.recording.stamps import stamp_layout, stamp_ns
from afm_msgs.msg import TipCommand
from afm_msgs.srv import PlanObservation
from afm_ros import topics

pytestmark = pytest.mark.ros

LINE_RATE = 1.0  # Hz: the 32-line scan takes 32 s of instrument time, more than the test's wall
# time, so a marker stamped with wall time would fall before the scan's end


def record_session(tmp_path, nodes, ros_node):
    from sensor_msgs.msg import Image

    from afm_bringup.commander import AfmCommander
    from afm_ros.qos_profiles import LATCHED

    path = tmp_path / "session.mcap"
    recorder = nodes("recorder", output=path, discovery_period=0.1)  # the default topics
    for name in ("driver", "imaging", "localizer", "planner"):
        nodes(name, **({"seed": 5} if name == "driver" else {}))
    maps = []
    ros_node.create_subscription(Image, topics.MAP_IMAGE, maps.append, LATCHED)
    with AfmCommander(server_timeout=60) as afm:
        afm.clients["scan_image"].wait_for_server(timeout_sec=60)
        afm.wait_until_subscribed([topics.TIP_COMMAND], "afm_localizer", timeout=30)
        # /tf is volatile: the recorder must hear the localizer's publisher before the session
        afm.wait_until_subscribed(
            [topics.SCAN_IMAGE, topics.TF_STATIC, topics.TF, topics.TIP_COMMAND], timeout=30
        )
        afm.wait_until_subscribed([topics.SCAN], "afm_imaging", timeout=30)
        scan = afm.send("scan_image", scan_goal(pixels=(32, 32), line_rate=LINE_RATE))
        assert scan.success, scan.message
    wait_for(lambda: maps, 30, what="the map image")
    request = PlanObservation.Request(
        start=start_pose(54.7e-6, 55.0e-6, 20e-9), landmark_id=-1, radius=100e-9
    )
    request.position.x, request.position.y = 55.0e-6, 55.0e-6
    assert call(ros_node, PlanObservation, topics.SERVICE_PLAN_OBSERVATION, request).success
    time.sleep(1.0)  # the markers and the last poses reach the recorder
    code, output = recorder.stop(signal.SIGINT)
    assert code == 0, output
    return path


def stamp_of(msg) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def read(path):
    """({topic: [(log time, decoded message)]}, [(topic, log time, stamp or None)])."""
    with RecordingReader(path) as reader:
        by_topic = {topic: [] for topic in reader.topics()}
        for topic, log_ns, msg in reader.messages():
            by_topic[topic].append((log_ns, msg))
        layouts, raw = {}, []
        for schema, channel, message in reader.raw_messages():
            if schema.name not in layouts:
                layouts[schema.name] = stamp_layout(schema.name, schema.data.decode())
            raw.append(
                (channel.topic, message.log_time, stamp_ns(message.data, layouts[schema.name]))
            )
    return by_topic, raw


def test_a_recorded_session_shows_frames_images_markers_on_one_time_base(
    tmp_path, nodes, ros_node
):
    by_topic, raw = read(record_session(tmp_path, nodes, ros_node))
    for topic in (
        topics.TF_STATIC,
        topics.TF,
        topics.SCAN_IMAGE,
        topics.MAP_IMAGE,
        topics.MARKERS,
    ):
        assert by_topic.get(topic), f"{topic} not recorded (recorded: {sorted(by_topic)})"

    # the static tree: afm_image coincides with afm_task
    static = [t for _, m in by_topic[topics.TF_STATIC] for t in m.transforms]
    assert {(t.header.frame_id, t.child_frame_id) for t in static} == {("afm_task", "afm_image")}
    for t in static:
        translation, rotation = t.transform.translation, t.transform.rotation
        assert (translation.x, translation.y, translation.z) == (0.0, 0.0, 0.0)
        assert (rotation.x, rotation.y, rotation.z, rotation.w) == (0.0, 0.0, 0.0, 1.0)

    # /tf: the commanded tip position mapped onto the localizer's estimate at the same stamp
    poses = {stamp_of(m): m.pose.pose.position for _, m in by_topic[topics.TIP_POSE]}
    ends = sorted(
        (stamp_of(m) + round(m.duration * 1e9), (m.end.x, m.end.y))
        for _, m in by_topic[topics.TIP_COMMAND]
    )
    checked = 0
    for _, msg in by_topic[topics.TF]:
        (t,) = msg.transforms
        assert (t.header.frame_id, t.child_frame_id) == ("afm_task", "afm_scanner")
        stamp = stamp_of(t)
        if stamp not in poses:
            continue  # its pose was published but is not the one recorded last with that stamp
        commanded = [end for end_ns, end in ends if end_ns <= stamp + 1000][-1]
        estimate = poses[stamp]
        np.testing.assert_allclose(
            [t.transform.translation.x, t.transform.translation.y],
            [estimate.x - commanded[0], estimate.y - commanded[1]],
            rtol=0,
            atol=1e-12,
        )
        checked += 1
    assert checked >= 1

    # every scan and map also as an rgb8 picture of its heights, same stamp and frame
    for source, image_topic in (
        (topics.SCAN, topics.SCAN_IMAGE),
        (topics.CORRECTED_MAP, topics.MAP_IMAGE),
    ):
        scans, images = by_topic[source], by_topic[image_topic]
        assert len(images) == len(scans) >= 1
        for (_, scan), (_, image) in zip(scans, images, strict=True):
            height = np.frombuffer(bytes(scan.height.data), "<f4").reshape(
                scan.height.height, scan.height.width
            )
            assert image.encoding == "rgb8" and image.step == 3 * image.width
            assert (image.height, image.width) == height.shape
            assert stamp_of(image) == stamp_of(scan)
            assert image.header.frame_id == scan.header.frame_id
            assert bytes(image.data) == height_to_rgb(height)[0].tobytes()

    # the landmark map as markers: per landmark its 3-sigma ellipse (and a sphere)
    (_, marks), (_, drawn) = by_topic[topics.LANDMARKS][-1], by_topic[topics.LANDMARK_MARKERS][-1]
    assert len(marks.landmarks) >= 1 and stamp_of(drawn.markers[0]) == stamp_of(marks)
    ellipses = {m.id: m for m in drawn.markers if m.ns == "afm_landmarks_sigma"}
    assert sorted(ellipses) == sorted(lm.id for lm in marks.landmarks)
    for lm in marks.landmarks:
        axes = 6 * np.sqrt(np.linalg.eigvalsh(np.reshape(lm.covariance, (2, 2))))
        ellipse = ellipses[lm.id]
        np.testing.assert_allclose([ellipse.scale.y, ellipse.scale.x], axes, rtol=1e-12)
        assert (ellipse.pose.position.x, ellipse.pose.position.y) == (lm.position.x, lm.position.y)

    # the markers are stamped on the instrument's clock: after the scan it followed ended
    raster = [m for _, m in by_topic[topics.TIP_COMMAND] if m.kind == TipCommand.RASTER][-1]
    raster_end = stamp_of(raster) + round(raster.duration * 1e9)
    marker_stamps = [stamp_of(m.markers[0]) for _, m in by_topic[topics.MARKERS]]
    assert min(marker_stamps) >= raster_end - 1000, (min(marker_stamps), raster_end)

    # one time base: every message's log time is the stamp it carries (bound: 0 ns); none here
    # lacks one, so none fell back to the recorder's clock
    unstamped = [(topic, log) for topic, log, stamp in raw if stamp is None]
    assert unstamped == []
    assert all(log == stamp for _, log, stamp in raw)
