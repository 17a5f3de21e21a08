"""The link check's decisions on a given graph (afm_ros.links), without ROS running."""

import importlib.util
import re
from pathlib import Path
from types import SimpleNamespace

import pytest
from rclpy.duration import Infinite
from rclpy.qos import (
    DurabilityPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

from afm_ros import links
from afm_ros.qos_profiles import LATCHED, STREAM_OFFERED

TOPIC = "/afm/scan_line"


def endpoint(node, qos, gid, namespace="/"):
    return SimpleNamespace(
        node_name=node, node_namespace=namespace, qos_profile=qos, endpoint_gid=list(gid)
    )


DRIVER = endpoint("afm_driver", STREAM_OFFERED, b"\x01" * 16)
RECORDER = endpoint("afm_recorder", STREAM_OFFERED, b"\x02" * 16)  # reliable, as it asks
VIEWER = endpoint("afm_viewer", qos_profile_sensor_data, b"\x03" * 16)  # best effort
REC, VIEW = links.endpoint_id(RECORDER), links.endpoint_id(VIEWER)


def state(matched, *known):
    return {"/afm_driver": {TOPIC: {"matched": matched, "known": set(known)}}}


def check(reports, targets=(RECORDER,), publishers=(DRIVER,), reporting=None):
    reporting = {"/afm_driver"} if reporting is None else reporting
    return links.unconfirmed(TOPIC, list(publishers), list(targets), reports, reporting)


def test_a_publisher_that_knows_and_matched_the_subscription_is_confirmed():
    assert check(state(2, REC, VIEW)) == ([], False)
    assert check(state(1, REC)) == ([], False)  # the viewer is not what we wait for


def test_a_subscription_the_publisher_has_not_discovered_is_named():
    reasons, unchecked = check(state(1, VIEW))
    assert reasons == [
        "/afm_driver has not yet discovered /afm_recorder's subscription to /afm/scan_line"
    ]
    assert not unchecked
    assert check({"/afm_driver": {}})[0]  # no entry for the topic: it knows nothing there


def test_a_known_subscription_not_yet_matched_is_waited_for():
    assert check(state(1, REC, VIEW)) == (
        [
            "/afm_driver's publisher on /afm/scan_line has matched 1 of the 2 subscriptions "
            "it knows"
        ],
        False,
    )


def test_a_node_that_reports_links_but_whose_report_has_not_arrived_is_waited_for():
    assert check({}) == (["/afm_driver has not reported its links yet"], False)


def test_a_publisher_that_reports_nothing_falls_back_to_the_graph():
    stranger = endpoint("lab_daq_bridge", STREAM_OFFERED, b"\x06" * 16)
    assert check({}, publishers=(stranger,), reporting=set()) == ([], True)


def test_an_afm_node_whose_links_publisher_is_not_yet_discovered_is_waited_for():
    # the graph shows the driver's scan line publisher before its LINKS publisher
    assert check({}, reporting=set()) == (["/afm_driver has not reported its links yet"], False)
    assert check(state(1, REC), reporting=set()) == ([], False)  # its report arrived


def test_every_afm_node_is_known_by_the_name_it_gives_itself():
    from afm_bringup.launcher import NODES

    given = set()
    for spec in NODES.values():
        source = Path(importlib.util.find_spec(spec.module).origin).read_text()
        given |= set(re.findall(r'super\(\).__init__\("([^"]+)"', source))
    assert len(given) == len(NODES)
    assert given == links.REPORTING_NODES


def test_a_subscription_that_cannot_match_the_offer_is_not_expected():
    # a transient-local request and a volatile offer never match: waiting would hang
    late_joiner = endpoint("afm_recorder", LATCHED, b"\x04" * 16)
    assert check(state(1, REC), targets=(RECORDER, late_joiner)) == ([], False)
    assert not links.compatible(STREAM_OFFERED, LATCHED)
    assert not links.compatible(qos_profile_sensor_data, STREAM_OFFERED)  # reliable of b.e.
    assert links.compatible(STREAM_OFFERED, qos_profile_sensor_data)


def test_a_publishers_own_profile_matches_the_graphs_view_of_a_subscription():
    # the graph gives Infinite deadlines and leases where a publisher's profile has 0 (unset)
    seen = QoSProfile(
        depth=5,
        reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
        deadline=Infinite,
        liveliness=LivelinessPolicy.AUTOMATIC,
        liveliness_lease_duration=Infinite,
    )
    assert links.compatible(STREAM_OFFERED, seen)


def test_namespaced_nodes_are_told_apart():
    other = endpoint("afm_driver", STREAM_OFFERED, b"\x05" * 16, namespace="/lab2")
    reasons, _ = check(
        state(1, REC), publishers=(DRIVER, other), reporting={"/afm_driver", "/lab2/afm_driver"}
    )
    assert reasons == ["/lab2/afm_driver has not reported its links yet"]


def test_a_report_survives_its_round_trip_and_a_malformed_one_is_refused_by_name():
    sent = {
        TOPIC: {"matched": 2, "known": {REC, VIEW}},
        "/afm/scan": {"matched": 0, "known": set()},
    }
    assert links.decode(links.encode("/afm_driver", sent)) == ("/afm_driver", sent)
    for bad in (
        "not json",
        '{"node": "/x"}',
        '{"node": 3, "topics": {}}',
        '{"node": "/x", "topics": {"/t": {"matched": 1}}}',
        "[1, 2]",
    ):
        with pytest.raises(ValueError, match="/afm/links: not a link report"):
            links.decode(bad)
