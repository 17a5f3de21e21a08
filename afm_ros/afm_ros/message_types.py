"""Conversions between rclpy objects and the core recording types."""

from __future__ import annotations

import importlib

from rclpy.duration import Duration
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
)

from afm_core.recording.qos import RMW_DURATION_INFINITE_NS, QosDescription


def import_message_type(type_name: str):
    """'pkg/msg/Type' -> the generated Python class; ValueError naming what is missing."""
    parts = type_name.split("/")
    if len(parts) != 3:
        raise ValueError(f"type {type_name!r}: expected 'package/msg/Type'")
    package, kind, name = parts
    try:
        module = importlib.import_module(f"{package}.{kind}")
        return getattr(module, name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(
            f"type {type_name!r} is not importable here ({exc}); "
            "is its interface package built and sourced?"
        ) from exc


def _ns(duration) -> int:
    ns = duration.nanoseconds if hasattr(duration, "nanoseconds") else int(duration)
    return min(int(ns), RMW_DURATION_INFINITE_NS)


def describe_qos(profile: QoSProfile) -> QosDescription:
    return QosDescription(
        history=HistoryPolicy(profile.history).name.lower(),
        depth=int(profile.depth),
        reliability=ReliabilityPolicy(profile.reliability).name.lower(),
        durability=DurabilityPolicy(profile.durability).name.lower(),
        liveliness=LivelinessPolicy(profile.liveliness).name.lower(),
        deadline_ns=_ns(profile.deadline),
        lifespan_ns=_ns(profile.lifespan),
        liveliness_lease_duration_ns=_ns(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def qos_from_description(desc: QosDescription) -> QoSProfile:
    def duration(ns):
        return Duration(nanoseconds=ns) if 0 < ns < RMW_DURATION_INFINITE_NS else Duration()

    history = HistoryPolicy.KEEP_ALL if desc.history == "keep_all" else HistoryPolicy.KEEP_LAST
    return QoSProfile(
        history=history,
        depth=max(1, desc.depth),
        reliability=ReliabilityPolicy[desc.reliability.upper()]
        if desc.reliability != "unknown"
        else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy[desc.durability.upper()]
        if desc.durability != "unknown"
        else DurabilityPolicy.VOLATILE,
        liveliness=LivelinessPolicy[desc.liveliness.upper()]
        if desc.liveliness != "unknown"
        else LivelinessPolicy.AUTOMATIC,
        deadline=duration(desc.deadline_ns),
        lifespan=duration(desc.lifespan_ns),
        liveliness_lease_duration=duration(desc.liveliness_lease_duration_ns),
        avoid_ros_namespace_conventions=desc.avoid_ros_namespace_conventions,
    )


def subscription_qos_for(offers: list[QosDescription]) -> QoSProfile:
    """Request QoS that matches every publisher and still gets latched messages when all
    publishers latch (rosbag2's rule), keeping every message until it is taken: a burst that
    arrives while the writer compresses a chunk waits instead of overwriting the oldest. (The
    publishers' own depth would do, as rosbag2 takes it, but the graph reports it as 0 for
    another process's publishers, and rosbag2 keeps all then too.)"""
    all_reliable = bool(offers) and all(o.reliability == "reliable" for o in offers)
    all_latched = bool(offers) and all(o.durability == "transient_local" for o in offers)
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL,
        reliability=ReliabilityPolicy.RELIABLE if all_reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if all_latched else DurabilityPolicy.VOLATILE,
    )


def publisher_qos_for(offers: list[QosDescription], depth: int) -> QoSProfile:
    """A replay publisher's QoS: the recorded durability (latched topics stay latched) and
    liveliness/deadline/lifespan of the first offer when the offers agree, always reliable,
    keeping the last `depth` messages (or the recorded depth, if deeper).

    A replay publishes in bursts, and a subscriber that matches a moment late or falls behind
    can be repaired only from the publisher's history: with the one-message history the
    graph API reports for recorded publishers, a burst reached a subscriber with a third of
    its messages missing. A reliable publisher still serves best-effort subscribers."""
    agreed = bool(offers) and all(
        (o.durability, o.liveliness) == (offers[0].durability, offers[0].liveliness)
        for o in offers
    )
    profile = qos_from_description(offers[0]) if agreed else QoSProfile(depth=1)
    profile.history = HistoryPolicy.KEEP_LAST
    profile.depth = max(depth, profile.depth)
    profile.reliability = ReliabilityPolicy.RELIABLE
    return profile
