"""The before/after images of a push near the scanner's edge (push_steps.rescan_request): a
window that would leave the range is refused in the push's words, not the scan request's
("origin + size.x=..."), which named a field the user never gave."""

import numpy as np
import pytest

from afm_core.instrument import ScannerLimits
from afm_core.manipulation.push_steps import rescan_request

LIMITS = ScannerLimits()
MARGIN = 500e-9


@pytest.mark.parametrize(
    "particle, goal",
    [
        ((109.6e-6, 50e-6), (109.9e-6, 50e-6)),  # the goal's window passes x = range
        ((0.3e-6, 50e-6), (0.6e-6, 50e-6)),  # the particle's passes x = 0
        ((50e-6, 109.8e-6), (50.2e-6, 109.8e-6)),  # and in y
    ],
)
def test_a_window_past_the_edge_is_refused_in_the_pushs_words(particle, goal):
    with pytest.raises(ValueError) as refused:
        rescan_request(np.array(particle), np.array(goal), MARGIN, 20e-9, 2.0, LIMITS)
    text = str(refused.value)
    assert text.startswith("goal: the before/after images around the particle and the goal")
    assert "would leave the scanner range [0, 110] x [0, 110] um" in text
    assert "500 nm margin" in text


def test_a_window_inside_the_range_is_the_square_around_both():
    a, b = np.array([50e-6, 50e-6]), np.array([50.4e-6, 50.1e-6])
    request = rescan_request(a, b, MARGIN, 20e-9, 2.0, LIMITS)
    assert request.origin_x == pytest.approx(50e-6 - MARGIN)
    assert request.size_x == request.size_y == pytest.approx(0.4e-6 + 2 * MARGIN)
