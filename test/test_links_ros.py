"""A client waits for the link a publisher has matched, not for what its own graph shows."""

import os
import signal
import time

import pytest
from conftest import wait_for
from rclpy.qos import qos_profile_sensor_data

from afm_bringup.commander import AfmCommander, AfmError
from afm_msgs.action import LocalScan
from afm_msgs.msg import ScanLine
from afm_ros.topics import SCAN_LINE

pytestmark = pytest.mark.ros


def test_a_subscription_the_driver_has_not_matched_is_waited_for(nodes):
    driver = nodes("driver", seed=2, real_time_factor=0.0)
    with AfmCommander(server_timeout=60) as afm:
        wait_for(lambda: "/afm_driver" in afm.link_reports(), 60, what="the driver's link report")
        before = afm.link_reports()["/afm_driver"][SCAN_LINE]["matched"]
        heard = []
        # a stopped driver cannot discover the new subscription, as when its discovery sample
        # is lost: the commander's own graph lists it all the same
        os.kill(driver.process.pid, signal.SIGSTOP)
        try:
            afm.node.create_subscription(
                ScanLine, SCAN_LINE, heard.append, qos_profile_sensor_data
            )
            wait_for(
                lambda: any(
                    s.node_name == "afm_commander"
                    for s in afm.node.get_subscriptions_info_by_topic(SCAN_LINE)
                ),
                10,
                what="the subscription in the commander's graph",
            )
            started = time.monotonic()
            with pytest.raises(
                AfmError, match=r"/afm_driver has not yet discovered /afm_commander"
            ):
                afm.wait_until_subscribed([SCAN_LINE], "afm_commander", timeout=2.0)
            assert time.monotonic() - started >= 2.0
        finally:
            os.kill(driver.process.pid, signal.SIGCONT)
        afm.wait_until_subscribed([SCAN_LINE], "afm_commander", timeout=20.0)
        assert afm.link_reports()["/afm_driver"][SCAN_LINE]["matched"] == before + 1
        line = LocalScan.Goal(samples=50, speed=1e-6)
        line.start.x, line.start.y, line.end.x, line.end.y = 54.7e-6, 55e-6, 55.3e-6, 55e-6
        assert afm.send("local_scan", line).success
        wait_for(lambda: heard, 10, what="the scan line on the matched subscription")
