"""Who can reach the graph: the DDS environment every process `afm` starts gets.

By default ("localhost") the graph is reachable from this machine only: each node's Fast DDS
participant uses a profile whose only transport is UDP on 127.0.0.1 (no shared memory), so
discovery and data never leave the loopback (measured: every UDP socket of a node is bound to
127.0.0.1, test_exposure). ROS_AUTOMATIC_DISCOVERY_RANGE is left unset there: with it set to
LOCALHOST, rmw_fastrtps (Jazzy) adds output sockets on every interface even with the profile.
A shell with `ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST` (scripts/env.sh) still talks to the
graph. "lab" opens the graph to the subnet (ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET, Fast DDS's
UDP on every interface); pair it with a domain id the lab has agreed on (`--domain-id`), and prefer
SROS2 (docker/README.md) on any network others share.

Both profiles leave out Fast DDS's shared-memory transport, so no publish waits on another
process's shared-memory lock with the GIL held, and every reliable writer asks for what its
readers missed every REPAIR_PERIOD_S instead of Fast DDS's 3 s, so a sample lost under load is
resent before a dead-man or a server's heartbeat gives up.

A node started on its own (`ros2 run`) applies the same default to itself (apply_node_default)
unless its environment asks for a wider range or names a profile.

What the user set wins: a ROS_DOMAIN_ID or FASTRTPS_DEFAULT_PROFILES_FILE already in the
environment is kept unless an option names another. The profile is for rmw_fastrtps (the
default middleware); another RMW ignores it, and then only the discovery range limits it.
"""

from __future__ import annotations

import fcntl
import os
import random
import tempfile
from collections.abc import MutableMapping
from pathlib import Path

NETWORKS = ("localhost", "lab")
# ROS 2's safe range on Linux: above 101 the participants' ports run into the ephemeral range
# (ROS 2 documentation, "The ROS_DOMAIN_ID")
MAX_DOMAIN_ID = 101
PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
PROFILE_NAME = "afm_dds_localhost.xml"
LAB_PROFILE_NAME = "afm_dds_lab.xml"
# s: how soon a reliable writer asks its readers what they miss. Fast DDS's default is 3 s, and
# a reliable reader holds every later sample back until a lost one is repaired, so one sample
# lost under load stalls its topic (or a service's replies) for up to 3 s: a teleop stream
# froze past the 0.5 s dead-man, and a server went silent for the 3 s its clients allow
# (action_client.SERVER_SILENCE_S). Measured in docs/interfaces.md ("Lost samples").
REPAIR_PERIOD_S = 0.1
# rmw_fastrtps's publication mode (bench_node_stalls compares both). Left synchronous: with
# asynchronous writes a burst of publishes (a test's four scans, an action's replies) returned
# before Fast DDS had sent them, and a KEEP_LAST history replaced samples not yet sent, so the
# imaging node never got a scan pair and a localizer's replies went missing (2026-11-28).
PUBLICATION_MODE = "RMW_FASTRTPS_PUBLICATION_MODE"
WRITER_TIMES = f"""    <data_writer profile_name="afm_writer" is_default_profile="true">
      <times>
        <heartbeatPeriod>
          <sec>0</sec>
          <nanosec>{round(REPAIR_PERIOD_S * 1e9)}</nanosec>
        </heartbeatPeriod>
      </times>
    </data_writer>
"""
# Fast DDS's shared-memory transport is left out: a write into another process's shared-memory
# port takes that port's interprocess mutex, and rclpy's publish holds the GIL through the
# write, so while another process held the mutex (itself stalled, or gone and leaving it to a
# timeout) the writer's whole process stood still for 0.1-0.35 s: driver, localizer and teleop
# node alike, with the teleop tip stopped by its own dead-man (measured with
# afm_ros.stall_watch; docs/interfaces.md). UDP on the loopback has no lock between processes,
# and images larger than the shared segment went by UDP already.
LOCALHOST_PROFILE = (
    """<?xml version="1.0" encoding="UTF-8" ?>
<!-- afm: DDS for one machine. UDP on 127.0.0.1 only, nothing else: no node binds or sends on
     another interface, and no shared memory (afm_ros.exposure). A lost sample is repaired
     within about REPAIR_PERIOD_S. -->
<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>afm_loopback_udp</transport_id>
        <type>UDPv4</type>
        <interfaceWhiteList>
          <address>127.0.0.1</address>
        </interfaceWhiteList>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="afm_localhost" is_default_profile="true">
      <rtps>
        <userTransports>
          <transport_id>afm_loopback_udp</transport_id>
        </userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
      </rtps>
    </participant>
"""
    + WRITER_TIMES
    + """  </profiles>
</dds>
"""
)
LAB_PROFILE = (
    """<?xml version="1.0" encoding="UTF-8" ?>
<!-- afm: DDS for a lab's subnet. UDP on every interface (Fast DDS's own UDP transport, without
     its shared memory); a lost sample is repaired within about REPAIR_PERIOD_S
     (afm_ros.exposure). -->
<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>afm_udp</transport_id>
        <type>UDPv4</type>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="afm_lab" is_default_profile="true">
      <rtps>
        <userTransports>
          <transport_id>afm_udp</transport_id>
        </userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
      </rtps>
    </participant>
"""
    + WRITER_TIMES
    + """  </profiles>
</dds>
"""
)


def check_domain_id(value) -> int:
    """A ROS domain id in [0, MAX_DOMAIN_ID]; ValueError naming the option and the limit."""
    try:
        domain = int(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"--domain-id={value!r}: must be a whole number") from exc
    if not 0 <= domain <= MAX_DOMAIN_ID or str(domain) != str(value).strip():
        raise ValueError(f"--domain-id={value!r}: must be a whole number in [0, {MAX_DOMAIN_ID}]")
    return domain


def private_folder() -> Path:
    """This user's folder for the profile under the temporary directory, readable by this user
    only, so no other user can swap the file before the nodes read it."""
    folder = Path(tempfile.gettempdir()) / f"afm-dds-{os.getuid()}"
    folder.mkdir(mode=0o700, exist_ok=True)
    info = folder.lstat()
    if folder.is_symlink() or info.st_uid != os.getuid() or info.st_mode & 0o077:
        raise ValueError(f"{folder}: not a private folder of this user; remove it")
    return folder


# the open lock files of the domain ids this process claimed: held until it exits (the kernel
# drops a flock with the process, however it dies)
_CLAIMED: list = []


def domains_in_use(proc: str | os.PathLike = "/proc") -> set[int]:
    """The ROS domain ids in the environments of the processes this user can read (a graph, a
    node left running, a test run that chose its id another way)."""
    used = set()
    for environ in Path(proc).glob("[0-9]*/environ"):
        try:
            entries = environ.read_bytes().split(b"\0")
        except OSError:  # gone, or another user's
            continue
        for entry in entries:
            if entry.startswith(b"ROS_DOMAIN_ID="):
                try:
                    used.add(int(entry[len(b"ROS_DOMAIN_ID=") :]))
                except ValueError:
                    pass
    return used


def claim_domain(first: int = 1, last: int = MAX_DOMAIN_ID, folder=None) -> int:
    """A ROS domain id in [first, last] that no other process on this machine uses, held (a
    lock file) until this process exits: for a run (tests, a benchmark) whose nodes must hear
    only each other. A random pick from a range collides: two runs of 91 ids share a domain
    one time in 91, and then each hears the other's nodes (measured: a teleop test on a domain
    another run's graph used was refused for that graph's running actions, another moved its
    tip the wrong way). Domain 0 (everyone's default) is never chosen; ids above 101 put DDS
    ports in the ephemeral range (MAX_DOMAIN_ID). RuntimeError when every id is taken."""
    if not 0 < first <= last <= MAX_DOMAIN_ID:
        raise ValueError(f"domain ids [{first}, {last}]: must lie in [1, {MAX_DOMAIN_ID}]")
    folder = Path(folder) if folder else private_folder()
    used = domains_in_use()
    ids = list(range(first, last + 1))
    start = random.Random(os.getpid()).randrange(len(ids))  # runs starting at once spread out
    for domain in ids[start:] + ids[:start]:
        if domain in used:
            continue
        handle = open(folder / f"domain-{domain}.lock", "a")  # noqa: SIM115 - held open
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # another run holds it
            handle.close()
            continue
        _CLAIMED.append(handle)
        return domain
    raise RuntimeError(f"no free ROS domain id in [{first}, {last}]: all used or claimed")


def isolate_run(environ=os.environ) -> int:
    """Give this run (tests, a benchmark) a domain of its own unless the caller chose one
    (claim_domain), and localhost-only discovery unless told otherwise; the domain id."""
    if "ROS_DOMAIN_ID" not in environ:
        environ["ROS_DOMAIN_ID"] = str(claim_domain())
    # the nodes' profile in this process too: its writers (a test's commands, a client's goals)
    # need the nodes' repair period
    apply_node_default(environ)
    if not any(is_ours(environ.get(name, "")) for name in PROFILE_VARIABLES):
        environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return int(environ["ROS_DOMAIN_ID"])


def localhost_profile(folder: str | os.PathLike | None = None) -> Path:
    """The localhost profile written into `folder` (default: private_folder())."""
    return _written(PROFILE_NAME, LOCALHOST_PROFILE, folder)


def lab_profile(folder: str | os.PathLike | None = None) -> Path:
    """The lab profile (the repair period only) written into `folder`."""
    return _written(LAB_PROFILE_NAME, LAB_PROFILE, folder)


def _written(name: str, text: str, folder) -> Path:
    folder = Path(folder) if folder else private_folder()
    path = folder / name
    if not path.is_file() or path.read_text() != text:
        # whole or not at all: nodes starting at once write it together while others read it
        fd, staged = tempfile.mkstemp(dir=folder, prefix=name, suffix=".tmp")
        with os.fdopen(fd, "w") as file:
            file.write(text)
        os.replace(staged, path)
    return path


def is_ours(path: str) -> bool:
    return Path(path).name in (PROFILE_NAME, LAB_PROFILE_NAME)


def apply_node_default(environment: MutableMapping[str, str]) -> MutableMapping[str, str]:
    """What a node started on its own (`ros2 run`, `python -m`) applies to its own environment
    before it joins ROS: the localhost profile when the environment asks for nothing wider
    (no profile, and a discovery range unset or LOCALHOST); a lab's SUBNET, OFF or own profile
    is kept, so a node can be opened up exactly as any ROS node is."""
    wider = environment.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST") != "LOCALHOST"
    if wider or any(environment.get(name) for name in PROFILE_VARIABLES):
        return environment
    return apply(environment)


def apply(
    environment: MutableMapping[str, str],
    *,
    domain_id: int | None = None,
    network: str = "localhost",
    folder: str | os.PathLike | None = None,
) -> MutableMapping[str, str]:
    """Set the DDS variables of `environment` (os.environ, or a child's copy) for `network`
    (module docstring); returns it."""
    if network not in NETWORKS:
        raise ValueError(f"--network={network!r}: must be one of {list(NETWORKS)}")
    if domain_id is not None:
        environment["ROS_DOMAIN_ID"] = str(check_domain_id(domain_id))
    own = [environment.get(name, "") for name in PROFILE_VARIABLES]
    user_profile = any(value and not is_ours(value) for value in own)
    if network == "lab":
        if not user_profile:
            for name in PROFILE_VARIABLES:
                environment[name] = str(lab_profile(folder))
        environment["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SUBNET"
        return environment
    if user_profile:  # the user's own Fast DDS profile: keep it, and localhost discovery
        environment.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        return environment
    profile = str(localhost_profile(folder))
    for name in PROFILE_VARIABLES:
        environment[name] = profile
    environment.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
    return environment
