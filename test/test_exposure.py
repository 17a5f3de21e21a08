"""Exposure: the graph's DDS stays on this machine unless asked (afm_ros.exposure).

Issue 30: every node bound its DDS sockets on all interfaces (discovery was localhost-only
only through scripts/env.sh), the domain id could not be chosen at launch.
"""

import ipaddress
import os
import socket
import struct
import time
from pathlib import Path

import pytest
from conftest import wait_for

from afm_bringup.cli import main
from afm_ros import exposure


def test_the_default_is_the_localhost_profile_and_what_the_user_set_wins(tmp_path):
    env = exposure.apply({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}, folder=tmp_path)
    profile = Path(env["FASTRTPS_DEFAULT_PROFILES_FILE"])
    assert profile.read_text() == exposure.LOCALHOST_PROFILE
    assert "<address>127.0.0.1</address>" in exposure.LOCALHOST_PROFILE
    assert "<useBuiltinTransports>false</useBuiltinTransports>" in exposure.LOCALHOST_PROFILE
    # with the profile, LOCALHOST would make rmw_fastrtps open sockets on every interface
    assert "ROS_AUTOMATIC_DISCOVERY_RANGE" not in env and "ROS_DOMAIN_ID" not in env
    # rmw_fastrtps's own (synchronous) writes: asynchronous ones lost bursts (exposure)
    assert exposure.PUBLICATION_MODE not in env
    mine = {"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/lab/dds.xml", "ROS_DOMAIN_ID": "7"}
    env = exposure.apply(dict(mine), folder=tmp_path)
    assert env["FASTRTPS_DEFAULT_PROFILES_FILE"] == "/etc/lab/dds.xml"
    assert (env["ROS_DOMAIN_ID"], env["ROS_AUTOMATIC_DISCOVERY_RANGE"]) == ("7", "LOCALHOST")
    env = exposure.apply(dict(mine), domain_id=42, folder=tmp_path)
    assert env["ROS_DOMAIN_ID"] == "42"
    lab = exposure.apply(
        exposure.apply({}, folder=tmp_path), network="lab", domain_id=3, folder=tmp_path
    )
    lab_profile = lab.pop("FASTRTPS_DEFAULT_PROFILES_FILE")
    assert lab_profile == lab.pop("FASTDDS_DEFAULT_PROFILES_FILE")
    assert lab == {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET", "ROS_DOMAIN_ID": "3"}
    # the lab's profile: Fast DDS's UDP on every interface, without its shared memory
    assert Path(lab_profile).read_text() == exposure.LAB_PROFILE
    assert "<type>UDPv4</type>" in exposure.LAB_PROFILE
    assert "<interfaceWhiteList>" not in exposure.LAB_PROFILE
    for profile in (exposure.LOCALHOST_PROFILE, exposure.LAB_PROFILE):
        assert "SHM" not in profile
    mine_lab = exposure.apply(dict(mine), network="lab", folder=tmp_path)
    assert mine_lab["FASTRTPS_DEFAULT_PROFILES_FILE"] == "/etc/lab/dds.xml"


@pytest.mark.ros
def test_fast_dds_reads_both_profiles_without_an_error(tmp_path):
    """Fast DDS says nothing of an element it does not know but an XMLPARSER error, and then
    runs on its defaults (a 3 s repair): a participant started with each profile must print
    none, and one with a misspelled element must (so the check can see it)."""
    import subprocess
    import sys

    heartbeat = f"<nanosec>{round(exposure.REPAIR_PERIOD_S * 1e9)}</nanosec>"
    for text in (exposure.LOCALHOST_PROFILE, exposure.LAB_PROFILE):
        assert "<heartbeatPeriod>" in text and heartbeat in text
    misspelled = exposure.LAB_PROFILE.replace("heartbeatPeriod>", "heartbeatPeriodX>")
    probe = (
        "import rclpy; from std_msgs.msg import String; rclpy.init(); "
        "rclpy.create_node('afm_profile_probe').create_publisher(String, '/afm_probe', 10); "
        "print('participant up')"
    )
    outputs = {}
    for name, text in (
        ("localhost", exposure.LOCALHOST_PROFILE),
        ("lab", exposure.LAB_PROFILE),
        ("misspelled", misspelled),
    ):
        path = tmp_path / f"{name}.xml"
        path.write_text(text)
        env = dict(os.environ, FASTRTPS_DEFAULT_PROFILES_FILE=str(path))
        env.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)
        env.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
        run = subprocess.run(
            [sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=60
        )
        outputs[name] = run.stdout + run.stderr
        assert "participant up" in outputs[name], outputs[name]
    assert "XMLPARSER" not in outputs["localhost"], outputs["localhost"]
    assert "XMLPARSER" not in outputs["lab"], outputs["lab"]
    assert "XMLPARSER" in outputs["misspelled"], outputs["misspelled"]


@pytest.mark.parametrize("value", [-1, 102, "abc", 1.5])
def test_a_bad_domain_id_is_refused_with_the_limit(value):
    with pytest.raises(ValueError, match=r"--domain-id=.*: must be a whole number"):
        exposure.check_domain_id(value)


def test_afm_launch_refuses_a_bad_domain_id_before_starting_anything(capsys):
    assert main(["launch", "--domain-id", "300", "--nodes", "planner"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["afm launch: --domain-id=300: must be a whole number in [0, 101]"]


def udp_sockets(pid: int) -> list[tuple[str, int]]:
    """(address, port) of every IPv4/IPv6 UDP socket process `pid` holds, from /proc."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    found = []
    for table, family in (("udp", socket.AF_INET), ("udp6", socket.AF_INET6)):
        lines = Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]
        for line in lines:
            fields = line.split()
            if fields[9] not in inodes:
                continue
            address, port = fields[1].split(":")
            raw = bytes.fromhex(address)
            if family == socket.AF_INET:
                raw = struct.pack("<I", int(address, 16))
            else:
                raw = b"".join(struct.pack("<I", w) for w in struct.unpack(">4I", raw))
            found.append((socket.inet_ntop(family, raw), int(port, 16)))
    return found


def shared_memory_files(pid: int) -> set[str]:
    """The Fast DDS shared-memory files (segments, ports) process `pid` has mapped."""
    lines = Path(f"/proc/{pid}/maps").read_text().splitlines()
    return {line.split()[-1] for line in lines if "/dev/shm/fastrtps" in line}


@pytest.mark.ros
def test_a_launched_node_binds_only_the_loopback_and_still_answers(tmp_path):
    from afm_bringup.commander import AfmCommander
    from afm_bringup.launcher import Graph
    from afm_msgs.action import MoveTip

    graph = Graph(tmp_path / "logs")  # the default: exposure.apply on this environment
    assert graph.environment["FASTRTPS_DEFAULT_PROFILES_FILE"].endswith(exposure.PROFILE_NAME)
    process = graph.start("driver", {"seed": "1"})
    try:
        with AfmCommander("exposure_test", server_timeout=60) as afm:
            goal = MoveTip.Goal(speed=10e-6)
            goal.target.point.x, goal.target.point.y = 20e-6, 20e-6
            assert afm.send("move_tip", goal).success  # a client in a LOCALHOST shell talks
        sockets = wait_for(lambda: udp_sockets(process.pid), 10, what="the driver's sockets")
        outside = outside_loopback(sockets)
        assert not outside, f"bound beyond the loopback: {outside} (all: {sockets})"
        # no shared memory: a write into another process's port waits on its interprocess
        # lock with the GIL held (afm_ros.exposure), which stood whole nodes still
        assert not shared_memory_files(process.pid)
    finally:
        graph.stop_all()


def test_a_node_on_its_own_takes_the_localhost_default_unless_told_wider(tmp_path):
    env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}  # scripts/env.sh, or nothing at all
    for start in (dict(env), {}):
        applied = exposure.apply_node_default(start)
        assert exposure.is_ours(applied["FASTRTPS_DEFAULT_PROFILES_FILE"])
        assert "ROS_AUTOMATIC_DISCOVERY_RANGE" not in applied
    for wider in (
        {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"},
        {"FASTDDS_DEFAULT_PROFILES_FILE": "/lab.xml"},
    ):
        assert exposure.apply_node_default(dict(wider)) == wider  # the lab's choice is kept


def test_an_isolated_run_takes_the_nodes_profile_itself_unless_told_otherwise():
    # a test's or a benchmark's own writers (commands, goals) repair as the nodes' do
    run = {"ROS_DOMAIN_ID": "9"}
    exposure.isolate_run(run)
    assert exposure.is_ours(run["FASTRTPS_DEFAULT_PROFILES_FILE"])
    assert "ROS_AUTOMATIC_DISCOVERY_RANGE" not in run
    wider = {"ROS_DOMAIN_ID": "9", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}
    assert exposure.isolate_run(dict(wider)) == 9
    own = {"ROS_DOMAIN_ID": "9", "FASTRTPS_DEFAULT_PROFILES_FILE": "/lab.xml"}
    exposure.isolate_run(own)
    assert own["FASTRTPS_DEFAULT_PROFILES_FILE"] == "/lab.xml"
    assert own["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"


def outside_loopback(sockets):
    return [
        (address, port)
        for address, port in sockets
        if not (
            ipaddress.ip_address(address).is_loopback or ipaddress.ip_address(address).is_multicast
        )
    ]


@pytest.mark.ros
@pytest.mark.parametrize("network", exposure.NETWORKS)
def test_a_participant_on_either_profile_maps_no_shared_memory(tmp_path, network):
    """Measured, as Fast DDS reads the profile with the discovery range `afm` sets for it
    (Fast DDS's own default maps a segment and ports in /dev/shm)."""
    import subprocess
    import sys

    env = exposure.apply(
        {k: v for k, v in os.environ.items() if k not in exposure.PROFILE_VARIABLES},
        network=network,
        folder=tmp_path,
    )
    script = (
        "import os, time, rclpy; from std_msgs.msg import String; rclpy.init(); "
        "node = rclpy.create_node('afm_shm_probe'); node.create_publisher(String, '/x', 10); "
        "time.sleep(1.0); print(sum('/dev/shm/fastrtps' in line for line in "
        "open(f'/proc/{os.getpid()}/maps')))"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split()[-1] == "0", f"shared memory mapped on {network}: {done.stdout}"


@pytest.mark.ros
def test_a_node_started_as_ros2_run_would_binds_only_the_loopback(nodes, monkeypatch):
    """No `afm` in between (the environment has only ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST,
    as scripts/env.sh sets): the node applies the localhost profile itself."""
    for name in exposure.PROFILE_VARIABLES:  # the test run's own (conftest's isolate_run)
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    driver = nodes("driver", seed=1)
    sockets = wait_for(lambda: udp_sockets(driver.process.pid), 20, what="the driver's sockets")
    time.sleep(1.0)  # all its transports are open by now
    sockets = udp_sockets(driver.process.pid)
    assert not outside_loopback(sockets), f"bound beyond the loopback: {sockets}"


def test_a_claimed_domain_is_not_claimed_again_until_its_holder_exits(tmp_path):
    import subprocess
    import sys

    # two ids no process uses (the holder's environment names none: it would count as a use)
    first, second = sorted(set(range(1, exposure.MAX_DOMAIN_ID + 1)) - exposure.domains_in_use())[
        :2
    ]
    environment = {k: v for k, v in os.environ.items() if k != "ROS_DOMAIN_ID"}
    # another process claims and holds one of them; this process gets the other
    code = (
        "import sys, time; from afm_ros import exposure; "
        f"print(exposure.claim_domain({first}, {second}, folder={str(tmp_path)!r}), flush=True); "
        "time.sleep(30)"
    )
    holder = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env=environment
    )
    try:
        held = int(holder.stdout.readline())
        mine = exposure.claim_domain(first, second, folder=tmp_path)
        assert {held, mine} == {first, second}
        with pytest.raises(RuntimeError, match="no free ROS domain id"):
            exposure.claim_domain(first, second, folder=tmp_path)
    finally:
        holder.kill()
        holder.wait()
    # the holder died (killed: no clean-up ran), so its id is free again
    assert exposure.claim_domain(held, held, folder=tmp_path) == held
    with pytest.raises(ValueError, match="must lie in"):
        exposure.claim_domain(0, 5, folder=tmp_path)


def test_a_domain_a_running_process_uses_is_skipped(tmp_path):
    import subprocess
    import sys

    free = exposure.claim_domain(folder=tmp_path)  # an id nobody uses (now held by us)
    user = subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(30)"],
        env={**os.environ, "ROS_DOMAIN_ID": str(free)},
    )
    try:
        wait_for(lambda: free in exposure.domains_in_use(), 10, what="the process listed")
        # a fresh lock folder: only the process's environment can keep the id from being chosen
        (tmp_path / "other").mkdir()
        with pytest.raises(RuntimeError):
            exposure.claim_domain(free, free, folder=tmp_path / "other")
    finally:
        user.kill()
        user.wait()
