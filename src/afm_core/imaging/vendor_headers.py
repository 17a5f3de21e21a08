"""Vendor scans whose text headers we read ourselves: Bruker NanoScope .spm, Nanonis .sxm and
WSxM .stp/.top. The formats' layout and conventions are described in imaging.vendor_files."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from afm_core.imaging.vendor_common import (
    VendorImage,
    choose_channel,
    finite_height,
    header_number,
    length_scale,
    scan_turn,
)

# -- Bruker NanoScope .spm ---------------------------------------------------------------------

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
# "V [Sens. Zscan] (0.006713765 V/LSB) 439.9866 V": the sensitivity's name, the full scale
_SPM_Z_SCALE = re.compile(rf"^\S+\s+\[([^\]]+)\]\s+\(({_NUMBER})\s+[^)]*\)\s+({_NUMBER})\s*\S*$")


def spm_header(path: Path) -> tuple[list[tuple[str, dict]], bytes]:
    data = path.read_bytes()
    if not data.lstrip(b"?").startswith(b"\\*File list"):
        raise ValueError(f"{path}: not a Bruker NanoScope file (no '\\*File list' header)")
    end = data.find(b"\\*File list end")
    if end < 0:
        raise ValueError(f"{path}: NanoScope header without '\\*File list end' (truncated?)")
    sections: list[tuple[str, dict]] = []
    for raw in data[:end].decode("latin-1").splitlines():
        line = raw.strip().lstrip("\\")
        if line.startswith("*"):
            sections.append((line[1:].strip(), {}))
        elif ": " in line and sections:
            key, _, value = line.partition(": ")
            sections[-1][1].setdefault(key.strip(), value.strip())
    return sections, data


def spm_images(sections, path: Path) -> list[tuple[str, dict]]:
    images = []
    for name, fields in sections:
        if name != "Ciao image list":
            continue
        match = re.search(r'"([^"]*)"', fields.get("@2:Image Data", ""))
        if match is None:
            raise ValueError(f"{path}: an image has no '@2:Image Data' channel name")
        retrace = fields.get("Line Direction", "").lower() == "retrace"
        images.append((match.group(1) + (" retrace" if retrace else ""), fields))
    if not images:
        raise ValueError(f"{path}: the NanoScope header lists no image ('*Ciao image list')")
    return images


def _spm_int(fields: dict, key: str, where: str) -> int:
    try:
        return int(fields[key].split()[0])
    except (KeyError, ValueError, IndexError):
        raise ValueError(f"{where}: '{key}' must be an integer, got {fields.get(key)!r}") from None


def _spm_scale(sections, fields: dict, bpp: int, where: str) -> float:
    """Metres per raw count."""
    text = fields.get("@2:Z scale", "")
    match = _SPM_Z_SCALE.match(text)
    if match is None:
        raise ValueError(
            f"{where}: '@2:Z scale' {text!r} names no sensitivity; the channel is not a height"
        )
    key = "@" + match.group(1)
    full_scale = header_number(match.group(3), where, "@2:Z scale")
    sens = next((f[key] for _, f in sections if key in f), None)
    parts = (sens or "").split()
    if len(parts) < 3 or not parts[2].endswith("/V"):
        raise ValueError(
            f"{where}: sensitivity {key!r} = {sens!r}: expected 'V <number> <unit>/V'"
        )
    per_volt = header_number(parts[1], where, key)
    per_volt *= length_scale(parts[2][:-2], f"{where} ({key})")
    return full_scale / 2.0 ** (8 * bpp) * per_volt


def spm_image(path: Path, channel, scan_frame: bool = False) -> VendorImage:
    sections, data = spm_header(path)
    images = spm_images(sections, path)
    index = choose_channel(path, [name for name, _ in images], channel)
    title, fields = images[index]
    where = f"{path} channel {title!r}"
    meta = {}
    for _, section in sections:
        angle = section.get("Rotate Ang.", "0").split()
        if angle:
            turn = header_number(angle[0], str(path), "Rotate Ang.")
            meta.update(scan_turn(turn, path, "Rotate Ang.", scan_frame))
    columns = _spm_int(fields, "Samps/line", where)
    lines = _spm_int(fields, "Number of lines", where)
    offset = _spm_int(fields, "Data offset", where)
    length = _spm_int(fields, "Data length", where)
    bpp = (
        _spm_int(fields, "Bytes/pixel", where)
        if "Bytes/pixel" in fields
        else length // max(columns * lines, 1)
    )
    if offset < 0:
        raise ValueError(f"{where}: 'Data offset' {offset}: must be >= 0 (bytes)")
    if bpp not in (2, 4) or columns < 1 or lines < 1:
        raise ValueError(f"{where}: {columns} x {lines} px of {bpp} bytes: expected 2 or 4 bytes")
    if len(data) < offset + columns * lines * bpp:
        raise ValueError(
            f"{path}: truncated: the image needs bytes {offset}.."
            f"{offset + columns * lines * bpp}, the file has {len(data)}"
        )
    size = fields.get("Scan Size", fields.get("Scan size", "")).split()
    if len(size) != 3:
        raise ValueError(f"{where}: 'Scan Size' {' '.join(size)!r}: expected 'x y unit'")
    unit = size[2].replace("~", "u")  # NanoScope writes the micro sign as '~'
    scale = length_scale(unit, f"{where} (Scan Size)")
    size_x = header_number(size[0], where, "Scan Size x") * scale
    size_y = header_number(size[1], where, "Scan Size y") * scale
    raw = np.frombuffer(data, dtype=f"<i{bpp}", count=columns * lines, offset=offset)
    height = raw.reshape(lines, columns) * _spm_scale(sections, fields, bpp, where)
    return VendorImage(
        finite_height(height, where), size_x / columns, size_y / lines, 0.0, 0.0, title, meta
    )


# -- Nanonis .sxm ---------------------------------------------------------------------------------


def sxm_header(path: Path) -> tuple[dict[str, list[str]], bytes, int]:
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


def sxm_layout(tags: dict, path: Path) -> list[tuple[str, str, bool]]:
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


def sxm_image(path: Path, channel, scan_frame: bool = False) -> VendorImage:
    tags, data, start = sxm_header(path)
    blocks = sxm_layout(tags, path)
    index = choose_channel(path, [b[0] for b in blocks], channel)
    title, unit, backward = blocks[index]
    where = f"{path} channel {title!r}"
    columns, lines = _sxm_field(tags, "SCAN_PIXELS", path, 2, int)
    size_x, size_y = _sxm_field(tags, "SCAN_RANGE", path, 2)
    centre_x, centre_y = _sxm_field(tags, "SCAN_OFFSET", path, 2)
    angle = _sxm_field(tags, "SCAN_ANGLE", path, 1)[0] if "SCAN_ANGLE" in tags else 0.0
    direction = " ".join(tags.get("SCAN_DIR", [])).strip()
    if columns < 1 or lines < 1 or not (size_x > 0 and size_y > 0):
        raise ValueError(f"{path}: SCAN_PIXELS {columns} x {lines} / SCAN_RANGE must be > 0")
    meta = scan_turn(angle, path, "SCAN_ANGLE", scan_frame)
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
    with np.errstate(invalid="ignore"):  # a signalling NaN: finite_height names the line
        height = raw.reshape(lines, columns).astype(np.float64) * z_scale
    if direction == "down":  # the first line scanned is the top one
        height = height[::-1]
    if backward:  # backward lines run right to left
        height = height[:, ::-1]
    # SCAN_OFFSET is the turned frame's centre in the scanner's: no corner of the own frame
    corner = (0.0, 0.0) if meta else (centre_x - size_x / 2, centre_y - size_y / 2)
    return VendorImage(
        finite_height(height, where), size_x / columns, size_y / lines, *corner, title, meta
    )


# -- WSxM .stp / .top -----------------------------------------------------------------------------

_WSXM_TYPES = {"double": "<f8", "float": "<f4", "integer": "<i2", "short": "<i2"}


def wsxm_header(path: Path) -> tuple[dict[str, str], bytes, int]:
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


def wsxm_title(fields: dict, path: Path) -> str:
    return fields.get("General Info::Acquisition channel") or path.stem


def _wsxm_quantity(fields: dict, key: str, path: Path) -> tuple[float, str]:
    text = fields.get(key)
    if text is None:
        raise ValueError(f"{path}: the WSxM header has no {key.replace('::', ' / ')!r}")
    match = re.fullmatch(r"([-+0-9.eE]+)\s*(\S*)", text)
    if not match:
        raise ValueError(f"{path}: {key.replace('::', ' / ')} {text!r}: expected 'number unit'")
    return header_number(match.group(1), str(path), key.replace("::", " / ")), match.group(2)


def wsxm_image(path: Path, channel, scan_frame: bool = False) -> VendorImage:
    fields, data, start = wsxm_header(path)
    title = wsxm_title(fields, path)
    choose_channel(path, [title], channel)
    where = f"{path} channel {title!r}"
    try:
        columns = int(fields["General Info::Number of columns"])
        rows = int(fields["General Info::Number of rows"])
    except (KeyError, ValueError):
        raise ValueError(
            f"{path}: General Info / Number of columns and Number of rows must be integers"
        ) from None
    angle = _wsxm_quantity(fields, "Control::Angle", path)[0] if "Control::Angle" in fields else 0
    meta = scan_turn(angle, path, "Control / Angle", scan_frame)
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
    with np.errstate(invalid="ignore"):  # a signalling NaN: finite_height names the line
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
    values = finite_height(values, where)
    return VendorImage(
        values * _wsxm_z_scale(fields, values, dtype, path, where),
        x_size / columns,
        y_size / rows,
        0.0,
        0.0,
        title,
        meta,
    )


def _wsxm_z_scale(fields: dict, values: np.ndarray, dtype, path: Path, where: str) -> float:
    """Metres per stored value. Integers are DAC counts: WSxM states no scale, only the range
    they span (Z Amplitude). Floating-point values are heights in Z Amplitude's unit, as
    Gwyddion 2.66 reads them ("value scale of floating point data was corrected"): stretching
    them to Z Amplitude, as before, zeroed a flat image and carried the header's rounding."""
    if "General Info::Z Amplitude" not in fields:
        return 1e-9
    z_range, z_unit = _wsxm_quantity(fields, "General Info::Z Amplitude", path)
    unit = length_scale(z_unit, f"{where} (Z Amplitude)")
    if dtype.kind == "f":
        return unit
    spread = float(values.max() - values.min())
    return z_range * unit / spread if spread else 0.0
