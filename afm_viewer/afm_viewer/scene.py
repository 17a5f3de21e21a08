"""The live scene as Foxglove messages, built from ROS-message-like data without ROS.

Every function takes objects with the attribute names of the ROS messages (a real message, or
anything shaped like one) and returns Foxglove SDK schema objects (foxglove.messages) or JSON
dicts; the viewer node (afm_viewer.viewer_node) is only the adapter between ROS topics and the
server's channels. Everything is in the frame of the message it comes from (afm_task for the
scene), in SI units; timestamps are the messages' header stamps (instrument time), which are
also the log times the viewer gives the WebSocket server.
"""

from __future__ import annotations

import math

import numpy as np
from foxglove.messages import (
    Color,
    CylinderPrimitive,
    FrameTransform,
    FrameTransforms,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    PoseInFrame,
    Quaternion,
    RawImage,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    Timestamp,
    Vector3,
)

SIGMAS = 3.0  # ellipse half-axes in standard deviations: 98.9 % of a 2-D Gaussian inside
FLAT = 1e-9  # m, thickness of a flat ellipse disc (a cylinder seen from above)
LINE_WIDTH = 5e-9  # m, path lines: visible at the 1-10 um scale of a push
TIP_SIZE = 20e-9  # m, the tip's dot (its true size is the tip shape's business)
# Force samples per trace sent to the Plot panel: a panel ~1000 px wide shows no more, and a
# push's traces at the DAQ rate would otherwise be tens of thousands of WebSocket messages.
MAX_FORCE_SAMPLES = 1000

LANDMARK = Color(r=0.2, g=0.6, b=1.0, a=0.5)
LANDMARK_SIGMA = Color(r=1.0, g=0.9, b=0.1, a=0.6)
TIP = Color(r=1.0, g=0.25, b=0.25, a=1.0)
TIP_SIGMA = Color(r=1.0, g=0.75, b=0.0, a=0.5)
PATH_LIFTED = Color(r=0.6, g=0.6, b=0.6, a=0.8)
PATH_PUSH = Color(r=1.0, g=0.2, b=0.6, a=1.0)
BELIEF_COLOURS = {  # afm_msgs/ObjectArray source: PREDICTED, OBSERVED
    0: Color(r=1.0, g=0.55, b=0.0, a=0.7),
    1: Color(r=0.2, g=0.9, b=0.3, a=0.7),
}
BELIEF_NAMES = {0: "predicted", 1: "observed"}


def stamp_ns(header) -> int:
    """A header's stamp in integer nanoseconds (the log time of what it stamps)."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def timestamp(header) -> Timestamp:
    return Timestamp(int(header.stamp.sec), int(header.stamp.nanosec))


def yaw_quaternion(angle: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(angle / 2), w=math.cos(angle / 2))


def ellipse_axes(covariance, sigmas: float = SIGMAS) -> tuple[float, float, float]:
    """(major, minor full axis length in m, major axis angle from +x in rad) of the
    `sigmas`-sigma ellipse of a 2x2 position covariance (m^2, any 4-sequence row-major)."""
    matrix = np.asarray(covariance, float).reshape(2, 2)
    if not np.all(np.isfinite(matrix)):
        raise ValueError(f"covariance {matrix.tolist()}: must be finite")
    values, vectors = np.linalg.eigh(0.5 * (matrix + matrix.T))
    minor, major = (2 * sigmas * math.sqrt(max(v, 0.0)) for v in values)
    return major, minor, math.atan2(vectors[1, 1], vectors[0, 1])


def ellipse(x: float, y: float, covariance, color: Color, z: float = 0.0) -> CylinderPrimitive:
    """A flat cylinder whose footprint is the 3-sigma ellipse of `covariance` about (x, y)."""
    major, minor, angle = ellipse_axes(covariance)
    return CylinderPrimitive(
        pose=Pose(position=Vector3(x=x, y=y, z=z), orientation=yaw_quaternion(angle)),
        size=Vector3(x=major, y=minor, z=FLAT),
        bottom_scale=1.0,
        top_scale=1.0,
        color=color,
    )


def ellipses(x: float, y: float, covariance, color: Color) -> list[CylinderPrimitive]:
    """[the 3-sigma ellipse], or [] when the covariance is not finite (a diverged estimate, a
    map from elsewhere): the object is still drawn, and the missing ellipse says its
    uncertainty is unknown, where one raise would have lost the whole map or killed the node."""
    if not np.all(np.isfinite(np.asarray(covariance, float))):
        return []
    return [ellipse(x, y, covariance, color)]


def sphere(x: float, y: float, z: float, diameter: float, color: Color) -> SpherePrimitive:
    return SpherePrimitive(
        pose=Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(w=1.0)),
        size=Vector3(x=diameter, y=diameter, z=diameter),
        color=color,
    )


def replace_all(header, entities: list[SceneEntity]) -> SceneUpdate:
    """An update that clears what the channel drew before (a new map replaces the old)."""
    deletion = SceneEntityDeletion(timestamp=timestamp(header), type=SceneEntityDeletionType.All)
    return SceneUpdate(deletions=[deletion], entities=entities)


def landmark_scene(landmarks) -> SceneUpdate:
    """A LandmarkArray: per landmark a sphere of its radius and its 3-sigma position ellipse
    (entity "landmark/<id>")."""
    header = landmarks.header
    entities = []
    for mark in landmarks.landmarks:
        x, y = float(mark.position.x), float(mark.position.y)
        entities.append(
            SceneEntity(
                timestamp=timestamp(header),
                frame_id=header.frame_id,
                id=f"landmark/{int(mark.id)}",
                spheres=[sphere(x, y, float(mark.radius), 2 * float(mark.radius), LANDMARK)],
                cylinders=ellipses(x, y, list(mark.covariance), LANDMARK_SIGMA),
            )
        )
    return replace_all(header, entities)


def pose_covariance_xy(pose_with_covariance) -> np.ndarray:
    """The (x, y) block of a PoseWithCovariance's 6x6 row-major covariance."""
    full = np.asarray(pose_with_covariance.covariance, float).reshape(6, 6)
    return full[:2, :2]


def tip_scene(msg) -> SceneUpdate:
    """A PoseWithCovarianceStamped tip estimate: a dot and its 3-sigma ellipse (entity "tip")."""
    p = msg.pose.pose.position
    x, y = float(p.x), float(p.y)
    entity = SceneEntity(
        timestamp=timestamp(msg.header),
        frame_id=msg.header.frame_id,
        id="tip",
        spheres=[sphere(x, y, 0.0, TIP_SIZE, TIP)],
        cylinders=ellipses(x, y, pose_covariance_xy(msg.pose), TIP_SIGMA),
    )
    return SceneUpdate(entities=[entity])


def tip_pose(msg) -> PoseInFrame:
    """A PoseWithCovarianceStamped as the SDK's PoseInFrame (for plots and the 3D panel)."""
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return PoseInFrame(
        timestamp=timestamp(msg.header),
        frame_id=msg.header.frame_id,
        pose=Pose(
            position=Vector3(x=float(p.x), y=float(p.y), z=float(p.z)),
            orientation=Quaternion(x=float(q.x), y=float(q.y), z=float(q.z), w=float(q.w)),
        ),
    )


def path_scene(planned) -> SceneUpdate:
    """A PlannedPath: its waypoints as segments, each coloured by how the tip reaches its end
    ("push": in contact; every other role lifted), and the tip's 3-sigma ellipse at the first
    waypoint (entity "planned_path", replacing the previous plan)."""
    header = planned.path.header
    xy = [(float(s.pose.position.x), float(s.pose.position.y)) for s in planned.path.poses]
    points = [Point3(x=x, y=y, z=0.0) for x, y in xy]
    roles = list(planned.waypoint_role) + [""] * (len(points) - len(planned.waypoint_role))
    lines = []
    for i in range(1, len(points)):
        push = roles[i] == "push"
        lines.append(
            LinePrimitive(
                type=LinePrimitiveLineType.LineStrip,
                thickness=LINE_WIDTH * (2 if push else 1),
                points=[points[i - 1], points[i]],
                color=PATH_PUSH if push else PATH_LIFTED,
            )
        )
    cylinders = []
    if points and len(planned.covariance_xx) > 0:
        cov = [
            planned.covariance_xx[0],
            planned.covariance_xy[0],
            planned.covariance_xy[0],
            planned.covariance_yy[0],
        ]
        cylinders = ellipses(*xy[0], cov, TIP_SIGMA)
    entity = SceneEntity(
        timestamp=timestamp(header),
        frame_id=header.frame_id,
        id="planned_path",
        lines=lines,
        cylinders=cylinders,
    )
    return replace_all(header, [entity])


def objects_scene(array) -> SceneUpdate:
    """An ObjectArray (objects as a model believes them): per object a sphere of its radius
    coloured by its source (predicted orange, observed green) and, where its position sigma is
    known, a 3-sigma circle; entity "<origin>/<id>", so a newer belief replaces the older."""
    header = array.header
    colour = BELIEF_COLOURS.get(int(array.source), BELIEF_COLOURS[0])
    sigmas = list(array.position_sigma)
    entities = []
    for i, obj in enumerate(array.objects):
        x, y = float(obj.position.x), float(obj.position.y)
        radius = float(obj.radius)
        circles = []
        sigma = float(sigmas[i]) if i < len(sigmas) else math.nan
        if math.isfinite(sigma) and sigma > 0:
            circles.append(ellipse(x, y, [sigma**2, 0.0, 0.0, sigma**2], colour))
        entities.append(
            SceneEntity(
                timestamp=timestamp(header),
                frame_id=header.frame_id,
                id=f"{array.origin or 'object'}/{int(obj.id)}",
                spheres=[sphere(x, y, radius, 2 * radius, colour)],
                cylinders=circles,
            )
        )
    return SceneUpdate(entities=entities)


def objects_json(array) -> dict:
    """An ObjectArray as plain numbers (the Raw Messages and Plot panels)."""
    sigmas = list(array.position_sigma)
    return {
        "source": BELIEF_NAMES.get(int(array.source), str(int(array.source))),
        "origin": array.origin,
        "objects": [
            {
                "id": int(o.id),
                "x": float(o.position.x),
                "y": float(o.position.y),
                "position_sigma": float(sigmas[i]) if i < len(sigmas) else None,
            }
            for i, o in enumerate(array.objects)
        ],
    }


def image(msg) -> RawImage:
    """A sensor_msgs/Image (the colour-mapped rgb8 map) as the SDK's RawImage."""
    return RawImage(
        timestamp=timestamp(msg.header),
        frame_id=msg.header.frame_id,
        width=int(msg.width),
        height=int(msg.height),
        encoding=msg.encoding,
        step=int(msg.step),
        data=bytes(msg.data),
    )


def transforms(tf_message) -> FrameTransforms:
    """A tf2_msgs/TFMessage as the SDK's FrameTransforms."""
    out = []
    for t in tf_message.transforms:
        v, q = t.transform.translation, t.transform.rotation
        out.append(
            FrameTransform(
                timestamp=timestamp(t.header),
                parent_frame_id=t.header.frame_id,
                child_frame_id=t.child_frame_id,
                translation=Vector3(x=float(v.x), y=float(v.y), z=float(v.z)),
                rotation=Quaternion(x=float(q.x), y=float(q.y), z=float(q.z), w=float(q.w)),
            )
        )
    return FrameTransforms(transforms=out)


def force_samples(trace, max_samples: int = MAX_FORCE_SAMPLES) -> list[tuple[int, dict]]:
    """A ForceTrace as per-sample (log time in ns, message) pairs for the Plot panel: the
    lateral force (N, torsion x lateral spring constant / tip height, afm_core's rule) and the
    normal force (N, deflection x normal spring constant) at header stamp + times[i]; at most
    `max_samples`, evenly spread, the last sample always kept; a sample at a time that is not
    finite is left out."""
    from afm_core.manipulation.execute import cantilever_forces

    times = np.asarray(trace.times, float)
    n = len(times)
    if n == 0:
        return []
    if not (len(trace.lateral_torsion) == len(trace.vertical_deflection) == n):
        raise ValueError(
            f"force trace: times ({n}), lateral_torsion ({len(trace.lateral_torsion)}) and "
            f"vertical_deflection ({len(trace.vertical_deflection)}) must have one length"
        )
    keep = np.unique(np.linspace(0, n - 1, min(n, max_samples)).round().astype(int))
    # a sample at no time (nan, inf) has no place on the plot's time axis
    keep = keep[np.isfinite(times[keep])]
    lateral, normal = cantilever_forces(
        trace.lateral_torsion,
        trace.vertical_deflection,
        trace.lateral_spring_constant,
        trace.normal_spring_constant,
    )
    start = stamp_ns(trace.header)
    out = []
    for i in keep:
        t_ns = start + int(round(times[i] * 1e9))
        out.append(
            (
                t_ns,
                {
                    "timestamp": {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000},
                    "lateral_force": float(lateral[i]),
                    "normal_force": float(normal[i]),
                    "task": trace.task,
                    "object_id": int(trace.object_id),
                },
            )
        )
    return out


def message_dict(msg, depth: int = 0):
    """Any ROS message (anything with get_fields_and_field_types) as JSON-ready data; arrays
    as lists, bytes as lists of numbers, nan/inf as None (JSON has no such numbers)."""
    if depth > 16:
        raise ValueError("message nests deeper than 16 levels")
    if hasattr(msg, "get_fields_and_field_types"):
        return {
            name: message_dict(getattr(msg, name), depth + 1)
            for name in msg.get_fields_and_field_types()
        }
    if isinstance(msg, bytes | bytearray):
        return list(msg)
    if isinstance(msg, float):
        return msg if math.isfinite(msg) else None
    if isinstance(msg, str | bool | int) or msg is None:
        return msg
    if isinstance(msg, np.ndarray):
        return [message_dict(v.item(), depth + 1) for v in msg.ravel()]
    try:
        return [message_dict(v, depth + 1) for v in msg]
    except TypeError:
        return str(msg)
