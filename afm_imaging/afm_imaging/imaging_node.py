"""Imaging node: drift-corrected map, landmarks and tip shape from the driver's scans.

A 0 deg scan with an empty pair_id is used as it is; scans sharing a pair_id are corrected
for thermal drift as a 0/90 deg pair once both are in; scans whose pair_id starts with
"local" are a requester's check of a small area (the nano-hand's before/after rescans) and
leave the map alone. The tip is estimated on demand
(service /afm/imaging/estimate_tip) or after every map (estimate_tip_on_scan). Bad scans
are reported and skipped; the node keeps running.
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Image
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from afm_core import checks
from afm_core.imaging.landmarks import MapErrorModel, extract_landmarks
from afm_core.parameters import Parameter, ParameterTable
from afm_msgs.msg import LandmarkArray, RasterScan, TipShape
from afm_ros import params, topics
from afm_ros.conversions import (
    FRAME_IMAGE,
    FRAME_TASK,
    array_to_image,
    landmarks_to_msg,
    msg_to_raster_scan,
    raster_scan_to_msg,
)
from afm_ros.height_image import height_image_msg
from afm_ros.markers import landmark_markers
from afm_ros.node_main import run
from afm_ros.qos_profiles import LATCHED

LOCAL_CHECK_PREFIX = "local"  # pair_id of scans that check an area (e.g. a push's verification)


def _odd(size: int) -> int:
    if size % 2 == 0:
        raise ValueError("must be odd")
    return size


def _rule_or_metres(text: str) -> str:
    from afm_core.imaging.tip_thresholds import RULES

    if text not in RULES:
        try:
            metres = float(text)
        except ValueError:
            raise ValueError(f"one of {', '.join(RULES)} or a threshold in metres") from None
        checks.non_negative("tip_threshold", metres, "m")
    return text


PARAMETERS = ParameterTable(
    Parameter(
        "min_landmark_height",
        10e-9,
        "Features lower than this above the substrate are not landmarks.",
        unit="m",
        minimum=0.0,
        runtime=True,
    ),
    Parameter(
        "map_sigma_x",
        5.0e-9,
        "Map error (1 sigma) along x added to every landmark's covariance (book Fig. 7.10).",
        unit="m",
        minimum=0.0,
    ),
    Parameter(
        "map_sigma_y",
        4.5e-9,
        "Map error along y (book Fig. 7.10).",
        unit="m",
        minimum=0.0,
    ),
    Parameter(
        "drift_order",
        1,
        "Offset-vector order of the 0/90 drift compensation: 1 (book) or 2.",
        minimum=1,
        maximum=2,
        runtime=True,
    ),
    Parameter(
        "tip_size",
        21,
        "Pixels (odd) of the blind-estimated tip's window.",
        minimum=3,
        check=_odd,
        runtime=True,
    ),
    Parameter(
        "tip_threshold",
        "auto",
        "Denoising threshold of the blind tip estimate: 'auto', 'consensus', 'book' or metres.",
        check=_rule_or_metres,
        runtime=True,
    ),
    Parameter(
        "estimate_tip_on_scan",
        False,
        "Re-estimate the tip after every new map (seconds of work each time).",
        runtime=True,
    ),
)


class ImagingNode(Node):
    def __init__(self):
        super().__init__("afm_imaging")
        self.config = params.declare(self, PARAMETERS)
        self.error_model = MapErrorModel(self.config["map_sigma_x"], self.config["map_sigma_y"])
        self.pending_0: dict[str, object] = {}
        self.pending_90: dict[str, object] = {}
        self.latest_map = None
        self.lock = threading.Lock()
        self.map_pub = self.create_publisher(RasterScan, topics.CORRECTED_MAP, LATCHED)
        self.map_image_pub = self.create_publisher(Image, topics.MAP_IMAGE, LATCHED)
        self.landmark_pub = self.create_publisher(LandmarkArray, topics.LANDMARKS, LATCHED)
        self.landmark_marker_pub = self.create_publisher(
            MarkerArray, topics.LANDMARK_MARKERS, LATCHED
        )
        self.tip_pub = self.create_publisher(TipShape, topics.TIP_SHAPE, LATCHED)
        group = MutuallyExclusiveCallbackGroup()
        # latched like the publisher, but a queue: a 0/90 pair may arrive back to back
        scans_qos = QoSProfile(
            depth=10, reliability=LATCHED.reliability, durability=LATCHED.durability
        )
        self.create_subscription(
            RasterScan, topics.SCAN, self.on_scan, scans_qos, callback_group=group
        )
        self.create_service(
            Trigger, "/afm/imaging/estimate_tip", self.on_estimate_tip, callback_group=group
        )

    # -- scans -------------------------------------------------------------------------------
    def on_scan(self, msg: RasterScan) -> None:
        try:
            scan = msg_to_raster_scan(msg)
            if not np.all(np.isfinite(scan.height)):
                raise ValueError(
                    f"{int(np.count_nonzero(~np.isfinite(scan.height)))} NaN/inf pixels"
                )
        except ValueError as exc:
            self.get_logger().error(f"scan {msg.scan_id} skipped: {exc}")
            return
        if msg.pair_id.startswith(LOCAL_CHECK_PREFIX):
            return  # a requester's own check of a small area, not a new map
        if msg.scan_angle_deg == 0.0 and not msg.pair_id:
            self.publish_map(scan, msg, corrected=None)
            return
        book, other = (
            (self.pending_0, self.pending_90)
            if msg.scan_angle_deg == 0.0
            else (self.pending_90, self.pending_0)
        )
        book[msg.pair_id] = (scan, msg)
        if msg.pair_id not in other:
            if msg.scan_angle_deg == 90.0:
                self.get_logger().warning(
                    f"90 deg scan {msg.scan_id} (pair_id {msg.pair_id!r}) has no 0 deg partner "
                    "yet; it waits for one"
                )
            return
        (scan0, msg0), (scan90, _msg90) = (
            self.pending_0.pop(msg.pair_id),
            self.pending_90.pop(msg.pair_id),
        )
        if scan0.scan_angle_deg != 0.0 or scan90.scan_angle_deg != 90.0:
            self.get_logger().error(f"pair {msg.pair_id!r}: needs one 0 deg and one 90 deg scan")
            return
        from afm_core.imaging.drift_compensation import compensate_pair

        try:
            correction = compensate_pair(scan0, scan90, order=self.config["drift_order"])
        except ValueError as exc:
            self.get_logger().error(f"pair {msg.pair_id!r}: drift compensation refused: {exc}")
            return
        for text in correction.timing.warnings if correction.timing else []:
            # the driver's times are true ones: a disagreement means the pair is not one drift
            self.get_logger().warning(f"pair {msg.pair_id!r}: scan timing: {text}")
        vx, vy = correction.velocity
        self.get_logger().info(
            f"pair {msg.pair_id!r}: drift ({vx * 1e9:.3f}, {vy * 1e9:.3f}) nm/s corrected in "
            f"{correction.seconds:.2f} s"
        )
        self.publish_map(scan0, msg0, corrected=correction.corrected)

    def publish_map(self, scan, msg: RasterScan, corrected) -> None:
        started = time.perf_counter()
        height = scan.height if corrected is None else corrected
        header = Header(stamp=msg.header.stamp, frame_id=FRAME_TASK)
        out = raster_scan_to_msg(scan, header, scan_id=msg.scan_id, pair_id=msg.pair_id)
        out.height = array_to_image(np.asarray(height, dtype=np.float32), header)
        self.map_pub.publish(out)
        self.map_image_pub.publish(height_image_msg(height, header)[0])
        try:
            marks = extract_landmarks(
                np.asarray(height, float),
                scan.pixel_size_x,
                scan.pixel_size_y,
                scan.origin_x,
                scan.origin_y,
                min_height=self.config["min_landmark_height"],
                error_model=self.error_model,
            )
        except ValueError as exc:
            self.get_logger().error(f"landmarks of scan {msg.scan_id} skipped: {exc}")
            return
        array = landmarks_to_msg(marks, header)
        self.landmark_pub.publish(array)
        self.landmark_marker_pub.publish(landmark_markers(array))
        with self.lock:
            self.latest_map = (height, scan.pixel_size_x, header)
        self.get_logger().info(
            f"map {msg.scan_id} ({'drift-corrected' if corrected is not None else 'as scanned'}): "
            f"{len(marks)} landmarks in {time.perf_counter() - started:.2f} s"
        )
        if self.config["estimate_tip_on_scan"]:
            self.estimate_tip()

    # -- the tip -----------------------------------------------------------------------------
    def estimate_tip(self) -> str:
        from afm_core.imaging.tip_apex import apex_radius, read_tip
        from afm_core.imaging.tip_estimation import estimate_tip
        from afm_core.imaging.tip_thresholds import RULES

        with self.lock:
            latest = self.latest_map
        if latest is None:
            raise ValueError("no map yet: scan first")
        height, pixel, header = latest
        threshold = self.config["tip_threshold"]
        estimate = estimate_tip(
            np.asarray(height, float),
            self.config["tip_size"],
            threshold=threshold if threshold in RULES else float(threshold),
            pixel_size=pixel,
        )
        for text in estimate.warnings:  # afm_core.imaging.tip_guard: what the image supports
            self.get_logger().warning(f"tip estimate: {text}")
        shape = TipShape(
            header=Header(stamp=header.stamp, frame_id=FRAME_IMAGE),
            pixel_size=float(pixel),
            apex_radius=float(apex_radius(estimate.tip, pixel)),
            source="blind_estimate",
        )
        shape.height = array_to_image(estimate.tip.astype(np.float32), shape.header)
        self.tip_pub.publish(shape)
        # the fit is published as the message defines it; whether it measures the apex at
        # all (afm_core.imaging.tip_apex) is said here
        reading = read_tip(estimate, pixel, height)
        if not reading.apex_measured:
            self.get_logger().warning(f"tip estimate: {reading.sentence()}")
        return (
            f"tip {self.config['tip_size']}x{self.config['tip_size']} estimated in "
            f"{estimate.seconds:.2f} s, threshold {estimate.threshold * 1e9:.3f} nm, apex radius "
            f"fit {shape.apex_radius * 1e9:.1f} nm: {reading.sentence()}"
        )

    def on_estimate_tip(self, _request, response):
        try:
            response.message = self.estimate_tip()
            response.success = True
        except ValueError as exc:
            response.success, response.message = False, str(exc)
        return response


def main(args=None):
    return run(ImagingNode, "afm imaging", args, threads=2)


if __name__ == "__main__":
    sys.exit(main())
