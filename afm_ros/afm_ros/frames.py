"""The graph's frame tree, defined once, as tf2 messages (`/tf_static`, `/tf`).

    afm_task (sample-fixed; maps, landmarks, the tip estimate)
    |-- afm_image    static, identity: the task frame is the frame of the instrument's own
    |                images (docs/localization.md, Frames), so the two coincide
    `-- afm_scanner  on /tf, from the localizer: where the commanded (scanner) coordinates sit
                     in the task frame as its estimate says, a translation

The scanner-to-task relation is not rigid: the calibration's scanner matrix is a gain and shear
of about 1 % (a tf transform can carry neither), and drift, creep and hysteresis residue move
it over time. The localizer publishes the translation that maps the commanded tip position onto
its estimate of the tip, which is exact at the tip, where the stack works.
"""

from __future__ import annotations

from geometry_msgs.msg import TransformStamped
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage

from afm_ros.conversions import FRAME_IMAGE, FRAME_SCANNER, FRAME_TASK

# (parent, child) pairs that coincide: identity transforms on /tf_static
STATIC_IDENTITIES = ((FRAME_TASK, FRAME_IMAGE),)
DYNAMIC = (FRAME_TASK, FRAME_SCANNER)  # (parent, child) on /tf

# tf2_ros's own QoS for the two topics, so its listeners (RViz, Foxglove bridges) match
STATIC_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
DYNAMIC_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


def transform(parent: str, child: str, stamp, x: float = 0.0, y: float = 0.0) -> TransformStamped:
    """A translation by (x, y) m, no rotation: the child's origin in the parent frame."""
    out = TransformStamped()
    out.header.stamp, out.header.frame_id, out.child_frame_id = stamp, parent, child
    out.transform.translation.x, out.transform.translation.y = float(x), float(y)
    out.transform.rotation.w = 1.0
    return out


def static_tree(stamp) -> TFMessage:
    """Every static transform of the tree in one message (as tf2's static broadcaster sends
    them: a latched topic keeps one message per publisher)."""
    return TFMessage(transforms=[transform(p, c, stamp) for p, c in STATIC_IDENTITIES])


def scanner_in_task(stamp, estimate, commanded) -> TFMessage:
    """afm_task -> afm_scanner: the estimated tip position (task, m) minus the commanded one
    (scanner, m), so that the commanded position maps onto the estimate."""
    parent, child = DYNAMIC
    dx, dy = estimate[0] - commanded[0], estimate[1] - commanded[1]
    return TFMessage(transforms=[transform(parent, child, stamp, dx, dy)])
