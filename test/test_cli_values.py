"""Values typed on the command line: negative quantities with units, and what must be above 0,
refused by argparse before anything is sent (no ROS needed)."""

import math

import pytest

from afm_bringup.cli import build_parser

PUSH = ["push", "--at", "55um", "55um", "--goal", "55um", "54.7um"]
SCAN = ["scan", "--origin", "54um", "54um", "--size", "2um", "2um"]


@pytest.mark.parametrize(
    "extra, expected",
    [
        (["--goal-angle", "-15deg"], -15 * math.pi / 180),
        (["--goal-angle", "-0.2"], -0.2),
        (["--goal-angle", "-.5rad"], -0.5),
        (["--goal-angle", "-1e-1rad"], -0.1),
    ],
)
def test_a_negative_quantity_with_a_unit_is_a_value_not_an_option(extra, expected):
    args = build_parser().parse_args(PUSH + extra)
    assert args.goal_angle == pytest.approx(expected)


def test_negative_lengths_where_they_mean_something_are_read(capsys):
    args = build_parser().parse_args(PUSH[:1] + ["--at", "-1nm", "2nm", "--goal", "0", "-2nm"])
    assert args.at == pytest.approx([-1e-9, 2e-9]) and args.goal == pytest.approx([0, -2e-9])
    # a sub-subcommand reads it as a value too, and its own check refuses it
    with pytest.raises(SystemExit):
        build_parser().parse_args(["image", "tip", "a.npz", "-o", "t.npy", "--threshold", "-1nm"])
    refusal = capsys.readouterr().err
    assert "--threshold='-1nm': must be >= 0" in refusal


def test_an_option_is_still_an_option():
    with pytest.raises(SystemExit):
        build_parser().parse_args(PUSH + ["--goal-angle", "--tolerance"])


@pytest.mark.parametrize(
    "argv, complaint",
    [
        (PUSH + ["--tolerance", "-5nm"], "--tolerance: tolerance='-5nm': must be above 0"),
        (PUSH + ["--tolerance", "0"], "tolerance='0': must be above 0"),
        (PUSH + ["--timeout", "0"], "timeout='0': must be above 0"),
        (PUSH + ["--timeout", "nan"], "timeout='nan': must be above 0"),
        (SCAN[:4] + ["--size", "-2um", "2um"], "size='-2um': must be above 0"),
        (SCAN + ["--pixels", "0", "256"], "pixels='0': must be above 0"),
        (SCAN + ["--pixels", "1.5", "2"], "pixels='1.5': expected int"),
        (SCAN + ["--line-rate", "-1"], "line-rate='-1': must be above 0"),
    ],
)
def test_what_must_be_above_zero_is_refused_by_name(argv, complaint, capsys):
    with pytest.raises(SystemExit) as stopped:
        build_parser().parse_args(argv)
    assert stopped.value.code == 2
    assert complaint in capsys.readouterr().err
