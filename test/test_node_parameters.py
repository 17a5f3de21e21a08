"""Bad node parameters: each node refuses at start with exit status 2 and one message naming the
parameter and what is wrong (issue 30: 7 of 22 gave a traceback or were accepted)."""

import pytest
from conftest import wait_for

pytestmark = pytest.mark.ros

NOT_MCAP = "not a recording\n"
BROKEN_YAML = "scanner: {hysteresis_fraction: [unclosed\n"


def cases(folder):
    """(node, parameters, words the message must contain)."""
    (folder / "text.mcap").write_text(NOT_MCAP)
    (folder / "broken.yaml").write_text(BROKEN_YAML)
    missing = str(folder / "missing")
    return [
        ("driver", {"seed": "abc"}, "parameter seed: the value given is not a whole number"),
        ("driver", {"max_queued_goals": -1}, "max_queued_goals=-1: must be >= 0"),
        ("driver", {"max_queued_goals": 1000}, "max_queued_goals=1000: must be <= 64"),
        ("driver", {"real_time_factor": -2}, "real_time_factor=-2.0: must be >= 0"),
        (
            "driver",
            {"backend": "replay", "replay_input": f"{missing}.mcap"},
            "replay_input=",
        ),
        (
            "driver",
            {"backend": "replay", "replay_input": str(folder / "text.mcap")},
            "is not an MCAP recording",
        ),
        ("driver", {"sim_config": str(folder / "broken.yaml")}, "is not valid YAML"),
        ("driver", {"sim_config": f"{missing}.yaml"}, "does not exist"),
        (
            "recorder",
            {"output": str(folder / "out.mcap"), "discovery_period": -1},
            "discovery_period=-1.0: must be > 0",
        ),
        ("replay", {"input": f"{missing}.mcap"}, "does not exist"),
        ("replay", {"input": str(folder / "text.mcap")}, "is not an MCAP recording"),
        ("nano_hand", {"push_speed": 1.0}, "push_speed=1.0: must be <= 0.0001 m/s"),
        ("nano_hand", {"calibration_file": f"{missing}.yaml"}, "does not exist"),
        ("localizer", {"calibration_file": str(folder / "broken.yaml")}, "calibration"),
        ("sim2real", {"model": f"{missing}.yaml"}, "parameter model="),
        ("sim2real", {"model": str(folder / "broken.yaml")}, "is not valid YAML"),
        ("viewer", {"port": 70000}, "port=70000: must be <= 65535"),
        ("viewer", {"port": 0, "port_file": f"{missing}/port"}, "parameter port_file="),
    ]


def test_each_bad_parameter_stops_its_node_with_status_2_and_the_reason(nodes, tmp_path):
    table = cases(tmp_path)
    # started all at once: each waits on ROS start-up, not on the others
    started = [
        (node, overrides, words, nodes(node, **overrides)) for node, overrides, words in table
    ]
    problems = []
    for node, overrides, words, process in started:
        code, output = process.wait(90)
        lines = [line for line in output.splitlines() if line.strip()]
        if code != 2 or "Traceback" in output or not any(words in line for line in lines):
            problems.append(f"{node} {overrides}: exit {code}: {output[-400:]!r}")
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize(
    "contents, words",
    [(None, "Error opening YAML file"), ("x: [\n", "Sequences can only be values")],
)
def test_a_params_file_ros_cannot_read_stops_the_node_with_status_2(tmp_path, contents, words):
    import subprocess

    from afm_bringup.launcher import node_command

    params = tmp_path / "driver.yaml"
    if contents is not None:
        params.write_text(contents)
    run = subprocess.run(
        node_command("driver", str(params), {}), capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr
    assert "afm driver: ROS refused the command line: " in run.stderr and words in run.stderr


def test_a_bad_topic_name_stops_the_recorder_before_its_file_exists(nodes, tmp_path):
    output = tmp_path / "session.mcap"
    code, said = nodes("recorder", output=output, topics="['bad topic']").wait(60)
    assert code == 2 and "parameter topics: 'bad topic' is not a topic name" in said, said
    assert not list(tmp_path.iterdir())  # no .part left to block the name


def test_a_relative_topic_name_is_recorded_under_its_full_name(nodes, tmp_path):
    recorder = nodes("recorder", output=tmp_path / "session.mcap", topics="['afm/scan']")
    try:
        wait_for(lambda: "recording ['/afm/scan']" in recorder.output(), 60, what="the start")
    finally:
        recorder.stop()
