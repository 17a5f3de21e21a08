"""The whole graph on the simulated instrument: scan a 0/90 pair, the imaging node maps the
particles, the nano-hand localizes, plans, pushes with the virtual nano-hand through the
driver, rescans and verifies (issue 7's end-to-end push, shortened for CI)."""

import math
import threading
import time

import numpy as np
import pytest
from conftest import wait_for
from sim_calibration import oracle_calibration

from afm_bringup.commander import AfmCommander
from afm_msgs.action import PushParticle
from afm_msgs.msg import GroundTruth, LandmarkArray
from afm_ros.qos_profiles import LATCHED

pytestmark = pytest.mark.ros

ORIGIN, SIZE, PIXELS = (54.3e-6, 54.3e-6), (1.8e-6, 1.8e-6), (128, 128)


def map_the_sample(afm, ros_node, pair_id):
    """Scan a 0/90 pair once the imaging node listens; the landmark maps and ground truths
    heard, once the corrected map and a truth have arrived."""
    maps, truths = [], []
    ros_node.create_subscription(LandmarkArray, "/afm/landmarks", maps.append, LATCHED)
    ros_node.create_subscription(GroundTruth, "/afm/ground_truth", truths.append, LATCHED)
    afm.wait_until_subscribed(["/afm/scan"], "afm_imaging", timeout=60.0)
    for angle in (0.0, 90.0):
        afm.scan(ORIGIN, SIZE, PIXELS, angle_deg=angle, line_rate=4.0, pair_id=pair_id)
    wait_for(
        lambda: maps and len(maps[-1].landmarks) >= 3, 60, what="the drift-corrected landmark map"
    )
    wait_for(lambda: truths, 30, what="the simulator's ground truth")
    return maps, truths


def true_sphere(truths, object_id):
    return next(
        np.array([o.position.x, o.position.y]) for o in truths[-1].objects if o.id == object_id
    )


def start_push_graph(tmp_path, nodes, planner: bool = True, extra=()) -> None:
    """The nodes a push needs (driver seed 4 as fast as it can, imaging, localizer, the planner
    unless told, nano-hand) and `extra` after them, with the oracle calibration."""
    calibration = str(oracle_calibration(tmp_path / "calibration.yaml"))
    nodes("driver", seed=4, real_time_factor=0.0)
    nodes("imaging")
    for name in ["localizer", *(["planner"] if planner else []), "nano_hand", *extra]:
        nodes(name, calibration_file=calibration)


@pytest.fixture
def graph(tmp_path, nodes):
    start_push_graph(tmp_path, nodes)


def test_push_a_particle_end_to_end_then_refusals_and_cancel(graph, ros_node):
    with AfmCommander(server_timeout=60) as afm:
        maps, truths = map_the_sample(afm, ros_node, "pair-e2e")
        marks = {lm.id: lm for lm in maps[-1].landmarks}
        # the map's particle nearest the simulator's first sphere (55, 55) um
        particle = min(
            marks.values(), key=lambda lm: math.hypot(lm.position.x - 55e-6, lm.position.y - 55e-6)
        )
        start_map = np.array([particle.position.x, particle.position.y])
        start_true = true_sphere(truths, 0)
        goal = start_map + np.array([0.0, -300e-9])  # away from the two other spheres

        phases, steps = [], []

        def on_feedback(f):
            phases.append(f.phase)
            steps.append(f.step)

        result = afm.push(
            goal, particle_id=particle.id, tolerance=40e-9, feedback=on_feedback, timeout=300
        )
        print("PUSH", result.message, result.error, result.success)
        assert result.message and result.steps >= 3, result.message
        assert {"localizing", "pushing", "verifying"} <= set(phases), phases
        assert max(steps) >= result.steps
        wait_for(
            lambda: np.linalg.norm(true_sphere(truths, 0) - start_true) > 100e-9,
            10,
            what="ground truth showing the pushed sphere",
        )
        moved_true = true_sphere(truths, 0) - start_true
        moved_verified = np.array([result.achieved.x, result.achieved.y]) - start_map
        # the rescan's verdict agrees with the truth (displacements: the map's frame is not the
        # sim's)
        assert np.linalg.norm(moved_verified - moved_true) < 25e-9, (moved_verified, moved_true)
        assert abs(moved_true[1] + 300e-9) < 60e-9 and abs(moved_true[0]) < 40e-9, moved_true
        assert result.error == pytest.approx(
            np.linalg.norm(moved_verified - (goal - start_map)), abs=1e-12
        )
        # the verdict states what the rescan's measurement supports at the tolerance
        assert result.error_sigma > 0 and result.verdict in (
            "within tolerance",
            "outside tolerance",
            "cannot tell at this tolerance",
        ), result.verdict
        assert result.success == (result.verdict == "within tolerance")
        if result.success:
            assert result.error <= 40e-9

        refused = afm.push((200e-6, 55e-6), particle_id=particle.id)
        assert not refused.success and "goal" in refused.message and "range" in refused.message
        refused = afm.push(goal, particle_id=999)
        assert not refused.success and "particle_id=999" in refused.message
        others = [lm for lm in marks.values() if lm.id != particle.id]
        blocker = min(
            others, key=lambda lm: math.hypot(lm.position.x - goal[0], lm.position.y - goal[1])
        )
        beyond = np.array([blocker.position.x, blocker.position.y])
        beyond = beyond + 300e-9 * (
            beyond - np.array([result.achieved.x, result.achieved.y])
        ) / np.linalg.norm(beyond - np.array([result.achieved.x, result.achieved.y]))
        refused = afm.push(beyond, particle_id=particle.id)
        assert not refused.success and "path blocked" in refused.message, refused.message
        # the goal's own fields, refused before anything moves (issue 30: after up to 2 um of
        # motion, with messages about internal quantities)
        for fields, complaint in (
            ({"push_length": -1.0}, "push_length=-1.0: must be finite and >= 0"),
            ({"push_length": math.nan}, "push_length=nan"),
            ({"max_steps": 4294967295}, "max_steps=4294967295"),
            ({"lateral_offset": 1e-3}, "lateral_offset=1.0000e-03 m: must be <"),
            ({"goal": (goal[0], goal[1] - 20e-6)}, "um from the particle; the before/after"),
        ):
            request = PushParticle.Goal(particle_id=int(particle.id))
            request.goal.x, request.goal.y = map(float, fields.pop("goal", goal))
            for name, value in fields.items():
                setattr(request, name, value)
            refused = afm.send("push_particle", request)
            assert not refused.success and complaint in refused.message, refused.message

        pushing = threading.Event()
        job = afm.push(
            np.array([result.achieved.x, result.achieved.y]) + np.array([-300e-9, 0.0]),
            particle_id=particle.id,
            wait=False,
            feedback=lambda f: pushing.set() if f.phase == "pushing" and f.step >= 1 else None,
        )
        if not pushing.wait(300):
            pytest.fail(f"no pushing feedback: {job.result(timeout=60).message}")
        assert job.cancel()
        cancelled = job.result(timeout=300)
        assert (
            not cancelled.success
            and "cancelled" in cancelled.message
            and "lifted" in cancelled.message
        )


def test_assemble_pushes_several_particles_in_the_planners_order(graph, ros_node):
    from geometry_msgs.msg import Point

    from afm_msgs.action import Assemble

    with AfmCommander(server_timeout=60) as afm:
        maps, truths = map_the_sample(afm, ros_node, "pair-assemble")
        marks = sorted(maps[-1].landmarks, key=lambda lm: lm.position.y)[
            :2
        ]  # the two lowest spheres
        mismatched = Assemble.Goal(particle_ids=[m.id for m in marks], goals=[Point()])
        refused = afm.send("assemble", mismatched)
        assert not refused.success and "one goal per particle" in refused.message
        starts = {m.id: np.array([m.position.x, m.position.y]) for m in marks}
        before = {i: true_sphere_near(truths, start) for i, start in starts.items()}
        assert all(
            np.linalg.norm(before[i] - starts[i]) < 100e-9 for i in starts
        )  # mapped where they are
        request = Assemble.Goal(particle_ids=[m.id for m in marks], tolerance=40e-9)
        for m in marks:
            request.goals.append(Point(x=m.position.x, y=m.position.y - 200e-9))
        result = afm.send("assemble", request, timeout=300)
        assert sorted(result.order) == sorted(request.particle_ids), result.message
        assert len(result.achieved) == len(result.errors) == 2
        assert all(np.isfinite(result.errors)), result.message
        # the instrument time of both pushes: at least their before and after rescans, each
        # (200 nm + 2 x 300 nm margin) / 8 nm = 100 lines at 4 Hz, 25 s
        assert result.duration >= 4 * 25.0, result.duration
        time.sleep(0.5)
        for m in marks:  # each moved about 200 nm down (truth)
            moved = true_sphere_near(truths, before[m.id]) - before[m.id]
            assert abs(moved[1] + 200e-9) < 60e-9 and abs(moved[0]) < 50e-9, (m.id, moved)


def true_sphere_near(truths, point):
    spheres = [np.array([o.position.x, o.position.y]) for o in truths[-1].objects if o.kind == 0]
    return min(spheres, key=lambda p: np.linalg.norm(p - point))
