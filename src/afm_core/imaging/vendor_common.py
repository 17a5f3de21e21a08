"""What the vendor-file readers share (imaging.vendor_files describes the formats): the
image record they return, length units, channel choice and the check for unscanned lines."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# SI prefixes of a length unit (Gwyddion's units and the vendors' headers); "A" is not
# Angstrom: it is the ampere of Nanonis channel tables
_SI_PREFIX = {
    "": 1.0,
    "Y": 1e24,
    "Z": 1e21,
    "E": 1e18,
    "P": 1e15,
    "T": 1e12,
    "G": 1e9,
    "M": 1e6,
    "k": 1e3,
    "h": 1e2,
    "da": 1e1,
    "d": 1e-1,
    "c": 1e-2,
    "m": 1e-3,
    "u": 1e-6,
    "\u00b5": 1e-6,
    "\u03bc": 1e-6,
    "n": 1e-9,
    "p": 1e-12,
    "f": 1e-15,
    "a": 1e-18,
    "z": 1e-21,
    "y": 1e-24,
}
_ANGSTROM = ("\u00c5", "\u212b", "angstrom", "Angstrom")


@dataclass
class VendorImage:
    height: np.ndarray  # m, rows along +y
    pixel_size_x: float  # m
    pixel_size_y: float  # m
    origin_x: float  # m, lower-left corner of the area
    origin_y: float
    title: str
    # how the scan was taken, for HeightMap.meta (SI numbers, strings)
    meta: dict = field(default_factory=dict)


# the option that reads a turned scan in its own frame, named in every refusal of one
SCAN_FRAME_HINT = (
    "read it in the scan's own frame (fast axis along x, origin 0, positions not the "
    "scanner's) with scan_frame=True (afm image --scan-frame), or scan it at 0 deg"
)


def scan_turn(angle_deg: float, path: Path, what: str, scan_frame: bool) -> dict:
    """The meta of a scan whose frame is turned by `angle_deg` from the scanner's axes.

    A turned frame's pixels are not at the scanner positions the map's axes stand for, so it
    is refused (ValueError naming `what`, the header field) unless `scan_frame`: then the map
    is the scan's own grid, which the imaging steps (tip, drift, landmarks, levelling) need
    and which Gwyddion and AFMReader show, with its turn in the meta and its origin at 0."""
    if angle_deg == 0.0:  # -0.0 too
        return {}
    if not scan_frame:
        raise ValueError(
            f"{path}: {what} {angle_deg:.6g} deg: the scan is turned from the scanner's axes, "
            f"so its map cannot be put in the scanner frame; {SCAN_FRAME_HINT}"
        )
    return {"scan_frame_turned_deg": float(angle_deg)}


def length_scale(unit: str, where: str, what: str = "unit") -> float:
    """Metres per `unit` (m with an SI prefix, or Angstrom); ValueError naming `where` and
    `what` the unit is."""
    text = unit.strip()
    if text in _ANGSTROM:
        return 1e-10
    if text.endswith("m") and text[:-1] in _SI_PREFIX:
        return _SI_PREFIX[text[:-1]]
    raise ValueError(f"{where}: {what} {text!r} is not a length; cannot convert it to metres")


def choose_channel(path: Path, names: list[str], channel) -> int:
    listing = ", ".join(f"{i}: {n!r}" for i, n in enumerate(names)) or "none"
    if isinstance(channel, str):
        if names.count(channel) > 1:  # the first of two "Height" may be the wrong one
            raise ValueError(
                f"{path}: {names.count(channel)} channels are titled {channel!r}; choose one by "
                f"index ({listing})"
            )
        if channel in names:
            return names.index(channel)
    elif isinstance(channel, (int, np.integer)) and not isinstance(channel, bool):
        if 0 <= channel < len(names):
            return int(channel)
    else:
        raise ValueError(f"channel={channel!r}: must be an index (int) or a title (str)")
    raise ValueError(f"{path}: channel {channel!r} does not exist; channels: {listing}")


def finite_height(height: np.ndarray, where: str) -> np.ndarray:
    bad_rows = int(np.count_nonzero(~np.isfinite(height).all(axis=1)))
    if bad_rows:
        raise ValueError(
            f"{where}: {bad_rows} line(s) hold NaN or infinite values (an interrupted scan?)"
        )
    return np.ascontiguousarray(height, dtype=np.float64)


def header_number(text, where: str, name: str) -> float:
    """A number from a vendor header's text; ValueError naming the file and the field when it
    is none (a header edited by hand, or written by another software version)."""
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {name} {text!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"{where}: {name} {text!r} is not a finite number")
    return value
