"""Progress of long actions (scan lines, push steps, calibration experiments, sim2real steps)
and one-line texts for action feedback, for the CLI and the Python API.

On a terminal a tqdm bar on stderr, redrawn in place. Into a log or a pipe (stderr not a
terminal) a bar's carriage returns would pile up as garbage, so there a plain line is written
when the count has moved by a tenth of the total, when the phase changes, and at the end.
"""

from __future__ import annotations

import math
import sys

from tqdm import tqdm

# In a log, one line per tenth of the work: about 10 lines for a 4096-line scan, not 4096.
LOG_FRACTION = 0.1


class Progress:
    """`update(done, total, status)` as the work goes; `note(text)` prints a line without
    breaking the bar; `close()` (or the `with` block's end) finishes it."""

    def __init__(self, what: str, unit: str = "", total: int | None = None, stream=None):
        self.what, self.unit, self.total = what, unit, total
        self.stream = stream if stream is not None else sys.stderr
        self.done, self.status, self.updated, self.closed = 0, "", False, False
        self._logged_done, self._logged_status = -1, None
        isatty = getattr(self.stream, "isatty", lambda: False)
        self._bar = (
            tqdm(
                total=total,
                desc=what,
                unit=f" {unit}" if unit else "it",
                file=self.stream,
                dynamic_ncols=True,
                leave=True,
            )
            if isatty()
            else None
        )

    @property
    def interactive(self) -> bool:
        """True while a bar is drawn in place (a terminal)."""
        return self._bar is not None

    def update(self, done: int, total: int | None = None, status: str = "") -> None:
        if self.closed:  # feedback travels apart from the result and may come after it
            return
        self.done, self.updated = int(done), True
        if total:
            self.total = int(total)
        self.status = status
        if self._bar is not None:
            if self.total and self._bar.total != self.total:
                self._bar.total = self.total
            self._bar.n = self.done
            self._bar.set_postfix_str(status, refresh=False)
            self._bar.refresh()
            return
        step = max(1, math.ceil(LOG_FRACTION * self.total)) if self.total else 1
        if (
            status != self._logged_status
            or self.done >= self._logged_done + step
            or (self.total and self.done >= self.total and self._logged_done < self.total)
        ):
            self._log()

    def note(self, text: str) -> None:
        if self._bar is not None:
            self._bar.write(text, file=self.stream)
        else:
            print(text, file=self.stream, flush=True)

    def _log(self) -> None:
        count = f"{self.done} of {self.total}" if self.total else f"{self.done}"
        unit = f" {self.unit}" if self.unit else ""
        status = f" ({self.status})" if self.status else ""
        print(f"{self.what}: {count}{unit}{status}", file=self.stream, flush=True)
        self._logged_done, self._logged_status = self.done, self.status

    def close(self, finished: bool = False) -> None:
        """finished: the work is known to be complete (the action succeeded), so the count
        ends at the total even when the last feedback was dropped or has not arrived yet
        (feedback is best effort and travels apart from the result)."""
        if self.closed:
            return
        self.closed = True
        if finished and self.total:
            self.done, self.updated = self.total, True
            if self._bar is not None:
                self._bar.n = self.total
                self._bar.refresh()
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif self.updated and self.done != self._logged_done:
            self._log()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# -- one-line texts for feedback messages (attributes only: no ROS import needed) ------------


def _nm(metres: float) -> str:
    return f"{metres * 1e9:.1f}"


def scan_feedback_text(feedback) -> str:
    return f"scan: line {feedback.lines_done} of {feedback.lines_total}"


def push_feedback_text(feedback) -> str:
    """PushParticle feedback in one line: step (once the strokes are planned), phase, the
    particle's estimate with its RMS 1-sigma, the tip's estimate (once there is one) and, while
    pushing, this step's peak forces."""
    est, cov = feedback.particle_estimate, list(feedback.particle_covariance)
    sigma = math.sqrt(max(0.0, 0.5 * (cov[0] + cov[3]))) if len(cov) == 4 else float("nan")
    step = f"step {feedback.step} of {feedback.steps_total} " if feedback.steps_total else ""
    text = (
        f"push {step}[{feedback.phase}]: particle at ({_nm(est.x)}, {_nm(est.y)}) nm "
        f"+- {_nm(sigma)} nm"
    )
    if feedback.tip_pose.header.frame_id:  # an empty pose: no estimate sent yet
        tip = feedback.tip_pose.pose.pose.position
        text += f", tip at ({_nm(tip.x)}, {_nm(tip.y)}) nm"
    if feedback.peak_lateral_force or feedback.peak_normal_force:
        text += (
            f", peak force {feedback.peak_lateral_force * 1e9:.2f} nN lateral, "
            f"{feedback.peak_normal_force * 1e9:.2f} nN normal"
        )
    return text


class Feedback:
    """An action's feedback message whose str() is one readable line (so `feedback=print`
    prints that, not the message's repr); every field reads as on the message."""

    def __init__(self, message, text):
        self._message, self._text = message, text

    @property
    def message(self):
        return self._message

    def __getattr__(self, name):
        if name.startswith("_"):  # not the message's (and no recursion before __init__ ran)
            raise AttributeError(name)
        return getattr(self._message, name)

    def __str__(self) -> str:
        return self._text(self._message)

    def __repr__(self) -> str:
        return f"Feedback({self._text(self._message)!r})"


FEEDBACK_TEXTS = {"scan_image": scan_feedback_text, "push_particle": push_feedback_text}
