"""Read and write height-map image files, so a lab can run our algorithms on its own scans.

Formats, chosen by the file name's suffix (case-insensitive):

- `.npz` (native): numpy archive with `height` (2-D, metres, rows = y), `pixel_size_x`,
  `pixel_size_y`, `origin_x`, `origin_y` (metres) and `title`; optional per-pixel `layer_NAME`
  arrays of the height's shape (`HeightMap.layers`, e.g. a tip's uncertainty and
  unconstrained mask) and scalar `meta_NAME` entries (`HeightMap.meta`: how the scan was
  taken, e.g. `scan_angle_deg`, `frame_id`, `stamp`). Loaded without pickle.
- `.npy` (read only): a plain 2-D height array in metres; it carries no pixel size, so the
  caller gives `pixel_size` (square pixels, origin 0).
- `.gwy`: Gwyddion's native format, through the `gwyfile` package (pure Python; install
  it with `pip install gwyfile`). A .gwy file holds channels (`/N/data` GwyDataField with
  xres, yres, xreal, yreal, xoff, yoff, si_unit_xy, si_unit_z and `/N/data/title`); one is
  read, chosen by its position in `list_channels` or by its title, and converted to metres
  by its units (m with an SI prefix: nm, um/µm, pm, ..., or Å). `HeightMap.meta` is the
  channel's metadata (`/N/meta`, text as Gwyddion shows it; numbers read back as floats).

- Vendors' scans (read only), by `vendor_files`: Asylum/Igor `.ibw` (through igor2), JPK
  `.jpk` (through tifffile), Bruker NanoScope `.spm`, Nanonis `.sxm`, WSxM `.stp`/`.top`,
  high-speed AFM movies `.asd` (through AFMReader; a frame by index, `count_frames`);
  channels by index or title as for .gwy (`list_channels`).

Which way rows go. A `HeightMap` has rows along +y: row 0 is the bottom of the area
(pixel (row, col) centre at origin_x + (col + 0.5) * pixel_size_x, origin_y + (row + 0.5) *
pixel_size_y), as in the scanner frame and in `RasterScanData`. Gwyddion stores rows top to
bottom as it displays them (its y axis points down the picture), and its importers put an
instrument's image the way the instrument shows it, so that the top of the picture is the
largest instrument y. So the rows are flipped on reading and on writing: a .gwy we write
looks in Gwyddion the way the scan looks with y up, and a lab's .gwy comes in with y up.
The offsets are kept as the area's position (xoff = origin_x, yoff = origin_y), so the
area spans the same ranges in both; Gwyddion's own y read-out of a point at our y is
2 * origin_y + size_y - y (measured down from the top edge).

Errors: a missing file raises `ImageFileNotFound` (both FileNotFoundError and ValueError);
an unknown suffix, a .npy without pixel size, a channel that does not exist (the message
lists the ones that do), units that cannot be converted to metres, NaN or infinite data and
malformed files raise ValueError naming the problem. Saving never overwrites a file
(FileExistsError).
"""

from __future__ import annotations

import io
import math
import re
import struct
import tokenize
import zipfile
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from afm_core.imaging.gwy_structure import check_gwy_structure
from afm_core.imaging.vendor_common import length_scale
from afm_core.imaging.vendor_files import (
    VENDOR_SUFFIXES,
    read_vendor,
    vendor_channels,
    vendor_frames,
)

SUFFIXES = (".npz", ".npy", ".gwy")  # read and written (.npy read only)
READ_SUFFIXES = SUFFIXES + VENDOR_SUFFIXES


class ImageFileNotFound(FileNotFoundError, ValueError):
    """The image file does not exist (catchable as FileNotFoundError or ValueError)."""


@dataclass
class HeightMap:
    height: np.ndarray  # m, rows = y (row 0 at origin_y), columns = x
    pixel_size_x: float  # m
    pixel_size_y: float  # m
    origin_x: float = 0.0  # m, lower-left corner of the area (pixel (0, 0)'s outer corner)
    origin_y: float = 0.0  # m
    title: str = ""
    # per-pixel arrays of the height's shape carried along (.npz only; .gwy drops them)
    layers: dict = field(default_factory=dict)
    # how the scan was taken (scan_angle_deg, frame_id, stamp in s since the epoch, ...):
    # numbers and strings, kept by .npz and .gwy
    meta: dict = field(default_factory=dict)

    @property
    def size_x(self) -> float:
        return self.height.shape[1] * self.pixel_size_x

    @property
    def size_y(self) -> float:
        return self.height.shape[0] * self.pixel_size_y

    def validate(self, where: str = "height map") -> None:
        """ValueError naming the field when the map is not a finite 2-D array with positive
        finite pixel sizes and finite origin."""
        h = np.asarray(self.height)
        if h.ndim != 2 or min(h.shape) < 1:
            raise ValueError(
                f"{where}: height must be a non-empty 2-D array (rows = y), got shape {h.shape}"
            )
        if not np.issubdtype(h.dtype, np.number) or np.iscomplexobj(h):
            raise ValueError(f"{where}: height must be real numbers (m), got dtype {h.dtype}")
        if not np.isfinite(h).all():
            raise ValueError(f"{where}: height has {_non_finite(h)}")
        for name in ("pixel_size_x", "pixel_size_y"):
            value = getattr(self, name)
            if not (_is_number(value) and math.isfinite(value) and value > 0):
                raise ValueError(f"{where}: {name}={value!r} must be a finite number > 0 (m)")
        for name in ("origin_x", "origin_y"):
            value = getattr(self, name)
            if not (_is_number(value) and math.isfinite(value)):
                raise ValueError(f"{where}: {name}={value!r} must be a finite number (m)")
        if not isinstance(self.title, str):
            raise ValueError(f"{where}: title={self.title!r} must be a string")
        for name, value in self.meta.items():
            if not (isinstance(name, str) and name.isidentifier()):
                raise ValueError(f"{where}: meta name {name!r} must be an identifier")
            if not (isinstance(value, str) or (_is_number(value) and math.isfinite(value))):
                raise ValueError(
                    f"{where}: meta {name}={value!r} must be a string or a finite number"
                )
        for name, layer in self.layers.items():
            if not (isinstance(name, str) and name.isidentifier()):
                raise ValueError(f"{where}: layer name {name!r} must be an identifier")
            if np.shape(layer) != h.shape:
                raise ValueError(
                    f"{where}: layer {name!r} has shape {np.shape(layer)}, expected {h.shape}"
                )


# What a file's numbers can mean in metres. An AFM's z range is at most about 100 um (large-range
# scanners; most are 5-25 um), and no AFM pixel is larger than 100 um (the widest scans are
# about 150 um over 128 px or more). A map beyond either is in a unit nobody stated (nm, um, raw
# counts: a nm map read as metres is 1e9 times too tall), and every later number would be
# nonsense in silence.
MAX_HEIGHT_SPAN_M = 1e-4
MAX_PIXEL_SIZE_M = 1e-4
# the layer a .gwy channel's mask is read into (files._gwy_mask)
GWYDDION_MASK = "gwyddion_mask"


def load_height_map(
    path,
    channel: int | str = 0,
    pixel_size: float | None = None,
    frame: int = 0,
    height_unit: float | None = None,
    *,
    unit_option: str = "--height-unit",
    scan_frame: bool = False,
) -> HeightMap:
    """The height map in `path` (.npz, .npy, .gwy or a vendor's file: .ibw, .jpk, .spm, .sxm,
    .stp, .top, .asd), heights in metres, rows along +y; `frame`: which frame of a movie
    (.asd, 0 first; `count_frames`), 0 for every other format.

    `channel`: for .gwy and vendor files, the position in `list_channels(path)` or the
    channel's title; a
    .npz/.npy holds one map (channel 0, or its title). `pixel_size` (m, square pixels) is
    needed for .npy; for the other formats, which carry their own, it is only checked
    against the file's (ValueError if it disagrees). `height_unit` (m per stored value, e.g.
    1e-9 for nm; default 1) is for .npy only, whose numbers carry no unit; `unit_option` is the
    command-line option a refusal of its heights names. `scan_frame`: a vendor scan turned
    from the scanner's axes is read in its own frame (origin 0, its turn in
    meta["scan_frame_turned_deg"]) instead of refused (vendor_files.read_vendor).

    A map whose heights span more than MAX_HEIGHT_SPAN_M or whose pixels are larger than
    MAX_PIXEL_SIZE_M is refused (ValueError): it is not in metres."""
    path, suffix = _checked_path(path, must_exist=True)
    if pixel_size is not None and not (
        _is_number(pixel_size) and math.isfinite(pixel_size) and pixel_size > 0
    ):
        raise ValueError(f"pixel_size={pixel_size!r}: must be a finite number > 0 (m)")
    if pixel_size is not None and pixel_size > MAX_PIXEL_SIZE_M:
        raise ValueError(
            f"pixel_size={pixel_size!r} m: must be <= {MAX_PIXEL_SIZE_M:g} m (no AFM pixel is "
            "larger); give it in metres (2e-9) or with a unit (2nm)"
        )
    if height_unit is not None:
        if suffix != ".npy":
            raise ValueError(
                f"{path}: height_unit is for .npy files only; a {suffix} file carries its unit"
            )
        if not (_is_number(height_unit) and math.isfinite(height_unit) and height_unit > 0):
            raise ValueError(f"height_unit={height_unit!r}: must be a finite number > 0 (m)")
    if frame != 0 and suffix not in VENDOR_SUFFIXES:
        raise ValueError(f"{path}: frame={frame!r}: a {suffix} file holds one frame (0)")
    if suffix == ".npy":
        hmap = _load_npy(path, channel, pixel_size)
        if height_unit is not None:
            hmap.height = hmap.height * float(height_unit)
    elif suffix == ".npz":
        hmap = _load_npz(path, channel, pixel_size)
    elif suffix == ".gwy":
        try:
            hmap = _load_gwy(path, channel)
        except (ValueError, ImportError):
            raise
        except (*DAMAGED, AttributeError) as exc:  # a damaged field's components
            raise ValueError(f"{path}: malformed .gwy file ({type(exc).__name__}: {exc})") from exc
    else:
        v = read_vendor(path, channel, frame, scan_frame=scan_frame)
        hmap = HeightMap(v.height, v.pixel_size_x, v.pixel_size_y, v.origin_x, v.origin_y, v.title)
        hmap.meta.update(v.meta)
    if pixel_size is not None and suffix != ".npy":
        for name in ("pixel_size_x", "pixel_size_y"):
            if not math.isclose(getattr(hmap, name), pixel_size, rel_tol=1e-6):
                raise ValueError(
                    f"{path}: pixel_size={pixel_size!r} m disagrees with the file's "
                    f"{name}={getattr(hmap, name)!r} m; leave pixel_size out for this format"
                )
    where = str(path) + (f" channel {channel!r}" if suffix in (".gwy",) + VENDOR_SUFFIXES else "")
    hmap.validate(where)
    _check_in_metres(hmap, where, suffix, unit_option)
    return hmap


def _check_in_metres(hmap: HeightMap, where: str, suffix: str, unit_option: str) -> None:
    """ValueError when the map cannot be in metres (MAX_HEIGHT_SPAN_M, MAX_PIXEL_SIZE_M)."""
    span = float(np.ptp(hmap.height))
    if span > MAX_HEIGHT_SPAN_M:
        fix = (
            f"give their unit (height_unit=1e-9 for nm; on the command line {unit_option} nm)"
            if suffix == ".npy"
            else "convert the heights to metres"
            if suffix == ".npz"
            else "the file's z scale was not read as metres"
        )
        raise ValueError(
            f"{where}: heights span {span:.4g} m, more than any AFM's z range "
            f"({MAX_HEIGHT_SPAN_M:g} m): they are not in metres (nm, um, raw counts?); {fix}"
        )
    for name in ("pixel_size_x", "pixel_size_y"):
        if getattr(hmap, name) > MAX_PIXEL_SIZE_M:
            raise ValueError(
                f"{where}: {name}={getattr(hmap, name)!r} m: must be <= {MAX_PIXEL_SIZE_M:g} m "
                "(no AFM pixel is larger): not in metres"
            )


def save_height_map(path, hmap: HeightMap | Sequence[HeightMap]) -> None:
    """Write `hmap` to `path`: .npz (one map) or .gwy (one map or a sequence of maps, one
    channel each, in order), by the suffix. Never overwrites: FileExistsError if the file
    exists. Heights in metres; the .gwy units are m (lateral and z)."""
    path, suffix = _checked_path(path, must_exist=False)
    maps = [hmap] if isinstance(hmap, HeightMap) else list(hmap)
    if not maps or not all(isinstance(m, HeightMap) for m in maps):
        raise ValueError(
            "hmap: expected a HeightMap or a non-empty sequence of them, "
            f"got {type(hmap).__name__}"
        )
    for number, m in enumerate(maps):
        m.validate(f"hmap[{number}]" if len(maps) > 1 else "hmap")
    if suffix == ".npy":
        raise ValueError(f"{path}: .npy cannot hold the pixel size; save as .npz (native) or .gwy")
    if suffix == ".npz":
        if len(maps) != 1:
            raise ValueError(
                f"{path}: a .npz holds one height map, got {len(maps)}; "
                "use .gwy for several channels"
            )
        payload = _npz_bytes(maps[0])
    else:
        payload = _gwy_bytes(maps)
    if path.exists():
        raise FileExistsError(
            f"{path}: already exists; not overwriting it (choose another name or remove it)"
        )
    try:
        with open(path, "xb") as f:  # exclusive create: never clobbers, even in a race
            f.write(payload)
    except FileExistsError:
        raise FileExistsError(
            f"{path}: already exists; not overwriting it (choose another name or remove it)"
        ) from None


def list_channels(path) -> list[str]:
    """Channel titles of a .gwy or vendor file, in order (the index `load_height_map`
    takes). A .npz or .npy holds one map: its title (the file's stem for .npy)."""
    path, suffix = _checked_path(path, must_exist=True)
    if suffix == ".gwy":
        return [title for _, title, _ in _gwy_channels(_read_gwy(path), path)]
    if suffix == ".npz":
        return [_npz_title(path)]
    if suffix in VENDOR_SUFFIXES:
        return vendor_channels(path)
    return [path.stem]


def count_frames(path) -> int:
    """How many frames `path` holds: a high-speed .asd movie's frame count, 1 otherwise."""
    path, suffix = _checked_path(path, must_exist=True)
    return vendor_frames(path) if suffix in VENDOR_SUFFIXES else 1


# -- .npy / .npz ----------------------------------------------------------------------------


def _load_npy(path: Path, channel, pixel_size) -> HeightMap:
    if pixel_size is None:
        raise ValueError(
            f"{path}: a .npy holds only heights; give pixel_size (m) or use a .npz/.gwy file"
        )
    _single_channel(path, channel, path.stem)
    try:
        height = np.load(path, allow_pickle=False)
    except (ValueError, *DAMAGED) as exc:
        raise ValueError(
            f"{path}: not a readable .npy array ({type(exc).__name__}: {exc})"
        ) from exc
    return HeightMap(_heights(height, path), float(pixel_size), float(pixel_size), title=path.stem)


# what numpy's readers raise on a damaged file besides ValueError and OSError: a broken zip
# directory or member, a truncated deflate stream, a header that does not parse, or a shape
# too large to allocate
DAMAGED = (
    OSError,
    EOFError,
    KeyError,
    IndexError,
    TypeError,
    SyntaxError,
    MemoryError,
    OverflowError,
    struct.error,
    zlib.error,
    zipfile.BadZipFile,
    NotImplementedError,
    tokenize.TokenError,  # numpy parses an .npy header's dict with tokenize
)


_NOT_NPZ = "{path}: not a .npz archive (not a zip of arrays; is it another format renamed?)"


def _load_npz(path: Path, channel, pixel_size) -> HeightMap:
    try:
        return _read_npz(path, channel, pixel_size)
    except ValueError as exc:
        if str(path) in str(exc) or str(exc).startswith("channel"):
            raise
        if "allow_pickle" in str(exc):  # numpy's hint would invite loading a pickle: never
            raise ValueError(_NOT_NPZ.format(path=path)) from exc
        raise ValueError(f"{path}: not a readable .npz archive ({exc})") from exc
    except DAMAGED as exc:
        raise ValueError(
            f"{path}: not a readable .npz archive ({type(exc).__name__}: {exc})"
        ) from exc


def _read_npz(path: Path, channel, pixel_size) -> HeightMap:
    archive = np.load(path, allow_pickle=False)
    with archive:
        if "height" not in archive.files:
            raise ValueError(
                f"{path}: no 'height' array in the archive (has {sorted(archive.files)})"
            )
        title = _npz_string(archive, "title", path)
        _single_channel(path, channel, title)
        values = {}
        for name in ("pixel_size_x", "pixel_size_y", "origin_x", "origin_y"):
            if name in archive.files:
                values[name] = _npz_scalar(archive, name, path)
        missing = [n for n in ("pixel_size_x", "pixel_size_y") if n not in values]
        if missing:
            if pixel_size is None:
                raise ValueError(
                    f"{path}: no {' or '.join(missing)} in the archive; give pixel_size (m)"
                )
            for name in missing:
                values[name] = float(pixel_size)
        height = _heights(archive["height"], path)
        layers = {n[6:]: archive[n] for n in archive.files if n.startswith("layer_")}
        meta = {
            n[5:]: _npz_string(archive, n, path)
            if archive[n].dtype.kind in "US"
            else _npz_scalar(archive, n, path)
            for n in archive.files
            if n.startswith("meta_")
        }
    return HeightMap(
        height,
        values["pixel_size_x"],
        values["pixel_size_y"],
        values.get("origin_x", 0.0),
        values.get("origin_y", 0.0),
        title,
        layers,
        meta,
    )


def _npz_title(path: Path) -> str:
    try:
        with np.load(path, allow_pickle=False) as archive:
            return _npz_string(archive, "title", path)
    except (ValueError, *DAMAGED) as exc:
        if "allow_pickle" in str(exc):  # numpy's hint would invite loading a pickle: never
            raise ValueError(_NOT_NPZ.format(path=path)) from exc
        raise ValueError(f"{path}: not a readable .npz archive ({exc})") from exc


def _npz_string(archive, name: str, path: Path) -> str:
    if name not in archive.files:
        return ""
    value = archive[name]
    if value.shape != () or value.dtype.kind not in "US":
        raise ValueError(f"{path}: '{name}' must be a single string")
    item = value.item()
    return item.decode("utf-8") if isinstance(item, bytes) else str(item)


def _npz_scalar(archive, name: str, path: Path) -> float:
    value = archive[name]
    if value.size != 1 or value.dtype.kind not in "iuf":
        raise ValueError(
            f"{path}: '{name}' must be a single number (m), "
            f"got {value.dtype} of shape {value.shape}"
        )
    return float(value.reshape(()))


def _npz_bytes(m: HeightMap) -> bytes:
    buffer = io.BytesIO()
    np.savez(
        buffer,
        height=np.asarray(m.height, dtype=np.float64),
        pixel_size_x=np.float64(m.pixel_size_x),
        pixel_size_y=np.float64(m.pixel_size_y),
        origin_x=np.float64(m.origin_x),
        origin_y=np.float64(m.origin_y),
        title=np.str_(m.title),
        **{f"layer_{name}": np.asarray(layer) for name, layer in m.layers.items()},
        **{
            f"meta_{name}": np.str_(value) if isinstance(value, str) else np.float64(value)
            for name, value in m.meta.items()
        },
    )
    return buffer.getvalue()


def _single_channel(path: Path, channel, title: str) -> None:
    if isinstance(channel, bool) or not (
        channel == 0 or (isinstance(channel, str) and channel == title)
    ):
        raise ValueError(
            f"{path}: channel {channel!r} does not exist; this file holds one map: "
            f"channel 0 {title!r}"
        )


# -- .gwy -------------------------------------------------------------------------------------


def _gwyfile():
    try:
        import gwyfile
    except ImportError as exc:
        raise ImportError(
            "reading and writing .gwy (Gwyddion) files needs the 'gwyfile' package: "
            "pip install gwyfile"
        ) from exc
    return gwyfile


def _read_gwy(path: Path):
    gwyfile = _gwyfile()
    data = path.read_bytes()
    if data[:4] != b"GWYP":
        hint = (
            " (an old Gwyddion 1 file: re-save it with a current Gwyddion)"
            if data[:4] == b"GWYO"
            else ""
        )
        raise ValueError(f"{path}: not a Gwyddion .gwy file (no GWYP header){hint}")
    try:
        check_gwy_structure(data[4:])  # gwyfile may loop for ever on a damaged size or count
    except ValueError as exc:
        raise ValueError(f"{path}: malformed .gwy file ({exc})") from exc
    try:
        container = gwyfile.objects.GwyObject.frombuffer(data[4:])
    except Exception as exc:  # truncated or corrupt: struct/unicode/index errors
        raise ValueError(f"{path}: malformed .gwy file ({type(exc).__name__}: {exc})") from exc
    if getattr(container, "name", None) != "GwyContainer":
        raise ValueError(
            f"{path}: the top object is {getattr(container, 'name', '?')!r}, not a GwyContainer"
        )
    return container


def _gwy_channels(container, path: Path) -> list[tuple[int, str, object]]:
    """(channel number, title, GwyDataField) sorted by number."""
    channels = []
    for key, value in container.items():
        match = re.fullmatch(r"/(\d+)/data", key)
        if match and getattr(value, "name", None) == "GwyDataField":
            number = int(match.group(1))
            title = container.get(f"/{number}/data/title", f"channel {number}")
            if isinstance(title, int):  # gwyfile reads a 1-char 'c' component as a byte
                title = chr(title)
            channels.append((number, str(title), value))
    return sorted(channels, key=lambda item: item[0])


def _load_gwy(path: Path, channel) -> HeightMap:
    container = _read_gwy(path)
    channels = _gwy_channels(container, path)
    available = ", ".join(f"{i}: {title!r}" for i, (_, title, _) in enumerate(channels)) or "none"
    if isinstance(channel, str):
        chosen = [c for c in channels if c[1] == channel]
        if len(chosen) > 1:
            raise ValueError(
                f"{path}: {len(chosen)} channels are titled {channel!r}; choose one by index "
                f"(channels: {available})"
            )
    elif isinstance(channel, (int, np.integer)) and not isinstance(channel, bool):
        chosen = [channels[channel]] if 0 <= channel < len(channels) else []
    else:
        raise ValueError(f"channel={channel!r}: must be an index (int) or a title (str)")
    if not chosen:
        raise ValueError(f"{path}: channel {channel!r} does not exist; channels: {available}")
    number, title, field = chosen[0]
    container_meta = container.get(f"/{number}/meta")
    where = f"{path} channel {title!r}"
    try:
        xres, yres = int(field["xres"]), int(field["yres"])
        raw = np.asarray(field["data"], dtype=np.float64)
    except KeyError as exc:
        raise ValueError(f"{where}: data field lacks {exc.args[0]!r}") from exc
    if xres < 1 or yres < 1 or raw.size != xres * yres:
        raise ValueError(f"{where}: {raw.size} values do not fill xres={xres} x yres={yres}")
    lateral = _unit_scale(field.get("si_unit_xy"), where, "lateral (si_unit_xy)")
    z_scale = _unit_scale(field.get("si_unit_z"), where, "height (si_unit_z)")
    sizes = {}
    for name in ("xreal", "yreal"):
        value = field.get(name)
        if not (_is_number(value) and math.isfinite(value) and value > 0):
            raise ValueError(f"{where}: {name}={value!r} must be a physical size > 0")
        sizes[name] = float(value) * lateral
    offsets = {}
    for name in ("xoff", "yoff"):
        value = field.get(name, 0.0)
        if not (_is_number(value) and math.isfinite(value)):
            raise ValueError(f"{where}: {name}={value!r} must be a finite offset")
        offsets[name] = float(value) * lateral
    height = (
        raw.reshape(yres, xres)[::-1] * z_scale
    )  # Gwyddion's top row becomes our last row (y up)
    bad = int(np.count_nonzero(~np.isfinite(height)))
    if bad:
        raise ValueError(f"{where}: {bad} NaN or infinite value(s) in the data")
    mask = _gwy_mask(container.get(f"/{number}/mask"), xres, yres)
    return HeightMap(
        np.ascontiguousarray(height),
        sizes["xreal"] / xres,
        sizes["yreal"] / yres,
        offsets["xoff"],
        offsets["yoff"],
        title,
        layers={GWYDDION_MASK: mask} if mask is not None else {},
        meta=_gwy_meta(container_meta),
    )


def _gwy_mask(field, xres: int, yres: int) -> np.ndarray | None:
    """A channel's /N/mask as 0/1 in our row order, None when there is none or it marks
    nothing. Kept, not applied: Gwyddion's masks mark grains, or (its importers') pixels that
    held no data and were filled in; only the lab knows which (`mask_note`)."""
    try:
        marked = np.asarray(field["data"], dtype=np.float64).reshape(yres, xres)[::-1] > 0
    except (KeyError, TypeError, ValueError):
        return None
    return marked.astype(np.uint8) if marked.any() else None


def mask_note(hmap: HeightMap, where: str) -> str:
    """What a user must hear about a .gwy channel's mask before its heights are used ("" if
    it has none)."""
    mask = hmap.layers.get(GWYDDION_MASK)
    if mask is None:
        return ""
    return (
        f"{where}: the channel has a Gwyddion mask over {int(mask.sum())} of {mask.size} pixels; "
        "it is not applied. If it marks pixels that held no data (Gwyddion's importers fill "
        "those and mask them), crop them out in Gwyddion first; a grain mask can be ignored"
    )


def _gwy_meta(meta) -> dict:
    """A channel's /N/meta container (text values) as numbers where they read as finite
    numbers, else text; entries whose names are not identifiers are left out."""
    out: dict = {}
    for key, value in meta.items() if hasattr(meta, "items") else ():
        if not (isinstance(key, str) and key.isidentifier()):
            continue
        text = value if isinstance(value, str) else str(value)
        try:
            number = float(text)
        except ValueError:
            out[key] = text
            continue
        out[key] = number if math.isfinite(number) else text
    return out


def _gwy_bytes(maps: list[HeightMap]) -> bytes:
    gwyfile = _gwyfile()
    objects = gwyfile.objects
    container = objects.GwyContainer()
    for number, m in enumerate(maps):
        data = np.ascontiguousarray(
            np.asarray(m.height, dtype=np.float64)[::-1]
        )  # our row 0 at the bottom
        field = objects.GwyDataField(
            data,
            xreal=float(m.size_x),
            yreal=float(m.size_y),
            xoff=float(m.origin_x),
            yoff=float(m.origin_y),
            si_unit_xy=objects.GwySIUnit(unitstr="m"),
            si_unit_z=objects.GwySIUnit(unitstr="m"),
        )
        container[f"/{number}/data"] = field
        container[f"/{number}/data/title"] = m.title or f"height {number}"
        container.typecodes[f"/{number}/data/title"] = (
            "s"  # gwyfile would guess 'c' for a 1-char title
        )
        if m.meta:  # Gwyddion's Metadata browser shows text
            meta = objects.GwyContainer()
            for name, value in m.meta.items():
                meta[name] = value if isinstance(value, str) else repr(float(value))
                meta.typecodes[name] = "s"
            container[f"/{number}/meta"] = meta
    buffer = io.BytesIO()
    container.tofile(buffer)
    return buffer.getvalue()


def _unit_scale(unit, where: str, what: str) -> float:
    """Metres per unit of a Gwyddion SI unit (GwySIUnit or string): m with an SI prefix, or Å."""
    text = (
        unit if isinstance(unit, str) else (unit.get("unitstr") if hasattr(unit, "get") else None)
    )
    if text is None or not str(text).strip():
        raise ValueError(f"{where}: no {what} unit; expected a length such as 'm' or 'nm'")
    return length_scale(str(text), where, f"{what} unit")


# -- common ---------------------------------------------------------------------------------


def _checked_path(path, must_exist: bool) -> tuple[Path, str]:
    if not isinstance(path, (str, Path)):
        raise ValueError(f"path={path!r}: must be a str or pathlib.Path")
    path = Path(path)
    suffix = path.suffix.lower()
    known = READ_SUFFIXES if must_exist else SUFFIXES
    if suffix not in known:
        purpose = "" if must_exist else " for writing (vendor formats are read only)"
        raise ValueError(
            f"{path}: unknown image file suffix {path.suffix!r}; supported{purpose}: "
            f"{', '.join(known)}"
        )
    if must_exist and not path.is_file():
        raise ImageFileNotFound(2, f"{path}: no such image file", str(path))
    return path, suffix


def _heights(values, path: Path) -> np.ndarray:
    height = np.asarray(values)
    if height.ndim != 2 or min(height.shape) < 1:
        raise ValueError(
            f"{path}: height must be a non-empty 2-D array (rows = y), got shape {height.shape}"
        )
    if height.dtype.kind not in "iuf":
        raise ValueError(f"{path}: height must be real numbers (m), got dtype {height.dtype}")
    # NaN and infinities: HeightMap.validate, which load_height_map runs on every map
    return height.astype(np.float64)


def _non_finite(height: np.ndarray) -> str:
    """What is missing, for the refusal: the count, and the lines that hold no value at all
    (an unfinished or aborted scan stores its remaining lines so), with the rows to keep."""
    finite = np.isfinite(height)
    text = f"{np.count_nonzero(~finite)} NaN or infinite pixel(s)"
    empty = np.flatnonzero(~finite.any(axis=1))
    if empty.size and empty.size < height.shape[0]:
        text += f"; {empty.size} of {height.shape[0]} rows hold no value (an unfinished scan?)"
        complete = np.r_[False, finite.all(axis=1), False].astype(int)
        starts, stops = (
            np.flatnonzero(np.diff(complete) == 1),
            np.flatnonzero(np.diff(complete) == -1),
        )
        if starts.size:
            longest = int(np.argmax(stops - starts))
            text += (
                f": crop to complete rows, e.g. {starts[longest]}-{stops[longest] - 1} "
                "(the longest run)"
            )
    return text


def _is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
