"""What a blind tip estimate says in numbers a microscopist can use (for reports and the
imaging node's log): how deep and how far out the image constrained the tip, how wide the
tip is at most there, and whether its apex radius is measured at all.

A blind estimate is an upper bound of the tip (Villarrubia): the true tip lies below it, so
at the constrained depth the true tip is at most as wide as the estimate. The estimate's top
is not resolved finer than its resolution band, threshold N_TH + 3 sigma of the image noise
(afm_core.imaging.tip_guard: the refinement leaves each pixel up to N_TH above its bound, and
the bound moves with the noise): within that band of the apex the estimate is a plateau
whatever the tip is. The apex radius is the paraboloid z = -r^2 / (2R) fitted (least
squares) to the estimate's top within APEX_FIT_PIXELS of the apex. If the estimate drops by d
at the fit ring and the band is U, the true drop there could lie anywhere in [d, d + U] from
the band alone, so R could lie anywhere in [R d / (d + U), R]: R is reported only when that
range is within a factor APEX_MAX_RANGE. And features blunter than the tip (spheres larger
than its apex) never image its apex: the estimate then follows the features' images, and
even a resolved R is only an upper bound of the tip's. Below SINGLE_EXCURSION sigma of the
noise (a threshold chosen by hand) single noise excursions refine the tip: the estimate is
then sharper than the tip, no upper bound, and neither the width bound nor R is claimed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from afm_core.imaging.tip_guard import NOISE_K
from afm_core.imaging.tip_refinement import estimate_noise
from afm_core.imaging.tip_thresholds import SINGLE_EXCURSION

# pixels from the apex the paraboloid is fitted over (the imaging node's TipShape.apex_radius)
APEX_FIT_PIXELS = 3
# the apex radius counts as measured when the resolution band allows it to be at most this
# factor smaller than the fit (U <= (APEX_MAX_RANGE - 1) d): beyond it the band, not the tip,
# sets the curvature
APEX_MAX_RANGE = 2.0


def apex_radius(tip: np.ndarray, pixel: float, depth_pixels: int = APEX_FIT_PIXELS) -> float:
    """Radius (m) of the paraboloid z = -r^2 / (2R) that fits the tip's top (least squares)
    within `depth_pixels` of the apex; inf for a flat top."""
    c = tip.shape[0] // 2
    k = min(depth_pixels, c)
    window = tip[c - k : c + k + 1, c - k : c + k + 1]
    offsets = np.arange(-k, k + 1) * pixel
    r2 = np.add.outer(offsets**2, offsets**2)
    mask = r2 > 0
    z = -window[mask]
    if not np.any(z > 0):
        return float("inf")
    return float(np.sum(r2[mask] ** 2) / (2.0 * np.sum(r2[mask] * z)))


@dataclass
class TipReading:
    """What an estimate supports, in m (`sentence` in nm for people)."""

    resolution: float  # threshold + 3 sigma: the estimate's top is flat within this
    threshold: float
    noise: float
    radius: float  # constrained all round within this distance of the apex
    depth: float  # ... down to this far below the apex
    max_width: float  # the tip is at most this wide at `depth` (2 x radius)
    fit_radius: float  # the paraboloid fit's R over APEX_FIT_PIXELS (inf: flat)
    fit_ring: float  # m from the apex where the fit's drop is read
    drop: float  # the estimate's mean drop at that ring
    apex_measured: bool
    apex_low: float  # the smallest apex radius the band allows (nan when not measured)
    whole_window: bool  # the constrained radius is the window's: a larger one may show more
    below_noise: bool  # threshold < SINGLE_EXCURSION sigma: not an upper bound (module notes)

    def sentence(self) -> str:
        """What the estimate is good for, in one paragraph (nm)."""
        if self.below_noise:
            return (
                f"nothing measured: the threshold {self.threshold * 1e9:.2f} nm is below "
                f"{SINGLE_EXCURSION:.0f} x the noise ({self.noise * 1e9:.2f} nm), so noise "
                "sharpens the estimate beyond the tip; neither its width nor its apex radius "
                "is bounded (use the automatic threshold)"
            )
        text = (
            f"constrained to {self.depth * 1e9:.1f} nm below the apex, within "
            f"{self.radius * 1e9:.0f} nm of it{' (the whole window)' if self.whole_window else ''}"
            f": there the tip is at most {self.max_width * 1e9:.0f} nm wide"
        )
        if self.apex_measured:
            return text + (
                f"; apex radius {self.apex_low * 1e9:.0f} to {self.fit_radius * 1e9:.0f} nm "
                "(an upper bound if the features were blunter than the tip)"
            )
        return text + (
            f"; apex radius not measurable from these images: the estimate drops only "
            f"{self.drop * 1e9:.1f} nm within {self.fit_ring * 1e9:.0f} nm of the apex, "
            f"against its resolution {self.resolution * 1e9:.1f} nm (threshold "
            f"{self.threshold * 1e9:.1f} nm + 3 x {self.noise * 1e9:.2f} nm noise); it needs "
            "features sharper than the tip"
        )


def read_tip(estimate, pixel: float, image: np.ndarray | None = None) -> TipReading:
    """The reading of a guarded TipEstimate (afm_core.imaging.tip_estimation: `.constraint`
    filled) at `pixel` m. The noise is the estimate's own (the automatic thresholds), else
    that of `image` (the estimate's, as the guard measures it)."""
    c = estimate.constraint
    noise = estimate.noise
    if noise is None and image is not None:
        noise = estimate_noise(np.asarray(image, float))
    if c is None or noise is None:
        raise ValueError(
            "tip estimate: no constraint, or no noise and no image (run it through estimate_tip)"
        )
    tip = np.asarray(estimate.tip, float)
    h = tip.shape[0] // 2
    k = min(APEX_FIT_PIXELS, h)
    a, b = np.mgrid[-h : h + 1, -h : h + 1]
    ring = np.rint(np.hypot(a, b)) == k
    drop = float(-tip[ring].mean()) if k > 0 else 0.0
    band = float(estimate.threshold) + NOISE_K * float(noise)
    fit = apex_radius(tip, pixel, k)
    below_noise = float(estimate.threshold) < SINGLE_EXCURSION * float(noise)
    measured = bool(
        not below_noise and np.isfinite(fit) and drop > 0 and band <= (APEX_MAX_RANGE - 1) * drop
    )
    return TipReading(
        resolution=band,
        threshold=float(estimate.threshold),
        noise=float(noise),
        radius=c.radius * pixel,
        depth=float(c.depth),
        max_width=2 * c.radius * pixel,
        fit_radius=fit,
        fit_ring=k * pixel,
        drop=drop,
        apex_measured=measured,
        apex_low=fit * drop / (drop + band) if measured else float("nan"),
        whole_window=c.radius == h,
        below_noise=below_noise,
    )


def width_at(tip: np.ndarray, pixel: float, depth: float) -> float:
    """Width (m) of a tip grid at `depth` below its apex: twice the largest distance from the
    apex of a pixel at or above -depth, along x and y (the wider)."""
    tip = np.asarray(tip, float)
    h = tip.shape[0] // 2
    widths = []
    for section in (tip[h, :], tip[:, h]):
        above = np.nonzero(section >= -depth)[0]
        widths.append((above.max() - above.min()) * pixel)
    return float(max(widths))
