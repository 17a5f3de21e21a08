"""Instrument vendors' scan files, read into heights in metres with rows along +y (row 0 at the
bottom of the area, as `HeightMap`), for `files.load_height_map`.

- `.ibw` (Asylum Research / Igor Pro binary wave, version 5): through `igor2` (LGPL-3.0+,
  numpy only, the reader AFMReader and the Igor community use). The wave is (x, y, channel);
  a channel is a layer of dimension 2, named by its dimension label (HeightTrace, ...). Pixel
  size and position come from the wave's scaling (sfA, sfB: the position of point e is
  sfA * e + sfB, taken as the pixel centre), units from its dimension and data units (a
  length: m with an SI prefix); Asylum's note (FastScanSize, SlowScanSize) must agree with
  the scaling.
- `.jpk` (JPK / Bruker JPK): a TIFF read through `tifffile` (BSD-3, numpy only); page 0
  holds the grid (Grid-x0, -y0: the area's corner; Grid-uLength, -vLength: its size in m;
  Grid-iLength, -jLength: pixels; Grid-Theta: only 0 is read), each further page one
  channel (name_trace / name_retrace) of raw integers; heights are raw * multiplier +
  offset of the page's default calibration slot, in that slot's unit (a length). The first
  stored row is the bottom line, as AFMReader and Gwyddion read it.
- `.sxm` (Nanonis): a text header of `:TAG:` blocks up to `:SCANIT_END:`, then 0x1A 0x04 and
  big-endian float32 blocks, one per channel and direction (forward, then backward when
  DATA_INFO says both), lines in the order scanned. SCAN_PIXELS (columns, lines),
  SCAN_RANGE (m), SCAN_OFFSET (the frame's centre, m), SCAN_DIR (up: the first line is the
  bottom one; down: the top one), SCAN_ANGLE (only 0 is read: a rotated frame does not fit
  the map's axes). Backward lines were taken right to left and are mirrored back.
- `.stp` / `.top` (WSxM): a text header ("Image header size", `[Section]`s, `Key: value`
  lines) up to `[Header end]`, then little-endian values (General Info / Image Data Type:
  double, float, or integer/short = int16, the default). The file holds the picture turned
  by 180 degrees from its display with x mirrored back, so the first stored row is the
  bottom line and columns run right to left (as Gwyddion reads and writes it). Heights are
  scaled so their range is General Info / Z Amplitude (WSxM stores the range, not a scale;
  without it the values are nm), lateral size from Control / X and Y Amplitude; WSxM gives
  no position: origin 0.

Each reader raises ValueError naming the file and the problem: a truncated or damaged file,
a missing header field, a channel that does not exist (the message lists those that do), a
unit that is not a length, a rotated frame, NaN lines of an interrupted scan.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

VENDOR_SUFFIXES = (".ibw", ".jpk", ".sxm", ".stp", ".top")
_PREFIX = {
    "": 1.0,
    "k": 1e3,
    "m": 1e-3,
    "u": 1e-6,
    "\u00b5": 1e-6,
    "\u03bc": 1e-6,
    "n": 1e-9,
    "p": 1e-12,
    "f": 1e-15,
}
_ANGSTROM = ("\u00c5", "\u212b", "angstrom")  # not "A": ampere in Nanonis tables
# Asylum's note gives the scan size to a few digits; the wave's scaling is exact
_NOTE_REL_TOL = 1e-3


@dataclass
class VendorImage:
    height: np.ndarray  # m, rows along +y
    pixel_size_x: float  # m
    pixel_size_y: float  # m
    origin_x: float  # m, lower-left corner of the area
    origin_y: float
    title: str


def read_vendor(path: Path, channel: int | str = 0) -> VendorImage:
    """The channel `channel` (index in `vendor_channels(path)` or its title) of a vendor file."""
    suffix = path.suffix.lower()
    if suffix == ".ibw":
        return _ibw(path, channel)
    if suffix == ".sxm":
        return _sxm(path, channel)
    if suffix == ".jpk":
        return _jpk(path, channel)
    if suffix in (".stp", ".top"):
        return _wsxm(path, channel)
    raise ValueError(f"{path}: {path.suffix!r} is not a vendor format read here")


def vendor_channels(path: Path) -> list[str]:
    suffix = path.suffix.lower()
    if suffix == ".ibw":
        return _ibw_names(_ibw_wave(path), path)
    if suffix == ".sxm":
        return [name for name, *_ in _sxm_layout(_sxm_header(path)[0], path)]
    if suffix == ".jpk":
        with _jpk_open(path) as tif:
            return _jpk_names(tif, path)
    return [_wsxm_title(_wsxm_header(path)[0], path)]


def length_scale(unit: str, where: str) -> float:
    """Metres per `unit` (m with an SI prefix, or Angstrom); ValueError naming `where`."""
    text = unit.strip()
    if text in _ANGSTROM:
        return 1e-10
    if text.endswith("m") and text[:-1] in _PREFIX:
        return _PREFIX[text[:-1]]
    raise ValueError(f"{where}: unit {unit!r} is not a length; cannot convert it to metres")


def _choose(path: Path, names: list[str], channel) -> int:
    listing = ", ".join(f"{i}: {n!r}" for i, n in enumerate(names)) or "none"
    if isinstance(channel, str):
        if channel in names:
            return names.index(channel)
    elif isinstance(channel, (int, np.integer)) and not isinstance(channel, bool):
        if 0 <= channel < len(names):
            return int(channel)
    else:
        raise ValueError(f"channel={channel!r}: must be an index (int) or a title (str)")
    raise ValueError(f"{path}: channel {channel!r} does not exist; channels: {listing}")


def _finite(height: np.ndarray, where: str) -> np.ndarray:
    bad_rows = int(np.count_nonzero(~np.isfinite(height).all(axis=1)))
    if bad_rows:
        raise ValueError(
            f"{where}: {bad_rows} line(s) hold NaN or infinite values (an interrupted scan?)"
        )
    return np.ascontiguousarray(height, dtype=np.float64)


# -- Asylum .ibw (igor2) -----------------------------------------------------------------------


def _ibw_wave(path: Path) -> dict:
    try:
        from igor2 import binarywave
    except ImportError as exc:
        raise ImportError(
            "reading Igor/Asylum .ibw files needs the 'igor2' package: pip install igor2"
        ) from exc
    try:
        return binarywave.load(str(path))["wave"]
    except Exception as exc:  # truncated or damaged: struct, assertion, value errors
        raise ValueError(
            f"{path}: not a readable Igor binary wave ({type(exc).__name__}: {exc})"
        ) from exc


def _text(value) -> str:
    if isinstance(value, bytes):
        return value.split(b"\x00")[0].decode("latin-1")
    if isinstance(value, np.ndarray):
        return b"".join(value.astype("S1").ravel().tolist()).split(b"\x00")[0].decode("latin-1")
    return str(value)


def _ibw_names(wave: dict, path: Path) -> list[str]:
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


def _ibw(path: Path, channel) -> VendorImage:
    wave = _ibw_wave(path)
    names = _ibw_names(wave, path)
    index = _choose(path, names, channel)
    where = f"{path} channel {names[index]!r}"
    header = wave["wave_header"]
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
    return VendorImage(
        _finite(height, where),
        step[0],
        step[1],
        first[0] - step[0] / 2,  # point positions are pixel centres
        first[1] - step[1] / 2,
        names[index],
    )


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
_JPK_CHANNEL, _JPK_RETRACE, _JPK_SLOTS, _JPK_DEFAULT_SLOT = 32848, 32849, 32896, 32897
_JPK_SLOT_BASE, _JPK_SLOT_SIZE = 32912, 48  # slot k's tags start at base + size * k
_JPK_SLOT_UNIT, _JPK_SLOT_SCALING, _JPK_SLOT_MULTIPLIER, _JPK_SLOT_OFFSET = 18, 19, 20, 21


def _jpk_open(path: Path):
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


def _jpk_names(tif, path: Path) -> list[str]:
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


def _jpk(path: Path, channel) -> VendorImage:
    with _jpk_open(path) as tif:
        names = _jpk_names(tif, path)
        index = _choose(path, names, channel)
        where = f"{path} channel {names[index]!r}"
        grid = {
            key: float(_jpk_tag(tif.pages[0], code, path, f"Grid-{key}"))
            for key, code in _JPK_GRID.items()
        }
        if grid["theta"] != 0.0:
            raise ValueError(
                f"{path}: Grid-Theta {math.degrees(grid['theta']):.4g} deg: a rotated scan grid "
                "is not read (the map's axes are the scanner's); export it unrotated"
            )
        page = tif.pages[index + 1]
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
    return VendorImage(
        _finite(height, where),
        grid["u"] / columns,
        grid["v"] / lines,
        grid["x0"],
        grid["y0"],
        names[index],
    )


# -- Nanonis .sxm ---------------------------------------------------------------------------------


def _sxm_header(path: Path) -> tuple[dict[str, list[str]], bytes, int]:
    data = path.read_bytes()
    end = data.find(b":SCANIT_END:")
    if end < 0:
        raise ValueError(f"{path}: not a Nanonis .sxm file (no :SCANIT_END: tag)")
    start = data.find(b"\x1a\x04", end)
    if start < 0:
        raise ValueError(f"{path}: truncated .sxm file (no 0x1A 0x04 mark before the data)")
    tags: dict[str, list[str]] = {}
    current = None
    for line in data[:end].decode("latin-1").splitlines():
        match = re.fullmatch(r":(.+):", line.strip())
        if match:
            current = match.group(1)
            tags[current] = []
        elif current is not None:
            tags[current].append(line)
    return tags, data, start + 2


def _sxm_field(tags: dict, name: str, path: Path, count: int, kind=float) -> list:
    if name not in tags:
        raise ValueError(f"{path}: the .sxm header has no :{name}: field")
    words = " ".join(tags[name]).split()
    try:
        values = [kind(w) for w in words[:count]]
    except ValueError:
        values = []
    if len(values) != count:
        raise ValueError(f"{path}: :{name}: must hold {count} number(s), got {words!r}")
    return values


def _sxm_layout(tags: dict, path: Path) -> list[tuple[str, str, bool]]:
    """(channel title, unit, backward?) for each data block, in file order."""
    rows = [r.strip().split("\t") for r in tags.get("DATA_INFO", []) if r.strip()]
    if len(rows) < 2:
        raise ValueError(f"{path}: the .sxm header has no :DATA_INFO: channel table")
    columns = [c.strip() for c in rows[0]]
    try:
        name_at, unit_at, dir_at = (columns.index(c) for c in ("Name", "Unit", "Direction"))
    except ValueError:
        raise ValueError(
            f"{path}: :DATA_INFO: lacks a Name, Unit or Direction column (has {columns})"
        ) from None
    blocks = []
    for row in rows[1:]:
        if len(row) <= max(name_at, unit_at, dir_at):
            raise ValueError(f"{path}: :DATA_INFO: row {row} is short of columns {columns}")
        name, unit, direction = row[name_at].strip(), row[unit_at].strip(), row[dir_at].strip()
        if direction not in ("both", "forward", "backward"):
            raise ValueError(f"{path}: channel {name!r}: direction {direction!r} is unknown")
        if direction in ("both", "forward"):
            blocks.append((name, unit, False))
        if direction in ("both", "backward"):
            blocks.append((f"{name} backward", unit, True))
    return blocks


def _sxm(path: Path, channel) -> VendorImage:
    tags, data, start = _sxm_header(path)
    blocks = _sxm_layout(tags, path)
    index = _choose(path, [b[0] for b in blocks], channel)
    title, unit, backward = blocks[index]
    where = f"{path} channel {title!r}"
    columns, lines = _sxm_field(tags, "SCAN_PIXELS", path, 2, int)
    size_x, size_y = _sxm_field(tags, "SCAN_RANGE", path, 2)
    centre_x, centre_y = _sxm_field(tags, "SCAN_OFFSET", path, 2)
    angle = _sxm_field(tags, "SCAN_ANGLE", path, 1)[0] if "SCAN_ANGLE" in tags else 0.0
    direction = " ".join(tags.get("SCAN_DIR", [])).strip()
    if columns < 1 or lines < 1 or not (size_x > 0 and size_y > 0):
        raise ValueError(f"{path}: SCAN_PIXELS {columns} x {lines} / SCAN_RANGE must be > 0")
    if angle != 0.0:
        raise ValueError(
            f"{path}: SCAN_ANGLE {angle} deg: a rotated frame is not read (the map's axes are "
            "the scanner's); rotate it to 0 deg in the vendor software first"
        )
    if direction not in ("up", "down"):
        raise ValueError(f"{path}: SCAN_DIR {direction!r}: expected up or down")
    z_scale = length_scale(unit, where)
    block = columns * lines
    needed = start + 4 * block * len(blocks)
    if len(data) < needed:
        raise ValueError(
            f"{path}: truncated: {len(data) - start} data bytes, the header announces "
            f"{4 * block * len(blocks)} ({len(blocks)} blocks of {columns} x {lines} float32)"
        )
    raw = np.frombuffer(data, dtype=">f4", count=block, offset=start + 4 * block * index)
    height = raw.reshape(lines, columns).astype(np.float64) * z_scale
    if direction == "down":  # the first line scanned is the top one
        height = height[::-1]
    if backward:  # backward lines run right to left
        height = height[:, ::-1]
    return VendorImage(
        _finite(height, where),
        size_x / columns,
        size_y / lines,
        centre_x - size_x / 2,
        centre_y - size_y / 2,
        title,
    )


# -- WSxM .stp / .top -----------------------------------------------------------------------------

_WSXM_TYPES = {"double": "<f8", "float": "<f4", "integer": "<i2", "short": "<i2"}


def _wsxm_header(path: Path) -> tuple[dict[str, str], bytes, int]:
    data = path.read_bytes()
    if b"Image header size:" not in data[:200]:
        raise ValueError(f"{path}: not a WSxM image file (no 'Image header size' line)")
    end = data.find(b"[Header end]")
    if end < 0:
        raise ValueError(f"{path}: WSxM header without its '[Header end]' line (truncated?)")
    # some programs miscount 'Image header size': the data start after the end line
    start = end + len(b"[Header end]")
    start += 2 if data[start : start + 2] == b"\r\n" else int(data[start : start + 1] == b"\n")
    fields, section = {}, ""
    for line in data[:end].decode("latin-1").splitlines():
        line = line.strip()
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
        elif ":" in line:
            key, _, value = line.partition(":")
            fields[f"{section}::{key.strip()}"] = value.strip()
    return fields, data, start


def _wsxm_title(fields: dict, path: Path) -> str:
    return fields.get("General Info::Acquisition channel") or path.stem


def _wsxm_quantity(fields: dict, key: str, path: Path) -> tuple[float, str]:
    text = fields.get(key)
    if text is None:
        raise ValueError(f"{path}: the WSxM header has no {key.replace('::', ' / ')!r}")
    match = re.fullmatch(r"([-+0-9.eE]+)\s*(\S*)", text)
    if not match:
        raise ValueError(f"{path}: {key.replace('::', ' / ')} {text!r}: expected 'number unit'")
    return float(match.group(1)), match.group(2)


def _wsxm(path: Path, channel) -> VendorImage:
    fields, data, start = _wsxm_header(path)
    title = _wsxm_title(fields, path)
    _choose(path, [title], channel)
    where = f"{path} channel {title!r}"
    try:
        columns = int(fields["General Info::Number of columns"])
        rows = int(fields["General Info::Number of rows"])
    except (KeyError, ValueError):
        raise ValueError(
            f"{path}: General Info / Number of columns and Number of rows must be integers"
        ) from None
    angle = _wsxm_quantity(fields, "Control::Angle", path)[0] if "Control::Angle" in fields else 0
    if angle != 0.0:
        raise ValueError(
            f"{path}: Control / Angle {angle} deg: a rotated frame is not read (the map's axes "
            "are the scanner's)"
        )
    kind = fields.get("General Info::Image Data Type", "integer")
    if kind not in _WSXM_TYPES:
        raise ValueError(f"{path}: Image Data Type {kind!r}: expected one of {list(_WSXM_TYPES)}")
    dtype = np.dtype(_WSXM_TYPES[kind])
    if columns < 1 or rows < 1 or len(data) - start < columns * rows * dtype.itemsize:
        raise ValueError(
            f"{path}: truncated: {len(data) - start} data bytes for {columns} x {rows} "
            f"{kind} values ({columns * rows * dtype.itemsize} bytes)"
        )
    raw = np.frombuffer(data, dtype=dtype, count=rows * columns, offset=start)
    values = raw.reshape(rows, columns)[:, ::-1].astype(np.float64)  # columns right to left
    x_size, x_unit = _wsxm_quantity(fields, "Control::X Amplitude", path)
    y_size, y_unit = (
        _wsxm_quantity(fields, "Control::Y Amplitude", path)
        if "Control::Y Amplitude" in fields
        else (x_size, x_unit)
    )
    x_size *= length_scale(x_unit, f"{where} (X Amplitude)")
    y_size *= length_scale(y_unit, f"{where} (Y Amplitude)")
    if not (x_size > 0 and y_size > 0):
        raise ValueError(f"{path}: X / Y Amplitude must be > 0, got {x_size}, {y_size} m")
    values = _finite(values, where)
    if "General Info::Z Amplitude" in fields:
        z_range, z_unit = _wsxm_quantity(fields, "General Info::Z Amplitude", path)
        spread = float(values.max() - values.min())
        scale = z_range * length_scale(z_unit, f"{where} (Z Amplitude)") / spread if spread else 0
    else:
        scale = 1e-9
    return VendorImage(values * scale, x_size / columns, y_size / rows, 0.0, 0.0, title)
