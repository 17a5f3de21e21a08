"""Which subscriptions each node's publishers send to, so a client can wait for a link the
ROS graph cannot show it.

The graph (get_subscriptions_info_by_topic) lists a subscription as soon as the asking
process has discovered it; the publisher's own process discovers it separately, and only then
sends it anything. On a loaded machine a lost discovery sample is repaired seconds later, so a
recorder the graph showed subscribed missed every scan line and force trace of a whole
session (CI, 2026-11-28: 11 messages recorded, the volatile topics empty). Every afm node
therefore reports on LINKS (latched, one JSON object per node), for each topic it publishes,
the subscriptions its own process knows (their endpoint ids) and how many its publishers have
matched; `unconfirmed` checks a given node's subscriptions against that. Identities rather
than counts: a node killed with -9 stays in other processes' graphs until its lease runs out
(20 s), and a publisher started after it never matches it. A publisher that does not report
(not an afm node) falls back to the graph.
"""

from __future__ import annotations

import json

from rclpy.exceptions import InvalidHandle
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from std_msgs.msg import String

from afm_ros import topics
from afm_ros.qos_profiles import LATCHED

# s: how often a node compares its link state with what it last reported (each look costs
# about 0.4 ms with ten topics: bench/results/links.md)
POLL_PERIOD_S = 0.25
NOT_REPORTED = {"/rosout", "/parameter_events", topics.LINKS}
# The names the afm nodes give themselves (each *_node.py; every one reports, from
# node_main.run). A publisher of one of these is waited for until its report arrives: its
# LINKS publisher is created last and can be discovered seconds after its other publishers,
# and taking it meanwhile for a node that never reports let a recorder miss the scan line sent
# next (CI, 2026-11-29). A node renamed at launch is known by its LINKS publisher only.
REPORTING_NODES = frozenset(
    {
        "afm_driver",
        "afm_imaging",
        "afm_localizer",
        "afm_planner",
        "afm_nano_hand",
        "afm_teleop",
        "afm_recorder",
        "afm_replay",
        "sim2real",
        "afm_viewer",
    }
)


def full_name(name: str, namespace: str) -> str:
    return f"{namespace.rstrip('/')}/{name}"


def endpoint_id(info) -> str:
    return bytes(info.endpoint_gid).hex()


def link_state(node) -> dict[str, dict]:
    """Topic -> {"matched": subscriptions its publishers have matched (the fewest, when the
    node has several there: each must have), "known": ids of the subscriptions on it the
    node's process has discovered and its publishers can match}."""
    offers: dict[str, list] = {}  # topic -> (matched count, offered QoS) per publisher
    for publisher in list(node.publishers):
        try:
            if publisher.topic_name not in NOT_REPORTED:
                offers.setdefault(publisher.topic_name, []).append(
                    (publisher.get_subscription_count(), publisher.qos_profile)
                )
        except InvalidHandle:  # destroyed by another thread meanwhile: no longer publishes
            continue
    state = {}
    for topic, offered in offers.items():
        subscriptions = node.get_subscriptions_info_by_topic(topic)  # once per topic
        state[topic] = {
            "matched": min(count for count, _ in offered),
            "known": {
                endpoint_id(s)
                for s in subscriptions
                if any(compatible(qos, s.qos_profile) for _, qos in offered)
            },
        }
    return state


class LinkReporter:
    """Publishes the node's link state on LINKS whenever it changes."""

    def __init__(self, node, period_s: float = POLL_PERIOD_S):
        self._node = node
        self._publisher = node.create_publisher(String, topics.LINKS, LATCHED)
        self._name = full_name(node.get_name(), node.get_namespace())
        self._last: dict | None = None
        node.create_timer(period_s, self.report_if_changed)
        self.report_if_changed()

    def report_if_changed(self) -> None:
        state = link_state(self._node)
        if state != self._last:
            self._last = state
            self._publisher.publish(String(data=encode(self._name, state)))


def encode(node: str, state: dict[str, dict]) -> str:
    topics_state = {
        t: {"matched": e["matched"], "known": sorted(e["known"])} for t, e in state.items()
    }
    return json.dumps({"node": node, "topics": topics_state}, sort_keys=True)


def decode(text: str) -> tuple[str, dict[str, dict]]:
    """(node, topic -> {"matched": int, "known": set of ids}); ValueError naming what is
    wrong."""
    try:
        report = json.loads(text)
        node = report["node"]
        state = {
            str(topic): {"matched": int(e["matched"]), "known": {str(k) for k in e["known"]}}
            for topic, e in report["topics"].items()
        }
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{topics.LINKS}: not a link report ({exc}): {text[:80]!r}") from None
    if not isinstance(node, str):
        raise ValueError(f"{topics.LINKS}: not a link report: {text[:80]!r}")
    return node, state


def compatible(offered, requested) -> bool:
    """False for a pair that never matches, so waiting for it would wait for nothing: a
    reliable request of a best-effort offer, a transient-local request of a volatile one. The
    graph's nodes set no deadline or liveliness, so only these two can part them (rclpy's
    qos_check_compatible takes a publisher's unset deadline, 0, for none against the graph's
    Infinite, and calls every pair an error)."""
    return not (
        (
            requested.reliability == ReliabilityPolicy.RELIABLE
            and offered.reliability == ReliabilityPolicy.BEST_EFFORT
        )
        or (
            requested.durability == DurabilityPolicy.TRANSIENT_LOCAL
            and offered.durability == DurabilityPolicy.VOLATILE
        )
    )


def unconfirmed(
    topic: str,
    publishers,
    targets,
    reports: dict[str, dict[str, dict]],
    reporting: set[str],
) -> tuple[list[str], bool]:
    """(why the topic's publishers may not yet send to every target subscription, whether some
    publisher could not be checked). publishers/targets: the graph's endpoint infos (targets:
    the waiting-for node's subscriptions); reports: node -> its latest link state; reporting:
    nodes the graph shows publishing on LINKS (an afm node by its name reports too)."""
    reasons, unchecked = [], False
    for publisher in publishers:
        node = full_name(publisher.node_name, publisher.node_namespace)
        will_report = node in reporting or publisher.node_name in REPORTING_NODES
        if not will_report and node not in reports:
            unchecked = True
            continue
        if node not in reports:
            reasons.append(f"{node} has not reported its links yet")
            continue
        entry = reports[node].get(topic, {"matched": 0, "known": set()})
        unknown = [
            t
            for t in targets
            if endpoint_id(t) not in entry["known"]
            and compatible(publisher.qos_profile, t.qos_profile)
        ]
        if unknown:
            who = full_name(unknown[0].node_name, unknown[0].node_namespace)
            reasons.append(f"{node} has not yet discovered {who}'s subscription to {topic}")
        elif entry["matched"] < len(entry["known"]):
            reasons.append(
                f"{node}'s publisher on {topic} has matched {entry['matched']} of the "
                f"{len(entry['known'])} subscriptions it knows"
            )
    return reasons, unchecked
