"""Teleop node: a person drives the tip with a Twist (Foxglove's Teleop panel, joystick
drivers) or a Joy, with force feedback (book 2.2.2, 7.1.2; issue 33).

The operator takes the tip with /afm/teleop/enable (std_srvs/SetBool true) and hands it back
with false. Taking is refused while an automatic action runs (a goal active on any of the
driver's, the localizer's or the nano-hand's actions, or a goal in the driver's queue); while
teleop holds the tip the driver runs only this node's goals (afm_driver.tip_owner). Handing
back stops the tip first (the segment in flight is cancelled and awaited), then the driver
takes the tip back.

While it holds the tip, a loop at `rate` turns the newest command into one short segment
(afm_core.manipulation.teleop: speed, acceleration and range limits, dead-man timeout) and runs
it as a MoveTip goal on /afm/teleop/move_tip, lifted or in contact (/afm/teleop/contact or the
Joy's contact button). After each segment: the wrench on /afm/teleop/wrench (zero when lifted),
the objects the push model says a contact segment pushed on /afm/objects/believed (origin
"teleop", PREDICTED; afm_core.manipulation.teleop_model), and the status on /afm/teleop/status
(one JSON object: owner, mode, speed limit, velocity, commanded position, clips, stop reason).
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from dataclasses import replace

from action_msgs.msg import GoalStatus, GoalStatusArray
from geometry_msgs.msg import PoseWithCovarianceStamped, Twist, WrenchStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import qos_profile_action_status_default
from sensor_msgs.msg import Joy
from std_msgs.msg import Empty, Header, String
from std_srvs.srv import SetBool

from afm_core.instrument import ScannerLimits
from afm_core.localization.calibration.model import Calibration, load_calibration
from afm_core.manipulation.teleop import (
    JoyMapping,
    TeleopController,
    TeleopSettings,
    joy_command,
    segment_wrench,
)
from afm_core.manipulation.teleop_model import BelievedTip, PushPredictor
from afm_core.physics.contact import ContactParams
from afm_manipulation.teleop_params import PARAMETERS, RUNTIME_SETTINGS
from afm_msgs.action import MoveTip
from afm_msgs.msg import LandmarkArray, ObjectArray, ObjectState, TipCommand
from afm_ros import params, topics
from afm_ros.action_client import SafeActionClient
from afm_ros.action_instrument import DriverUnavailable, call_service
from afm_ros.conversions import FRAME_SCANNER, FRAME_TASK, seconds_to_time, stamp_of
from afm_ros.landmark_map import NewestLandmarkMap
from afm_ros.node_main import run
from afm_ros.qos_profiles import EVENTS, LATCHED

# the automatic actions whose running goals make taking the tip wait (their status topics)
AUTOMATIC_ACTIONS = (
    topics.ACTION_SCAN_IMAGE,
    topics.ACTION_LOCAL_SCAN,
    topics.ACTION_MOVE_TIP,
    topics.ACTION_INDENT,
    topics.ACTION_LOCALIZE,
    topics.ACTION_PUSH_PARTICLE,
    topics.ACTION_ASSEMBLE,
)
# s: a command that waited longer than this in the middleware before its callback ran is
# reported in the status (`late_commands`): a tenth of the dead-man timeout, the share of it an
# operator would notice as a stutter
LATE_COMMAND_S = 0.05
ACTIVE = (GoalStatus.STATUS_ACCEPTED, GoalStatus.STATUS_EXECUTING, GoalStatus.STATUS_CANCELING)
KINDS = {"sphere": ObjectState.SPHERE, "tube": ObjectState.TUBE, "rod": ObjectState.ROD}


class TeleopNode(Node):
    def __init__(self):
        super().__init__("afm_teleop")
        self.config = params.declare(self, PARAMETERS, apply=self.apply_parameter)
        path = self.config["calibration_file"]
        calibration = load_calibration(path) if path else Calibration()
        self.limits = ScannerLimits()
        self.controller = TeleopController(
            self.settings(), self.limits, calibration.scanner_matrix
        )
        self.believed = BelievedTip(calibration.scanner_matrix)
        self.predictor = PushPredictor(ContactParams(tip_radius=self.config["tip_radius"]))
        self.lock = threading.RLock()
        self.holding = False
        self.position = (0.0, 0.0)  # commanded (scanner) position of the tip, m
        self.joy_contact_down = False
        self.goal_handle = None  # the segment in flight
        self.last_stamp = 0.0  # instrument time (s) at the end of the last segment
        self.idle = threading.Event()
        self.idle.set()
        self.active: dict[str, list[str]] = {}
        self.commands: list[tuple[float, tuple[float, float]]] = []  # (end time, end)
        self.status = {"clip": "", "last_clip": "", "stop": "", "velocity": [0.0, 0.0]}
        self.timing = CommandTiming()
        self.landmarks = NewestLandmarkMap(self.get_logger())
        self._build_interfaces()
        self.stopping = threading.Event()
        self.loop = threading.Thread(target=self.run_loop, daemon=True)
        self.loop.start()
        self.publish_status()

    def settings(self) -> TeleopSettings:
        return TeleopSettings(
            max_speed=self.config["max_speed"],
            max_acceleration=self.config["max_acceleration"],
            command_timeout=self.config["command_timeout"],
            period=1.0 / self.config["rate"],
            range_margin=self.config["range_margin"],
        )

    def joy_mapping(self) -> JoyMapping:
        return JoyMapping(
            **{name: self.config[f"joy_{name}"] for name in JoyMapping.__dataclass_fields__}
        )

    def _build_interfaces(self) -> None:
        inputs = MutuallyExclusiveCallbackGroup()
        # the operator's commands in a group of their own: the dead-man counts from their
        # arrival, so no other input (action states, poses, maps) may queue ahead of them
        commands = MutuallyExclusiveCallbackGroup()
        for msg_type, topic, callback in (
            (Twist, topics.TELEOP_CMD_VEL, self.on_twist),
            (Joy, topics.TELEOP_JOY, self.on_joy),
        ):
            self.create_subscription(msg_type, topic, callback, 10, callback_group=commands)
        for msg_type, topic, callback, qos in (
            (LandmarkArray, topics.LANDMARKS, self.on_landmarks, LATCHED),
            (PoseWithCovarianceStamped, topics.TIP_POSE, self.on_tip_pose, 10),
            (TipCommand, topics.TIP_COMMAND, self.on_tip_command, EVENTS),
        ):
            self.create_subscription(msg_type, topic, callback, qos, callback_group=inputs)
        for name in AUTOMATIC_ACTIONS:
            self.create_subscription(
                GoalStatusArray,
                f"{name}/_action/status",
                lambda msg, name=name: self.on_action_status(name, msg),
                qos_profile_action_status_default,
                callback_group=inputs,
            )
        self.wrench_pub = self.create_publisher(WrenchStamped, topics.TELEOP_WRENCH, 10)
        self.status_pub = self.create_publisher(String, topics.TELEOP_STATUS, LATCHED)
        self.objects_pub = self.create_publisher(ObjectArray, topics.OBJECTS_BELIEVED, EVENTS)
        self.lease_pub = self.create_publisher(Empty, topics.TELEOP_LEASE, 10)
        clients = ReentrantCallbackGroup()
        self.move_client = SafeActionClient(
            self, MoveTip, topics.ACTION_TELEOP_MOVE_TIP, callback_group=clients
        )
        self.owner_client = self.create_client(
            SetBool, topics.SERVICE_DRIVER_TELEOP, callback_group=clients
        )
        services = MutuallyExclusiveCallbackGroup()
        self.create_service(
            SetBool, topics.SERVICE_TELEOP_ENABLE, self.on_enable, callback_group=services
        )
        self.create_service(
            SetBool, topics.SERVICE_TELEOP_CONTACT, self.on_contact, callback_group=services
        )
        self.create_timer(topics.TELEOP_LEASE_RENEW_S, self.renew, callback_group=clients)

    def apply_parameter(self, name: str, value) -> None:
        if name in RUNTIME_SETTINGS:
            with self.lock:
                self.controller.settings = replace(
                    self.controller.settings, **{RUNTIME_SETTINGS[name]: value}
                )

    # -- inputs ------------------------------------------------------------------------------
    def on_twist(self, msg: Twist, info) -> None:
        scale = self.config["twist_scale"]
        self.take_command(msg.linear.x * scale, msg.linear.y * scale, arrival(info))

    def on_joy(self, msg: Joy, info) -> None:
        try:
            command = joy_command(
                msg.axes,
                msg.buttons,
                self.joy_mapping(),
                self.controller.settings.max_speed,
                self.joy_contact_down,
            )
        except ValueError as exc:
            self.get_logger().error(f"joy message ignored: {exc}", throttle_duration_sec=5.0)
            return
        self.joy_contact_down = command.contact_down
        if command.contact_pressed:
            with self.lock:
                self.controller.contact = not self.controller.contact
            self.publish_status()
        self.take_command(command.vx, command.vy, arrival(info))

    def take_command(self, vx: float, vy: float, arrived: float) -> None:
        """arrived: when the middleware received the command (monotonic s): the dead-man
        counts from there, not from when an executor thread got round to this callback. A
        command not taken says why on the status at once: while teleop does not hold the tip
        the loop publishes nothing, so the operator's panel never learnt it was ignored."""
        called = time.monotonic()
        with self.lock:
            before = self.status["stop"]
            self._take(vx, vy, arrived, called)
            news = self.status["stop"] != before and self.status["stop"].startswith("command ")
        if news:
            self.publish_status()

    def _take(self, vx: float, vy: float, arrived: float, called: float) -> None:
        if not self.holding:
            self.status["stop"] = (
                f"command ignored: teleop does not hold the tip "
                f"(call {topics.SERVICE_TELEOP_ENABLE} true)"
            )
            return
        try:
            clip = self.controller.command(vx, vy, arrived)
            self.timing.command(arrived, called)
        except ValueError as exc:
            self.status["stop"] = f"command refused: {exc}"
            return
        if clip:
            self.status["last_clip"] = clip

    def on_landmarks(self, msg: LandmarkArray) -> None:
        self.landmarks.take(msg)
        with self.lock:
            self.predictor.load(self.landmarks.current().values())

    def on_tip_command(self, msg: TipCommand) -> None:
        end = stamp_of(msg.header) + msg.duration
        with self.lock:
            self.commands = [*self.commands[-199:], (end, (msg.end.x, msg.end.y))]

    def on_tip_pose(self, msg: PoseWithCovarianceStamped) -> None:
        """The localizer's estimate as a command ended: tie it to that command's end."""
        stamp = stamp_of(msg.header)
        with self.lock:
            ended = [c for t, c in self.commands if t <= stamp + 1e-6]
            if ended:
                pose = msg.pose.pose.position
                self.believed.observe((pose.x, pose.y), ended[-1])

    def on_action_status(self, name: str, msg: GoalStatusArray) -> None:
        running = [
            bytes(s.goal_info.goal_id.uuid).hex()[:8]
            for s in msg.status_list
            if s.status in ACTIVE
        ]
        with self.lock:
            self.active[name] = running

    def running_actions(self) -> list[str]:
        with self.lock:
            return sorted(name for name, goals in self.active.items() if goals)

    # -- ownership ---------------------------------------------------------------------------
    def on_enable(self, request, response):
        response.success, response.message = self.take_tip() if request.data else self.hand_back()
        self.publish_status()
        return response

    def on_contact(self, request, response):
        with self.lock:
            self.controller.contact = bool(request.data)
        response.success = True
        response.message = "contact" if request.data else "lifted"
        self.publish_status()
        return response

    def ask_driver(self, take: bool) -> dict:
        answer = call_service(
            self.owner_client,
            SetBool.Request(data=take),
            self.config["server_timeout"],
            self.config["server_timeout"],
            "; is the driver running?",
        )
        reply = json.loads(answer.message)
        reply["success"] = answer.success
        return reply

    def renew(self) -> None:
        """Renew the driver's lease on the tip while holding it (afm_driver.tip_owner)."""
        if self.holding:
            self.lease_pub.publish(Empty())

    def take_tip(self) -> tuple[bool, str]:
        if self.holding:
            return True, "teleop already holds the tip"
        running = self.running_actions()
        if running:
            return False, f"refused: an automatic action runs ({', '.join(running)})"
        # the driver's teleop endpoint must answer before the operator drives: found later,
        # in the first segment, its discovery (a probe every second until one is answered)
        # would hold the tip still while the operator's commands come
        if not self.move_client.wait_until_answering(self.config["server_timeout"]):
            return False, (
                f"refused: the driver's {topics.ACTION_TELEOP_MOVE_TIP} does not answer "
                f"({self.move_client.not_answering}); is the driver running?"
            )
        # every segment goes to every server of the endpoint and the first answer wins: a
        # second driver on this domain (which teleop does not hold) refuses them, and the tip
        # stops while the operator's commands still come (measured: after 4 commands)
        servers = self.move_client.servers()
        if len(servers) > 1:
            return False, (
                f"refused: {len(servers)} servers of {topics.ACTION_TELEOP_MOVE_TIP} on this "
                f"ROS domain ({', '.join(servers)}): one driver per domain (a driver stopped "
                "just now stays listed for about 20 s)"
            )
        try:
            reply = self.ask_driver(True)
        except DriverUnavailable as exc:
            return False, f"refused: {exc}"
        if not reply["success"]:
            return False, f"refused by the driver: {reply['reason']}"
        with self.lock:
            self.position = tuple(reply["commanded_position"])
            self.controller.stop()
            self.controller.contact = False
            self.predictor.load(self.landmarks.current().values())
            self.holding = True
            self.status["stop"] = ""
            self.timing = CommandTiming()
        self.get_logger().info("teleop holds the tip")
        return True, "teleop holds the tip (lifted); commands on " + topics.TELEOP_CMD_VEL

    def hand_back(self) -> tuple[bool, str]:
        """Stop the tip (the segment in flight cancelled and awaited), then release it."""
        with self.lock:
            was = self.holding
            self.holding = False
            self.controller.stop()
            handle = self.goal_handle
        if handle is not None:
            handle.cancel_goal_async()
        if not self.idle.wait(self.config["server_timeout"]):
            return False, "the segment in flight did not end; the tip is still held"
        try:
            reply = self.ask_driver(False)
        except DriverUnavailable as exc:
            return False, f"the tip stopped but the driver did not take it back: {exc}"
        with self.lock:
            self.status["stop"] = "handed back"
            self.status["velocity"] = [0.0, 0.0]
        self.publish_wrench(self.last_stamp, (0.0, 0.0, 0.0))
        return True, f"{reply['reason'] if was else 'teleop did not hold the tip'}; tip stopped"

    # -- the loop ----------------------------------------------------------------------------
    def run_loop(self) -> None:
        next_tick = time.monotonic()
        while not self.stopping.is_set():
            period = 1.0 / self.config["rate"]
            next_tick = max(next_tick + period, time.monotonic())
            self.stopping.wait(max(0.0, next_tick - time.monotonic()))
            with self.lock:
                if not self.holding:
                    continue
                step = self.controller.step(time.monotonic(), self.position)
                self.status["clip"] = step.clip
                if step.clip:
                    self.status["last_clip"] = step.clip
                if step.stop:
                    self.status["stop"] = step.stop
                self.status["velocity"] = [float(v) for v in self.controller.velocity]
                if step.segment is not None:
                    self.idle.clear()
            if step.segment is not None:
                try:
                    self.run_segment(step.segment)
                finally:
                    self.idle.set()
            self.publish_status()

    def run_segment(self, segment) -> None:
        goal = MoveTip.Goal(speed=float(segment.speed), contact=segment.contact)
        goal.target.header.frame_id = FRAME_SCANNER
        goal.target.point.x, goal.target.point.y = segment.end
        started = time.monotonic()
        result = self.send(goal)
        with self.lock:
            self.timing.segment(time.monotonic() - started)
            if result is None or not result.success:
                # refused, cancelled or lost: the tip stands still (where a cancelled move
                # stopped, if it ran at all; a refused one has no command)
                reason = "no answer from the driver" if result is None else result.message
                self.controller.stop()
                self.status["stop"] = f"segment not run: {reason}"
                if result is not None and result.command.duration > 0:
                    self.position = (result.commanded_position.x, result.commanded_position.y)
                if result is not None and "teleop does not hold" in result.message:
                    self.holding = False
                return
            end = (result.commanded_position.x, result.commanded_position.y)
            start_task = self.believed.to_task(self.position)
            self.position = end
            end_task = self.believed.to_task(end)
        stamp = stamp_of(result.command.header) + result.command.duration
        self.last_stamp = stamp
        if not segment.contact or len(result.trace.times) == 0:
            self.publish_wrench(stamp, (0.0, 0.0, 0.0))
            return
        trace = result.trace
        wrench = segment_wrench(
            end_task - start_task,
            trace.lateral_torsion,
            trace.vertical_deflection,
            trace.lateral_spring_constant,
            trace.normal_spring_constant,
            self.config["tip_height"],
        )
        self.publish_wrench(stamp, wrench)
        with self.lock:
            self.predictor.push(start_task, end_task, max(result.command.duration, 1e-6))
            objects = self.predictor.objects()
        if objects:
            self.publish_objects(stamp, objects)

    def send(self, goal):
        """Run one goal; its result, or None when the driver did not answer in time."""
        timeout = self.config["server_timeout"]
        if not self.move_client.wait_until_answering(timeout):
            return None
        accepted = threading.Event()
        sent = self.move_client.send_goal_async(goal)
        sent.add_done_callback(lambda _f: accepted.set())
        if not accepted.wait(timeout) or not sent.result().accepted:
            return None
        handle = sent.result()
        with self.lock:
            self.goal_handle = handle
        finished = threading.Event()
        future = handle.get_result_async()
        future.add_done_callback(lambda _f: finished.set())
        try:
            if not finished.wait(timeout + 10.0 / self.config["rate"]):
                return None
            return future.result().result
        finally:
            with self.lock:
                self.goal_handle = None

    # -- outputs -----------------------------------------------------------------------------
    def publish_wrench(self, stamp: float, force) -> None:
        """The force on the tip (N, afm_task), stamped at the instrument time it ended."""
        msg = WrenchStamped()
        msg.header = Header(stamp=seconds_to_time(stamp), frame_id=FRAME_TASK)
        msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = (float(f) for f in force)
        self.wrench_pub.publish(msg)

    def publish_objects(self, stamp: float, objects) -> None:
        msg = ObjectArray(source=ObjectArray.PREDICTED, origin="teleop")
        msg.header = Header(stamp=seconds_to_time(stamp), frame_id=FRAME_TASK)
        for obj in objects:
            state = ObjectState(
                id=obj.id,
                kind=KINDS[obj.kind],
                orientation=obj.orientation,
                radius=obj.radius,
                length=obj.length,
            )
            state.position.x, state.position.y, state.position.z = obj.x, obj.y, obj.radius
            msg.objects.append(state)
            msg.position_sigma.append(float(obj.sigma))
        self.objects_pub.publish(msg)

    def publish_status(self) -> None:
        with self.lock:
            status = {
                "owner": "teleop" if self.holding else "automatic",
                "mode": "contact" if self.controller.contact else "lifted",
                "speed_limit": self.controller.settings.max_speed,
                "command_timeout": self.controller.settings.command_timeout,
                "commanded_position": [float(p) for p in self.position],
                **self.status,
                **self.timing.figures(),
                "automatic_actions": sorted(n for n, g in self.active.items() if g),
            }
        self.status_pub.publish(String(data=json.dumps(status)))

    def destroy_node(self):
        self.stopping.set()
        self.loop.join(timeout=2.0)
        super().destroy_node()


def arrival(info) -> float:
    """When the middleware received a message (rclpy's message info: received_timestamp, ns
    on the system clock), on the monotonic clock the teleop loop steps on; now when unknown."""
    now, wall = time.monotonic(), time.time()
    received = info.get("received_timestamp", 0) * 1e-9 if info else 0.0
    if received <= 0.0:
        return now
    return now - min(max(wall - received, 0.0), now)


class CommandTiming:
    """What the status reports of the operator's commands and the segments since the take, so
    a tip that stood still while commands came says why: commands arriving apart by more than
    the dead-man timeout (the sender or the transport), waiting in this node before their
    callback ran (its executor), or segments the driver took long to run (the loop blocked).
    A late command's wait is split where it was spent: before its callback ran (no executor
    thread free, the GIL held by another thread, or the process starved of CPU; the machine's
    load at that moment tells the last apart) and on the node's lock (another of its threads
    held it: the loop, a segment's end, the landmarks)."""

    def __init__(self):
        self.commands = 0
        self.last = None
        self.longest_gap = 0.0
        self.longest_wait = 0.0
        self.longest_callback_wait = 0.0
        self.longest_lock_wait = 0.0
        self.load_at_longest_wait = 0.0
        self.late = 0
        self.longest_segment = 0.0

    def command(self, arrived: float, called: float | None = None) -> None:
        """arrived: when the middleware had the command; called: when its callback began
        (None: not known, all of the wait is counted before the callback)."""
        now = time.monotonic()
        called = now if called is None else called
        waited = now - arrived
        if waited > self.longest_wait:
            self.load_at_longest_wait = os.getloadavg()[0]
        self.longest_wait = max(self.longest_wait, waited)
        self.longest_callback_wait = max(self.longest_callback_wait, called - arrived)
        self.longest_lock_wait = max(self.longest_lock_wait, now - called)
        self.late += waited > LATE_COMMAND_S
        if self.last is not None:
            self.longest_gap = max(self.longest_gap, arrived - self.last)
        self.last = arrived
        self.commands += 1

    def segment(self, seconds: float) -> None:
        self.longest_segment = max(self.longest_segment, seconds)

    def figures(self) -> dict:
        return {
            "commands": self.commands,
            "longest_command_gap": round(self.longest_gap, 4),
            "longest_command_wait": round(self.longest_wait, 4),
            "longest_wait_before_callback": round(self.longest_callback_wait, 4),
            "longest_wait_on_lock": round(self.longest_lock_wait, 4),
            "load_at_longest_wait": round(self.load_at_longest_wait, 2),
            "late_commands": self.late,
            "longest_segment": round(self.longest_segment, 4),
        }


def main(args=None):
    return run(TeleopNode, "afm_teleop", args, config_errors=(ValueError,), threads=4)


if __name__ == "__main__":
    sys.exit(main())
