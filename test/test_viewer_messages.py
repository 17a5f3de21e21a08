"""The messages viewers draw, built without a running graph: the frame tree, the landmark
markers' 3-sigma ellipses, the rgb8 height image; against closed forms."""

import math

import numpy as np
from std_msgs.msg import Header

from afm_core.imaging.colour_map import height_to_rgb
from afm_msgs.msg import Landmark, LandmarkArray
from afm_ros import frames
from afm_ros.height_image import height_image_msg
from afm_ros.markers import SIGMAS, landmark_markers


def test_the_static_tree_is_task_to_image_identity():
    stamp = Header().stamp
    stamp.sec = 12
    (t,) = frames.static_tree(stamp).transforms
    assert (t.header.frame_id, t.child_frame_id, t.header.stamp.sec) == (
        "afm_task",
        "afm_image",
        12,
    )
    assert (t.transform.translation.x, t.transform.translation.y) == (0.0, 0.0)
    assert t.transform.rotation.w == 1.0


def test_the_scanner_frame_maps_the_commanded_position_onto_the_estimate():
    estimate, commanded = (55.02e-6, 54.97e-6), (55.0e-6, 55.0e-6)
    (t,) = frames.scanner_in_task(Header().stamp, estimate, commanded).transforms
    assert (t.header.frame_id, t.child_frame_id) == ("afm_task", "afm_scanner")
    # a point p in afm_scanner is p + translation in afm_task (no rotation)
    mapped = np.add(commanded, [t.transform.translation.x, t.transform.translation.y])
    np.testing.assert_allclose(mapped, estimate, rtol=0, atol=1e-18)


def test_landmark_ellipses_have_3_sigma_axes_along_the_covariance():
    angle, major, minor = math.radians(30.0), 12e-9, 4e-9  # sigmas, m
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    covariance = rotation @ np.diag([major**2, minor**2]) @ rotation.T
    mark = Landmark(id=7, kind=Landmark.SPHERE, radius=50e-9, height=100e-9)
    mark.position.x, mark.position.y = 55e-6, 54e-6
    mark.covariance = [float(v) for v in covariance.ravel()]
    drawn = landmark_markers(LandmarkArray(header=Header(frame_id="afm_task"), landmarks=[mark]))
    assert drawn.markers[0].action == drawn.markers[0].DELETEALL
    (body,) = [m for m in drawn.markers if m.ns == "afm_landmarks"][1:]
    (ellipse,) = [m for m in drawn.markers if m.ns == "afm_landmarks_sigma"]
    assert body.id == ellipse.id == 7 and body.scale.x == 2 * mark.radius
    np.testing.assert_allclose(
        [ellipse.scale.x, ellipse.scale.y], [2 * SIGMAS * major, 2 * SIGMAS * minor], rtol=1e-9
    )
    yaw = 2 * math.atan2(ellipse.pose.orientation.z, ellipse.pose.orientation.w)
    assert math.isclose(math.remainder(yaw - angle, math.pi), 0.0, abs_tol=1e-9)
    assert (ellipse.pose.position.x, ellipse.pose.position.y) == (55e-6, 54e-6)
    assert ellipse.header.frame_id == "afm_task"


def test_height_image_message_is_rgb8_of_the_colour_map():
    height = np.outer(np.arange(6), np.ones(9)) * 1e-9
    image, scale = height_image_msg(height, Header(frame_id="afm_scanner"))
    assert (image.encoding, image.height, image.width, image.step) == ("rgb8", 6, 9, 27)
    assert image.header.frame_id == "afm_scanner" and image.is_bigendian == 0
    rgb, same_scale = height_to_rgb(height)
    assert bytes(image.data) == rgb.tobytes() and scale == same_scale
