"""The push procedure as the core tests run it on the simulator: a Localizer started at the
commanded position (50 nm sigma) and a landmark map the pushes update in place."""

import numpy as np

from afm_core.localization import Localizer
from afm_core.manipulation import PushProcedure, localize_with

START_SIGMA = 50e-9  # m, the localizer's initial sigma per axis


def sim_procedure(sim, calibration, landmarks: dict, instrument=None, **options) -> PushProcedure:
    """PushProcedure on `sim` (or `instrument`, a wrapper of it) with `landmarks` ({id:
    Landmark}, kept current: a pushed particle is put where its rescan found it); `options`
    go to PushProcedure (map_time, settings, ...)."""
    localizer = Localizer(
        sim, calibration, np.array(sim.commanded_position()), np.diag([START_SIGMA**2] * 2)
    )
    return PushProcedure(
        sim if instrument is None else instrument,
        localize_with(localizer),
        lambda: landmarks,
        calibration=calibration,
        on_moved=lambda mark: landmarks.__setitem__(mark.id, mark),
        **options,
    )
