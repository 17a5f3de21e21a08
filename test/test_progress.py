"""Progress of long actions and one-line feedback texts (afm_bringup.progress), no ROS."""

import io
from types import SimpleNamespace

from afm_bringup.cli_calibrate import _experiment_progress
from afm_bringup.progress import Feedback, Progress, push_feedback_text, scan_feedback_text


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_in_a_log_a_line_per_tenth_and_the_end():
    log = io.StringIO()
    with Progress("scan", "lines", 256, log) as bar:
        assert not bar.interactive
        for k in range(1, 257):
            bar.update(k, 256)
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue()
    assert lines[0] == "scan: 1 of 256 lines" and lines[-1] == "scan: 256 of 256 lines"
    assert 10 <= len(lines) <= 12  # a tenth of 256 is 26 lines: 1, 27, ..., 235, 256


def test_a_bar_never_updated_says_nothing():
    log = io.StringIO()
    with Progress("push", "steps", stream=log):
        pass
    assert log.getvalue() == ""


def test_in_a_log_a_new_phase_gets_its_line():
    log = io.StringIO()
    with Progress("push", "steps", stream=log) as bar:
        bar.update(0, 12, "localizing")
        bar.update(0, 12, "scanning")
        bar.update(1, 12, "pushing")
        bar.update(2, 12, "pushing")  # a tenth of 12 is 2 steps: no line yet
        bar.update(3, 12, "pushing")
    assert log.getvalue().splitlines() == [
        "push: 0 of 12 steps (localizing)",
        "push: 0 of 12 steps (scanning)",
        "push: 1 of 12 steps (pushing)",
        "push: 3 of 12 steps (pushing)",
    ]


def test_on_a_terminal_a_bar_redrawn_in_place():
    tty = Terminal()
    with Progress("scan", "lines", 64, tty) as bar:
        assert bar.interactive
        for k in range(1, 65):
            bar.update(k, 64)
        bar.note("a line above the bar")
    text = tty.getvalue()
    assert "\r" in text and "64/64" in text and "a line above the bar\n" in text


def push_feedback():
    point = SimpleNamespace(x=55.0e-6, y=54.85e-6)
    tip = SimpleNamespace(
        header=SimpleNamespace(frame_id="afm_task"),
        pose=SimpleNamespace(pose=SimpleNamespace(position=point)),
    )
    return SimpleNamespace(
        step=3,
        steps_total=12,
        phase="pushing",
        particle_estimate=point,
        particle_covariance=[9e-18, 0.0, 0.0, 16e-18],  # sigma 3 and 4 nm
        tip_pose=tip,
        peak_lateral_force=1.234e-9,
        peak_normal_force=5e-9,
    )


def test_push_feedback_reads_as_one_line():
    text = push_feedback_text(push_feedback())
    assert text == (
        "push step 3 of 12 [pushing]: particle at (55000.0, 54850.0) nm +- 3.5 nm, tip at "
        "(55000.0, 54850.0) nm, peak force 1.23 nN lateral, 5.00 nN normal"
    )
    before = push_feedback()  # before the strokes are planned: no count, no forces, no tip
    before.steps_total, before.phase, before.tip_pose.header.frame_id = 0, "localizing", ""
    before.peak_lateral_force = before.peak_normal_force = 0.0
    assert push_feedback_text(before) == (
        "push [localizing]: particle at (55000.0, 54850.0) nm +- 3.5 nm"
    )
    wrapped = Feedback(push_feedback(), push_feedback_text)
    assert str(wrapped) == text and wrapped.step == 3 and wrapped.phase == "pushing"
    scan = Feedback(SimpleNamespace(lines_done=5, lines_total=256), scan_feedback_text)
    assert str(scan) == "scan: line 5 of 256" and scan.lines_total == 256


def test_calibrate_counts_the_experiments_the_core_reports():
    from afm_core.localization.calibration.procedure import _attempt

    tty = Terminal()
    with Progress("calibrate", "experiments", 2, tty) as bar:
        report = {"_chosen": ("drift", "creep")}
        _attempt(report, "drift", lambda: 1, lambda t: _experiment_progress(bar, t))
        assert bar.done == 1
        _attempt(report, "creep", lambda: 2, lambda t: _experiment_progress(bar, t))
        assert bar.done == 2
    assert "afm calibrate: experiment 2 of 2: creep done in" in tty.getvalue()


def test_a_finished_action_ends_at_its_total_and_late_feedback_is_ignored():
    """Feedback is best effort and travels apart from the result: a scan whose last lines'
    feedback was dropped (or comes after the result) still ends its log at the total."""
    log = io.StringIO()
    bar = Progress("scan", "lines", 100, log)
    for k in range(1, 91):
        bar.update(k, 100)
    bar.close(finished=True)
    bar.update(95, 100)  # the late feedback
    lines = log.getvalue().splitlines()
    assert lines[-1] == "scan: 100 of 100 lines", lines
    assert "scan: 95 of 100 lines" not in lines


def test_an_unfinished_action_ends_at_what_was_done():
    log = io.StringIO()
    bar = Progress("scan", "lines", 100, log)
    bar.update(37, 100)
    bar.close()  # failed or cancelled: the count stays where the work stopped
    assert log.getvalue().splitlines()[-1] == "scan: 37 of 100 lines"


def test_on_a_terminal_a_finished_bar_shows_the_total():
    screen = Terminal()
    bar = Progress("scan", "lines", 64, screen)
    bar.update(60, 64)
    bar.close(finished=True)
    assert "64/64" in screen.getvalue().split("\r")[-1]
