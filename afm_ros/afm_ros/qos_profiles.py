"""The graph's QoS: full scans and maps latched, streams as sensor data."""

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

LATCHED = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# Full scans: latched, and the last few kept, so a node that joins late still gets both scans
# of a 0/90 pair (depth 4: a few 4096 x 4096 images at most in memory).
SCANS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=4,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# Subscribers to streams take sensor-data QoS (best effort: a viewer wants the newest, not every
# one). The driver offers them reliably, which a best-effort subscriber still matches, so a
# recorder (which subscribes reliably when every publisher offers it) keeps every scan line and
# force trace: the replay backend serves a local scan from the recorded line, and one lost best
# effort sample on a loaded machine made that replay refuse it.
STREAM = qos_profile_sensor_data
STREAM_OFFERED = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
# Commands and goals: reliable, and the last 100 kept for late joiners, so a recorder that
# matched a moment after the first command still records it.
EVENTS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# Action feedback arrives in bursts (a scan's lines): a deep queue keeps most of it.
FEEDBACK = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=200,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
