"""The imaging node between the driver's scans and the landmark map."""

import numpy as np
import pytest
from conftest import wait_for
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from afm_core.instrument import ScanRequest
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm
from afm_msgs.msg import LandmarkArray, RasterScan, TipShape
from afm_ros.conversions import FRAME_SCANNER, raster_scan_to_msg
from afm_ros.qos_profiles import LATCHED

pytestmark = pytest.mark.ros

SPHERES = [
    {"x": 55.0e-6, "y": 55.0e-6, "radius": 60e-9},
    {"x": 55.5e-6, "y": 55.4e-6, "radius": 60e-9},
    {"x": 54.6e-6, "y": 55.6e-6, "radius": 60e-9},
    {"x": 55.3e-6, "y": 54.6e-6, "radius": 60e-9},
]


def simulated_scans():
    afm = SimulatedAfm(merge(load_config(), {"sample": {"spheres": SPHERES}}))
    request = dict(
        origin_x=54.2e-6,
        origin_y=54.2e-6,
        size_x=1.8e-6,
        size_y=1.8e-6,
        pixels_x=128,
        pixels_y=128,
        line_rate=2.0,
    )
    scan0 = afm.raster_scan(ScanRequest(**request))
    scan90 = afm.raster_scan(ScanRequest(**request, scan_angle_deg=90.0))
    return scan0, scan90


def to_msg(scan, scan_id, pair_id):
    header = Header(frame_id=FRAME_SCANNER)
    header.stamp.sec = int(scan.start_time)
    header.stamp.nanosec = int((scan.start_time % 1) * 1e9)
    return raster_scan_to_msg(scan, header, scan_id=scan_id, pair_id=pair_id)


def test_maps_landmarks_tip_and_bad_scans(nodes, ros_node):
    imaging = nodes("imaging", tip_size=15)
    scan_pub = ros_node.create_publisher(RasterScan, "/afm/scan", LATCHED)
    maps, marks, tips = [], [], []
    ros_node.create_subscription(RasterScan, "/afm/map", maps.append, LATCHED)
    ros_node.create_subscription(LandmarkArray, "/afm/landmarks", marks.append, LATCHED)
    ros_node.create_subscription(TipShape, "/afm/tip_shape", tips.append, LATCHED)
    wait_for(lambda: scan_pub.get_subscription_count() > 0, 20, what="imaging node subscription")
    scan0, scan90 = simulated_scans()

    # a lone 0 deg scan: used as scanned
    scan_pub.publish(to_msg(scan0, 1, ""))
    wait_for(lambda: marks, 30, what="landmarks of a single scan")
    assert len(marks[-1].landmarks) == 4 and maps[-1].header.frame_id == "afm_task"
    for lm in marks[-1].landmarks:
        assert lm.covariance[0] >= (5.0e-9) ** 2 and lm.covariance[3] >= (4.5e-9) ** 2

    # malformed: NaN pixels, and line times that do not fit the image
    bad = to_msg(scan0, 2, "")
    heights = np.frombuffer(bytes(bad.height.data), dtype="<f4").copy()
    heights[10] = np.nan
    bad.height.data = heights.tobytes()
    scan_pub.publish(bad)
    broken = to_msg(scan0, 3, "")
    broken.line_start_times = broken.line_start_times[:5]
    scan_pub.publish(broken)

    # a 90 deg scan alone waits for its partner; then the pair is drift-corrected
    count = len(marks)
    scan_pub.publish(to_msg(scan90, 4, "pair-a"))
    scan_pub.publish(to_msg(scan0, 5, "pair-a"))
    wait_for(
        lambda: len(marks) > count and maps[-1].scan_id == 5, 60, what="the corrected pair's map"
    )
    assert len(marks[-1].landmarks) == 4

    # the node is alive and estimates the tip on demand
    client = ros_node.create_client(Trigger, "/afm/imaging/estimate_tip")
    assert client.wait_for_service(timeout_sec=10)
    future = client.call_async(Trigger.Request())
    wait_for(future.done, 120, what="tip estimate")
    assert future.result().success, future.result().message
    wait_for(lambda: tips, 10, what="tip shape")
    tip = np.frombuffer(bytes(tips[-1].height.data), dtype="<f4").reshape(15, 15)
    assert tip[7, 7] == 0.0 and tip.max() == 0.0 and tips[-1].apex_radius > 0
    code, output = imaging.stop()
    assert code == 0
    assert "NaN" in output and "line_start_times" in output
