"""A normal-work session (afm_core.sim2real.work_session) recorded ROS-free and read back."""

import pytest

from afm_core.sim.config import merge
from afm_core.sim2real.session_reader import read_operations
from afm_core.sim2real.work_session import record_work_session, work_config


def test_a_work_session_records_what_the_graph_does_and_reads_back(tmp_path):
    config = merge(work_config(), {"seed": 3})
    summary = record_work_session(tmp_path / "work.mcap", config, seed=1, pushes=1)

    assert summary.path.is_file() and summary.path.name == "work.mcap"
    with read_operations(summary.path) as stream:
        ops = list(stream)
    kinds = [op.kind for op in ops]
    # scan pair, local image, rescans (rasters); localization lines; pits (indents); strokes
    assert {"raster", "scan_line", "move", "push", "indent"} <= set(kinds)
    assert summary.operations == {k: kinds.count(k) for k in set(kinds)}
    # the 0/90 pair of the area first and last, each published with its pair id
    rasters = [op for op in ops if op.kind == "raster"]
    assert [r.data.scan_angle_deg for r in rasters[:2]] == [0.0, 90.0]
    assert [r.data.scan_angle_deg for r in rasters[-2:]] == [0.0, 90.0]
    assert summary.particles == len(config.sample.spheres)
    assert len(summary.pushes) == 1 and summary.pushes[0]["ran"]
    assert summary.seconds > 0


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [("pushes", -1, "pushes=-1"), ("push_distance", 0.0, "push_distance=0.0")],
)
def test_bad_arguments_are_refused_naming_the_field(tmp_path, field, value, words):
    with pytest.raises(ValueError, match=words):
        record_work_session(tmp_path / "w.mcap", work_config(), **{field: value})
    assert not (tmp_path / "w.mcap").exists()
