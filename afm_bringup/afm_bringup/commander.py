"""A small Python API over the graph's actions, for scripts and notebooks.

    from afm_bringup.commander import AfmCommander
    with AfmCommander() as afm:
        scan = afm.scan(origin=(54.2e-6, 54.5e-6), size=(2e-6, 2e-6), progress=True)
        job = afm.push(particle_id=1, goal=(55e-6, 54.7e-6), feedback=print, wait=False)
        job.cancel()            # or: result = job.result(timeout=600)

Everything is SI (metres, seconds). The commander spins its own node in a background
thread, so calls block only the caller.
"""

from __future__ import annotations

import contextlib
import threading
import time

import rclpy
from action_msgs.msg import GoalStatus
from builtin_interfaces.msg import Time
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Header, String

from afm_bringup.progress import FEEDBACK_TEXTS, Feedback, Progress
from afm_msgs.action import (
    Assemble,
    Indent,
    Localize,
    LocalScan,
    MoveTip,
    PushParticle,
    ScanImage,
    Sim2Real,
)
from afm_ros import links, topics
from afm_ros.action_client import CANCEL_ACK_TIMEOUT_S, Heartbeat, SafeActionClient
from afm_ros.conversions import FRAME_SCANNER
from afm_ros.executor import collect_stopped_tasks
from afm_ros.qos_profiles import FEEDBACK, LATCHED
from afm_ros.teardown import destroy_node_fully

# why a server may refuse a goal (rclpy's rejection carries no reason; the server's log has it)
REJECTED = {
    "localize": " (three Localize goals already run or wait: at most three at once)",
    "push_particle": " (a push or an assembly is running: one manipulation at a time)",
    "assemble": " (a push or an assembly is running: one manipulation at a time)",
}
# s a published scan file waits for the graph's clock and latched maps before it is stamped
# (discovery of the driver's and the nodes' participants takes seconds on a loaded machine)
GRAPH_TIME_WAIT_S = 5.0
# s before a topic with no publisher is taken to have none (not merely one not yet discovered)
DISCOVERY_S = 1.0
# every node's latest link report: latched, and room for the whole graph's at once
LINK_REPORTS = QoSProfile(depth=64, reliability=LATCHED.reliability, durability=LATCHED.durability)


class AfmError(RuntimeError):
    """The graph did not do what was asked; the message says what and why."""


class ServerGone(AfmError):
    """The action server stopped answering while we waited (its node died or hangs)."""


def succeeded(result_future) -> bool:
    """The action ended with its work done: status SUCCEEDED and, where the result has one,
    success set."""
    if result_future.cancelled() or result_future.exception() is not None:
        return False
    response = result_future.result()
    return response.status == GoalStatus.STATUS_SUCCEEDED and getattr(
        response.result, "success", True
    )


class Job:
    """A sent goal: wait for its result, read its latest feedback, or cancel it. While waiting
    the server is probed (a heartbeat): one that stops answering (its node died) ends the
    wait within SERVER_SILENCE_S with an AfmError, instead of never."""

    def __init__(self, name: str, goal_handle, feedback_box: dict, client=None, progress=None):
        self.name = name
        self._handle = goal_handle
        self._feedback = feedback_box
        self._client = client
        self._result_future = goal_handle.get_result_async()
        if progress is not None:  # the bar ends with the action, whoever waits for it
            self._result_future.add_done_callback(
                lambda future: progress.close(finished=succeeded(future))
            )

    @property
    def feedback(self):
        return self._feedback.get("latest")

    def done(self) -> bool:
        return self._result_future.done()

    def result(self, timeout: float | None = None):
        """The action's result message; AfmError if it did not finish in `timeout` s (None:
        as long as the server answers) or the server stopped answering."""
        event = threading.Event()
        self._result_future.add_done_callback(lambda _f: event.set())
        heartbeat = Heartbeat(self._client) if self._client is not None else None
        deadline = None if timeout is None else time.monotonic() + timeout
        try:
            while not event.wait(0.05):
                if deadline is not None and time.monotonic() > deadline:
                    raise AfmError(f"{self.name}: no result after {timeout} s")
                if heartbeat is not None:
                    heartbeat.beat()
                    if heartbeat.gone():
                        raise ServerGone(
                            f"{self.name}: aborted: server gone ({self._client._action_name} "
                            f"has not answered for {heartbeat.silent_for():.1f} s; its node "
                            "died or hangs)"
                        )
        finally:
            if heartbeat is not None:
                heartbeat.forget()
        return self._result_future.result().result

    def cancel_quietly(self) -> None:
        """Ask the server to stop, without waiting to hear that it did (Ctrl-C's path)."""
        with contextlib.suppress(AfmError):
            self.cancel()

    def cancel(self, timeout: float = CANCEL_ACK_TIMEOUT_S) -> bool:
        """Ask the server to stop; True when it accepted the cancel. AfmError when it does not
        acknowledge within `timeout` s."""
        future = self._handle.cancel_goal_async()
        event = threading.Event()
        future.add_done_callback(lambda _f: event.set())
        if not event.wait(timeout):
            raise AfmError(f"{self.name}: cancel not answered within {timeout} s")
        return len(future.result().goals_canceling) > 0


class AfmCommander:
    ACTIONS = {
        "scan_image": (ScanImage, topics.ACTION_SCAN_IMAGE),
        "local_scan": (LocalScan, topics.ACTION_LOCAL_SCAN),
        "move_tip": (MoveTip, topics.ACTION_MOVE_TIP),
        "indent": (Indent, topics.ACTION_INDENT),
        "localize": (Localize, topics.ACTION_LOCALIZE),
        "push_particle": (PushParticle, topics.ACTION_PUSH_PARTICLE),
        "assemble": (Assemble, topics.ACTION_ASSEMBLE),
        "sim2real": (Sim2Real, topics.ACTION_SIM2REAL),
    }

    def __init__(self, node_name: str = "afm_commander", server_timeout: float = 10.0):
        self.server_timeout = server_timeout
        self._closed = False
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = Node(node_name, context=self.context)
        self.clients = {
            name: SafeActionClient(
                self.node, action_type, action_name, feedback_sub_qos_profile=FEEDBACK
            )
            for name, (action_type, action_name) in self.ACTIONS.items()
        }
        self._links: dict[str, dict[str, dict]] = {}
        self._links_lock = threading.Lock()
        self.node.create_subscription(String, topics.LINKS, self._take_links, LINK_REPORTS)
        self.executor = MultiThreadedExecutor(num_threads=2, context=self.context)
        self.executor.add_node(self.node)
        self._spinner = threading.Thread(target=self.executor.spin, daemon=True)
        self._spinner.start()

    # -- plumbing --------------------------------------------------------------------------
    def send(
        self,
        action: str,
        goal,
        feedback=None,
        wait: bool = True,
        timeout: float | None = None,
        progress=None,
    ):
        """Send a goal; returns the result (wait=True) or a Job. `feedback(f)` hears each
        feedback (str(f) is one readable line; its fields read as on the message);
        `progress`, a `Progress` and a function of the feedback giving (done, total, status),
        is updated with each and closed with the result."""
        client = self.clients[action]
        if not client.wait_until_answering(self.server_timeout):
            if progress is not None:
                progress[0].close()
            raise AfmError(
                f"no action server at {self.ACTIONS[action][1]} answered within "
                f"{self.server_timeout} s ({client.not_answering}); is the graph running "
                "(`afm launch`)?"
            )
        box: dict = {}

        text = FEEDBACK_TEXTS.get(action, repr)

        def on_feedback(message):
            box["latest"] = message.feedback
            if progress is not None:
                progress[0].update(*progress[1](message.feedback))
            if feedback is not None:
                feedback(Feedback(message.feedback, text))

        future = client.send_goal_async(goal, feedback_callback=on_feedback)
        event = threading.Event()
        future.add_done_callback(lambda _f: event.set())
        try:
            if not event.wait(self.server_timeout):
                raise AfmError(f"{action}: goal not acknowledged within {self.server_timeout} s")
            handle = future.result()
            if not handle.accepted:
                raise AfmError(f"{action}: goal rejected by the server{REJECTED.get(action, '')}")
        except AfmError:
            if progress is not None:
                progress[0].close()
            raise
        except KeyboardInterrupt:  # a goal the server accepts after Ctrl-C would still run
            if event.wait(CANCEL_ACK_TIMEOUT_S) and future.result().accepted:
                Job(action, future.result(), box, client).cancel_quietly()
            raise
        job = Job(action, handle, box, client, progress[0] if progress is not None else None)
        if not wait:
            return job
        try:
            return job.result(timeout)
        except KeyboardInterrupt:  # a goal nobody waits for any more is stopped, not left running
            job.cancel_quietly()
            raise

    def wait_until_subscribed(
        self, topics_to_check, node_name: str = "afm_recorder", timeout: float = 15.0
    ) -> None:
        """Block until node `node_name` subscribes to every listed topic that has a publisher
        (the recorder before a recorded session, a processing node before its input is sent)
        and every afm publisher of it has matched the subscriptions the graph lists (its
        report on /afm/links), so nothing this script triggers next goes unheard."""
        deadline = time.monotonic() + timeout
        while True:
            missing, unchecked = self._not_yet_heard(topics_to_check, node_name)
            if not missing:
                if unchecked:  # the graph shows a subscription a moment before DDS matches it
                    time.sleep(0.5)
                return
            if time.monotonic() > deadline:
                raise AfmError(
                    f"node {node_name!r} did not hear every topic within {timeout} s: "
                    + "; ".join(missing)
                )
            time.sleep(0.05)

    def _not_yet_heard(self, topics_to_check, node_name: str) -> tuple[list[str], bool]:
        reporting = {
            links.full_name(p.node_name, p.node_namespace)
            for p in self.node.get_publishers_info_by_topic(topics.LINKS)
        }
        own = links.full_name(self.node.get_name(), self.node.get_namespace())
        reporting.add(own)
        with self._links_lock:
            reports = dict(self._links)
        reports[own] = links.link_state(self.node)
        missing, unchecked = [], False
        for topic in topics_to_check:
            publishers = self.node.get_publishers_info_by_topic(topic)
            publishers = [p for p in publishers if p.node_name != node_name]
            if not publishers:
                continue
            targets = [
                s
                for s in self.node.get_subscriptions_info_by_topic(topic)
                if s.node_name == node_name
            ]
            if not targets:
                missing.append(f"no subscription to {topic}")
                continue
            reasons, some_unchecked = links.unconfirmed(
                topic, publishers, targets, reports, reporting
            )
            missing += reasons
            unchecked = unchecked or some_unchecked
        return missing, unchecked

    def link_reports(self) -> dict[str, dict[str, dict]]:
        """Each afm node's latest report on /afm/links, by the node's full name: topic ->
        {"matched": subscriptions its publishers there have matched, "known": the ids of
        those its process has discovered}."""
        with self._links_lock:
            return {node: dict(state) for node, state in self._links.items()}

    def _take_links(self, message) -> None:
        try:
            node, state = links.decode(message.data)
        except ValueError as exc:
            self.node.get_logger().warning(str(exc))
            return
        with self._links_lock:
            self._links[node] = state

    # -- the instrument --------------------------------------------------------------------
    def scan(
        self,
        origin,
        size,
        pixels=(256, 256),
        angle_deg=0.0,
        frame_up=True,
        line_rate=1.0,
        mode="tapping",
        pair_id="",
        timeout=None,
        feedback=None,
        progress=False,
    ):
        """One raster image (the result's RasterScan); AfmError if it fails. `feedback(f)`
        hears each line's feedback (str(f): "scan: line k of n"); `progress=True` shows the
        lines done on stderr."""
        goal = ScanImage.Goal(
            size_x=float(size[0]),
            size_y=float(size[1]),
            pixels_x=int(pixels[0]),
            pixels_y=int(pixels[1]),
            scan_angle_deg=float(angle_deg),
            slow_scan_up=bool(frame_up),
            line_rate=float(line_rate),
            mode=mode,
            pair_id=pair_id,
        )
        goal.origin.x, goal.origin.y = float(origin[0]), float(origin[1])
        bar = None
        if progress:
            bar = (
                Progress("scan", "lines", int(pixels[1] if angle_deg == 0 else pixels[0])),
                lambda f: (f.lines_done, f.lines_total, ""),
            )
        result = self.send("scan_image", goal, feedback=feedback, timeout=timeout, progress=bar)
        if not result.success:
            raise AfmError(result.message)
        return result.scan

    def localize(
        self, landmark_id: int = -1, position=None, both_axes=True, toward=None, timeout=None
    ):
        goal = Localize.Goal(
            landmark_id=int(landmark_id),
            one_line=not both_axes,
            continue_toward=toward is not None,
        )
        if position is not None:
            goal.position.x, goal.position.y = float(position[0]), float(position[1])
        if toward is not None:
            goal.toward.x, goal.toward.y = float(toward[0]), float(toward[1])
        return self.send("localize", goal, timeout=timeout)

    def push(
        self,
        goal,
        particle_id: int = -1,
        particle_position=None,
        strategy="",
        tolerance=0.0,
        feedback=None,
        wait=True,
        timeout=None,
        progress=False,
        goal_angle=None,
        angle_tolerance=0.0,
    ):
        """Push a particle (by landmark id, or the one at `particle_position`) to `goal`;
        strategy "" is the nano-hand node's default (closed_loop). A tube or rod: goal_angle
        (rad, afm_task; None: keep its orientation) and angle_tolerance (rad, 0: 3 deg).
        `feedback(f)` hears each step (str(f) is one line: step, phase, the particle's and the
        tip's estimates, peak forces); `progress=True` shows the steps done on stderr."""
        request = PushParticle.Goal(
            particle_id=int(particle_id),
            strategy=strategy,
            tolerance=float(tolerance),
            use_goal_angle=goal_angle is not None,
            goal_angle=0.0 if goal_angle is None else float(goal_angle),
            angle_tolerance=float(angle_tolerance),
        )
        request.goal.x, request.goal.y = float(goal[0]), float(goal[1])
        if particle_position is not None:
            request.particle_position.x, request.particle_position.y = map(
                float, particle_position[:2]
            )
        bar = None
        if progress:
            bar = (
                Progress("push", "steps"),
                lambda f: (f.step, f.steps_total, f.phase),
            )
        return self.send(
            "push_particle",
            request,
            feedback=feedback,
            wait=wait,
            timeout=timeout,
            progress=bar,
        )

    # -- a lab's own scan --------------------------------------------------------------------
    def publish_scan(self, scan, scan_id: int = 0, timeout: float = 30.0):
        """Publish a core `RasterScanData` (e.g. a file's, `raster_scan_of`) on the driver's
        scan topic, so the imaging node turns it into the map and its landmarks, which the
        localizer, planner and nano-hand use. Blocks until the imaging node has published
        both for this scan; returns (map RasterScan, LandmarkArray)."""
        from afm_msgs.msg import LandmarkArray, RasterScan
        from afm_ros.conversions import raster_scan_to_msg
        from afm_ros.qos_profiles import LATCHED, SCANS

        got: dict = {}
        header = Header(frame_id=FRAME_SCANNER)  # stamped once the graph's present is known
        # The nodes keep the newest landmark map by its stamp, and the simulator's clock runs
        # far ahead of wall time: stamped by this process's wall clock, the file's map would be
        # older than the one they hold after any scan, and they would keep that one. So the
        # stamp is the graph's present: no earlier than the instrument's clock and any map.
        heard = {"newest_ns": 0, "clock": 0, "maps": 0}

        def note(stamp, kind: str) -> None:
            heard["newest_ns"] = max(heard["newest_ns"], stamp.sec * 10**9 + stamp.nanosec)
            heard[kind] += 1

        def take(msg, key) -> None:
            note(msg.header.stamp, "maps")
            if msg.header.stamp == header.stamp:  # the imaging node keeps the scan's stamp
                got.setdefault(key, msg)

        subscriptions = [
            self.node.create_subscription(kind, topic, lambda m, k=key: take(m, k), LATCHED)
            for key, kind, topic in (
                ("map", RasterScan, topics.CORRECTED_MAP),
                ("landmarks", LandmarkArray, topics.LANDMARKS),
            )
        ]
        subscriptions.append(
            self.node.create_subscription(Clock, "/clock", lambda m: note(m.clock, "clock"), 10)
        )
        publisher = self.node.create_publisher(RasterScan, topics.SCAN, SCANS)
        try:
            self.wait_until_subscribed([topics.SCAN], "afm_imaging", timeout=timeout)
            begun = time.monotonic()

            def present(kind: str, topic: str) -> bool:  # heard, or surely no publisher
                if heard[kind]:
                    return True
                return time.monotonic() - begun > DISCOVERY_S and not self.node.count_publishers(
                    topic
                )

            while time.monotonic() - begun < GRAPH_TIME_WAIT_S and not (
                present("clock", "/clock") and present("maps", topics.LANDMARKS)
            ):
                time.sleep(0.05)
            now_ns = self.node.get_clock().now().nanoseconds
            stamp_ns = max(now_ns, heard["newest_ns"] + 1000)  # 1 us after the newest heard
            header.stamp = Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
            publisher.publish(raster_scan_to_msg(scan, header, scan_id=scan_id))
            deadline = time.monotonic() + timeout
            while len(got) < 2 and time.monotonic() < deadline:
                time.sleep(0.05)
        except AfmError as exc:
            raise AfmError(f"{exc}; is the imaging node running (`afm launch`)?") from None
        finally:
            for subscription in subscriptions:
                self.node.destroy_subscription(subscription)
            self.node.destroy_publisher(publisher)
        if len(got) < 2:
            raise AfmError(
                f"the imaging node published no map and landmarks for the scan within "
                f"{timeout} s (its log says why)"
            )
        return got["map"], got["landmarks"]

    # -- lifetime --------------------------------------------------------------------------
    def close(self):
        if self._closed:
            return
        self._closed = True
        self.executor.shutdown()
        self._spinner.join(timeout=5.0)
        for error in collect_stopped_tasks(self.executor):
            self.node.get_logger().error(f"a callback failed while stopping: {error!r}")
        destroy_node_fully(self.node, self.context)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
