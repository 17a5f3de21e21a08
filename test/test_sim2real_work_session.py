"""A normal-work session (afm_core.sim2real.work_session) recorded ROS-free and read back."""

import pytest

from afm_core.sim.config import merge
from afm_core.sim2real.results import UNEXPLAINED_P
from afm_core.sim2real.session_reader import read_operations
from afm_core.sim2real.work_session import WORK_SPHERES, record_work_session, work_config


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
    [
        ("pushes", -1, "pushes=-1"),
        ("push_distance", 0.0, "push_distance=0.0"),
        ("strategy", "zigzag", "strategy='zigzag'"),
    ],
)
def test_bad_arguments_are_refused_naming_the_field(tmp_path, field, value, words):
    with pytest.raises(ValueError, match=words):
        record_work_session(tmp_path / "w.mcap", work_config(), **{field: value})
    assert not (tmp_path / "w.mcap").exists()


# -- the diagnosis on normal work -------------------------------------------------------------
# restricted libraries: the tests are about what ordinary sessions can and cannot inform; the
# terms are those a normal-work session acts on (heights, widths, positions) and the friction
# patch a null session was once named with from its pushed particles' torsion
WORK_EFFECTS = ["height_gain", "tip_radius", "coupling", "creep_amplitude", "friction"]


def _work_case(folder, seed, overrides=None, pushes=2):
    from afm_core.sim.config import dump_config

    folder.mkdir(parents=True, exist_ok=True)
    model = work_config()
    (folder / "model.yaml").write_text(dump_config(model))
    truth = merge(model, {"seed": seed, **(overrides or {})})
    record_work_session(folder / "session.mcap", truth, seed=seed, pushes=pushes)
    return folder


def test_a_null_work_session_names_nothing_and_lists_what_it_left_out(tmp_path):
    from afm_core.sim2real.diagnose import run_sim2real

    case = _work_case(tmp_path / "null", seed=1)
    diagnosis = run_sim2real(
        case / "session.mcap", case / "model.yaml", case / "report", effects=WORK_EFFECTS
    )

    assert diagnosis.chosen == [] and diagnosis.updated_config is None
    assert not (case / "report" / "updated_config.yaml").exists()
    # and the residual is the noise model's (with the pushed particles' features in, this
    # session's was not: chi^2 305 for 132, p 1e-15, "no candidate explains")
    assert diagnosis.overall["p"] >= UNEXPLAINED_P
    # the pushed particles' contact history is left out, each kind with its reason
    left_out = {row["what"]: row for row in diagnosis.excluded}
    assert left_out["push torsion"]["count"] > 0
    assert left_out["moved particles' features"]["count"] > 0
    assert all(row["reason"] for row in diagnosis.excluded)
    # with every stroke on a particle, nothing in the session informs the friction
    assert "friction" in {row["term"] for row in diagnosis.cannot_tell}
    report = (case / "report" / "report.md").read_text()
    assert "## What this session cannot inform" in report and "push torsion" in report


def test_a_z_gain_in_a_work_session_is_named_with_its_value(tmp_path):
    from afm_core.sim2real.diagnose import run_sim2real

    truth = 1.03
    case = _work_case(tmp_path / "gain", seed=11, overrides={"noise": {"height_gain": truth}})
    diagnosis = run_sim2real(
        case / "session.mcap", case / "model.yaml", case / "report", effects=WORK_EFFECTS
    )

    assert diagnosis.chosen and diagnosis.chosen[0] == "height_gain"
    fitted = diagnosis.parameters["noise.height_gain"]
    # within 10 % of the change, and the truth within 3 of its reported sigmas
    assert abs(fitted["value"] - truth) <= 0.1 * (truth - 1.0)
    assert abs(fitted["value"] - truth) <= 3 * fitted["sigma"]
    assert diagnosis.heldout["excess_reduction"] > 0.5


def test_a_session_of_one_small_image_is_too_little_and_the_protocol_is_suggested(tmp_path):
    from afm_core.instrument import ScanRequest
    from afm_core.sim.config import dump_config
    from afm_core.sim.instrument import SimulatedAfm
    from afm_core.sim2real.diagnose import run_sim2real
    from afm_core.sim2real.session_scope import TooLittleError
    from afm_core.sim2real.session_writer import RecordingInstrument

    model = work_config()
    (tmp_path / "model.yaml").write_text(dump_config(model))
    x, y = WORK_SPHERES[0]
    with RecordingInstrument(SimulatedAfm(model), tmp_path / "one.mcap") as rec:
        rec.raster_scan(ScanRequest(x - 0.5e-6, y - 0.5e-6, 1e-6, 1e-6, 64, 64, line_rate=4.0))

    with pytest.raises(TooLittleError, match="too little to diagnose") as caught:
        run_sim2real(tmp_path / "one.mcap", tmp_path / "model.yaml", tmp_path / "report")
    assert "diagnostic protocol" in str(caught.value)


def test_exclusions_leave_out_strokes_on_particles_and_what_they_moved_not_bare_slides():
    """The rule on hand-made commands: a stroke through a particle is left out, a slide 1 um
    from every particle is kept, and the particle's image features after the push are left out
    while another particle's are kept."""
    from afm_core.sim2real.exclusions import ordinary_exclusions
    from afm_core.sim2real.features import Feature
    from afm_core.sim2real.protocol import Operation

    config = work_config()
    (x0, y0), (x1, y1) = WORK_SPHERES[:2]

    def op(index, kind, start, end, t):
        return Operation(index=index, kind=kind, start_time=t, start=start, end=end)

    ops = [
        op(0, "push", (x0 - 0.3e-6, y0), (x0 + 0.2e-6, y0), 10.0),  # through particle 0
        op(1, "push", (x0, y0 - 1.0e-6), (x0 + 0.5e-6, y0 - 1.0e-6), 11.0),  # bare substrate
        op(2, "raster", (x0, y0), (x0, y0), 12.0),
    ]

    def feature(key, group, x, y, t):
        return Feature(key, group, 0.0, t, x, y)

    features = {
        f.key: f
        for f in [
            feature((0, "push.torsion0"), "push.torsion", x0, y0, 10.0),
            feature((1, "push.torsion0"), "push.torsion", x0, y0 - 1e-6, 11.0),
            feature((2, "raster.x0"), "raster.x", x0 + 0.32e-6, y0, 20.0),  # pushed along
            feature((2, "raster.x1"), "raster.x", x1, y1, 20.0),
        ]
    }
    excluded = ordinary_exclusions(ops, features, config)

    assert excluded.keys == {(0, "push.torsion0"), (2, "raster.x0")}
    assert excluded.strokes == 1
    assert {row["what"] for row in excluded.rows} == {
        "push torsion",
        "moved particles' features",
    }
