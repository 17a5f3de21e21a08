"""A term that only moves the tip (a scanner term) leaves what is compared at the recorded
geometry as it is: heights and profiles, and the substrate's absolute levels
(features_absolute.py); sizes in commanded coordinates (widths) scale with the scanner's local
gain and move with it. On a closed-loop work session with a feed-forward loop-width error, a
re-simulation put two scan lines' edges on a particle's flank (levels 18 and 63 sigma off) where
the recording's lines had none, and the images' half-widths (17 nm off, the largest part of the
excess) were held at the model's: the held-out check of the true value got worse, and the term
was not named."""

from types import SimpleNamespace

import numpy as np
import pytest

from afm_core.sim2real.candidates import library
from afm_core.sim2real.design_columns import _feature_change
from afm_core.sim2real.features_absolute import LEVEL_GROUPS
from afm_core.sim2real.protocol import session_config
from afm_core.sim2real.reference import AT_GEOMETRY_GROUPS

GROUPS = np.array(
    ["raster.x", "line.mid", "line.level", "raster.level", "raster.half_width", "raster.height"]
)


def _sess(jump):
    """A fake session whose re-simulation moves the positions by 5 nm and puts one scan line's
    edge on a particle's flank (its level `jump` m off)."""
    nom = np.array([55e-6, 54e-6, 0.0, 0.0, 120e-9, 200e-9])

    def features(config, imaging=True):
        return nom + np.array([5e-9, 5e-9, jump, 0.0, -15e-9, 0.5e-9])

    return (
        SimpleNamespace(
            features=features,
            noisy=np.zeros(len(GROUPS), bool),
            push=np.zeros(len(GROUPS), bool),
            at_geometry=np.isin(GROUPS, AT_GEOMETRY_GROUPS),
        ),
        nom,
    )


def test_levels_and_heights_are_compared_at_the_recorded_geometry_widths_not():
    assert set(LEVEL_GROUPS) <= set(AT_GEOMETRY_GROUPS)
    assert {"raster.height", "line.peak", "line.width"} <= set(AT_GEOMETRY_GROUPS)
    assert "raster.half_width" not in AT_GEOMETRY_GROUPS
    assert not {"raster.x", "raster.y", "line.mid"} & set(AT_GEOMETRY_GROUPS)


def test_a_scanner_term_moves_positions_and_no_level():
    lib = {c.name: c for c in library()}
    scanner = lib["hysteresis_residual"]
    assert scanner.geometric
    sess, nom = _sess(jump=-19e-9)
    col, lost = _feature_change(sess, scanner, session_config(), nom, np.array([0.3]))
    assert np.allclose(col[:2], 5e-9)  # the positions move with the tip
    assert col[4] == pytest.approx(-15e-9)  # a width in commanded coordinates: the local gain
    # levels and heights at the recorded geometry
    assert col[2] == 0.0 and col[3] == 0.0 and col[5] == 0.0 and not lost.any()
    # a term that is not geometric (the tip's radius) does change what it images
    tip = lib["tip_radius"]
    assert not tip.geometric
    col, _ = _feature_change(sess, tip, session_config(), nom, np.array([30e-9]))
    assert col[2] == pytest.approx(-19e-9) and col[5] == pytest.approx(0.5e-9)
