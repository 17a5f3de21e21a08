"""Approaching an image from beyond its start, so every image is on the same hysteresis branch.

A piezo scanner's small-signal gain depends on its hysteresis state. Along the fast axis every
line reverses the motion, so the fast axis always sweeps a minor loop. The slow axis does not:
it steps one way through the image, and whether that continues the long move that brought the
tip there or reverses it decides its gain. On the default simulated scanner, measured on
noise-, drift- and creep-free images of spheres 0.8 um apart (issue 36):

- at the range centre both axes image at 1.060 true per commanded (every approach);
- 30-45 um from it, an image whose slow axis continued the approach's direction imaged that
  axis at 0.990, the other axis (and every axis after a reversal) at 1.059: a 7 % difference
  between the two images of one 0/90 deg pair, and between the map and the short moves and
  lines of a push planned on it (about 25 nm over a 400 nm push);
- approached from one image size beyond its first sample along both axes, every image imaged
  1.059-1.060 on both axes, at the centre and at all four places away from it.

The calibration's scanner matrix is measured at the centre, i.e. on the reversal branch; so
the driver approaches every image from beyond its start (`approach_point`). The cost is one
lifted move of about 1.4 image sizes before each image.
"""

from __future__ import annotations

from afm_core.instrument import ScannerLimits, ScanRequest
from afm_core.parameters import Parameter

RASTER_APPROACH_OVERSHOOT = Parameter(
    "raster_approach_overshoot",
    1.0,
    "Before an image the tip approaches its first sample from this many image sizes beyond it "
    "(along the fast axis and the slow scan direction), so both axes sweep a reversed "
    "hysteresis branch wherever the image is, as at the calibration; 0 approaches directly.",
    unit="image sizes",
    minimum=0.0,
    maximum=4.0,
)


def approach_point(
    request: ScanRequest, overshoot: float, limits: ScannerLimits = ScannerLimits()
) -> tuple[float, float]:
    """Where to come from before `request` (m, scanner frame): `overshoot` image sizes beyond
    its first sample along both axes, on the side the scan moves away from (the fast axis
    traces towards +; the slow axis moves up or down), inside the scanner's range. A point cut
    by the range edge still reverses the motion, over a shorter distance."""
    if not 0.0 <= overshoot <= RASTER_APPROACH_OVERSHOOT.maximum:
        raise ValueError(
            f"raster_approach_overshoot={overshoot}: must be within "
            f"[0, {RASTER_APPROACH_OVERSHOOT.maximum:g}] image sizes"
        )
    x, y = request.first_point()
    slow_sign = 1.0 if request.slow_scan_up else -1.0
    if request.scan_angle_deg == 0.0:  # fast x, slow y
        x += overshoot * request.size_x
        y += slow_sign * overshoot * request.size_y
    else:  # fast y, slow x
        y += overshoot * request.size_y
        x += slow_sign * overshoot * request.size_x
    return (
        min(max(x, 0.0), limits.range_x),
        min(max(y, 0.0), limits.range_y),
    )
