"""`afm map publish`: a lab's scan file becomes the running graph's map. A tilted Nanonis scan
with two particles goes in; the imaging node publishes it as /afm/map and finds the
particles where the file's coordinates put them (the landmarks the planner and nano-hand use)."""

import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import wait_for
from vendor_writers import write_sxm

from afm_msgs.msg import LandmarkArray, RasterScan
from afm_ros.conversions import image_msg_to_array
from afm_ros.qos_profiles import LATCHED

pytestmark = pytest.mark.ros

PIXEL, PIXELS = 4e-9, 96
ORIGIN = (20.0e-6, 30.0e-6)
PARTICLES = [(20.10e-6, 30.12e-6), (20.28e-6, 30.25e-6)]  # m, scanner frame


def lab_scan(path):
    centres = (np.arange(PIXELS) + 0.5) * PIXEL
    xx, yy = np.meshgrid(ORIGIN[0] + centres, ORIGIN[1] + centres)
    height = 15e-9 * (xx - ORIGIN[0]) / (PIXELS * PIXEL)  # a 15 nm tilt along x
    for cx, cy in PARTICLES:  # 30 nm spherical caps, 20 nm in radius
        height = height + np.sqrt(np.clip((20e-9) ** 2 - (xx - cx) ** 2 - (yy - cy) ** 2, 0, None))
    height += np.random.default_rng(0).normal(0.0, 0.1e-9, height.shape)
    size = (PIXELS * PIXEL, PIXELS * PIXEL)
    centre = (ORIGIN[0] + size[0] / 2, ORIGIN[1] + size[1] / 2)
    write_sxm(path, [("Z", "m", height, None)], size, centre, "down")


def test_a_scan_file_becomes_the_map_with_its_landmarks(nodes, ros_node, tmp_path):
    nodes("imaging")
    maps, marks = [], []
    ros_node.create_subscription(RasterScan, "/afm/map", maps.append, LATCHED)
    ros_node.create_subscription(LandmarkArray, "/afm/landmarks", marks.append, LATCHED)
    lab_scan(tmp_path / "lab.sxm")
    command = [
        sys.executable,
        "-m",
        "afm_bringup.cli",
        "map",
        "publish",
        str(tmp_path / "lab.sxm"),
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "as the map: 2 landmarks" in done.stdout
    wait_for(lambda: maps and marks, 20, what="map and landmarks")
    the_map = maps[-1]
    assert (the_map.origin.x, the_map.origin.y) == pytest.approx(ORIGIN, abs=1e-12)
    assert the_map.pixel_size_x == pytest.approx(PIXEL)
    heights = image_msg_to_array(the_map.height)
    assert heights.shape == (PIXELS, PIXELS)
    assert np.ptp(heights[:, :10]) < 25e-9  # levelled: no 15 nm tilt left under the caps
    found = sorted((m.position.x, m.position.y) for m in marks[-1].landmarks)
    for (x, y), (tx, ty) in zip(found, sorted(PARTICLES), strict=True):
        assert abs(x - tx) < PIXEL and abs(y - ty) < PIXEL


def test_publishing_without_the_imaging_node_says_so(tmp_path):
    lab_scan(tmp_path / "lab.sxm")
    command = [sys.executable, "-m", "afm_bringup.cli", "map", "publish",
               str(tmp_path / "lab.sxm"), "--timeout", "2"]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=60)
    assert done.returncode != 0
    assert "afm_imaging" in done.stderr and "afm launch" in done.stderr


def test_the_file_replaces_a_map_stamped_on_an_instrument_clock_ahead_of_wall_time(
    nodes, ros_node, tmp_path
):
    """The simulator's clock runs far ahead of wall time: after a scan the nodes hold a map
    stamped minutes ahead of the wall clock, and keep the newest map by its stamp. The file's
    map must be stamped no earlier than the instrument's clock and that map, or the localizer,
    planner and nano-hand ignore it (they did: `afm push --particle` found no landmark)."""
    from builtin_interfaces.msg import Time
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import Header

    from afm_ros.conversions import landmarks_to_msg, stamp_of
    from afm_ros.landmark_map import NewestLandmarkMap

    nodes("imaging")
    ahead_ns = time.time_ns() + 900 * 10**9  # the instrument's clock, 15 min ahead of wall time
    held_ns = ahead_ns - 60 * 10**9  # the map the nodes hold: a scan a minute before that
    ahead = Time(sec=ahead_ns // 10**9, nanosec=ahead_ns % 10**9)
    held_stamp = Time(sec=held_ns // 10**9, nanosec=held_ns % 10**9)
    clock = ros_node.create_publisher(Clock, "/clock", 10)
    ros_node.create_timer(0.05, lambda: clock.publish(Clock(clock=ahead)))
    earlier = landmarks_to_msg([], Header(stamp=held_stamp, frame_id="afm_task"))
    ros_node.create_publisher(LandmarkArray, "/afm/landmarks", LATCHED).publish(earlier)
    marks = []
    ros_node.create_subscription(LandmarkArray, "/afm/landmarks", marks.append, LATCHED)
    lab_scan(tmp_path / "lab.sxm")
    command = [sys.executable, "-m", "afm_bringup.cli", "map", "publish",
               str(tmp_path / "lab.sxm")]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    wait_for(lambda: any(len(m.landmarks) == 2 for m in marks), 20, what="the file's landmarks")
    published = next(m for m in marks if len(m.landmarks) == 2)
    assert stamp_of(published.header) >= stamp_of(Header(stamp=ahead))
    held = NewestLandmarkMap(ros_node.get_logger())
    held.take(earlier)
    held.take(published)
    assert len(held.current()) == 2  # what the localizer, planner and nano-hand now hold
