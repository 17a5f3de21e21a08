"""Vendor scans read through libraries: Asylum/Igor .ibw (igor2) and JPK .jpk (tifffile).
The formats' layout and conventions are described in imaging.vendor_files."""

from __future__ import annotations

import math
import re
import struct
from pathlib import Path

import numpy as np

from afm_core.imaging.vendor_common import (
    VendorImage,
    choose_channel,
    finite_height,
    length_scale,
    scan_turn,
)

# Asylum's note gives the scan size to a few digits; the wave's scaling is exact
_NOTE_REL_TOL = 1e-3


# -- Asylum .ibw (igor2) -----------------------------------------------------------------------


# Igor wave types (Technical Note 003): bytes per point; complex doubles the size
_IGOR_TYPE_BYTES = {0x02: 4, 0x04: 8, 0x08: 1, 0x10: 2, 0x20: 4, 0x48: 1, 0x50: 2, 0x60: 4}


def check_ibw_header(path: Path) -> None:
    """ValueError unless the file's version-5 headers fit the file: every section size
    non-negative and within it, the points within the wave section. igor2 builds its record
    formats from these counts and keeps them between files, so a damaged count made later,
    valid files take seconds to parse (found by test_fuzz_files); it must not see one."""
    data = path.read_bytes()
    if len(data) < 64 + 320:
        raise ValueError(f"{path}: not a readable Igor binary wave ({len(data)} bytes)")
    order = "<" if int.from_bytes(data[:2], "little") == 5 else ">"
    if int.from_bytes(data[:2], "little" if order == "<" else "big") != 5:
        raise ValueError(f"{path}: not a version-5 Igor binary wave (Asylum writes version 5)")
    sizes = struct.unpack(order + "iiii4i4iiii", data[4:64])
    if min(sizes) < 0 or 64 + sum(sizes) > len(data):
        raise ValueError(
            f"{path}: damaged Igor header (section sizes {list(sizes)} for {len(data)} bytes)"
        )
    npnts, wave_type = struct.unpack(order + "ih", data[64 + 12 : 64 + 18])
    dims = struct.unpack(order + "4i", data[64 + 68 : 64 + 84])
    width = _IGOR_TYPE_BYTES.get(wave_type & ~0x01, 0) * (2 if wave_type & 0x01 else 1)
    if width == 0 or npnts < 0 or min(dims) < 0 or 320 + npnts * width > sizes[0]:
        raise ValueError(
            f"{path}: damaged Igor wave header (type {wave_type}, {npnts} points, dims "
            f"{list(dims)}, wave section {sizes[0]} bytes)"
        )


def ibw_wave(path: Path) -> dict:
    check_ibw_header(path)
    try:
        from igor2 import binarywave
    except ImportError as exc:
        raise ImportError(
            "reading Igor/Asylum .ibw files needs the 'igor2' package: pip install igor2"
        ) from exc
    try:
        return binarywave.load(str(path))["wave"]
    except Exception as exc:  # truncated or damaged: struct, assertion, value errors
        # igor2's assertions carry the whole header as their text: one short line of it
        detail = " ".join(str(exc).split())[:160]
        raise ValueError(
            f"{path}: not a readable Igor binary wave ({type(exc).__name__}: {detail})"
        ) from exc


def _text(value) -> str:
    if isinstance(value, bytes):
        return value.split(b"\x00")[0].decode("latin-1")
    if isinstance(value, np.ndarray):
        return b"".join(value.astype("S1").ravel().tolist()).split(b"\x00")[0].decode("latin-1")
    return str(value)


def ibw_names(wave: dict, path: Path) -> list[str]:
    data = np.asarray(wave["wData"])
    if data.ndim == 2:
        return [_text(wave["wave_header"]["bname"]) or path.stem]
    if data.ndim != 3:
        raise ValueError(
            f"{path}: the wave has shape {data.shape}, not an image (x, y[, channel])"
        )
    labels = wave.get("labels") or []
    layer = [_text(x) for x in (labels[2] if len(labels) > 2 else [])][1:]  # [0]: the axis
    return [
        layer[k] if k < len(layer) and layer[k] else f"channel {k}" for k in range(data.shape[2])
    ]


def _ibw_units(wave: dict, header: dict) -> tuple[str, list[str]]:
    data_unit = _text(wave.get("data_units") or b"") or _text(header["dataUnits"])
    extended = wave.get("dimension_units") or b""
    extended = [_text(u) for u in extended] if isinstance(extended, list) else []
    dims = []
    for d in range(2):
        unit = extended[d] if d < len(extended) and extended[d] else ""
        dims.append(unit or _text(np.asarray(header["dimUnits"])[d]))
    return data_unit, dims


def _asylum_note(wave: dict) -> dict[str, str]:
    note = wave.get("note") or b""
    text = note.decode("latin-1") if isinstance(note, bytes) else str(note)
    pairs = {}
    for line in re.split(r"[\r\n]+", text):
        key, sep, value = line.partition(":")
        if sep:
            pairs[key.strip()] = value.strip()
    return pairs


def ibw_image(path: Path, channel, scan_frame: bool = False) -> VendorImage:
    wave = ibw_wave(path)
    names = ibw_names(wave, path)
    index = choose_channel(path, names, channel)
    where = f"{path} channel {names[index]!r}"
    header = wave["wave_header"]
    with np.errstate(invalid="ignore"):  # a signalling NaN: finite_height names the line
        data = np.asarray(wave["wData"], dtype=np.float64)
    layer = data if data.ndim == 2 else data[:, :, index]
    data_unit, dim_units = _ibw_units(wave, header)
    z_scale = length_scale(data_unit, f"{where} (data units)")
    lateral = [length_scale(u, f"{where} (dimension {d} units)") for d, u in enumerate(dim_units)]
    step = [float(header["sfA"][d]) * lateral[d] for d in range(2)]
    first = [float(header["sfB"][d]) * lateral[d] for d in range(2)]
    if not all(math.isfinite(s) and s != 0 for s in step):
        raise ValueError(f"{where}: point spacing (sfA) {step} must be finite and non-zero")
    height = layer.T * z_scale  # Igor's dimension 0 is x: rows become y
    if step[0] < 0:  # x decreasing with the index: mirror so columns run along +x
        height, step[0], first[0] = (
            height[:, ::-1],
            -step[0],
            first[0] + step[0] * (height.shape[1] - 1),
        )
    if step[1] < 0:
        height, step[1], first[1] = (
            height[::-1],
            -step[1],
            first[1] + step[1] * (height.shape[0] - 1),
        )
    note = _asylum_note(wave)
    meta = scan_turn(_note_number(note, "ScanAngle", where), path, "ScanAngle", scan_frame)
    for key, size, pixels in (
        ("FastScanSize", step[0], height.shape[1]),
        ("SlowScanSize", step[1], height.shape[0]),
    ):
        if key in note:
            try:
                stated = float(note[key])
            except ValueError:
                continue
            if not math.isclose(stated, size * pixels, rel_tol=_NOTE_REL_TOL):
                raise ValueError(
                    f"{where}: the note's {key}={stated!r} m disagrees with the wave's scaling "
                    f"({pixels} x {size!r} m = {size * pixels!r} m)"
                )
    # the wave's scaling is along the turned scan's own axes: no position in the scanner's
    corner = (0.0, 0.0) if meta else (first[0] - step[0] / 2, first[1] - step[1] / 2)
    return VendorImage(  # point positions are pixel centres
        finite_height(height, where), step[0], step[1], *corner, names[index], meta
    )


def _note_number(note: dict[str, str], key: str, where: str) -> float:
    """Asylum's note value `key` as a number, 0 when absent."""
    if key not in note:
        return 0.0
    try:
        value = float(note[key])
    except ValueError:
        raise ValueError(f"{where}: the note's {key}={note[key]!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"{where}: the note's {key}={note[key]!r} must be finite")
    return value


# -- JPK .jpk (tifffile) ----------------------------------------------------------------------

# JPK's private TIFF tags (JPKImageSpec 2.0, as AFMReader and Gwyddion read them)
_JPK_GRID = {
    "x0": 32832,
    "y0": 32833,
    "u": 32834,
    "v": 32835,
    "theta": 32836,
    "i": 32838,
    "j": 32839,
}
_JPK_REFLECT = 32837  # Grid-Reflect: a mirrored grid
_JPK_CHANNEL, _JPK_RETRACE, _JPK_SLOTS, _JPK_DEFAULT_SLOT = 32848, 32849, 32896, 32897
_JPK_SLOT_BASE, _JPK_SLOT_SIZE = 32912, 48  # slot k's tags start at base + size * k
_JPK_SLOT_UNIT, _JPK_SLOT_SCALING, _JPK_SLOT_MULTIPLIER, _JPK_SLOT_OFFSET = 18, 19, 20, 21


def jpk_open(path: Path):
    try:
        import tifffile
    except ImportError as exc:
        raise ImportError(
            "reading JPK .jpk files needs the 'tifffile' package: pip install tifffile"
        ) from exc
    try:
        return tifffile.TiffFile(path)
    except Exception as exc:  # not a TIFF, truncated
        raise ValueError(f"{path}: not a readable JPK TIFF ({type(exc).__name__}: {exc})") from exc


def _jpk_tag(page, code: int, path: Path, what: str):
    tag = page.tags.get(code)
    if tag is None:
        raise ValueError(f"{path}: the JPK file has no {what} (TIFF tag {code})")
    return tag.value


def jpk_names(tif, path: Path) -> list[str]:
    names = []
    for page in tif.pages[1:]:
        name = _jpk_tag(page, _JPK_CHANNEL, path, "channel name")
        retrace = page.tags.get(_JPK_RETRACE)
        names.append(f"{name}_{'retrace' if retrace is not None and retrace.value else 'trace'}")
    if not names:
        raise ValueError(f"{path}: the JPK file holds no channel page (only the thumbnail)")
    return names


def _jpk_scaling(page, path: Path, where: str) -> tuple[float, float, str]:
    """(multiplier, offset, unit) of the page's default calibration slot."""
    default = _jpk_tag(page, _JPK_DEFAULT_SLOT, path, "default calibration slot")
    slots = int(_jpk_tag(page, _JPK_SLOTS, path, "number of calibration slots"))
    for k in range(slots):
        base = _JPK_SLOT_BASE + _JPK_SLOT_SIZE * k
        name = page.tags.get(base)
        if name is None or name.value != default:
            continue
        kind = _jpk_tag(page, base + _JPK_SLOT_SCALING, path, f"slot {default!r} scaling")
        if kind != "LinearScaling":
            raise ValueError(f"{where}: calibration slot {default!r} is {kind}, not a length")
        return (
            float(
                _jpk_tag(page, base + _JPK_SLOT_MULTIPLIER, path, f"slot {default!r} multiplier")
            ),
            float(_jpk_tag(page, base + _JPK_SLOT_OFFSET, path, f"slot {default!r} offset")),
            str(_jpk_tag(page, base + _JPK_SLOT_UNIT, path, f"slot {default!r} unit")),
        )
    raise ValueError(f"{where}: the default calibration slot {default!r} is not among its slots")


def _jpk_check_grid_frame(theta: float, pages, path: Path, scan_frame: bool) -> dict:
    """ValueError unless the grid is the scanner's frame (Grid-Theta 0) or `scan_frame` asks
    for the grid's own (vendor_common.scan_turn; its meta returned), and not mirrored
    (Grid-Reflect).

    A turned grid is not put in the scanner frame, even by a multiple of 90 deg, because JPK's
    convention for it
    is documented nowhere we could check: Gwyddion's jpkscan.c, AFMReader, SurfaceTopography
    and tifffile all ignore Grid-Theta, so neither the sense of the turn nor which corner
    Grid-x0/-y0 names is known. A real NanoWizard file at theta = pi/2 (the tip's
    start-position in its tag 32791 lies at x0 - uLength + a half pixel, y0) fits both a
    counter-clockwise turn of a y-up grid about (x0, y0) (the tip then sat at the start of
    the last line) and a clockwise turn of a y-down grid (at the first line's), which turn the
    picture 180 deg apart and put the area on either side of y0. Gwyddion reads Grid-Reflect
    (a mirrored grid) from the channel page, where JPK does not write it (it is on page 0):
    that convention is unknown too."""
    meta = scan_turn(math.degrees(theta), path, "Grid-Theta", scan_frame)
    for page in pages:
        tag = page.tags.get(_JPK_REFLECT)
        value = None if tag is None else tag.value
        if value is None or (isinstance(value, (int, float, np.number)) and value == 0):
            continue
        raise ValueError(
            f"{path}: Grid-Reflect {value!r}: a mirrored scan grid is not read "
            "(which axis JPK mirrors is undocumented); scan without mirroring, or open it "
            "in Gwyddion and save it as .gwy"
        )
    return meta


def jpk_image(path: Path, channel, scan_frame: bool = False) -> VendorImage:
    with jpk_open(path) as tif:
        names = jpk_names(tif, path)
        index = choose_channel(path, names, channel)
        where = f"{path} channel {names[index]!r}"
        grid = {
            key: float(_jpk_tag(tif.pages[0], code, path, f"Grid-{key}"))
            for key, code in _JPK_GRID.items()
        }
        page = tif.pages[index + 1]
        meta = _jpk_check_grid_frame(grid["theta"], (tif.pages[0], page), path, scan_frame)
        try:
            raw = np.asarray(page.asarray(), dtype=np.float64)
        except Exception as exc:  # truncated strips
            raise ValueError(f"{where}: unreadable image data ({exc})") from exc
        multiplier, offset, unit = _jpk_scaling(page, path, where)
    columns, lines = int(grid["i"]), int(grid["j"])
    if raw.shape != (lines, columns):
        raise ValueError(
            f"{where}: image of {raw.shape[1]} x {raw.shape[0]} px, the grid says "
            f"{columns} x {lines} (Grid-iLength x Grid-jLength)"
        )
    if not (grid["u"] > 0 and grid["v"] > 0):
        raise ValueError(
            f"{path}: Grid-uLength, -vLength must be > 0 m, got {grid['u']}, {grid['v']}"
        )
    height = (raw * multiplier + offset) * length_scale(unit, f"{where} (slot unit)")
    # which corner Grid-x0/-y0 names in a turned grid is unknown: its own frame starts at 0
    corner = (0.0, 0.0) if meta else (grid["x0"], grid["y0"])
    return VendorImage(
        finite_height(height, where),
        grid["u"] / columns,
        grid["v"] / lines,
        *corner,
        names[index],
        meta,
    )
