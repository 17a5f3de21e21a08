"""A simulated AFM: raster scans of a sample with a finite tip, noise and real line timing."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from afm_core.sim.imaging import dilate
from afm_core.sim.sample import Sample, Sphere
from afm_core.sim.tip import paraboloid_cone_tip

SCANNER_RANGE_XY = 110e-6   # m, Veeco Dimension 3100 (book 7.1)
MAX_PIXELS = 4096


@dataclass
class ScanRequest:
    origin_x: float
    origin_y: float
    size_x: float
    size_y: float
    pixels_x: int
    pixels_y: int
    scan_angle_deg: float = 0.0
    slow_scan_up: bool = True
    line_rate: float = 1.0          # Hz
    mode: str = "tapping"

    def validate(self, scanner_range: float = SCANNER_RANGE_XY) -> None:
        """Raise ValueError naming the first field out of its limits."""
        values = {k: getattr(self, k) for k in ("origin_x", "origin_y", "size_x", "size_y", "line_rate")}
        for name, value in values.items():
            if not np.isfinite(value):
                raise ValueError(f"{name}={value}: must be finite")
        for name in ("size_x", "size_y", "line_rate"):
            if not values[name] > 0:
                raise ValueError(f"{name}={values[name]}: must be > 0")
        for name in ("pixels_x", "pixels_y"):
            value = getattr(self, name)
            if not 2 <= value <= MAX_PIXELS:
                raise ValueError(f"{name}={value}: must be within [2, {MAX_PIXELS}]")
        if self.scan_angle_deg not in (0.0, 90.0):
            raise ValueError(f"scan_angle_deg={self.scan_angle_deg}: must be 0 or 90")
        if self.mode not in ("tapping", "contact"):
            raise ValueError(f"mode={self.mode!r}: must be 'tapping' or 'contact'")
        for axis in ("x", "y"):
            lo = getattr(self, f"origin_{axis}")
            hi = lo + getattr(self, f"size_{axis}")
            if lo < 0 or hi > scanner_range:
                raise ValueError(f"origin_{axis}/size_{axis}: area [{lo:.3e}, {hi:.3e}] m leaves the "
                                 f"scanner range [0, {scanner_range:.3e}] m")


@dataclass
class RasterScanData:
    height: np.ndarray              # (pixels_y, pixels_x), m, scanner-frame orientation
    pixel_size_x: float
    pixel_size_y: float
    origin_x: float
    origin_y: float
    scan_angle_deg: float
    slow_scan_up: bool
    line_period: float
    line_start_times: np.ndarray    # s since start_time, per line index
    start_time: float               # s, instrument clock
    mode: str


@dataclass
class SimConfig:
    tip_apex_radius: float = 20e-9
    tip_half_angle_deg: float = 20.0
    noise_sigma: float = 0.3e-9                 # m, white height noise
    seed: int = 0
    spheres: list[tuple[float, float, float]] = field(default_factory=lambda: [
        (5.0e-6, 5.0e-6, 100e-9), (5.6e-6, 5.3e-6, 100e-9), (4.6e-6, 5.7e-6, 100e-9)])


class SimulatedAfm:
    """The instrument: keeps its own clock (s) advanced by every acquisition."""

    def __init__(self, config: SimConfig | None = None):
        self.config = config or SimConfig()
        self.rng = np.random.default_rng(self.config.seed)
        self.sample = Sample([Sphere(i, x, y, r) for i, (x, y, r) in enumerate(self.config.spheres)])
        self.time = 0.0

    def raster_scan(self, request: ScanRequest) -> RasterScanData:
        request.validate()
        px = request.size_x / request.pixels_x
        py = request.size_y / request.pixels_y
        xs = request.origin_x + (np.arange(request.pixels_x) + 0.5) * px
        ys = request.origin_y + (np.arange(request.pixels_y) + 0.5) * py
        pixel = min(px, py)
        tip = paraboloid_cone_tip(self.config.tip_apex_radius, self.config.tip_half_angle_deg,
                                  pixel, depth=max(4 * max((s.radius for s in self.sample.spheres), default=1e-7), 8 * pixel))
        # Dilate on a grid of the finer pixel size so the tip is sampled isotropically.
        fine_x = request.origin_x + (np.arange(int(np.ceil(request.size_x / pixel))) + 0.5) * pixel
        fine_y = request.origin_y + (np.arange(int(np.ceil(request.size_y / pixel))) + 0.5) * pixel
        surface = self.sample.height(*np.meshgrid(fine_x, fine_y))
        image_fine = dilate(surface, tip)
        iy = np.clip(np.round((ys - fine_y[0]) / pixel).astype(int), 0, len(fine_y) - 1)
        ix = np.clip(np.round((xs - fine_x[0]) / pixel).astype(int), 0, len(fine_x) - 1)
        image = image_fine[np.ix_(iy, ix)]
        image = image + self.rng.normal(0.0, self.config.noise_sigma, image.shape)

        lines = request.pixels_y if request.scan_angle_deg == 0 else request.pixels_x
        line_period = 1.0 / request.line_rate
        order = np.arange(lines) if request.slow_scan_up else np.arange(lines)[::-1]
        line_start = np.empty(lines)
        line_start[order] = np.arange(lines) * line_period   # trace + retrace fill one period
        start = self.time
        self.time += line_period * lines
        return RasterScanData(height=image.astype(np.float32), pixel_size_x=px, pixel_size_y=py,
                              origin_x=request.origin_x, origin_y=request.origin_y,
                              scan_angle_deg=request.scan_angle_deg, slow_scan_up=request.slow_scan_up,
                              line_period=line_period, line_start_times=line_start, start_time=start,
                              mode=request.mode)
