"""visualization_msgs markers for viewers (Foxglove's 3D panel, RViz): Gaussian position
estimates as 3-sigma ellipses, and the landmark map (each landmark's extent and its
uncertainty), all in the frame of the message they draw (afm_task)."""

from __future__ import annotations

import math

import numpy as np
from geometry_msgs.msg import Point
from visualization_msgs.msg import Marker, MarkerArray

SIGMAS = 3.0  # ellipse half-axes in standard deviations: 98.9 % of a 2-D Gaussian inside
FLAT = 1e-9  # m, thickness of the flat ellipse disc (drawn as a cylinder)


def sigma_ellipse(header, ns: str, marker_id: int, position, covariance, rgba) -> Marker:
    """A flat cylinder whose footprint is the 3-sigma ellipse of a 2x2 covariance (m^2)."""
    values, vectors = np.linalg.eigh(np.asarray(covariance, float).reshape(2, 2))
    angle = math.atan2(vectors[1, 1], vectors[0, 1])  # of the major axis
    ellipse = Marker(header=header, ns=ns, id=marker_id, type=Marker.CYLINDER, action=Marker.ADD)
    ellipse.pose.position = position
    ellipse.pose.orientation.z, ellipse.pose.orientation.w = (
        math.sin(angle / 2),
        math.cos(angle / 2),
    )
    ellipse.scale.y, ellipse.scale.x = (2 * SIGMAS * math.sqrt(max(v, 0.0)) for v in values)
    ellipse.scale.z = FLAT
    ellipse.color.r, ellipse.color.g, ellipse.color.b, ellipse.color.a = rgba
    return ellipse


def landmark_markers(landmarks) -> MarkerArray:
    """A LandmarkArray as markers: per landmark a sphere of its radius at its place (ns
    afm_landmarks) and its 3-sigma position ellipse (ns afm_landmarks_sigma), ids = landmark
    ids. The first marker deletes what the previous map drew."""
    header = landmarks.header
    out = MarkerArray(markers=[Marker(header=header, ns="afm_landmarks", action=Marker.DELETEALL)])
    for mark in landmarks.landmarks:
        body = Marker(
            header=header,
            ns="afm_landmarks",
            id=int(mark.id),
            type=Marker.SPHERE,
            action=Marker.ADD,
        )
        body.pose.position.x, body.pose.position.y = mark.position.x, mark.position.y
        body.pose.position.z = mark.radius
        body.pose.orientation.w = 1.0
        body.scale.x = body.scale.y = body.scale.z = 2 * mark.radius
        body.color.r, body.color.g, body.color.b, body.color.a = 0.2, 0.6, 1.0, 0.5
        out.markers.append(body)
        centre = Point(x=mark.position.x, y=mark.position.y)
        out.markers.append(
            sigma_ellipse(
                header,
                "afm_landmarks_sigma",
                int(mark.id),
                centre,
                mark.covariance,
                (1.0, 0.9, 0.1, 0.8),
            )
        )
    return out
