"""The offered QoS of a recorded topic, stored per MCAP channel as rosbag2 reads it.

rosbag2's MCAP plugin reads the channel metadata key `offered_qos_profiles` as a YAML list.
We write the integer-enum form (bag metadata version 8), which rosbag2 reads for every file
whose `rosbag2` metadata record carries no serialized bag metadata, as ours does.
"""

from __future__ import annotations

from dataclasses import dataclass

import yaml

# rmw enum values (rmw/types.h). A publisher seen through DDS discovery reports history as
# "unknown": history is local to the writer and not sent over the wire.
HISTORY = {"system_default": 0, "keep_last": 1, "keep_all": 2, "unknown": 3}
RELIABILITY = {
    "system_default": 0,
    "reliable": 1,
    "best_effort": 2,
    "unknown": 3,
    "best_available": 4,
}
DURABILITY = {
    "system_default": 0,
    "transient_local": 1,
    "volatile": 2,
    "unknown": 3,
    "best_available": 4,
}
LIVELINESS = {
    "system_default": 0,
    "automatic": 1,
    "manual_by_topic": 3,
    "unknown": 4,
    "best_available": 5,
}
RMW_DURATION_INFINITE_NS = 2**63 - 1


def _duration(ns: int) -> dict:
    ns = min(int(ns), RMW_DURATION_INFINITE_NS)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _from_duration(node: dict) -> int:
    return int(node["sec"]) * 1_000_000_000 + int(node["nsec"])


@dataclass(frozen=True)
class QosDescription:
    """One publisher's offered QoS, in rmw terms (durations in nanoseconds, 0 = default)."""

    history: str = "keep_last"
    depth: int = 10
    reliability: str = "reliable"
    durability: str = "volatile"
    liveliness: str = "automatic"
    deadline_ns: int = 0
    lifespan_ns: int = 0
    liveliness_lease_duration_ns: int = 0
    avoid_ros_namespace_conventions: bool = False

    def __post_init__(self):
        for field, table in (
            ("history", HISTORY),
            ("reliability", RELIABILITY),
            ("durability", DURABILITY),
            ("liveliness", LIVELINESS),
        ):
            if getattr(self, field) not in table:
                raise ValueError(
                    f"QoS {field}={getattr(self, field)!r}: expected one of {sorted(table)}"
                )

    def to_rosbag2(self) -> dict:
        return {
            "history": HISTORY[self.history],
            "depth": int(self.depth),
            "reliability": RELIABILITY[self.reliability],
            "durability": DURABILITY[self.durability],
            "deadline": _duration(self.deadline_ns),
            "lifespan": _duration(self.lifespan_ns),
            "liveliness": LIVELINESS[self.liveliness],
            "liveliness_lease_duration": _duration(self.liveliness_lease_duration_ns),
            "avoid_ros_namespace_conventions": bool(self.avoid_ros_namespace_conventions),
        }

    @classmethod
    def from_rosbag2(cls, node: dict) -> QosDescription:
        def name(table, value):
            if isinstance(value, str):
                return value.lower()
            return {v: k for k, v in table.items()}[int(value)]

        return cls(
            history=name(HISTORY, node["history"]),
            depth=int(node.get("depth", 0)),
            reliability=name(RELIABILITY, node["reliability"]),
            durability=name(DURABILITY, node["durability"]),
            liveliness=name(LIVELINESS, node["liveliness"]),
            deadline_ns=_from_duration(node["deadline"]),
            lifespan_ns=_from_duration(node["lifespan"]),
            liveliness_lease_duration_ns=_from_duration(node["liveliness_lease_duration"]),
            avoid_ros_namespace_conventions=bool(
                node.get("avoid_ros_namespace_conventions", False)
            ),
        )


def dump_profiles(profiles: list[QosDescription]) -> str:
    return yaml.safe_dump([p.to_rosbag2() for p in profiles], sort_keys=False)


def load_profiles(text: str) -> list[QosDescription]:
    if not text:
        return []
    return [QosDescription.from_rosbag2(node) for node in yaml.safe_load(text) or []]
