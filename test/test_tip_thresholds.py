"""The automatic threshold's descent (tip_thresholds.runaway_threshold) on scripted ladders: how
each estimate moves with the threshold is set by hand, so the rule's decision is checked
alone, apart from any image."""

import numpy as np

from afm_core.imaging import tip_thresholds as tt

K = 5  # tip window, px
DIST = np.hypot(*np.mgrid[-2:3, -2:3])
RING = np.rint(DIST) == 1  # the apex's 8 neighbours
OUTER = DIST > 1.5


class ScriptedSweep:
    """ThresholdSweep's interface; the estimate at threshold th (sigma = 1) is:
    outer pixels follow the threshold one for one below 30 (th - 30); the apex ring stays at
    the flat start down to `first_refinement`, then drops at once by 20 and follows; below
    `runaway` every pixel drops ten times as fast as the threshold (noise running away)."""

    def __init__(self, first_refinement: float, runaway: float):
        self.first, self.runaway = first_refinement, runaway
        self.tips: dict = {}
        self.converged: dict = {}
        self.passes = 0

    def run(self, th: float, cap=None) -> np.ndarray:
        th = float(th)
        tip = np.zeros((K, K))
        tip[OUTER] = min(th - 30.0, 0.0)
        if th < self.first:
            tip[RING] = th - self.first - 20.0
        if th < self.runaway:
            tip[OUTER | RING] -= 10.0 * (self.runaway - th)
        self.tips[th] = tip
        self.converged[th] = True
        return tip


def resolves(tip, th) -> bool:
    return bool((tip[RING] < 0).all())


def test_a_jump_that_first_refines_the_apex_ring_is_not_taken_for_the_noise_runaway():
    """A jump below a rung whose apex ring is still the flat start refines the apex (noise cannot
    cut a needle into a plate); the choice is above the later runaway. Without the test the
    choice was the unresolved plate, which guard_estimate refuses (a 512 x 512 step grating at
    10 nm pixels was refused though a fixed threshold estimated it)."""
    plain, _ = tt.runaway_threshold(ScriptedSweep(9.0, 3.0), 1.0, 1e3, None)
    assert plain >= 9.0  # stopped at the first jump: its choice constrains no ring
    assert not resolves(ScriptedSweep(9.0, 3.0).run(plain), plain)
    chosen, rates = tt.runaway_threshold(ScriptedSweep(9.0, 3.0), 1.0, 1e3, None, resolves)
    assert 3.0 <= chosen < 9.0
    below = [t for t in rates if t < chosen]
    assert below and rates[max(below)] > tt.RUNAWAY  # the rung below the choice ran away
    assert resolves(ScriptedSweep(9.0, 3.0).run(chosen), chosen)


def test_a_runaway_below_a_resolved_apex_is_chosen_as_before():
    """With the ring already refined when the runaway comes, the test changes nothing."""
    sweep_a, sweep_b = ScriptedSweep(40.0, 3.0), ScriptedSweep(40.0, 3.0)
    plain, _ = tt.runaway_threshold(sweep_a, 1.0, 1e3, None)
    tested, _ = tt.runaway_threshold(sweep_b, 1.0, 1e3, None, resolves)
    assert plain == tested and 3.0 <= tested < 4.0
