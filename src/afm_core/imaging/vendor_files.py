"""Instrument vendors' scan files, read into heights in metres with rows along +y (row 0 at the
bottom of the area, as `HeightMap`), for `files.load_height_map`.

- `.ibw` (Asylum Research / Igor Pro binary wave, version 5): through `igor2` (LGPL-3.0+,
  numpy only, the reader AFMReader and the Igor community use). The wave is (x, y, channel);
  a channel is a layer of dimension 2, named by its dimension label (HeightTrace, ...). Pixel
  size and position come from the wave's scaling (sfA, sfB: the position of point e is
  sfA * e + sfB, taken as the pixel centre), units from its dimension and data units (a
  length: m with an SI prefix); Asylum's note (FastScanSize, SlowScanSize) must agree with
  the scaling; its ScanAngle other than 0 only in the scan's own frame.
- `.jpk` (JPK / Bruker JPK): a TIFF read through `tifffile` (BSD-3, numpy only); page 0
  holds the grid (Grid-x0, -y0: the area's corner; Grid-uLength, -vLength: its size in m;
  Grid-iLength, -jLength: pixels; Grid-Theta: other than 0 only in the scan's
  own frame, and Grid-Reflect only 0: JPK's convention for a turned or mirrored grid is
  undocumented, see
  vendor_libraries._jpk_check_grid_frame), each further page one channel (name_trace /
  name_retrace) of raw integers; heights are raw * multiplier + offset of the page's
  default calibration slot, in that slot's unit (a length; the instrument chains its slots
  raw, volts, nominal, calibrated, each slot's multiplier already taken from raw). The first
  stored row is the bottom line, as AFMReader and Gwyddion read it.
- `.spm` (Bruker / Veeco NanoScope, version 5 and later; rename an old numbered file such as
  `scan.002` to `.spm`): a text header (`\\*Section` lines and `\\key: value` lines) up to
  `\\*File list end`, then per `*Ciao image list` a block of little-endian 2- or 4-byte
  integers at `Data offset`, `Number of lines` x `Samps/line`, the first stored row the bottom
  line (as pySPM, AFMReader and Gwyddion read it). The channel is `@2:Image Data`'s quoted
  name (" retrace" added for Line Direction Retrace). Heights are raw x (the `@2:Z scale`
  full-scale value / 2^(8 bytes per pixel)) x the sensitivity it names in brackets
  (`@Sens. Zscan: V 15.07 nm/V`), which must be a length per volt; the size is `Scan Size`
  (x y unit, "~m" = um). Rotate Ang. other than 0 only in the scan's own frame; origin 0
  (NanoScope gives none).
- `.sxm` (Nanonis): a text header of `:TAG:` blocks up to `:SCANIT_END:`, then 0x1A 0x04 and
  big-endian float32 blocks, one per channel and direction (forward, then backward when
  DATA_INFO says both), lines in the order scanned. SCAN_PIXELS (columns, lines),
  SCAN_RANGE (m), SCAN_OFFSET (the frame's centre, m), SCAN_DIR (up: the first line is the
  bottom one; down: the top one), SCAN_ANGLE (other than 0 only in the scan's own frame:
  a turned frame does not fit the map's axes). Backward lines were taken right to left and
  are mirrored back.
- `.stp` / `.top` (WSxM): a text header ("Image header size", `[Section]`s, `Key: value`
  lines) up to `[Header end]`, then little-endian values (General Info / Image Data Type:
  double, float, or integer/short = int16, the default). The file holds the picture turned
  by 180 degrees: the first stored row is the bottom line and its columns run right to left
  (Gwyddion's wsxmfile flips both axes on reading and writing; AFMReader takes the stored
  order as it is). int16 counts are scaled so their range is General Info / Z Amplitude
  (WSxM stores the range, not a scale); double and float values are heights in Z
  Amplitude's unit (as Gwyddion 2.66 reads them); without Z Amplitude they are nm. Lateral
  size from Control / X and Y Amplitude (in nm, or um written with the latin-1 micro
  sign 0xB5). Origin 0: Control / X and Y Offset are not used, as no documented convention
  (centre or corner, sign) says where they put the area, and Gwyddion ignores them too.
- `.asd` (high-speed AFM movies, Ando lab / RIBM, versions 0-2): through AFMReader, one
  frame at a time; vendor_asd describes the layout and what is checked.

The readers live in vendor_libraries (.ibw, .jpk), vendor_headers (.spm, .sxm, .stp/.top)
and vendor_asd (.asd),
their shared pieces in vendor_common. Each raises ValueError naming the file and the problem:
a truncated or damaged file, a missing header field, a channel that does not exist (the
message lists those that do), a unit that is not a length, a turned frame (.spm Rotate Ang.,
.sxm SCAN_ANGLE, .ibw the note's ScanAngle, .jpk Grid-Theta, WSxM Control / Angle other than 0;
unless `scan_frame`, which reads it in its own frame), a mirrored one (.jpk Grid-Reflect), NaN
lines of an interrupted scan.
"""

from __future__ import annotations

from pathlib import Path

from afm_core.imaging.vendor_asd import asd_channels, asd_frame_count, asd_header, asd_image
from afm_core.imaging.vendor_common import VendorImage, length_scale
from afm_core.imaging.vendor_headers import (
    spm_header,
    spm_image,
    spm_images,
    sxm_header,
    sxm_image,
    sxm_layout,
    wsxm_header,
    wsxm_image,
    wsxm_title,
)
from afm_core.imaging.vendor_libraries import (
    ibw_image,
    ibw_names,
    ibw_wave,
    jpk_image,
    jpk_names,
    jpk_open,
)

__all__ = [
    "VENDOR_SUFFIXES",
    "VendorImage",
    "length_scale",
    "read_vendor",
    "vendor_channels",
    "vendor_frames",
]

VENDOR_SUFFIXES = (".ibw", ".jpk", ".spm", ".sxm", ".stp", ".top", ".asd")


def read_vendor(
    path: Path, channel: int | str = 0, frame: int = 0, *, scan_frame: bool = False
) -> VendorImage:
    """The channel `channel` (index in `vendor_channels(path)` or its title) of a vendor file;
    `frame`: which frame of a movie (.asd; 0 first), 0 for the single-frame formats.
    `scan_frame`: a scan turned from the scanner's axes is read in its own frame (origin 0,
    the turn in meta["scan_frame_turned_deg"]) instead of refused (vendor_common.scan_turn)."""
    suffix = path.suffix.lower()
    if suffix == ".asd":  # records no turn
        return asd_image(path, channel, frame)
    if frame != 0:
        raise ValueError(f"{path}: frame={frame!r}: a {suffix} file holds one frame (0)")
    readers = {
        ".ibw": ibw_image,
        ".sxm": sxm_image,
        ".jpk": jpk_image,
        ".spm": spm_image,
        ".stp": wsxm_image,
        ".top": wsxm_image,
    }
    if suffix not in readers:
        raise ValueError(f"{path}: {path.suffix!r} is not a vendor format read here")
    return readers[suffix](path, channel, scan_frame)


def vendor_frames(path: Path) -> int:
    """How many frames the file holds (a high-speed .asd movie: its num_frames; others 1)."""
    return asd_frame_count(path) if path.suffix.lower() == ".asd" else 1


def vendor_channels(path: Path) -> list[str]:
    suffix = path.suffix.lower()
    if suffix == ".asd":
        return asd_channels(asd_header(path)[0])
    if suffix == ".ibw":
        return ibw_names(ibw_wave(path), path)
    if suffix == ".sxm":
        return [name for name, *_ in sxm_layout(sxm_header(path)[0], path)]
    if suffix == ".jpk":
        with jpk_open(path) as tif:
            return jpk_names(tif, path)
    if suffix == ".spm":
        return [name for name, _ in spm_images(spm_header(path)[0], path)]
    return [wsxm_title(wsxm_header(path)[0], path)]
