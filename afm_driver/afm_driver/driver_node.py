"""Driver node: the instrument behind ROS actions. Backend `sim` (afm_core.sim).

Actions: /afm/scan_image (ScanImage). Publishes /afm/scan (latched), /afm/tip_command,
/afm/ground_truth (latched, sim only).
"""
from __future__ import annotations

import sys
import threading

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from std_msgs.msg import Header

from afm_bringup import params, topics
from afm_bringup.node_main import run
from afm_bringup.conversions import FRAME_SCANNER, FRAME_TASK, raster_scan_to_msg
from afm_bringup.qos_profiles import EVENTS, LATCHED
from afm_core.sim.instrument import ScanRequest, SimConfig, SimulatedAfm
from afm_msgs.action import ScanImage
from afm_msgs.msg import GroundTruth, ObjectState, RasterScan, TipCommand

PARAMETERS = [
    ("backend", "sim", "Instrument backend: 'sim' (simulated AFM)."),
    ("seed", 0, "Random seed of the simulated instrument (noise); same seed, same data."),
    ("tip_apex_radius", 20e-9, "m, apex radius of the simulated tip."),
    ("tip_half_angle_deg", 20.0, "deg, cone half-angle of the simulated tip."),
    ("noise_sigma", 0.3e-9, "m, white height noise of the simulated sensor."),
]
SUPPORTED_BACKENDS = ("sim",)


class DriverNode(Node):
    def __init__(self):
        super().__init__("afm_driver")
        self.config = params.declare(self, PARAMETERS)
        if self.config["backend"] not in SUPPORTED_BACKENDS:
            raise ValueError(f"parameter backend={self.config['backend']!r}: supported {SUPPORTED_BACKENDS}")
        self.instrument = SimulatedAfm(SimConfig(
            tip_apex_radius=self.config["tip_apex_radius"], tip_half_angle_deg=self.config["tip_half_angle_deg"],
            noise_sigma=self.config["noise_sigma"], seed=self.config["seed"]))
        self.lock = threading.Lock()   # one acquisition at a time, as on a real scanner
        self.scan_count = 0
        self.scan_pub = self.create_publisher(RasterScan, topics.SCAN, LATCHED)
        self.command_pub = self.create_publisher(TipCommand, topics.TIP_COMMAND, EVENTS)
        self.truth_pub = self.create_publisher(GroundTruth, topics.GROUND_TRUTH, LATCHED)
        group = ReentrantCallbackGroup()
        self.scan_server = ActionServer(
            self, ScanImage, topics.ACTION_SCAN_IMAGE, self.execute_scan, callback_group=group,
            goal_callback=lambda _goal: GoalResponse.ACCEPT,
            cancel_callback=lambda _goal: CancelResponse.ACCEPT)
        self.publish_truth()

    def header(self, frame=FRAME_SCANNER) -> Header:
        return Header(stamp=self.get_clock().now().to_msg(), frame_id=frame)

    def execute_scan(self, goal_handle):
        goal = goal_handle.request
        request = ScanRequest(origin_x=goal.origin.x, origin_y=goal.origin.y, size_x=goal.size_x,
                              size_y=goal.size_y, pixels_x=goal.pixels_x, pixels_y=goal.pixels_y,
                              scan_angle_deg=goal.scan_angle_deg, slow_scan_up=goal.slow_scan_up,
                              line_rate=goal.line_rate, mode=goal.mode or "tapping")
        result = ScanImage.Result()
        try:
            request.validate()
        except ValueError as exc:
            goal_handle.abort()
            result.message = f"scan refused: {exc}"
            return result
        with self.lock:
            header = self.header()
            scan = self.instrument.raster_scan(request)
            self.scan_count += 1
            msg = raster_scan_to_msg(scan, header, scan_id=self.scan_count, pair_id=goal.pair_id)
        command = TipCommand(header=header, kind=TipCommand.RASTER)
        command.start.x, command.start.y = request.origin_x, request.origin_y
        command.end.x, command.end.y = request.origin_x + request.size_x, request.origin_y + request.size_y
        command.duration = float(scan.line_period * len(scan.line_start_times))
        command.start_voltage = command.end_voltage = [float("nan")] * 3
        self.command_pub.publish(command)
        lines = len(scan.line_start_times)
        goal_handle.publish_feedback(ScanImage.Feedback(lines_done=lines, lines_total=lines))
        self.scan_pub.publish(msg)
        self.publish_truth()
        goal_handle.succeed()
        result.success, result.message, result.scan = True, "ok", msg
        return result

    def publish_truth(self):
        truth = GroundTruth(header=self.header(FRAME_TASK))
        truth.tip_apex_radius = float(self.instrument.config.tip_apex_radius)
        for sphere in self.instrument.sample.spheres:
            obj = ObjectState(id=sphere.id, kind=ObjectState.SPHERE, radius=float(sphere.radius))
            obj.position.x, obj.position.y, obj.position.z = float(sphere.x), float(sphere.y), float(sphere.radius)
            truth.objects.append(obj)
        self.truth_pub.publish(truth)


def main(args=None):
    return run(DriverNode, "afm driver", args, threads=4)


if __name__ == "__main__":
    sys.exit(main())
