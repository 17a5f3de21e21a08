"""High-speed AFM movies, `.asd` (Ando lab / RIBM, file versions 0, 1 and 2), read through
AFMReader (the TopoStats team's reader, `AFMReader.asd`).

Layout (as AFMReader and libasd read it): an int32 file version; a header (v0: 2-byte channel
codes and int16 sizes; v1/v2: int32 fields, 4-byte channel codes; v2 adds feed-forward and
colour-map fields) ending at `header_length` bytes from the start, where the data starts (as
libasd takes it: AFMReader reads v2's feed-forward flag as 4 bytes where libasd reads 1, so
its parse may stop short of `header_length`; v0 files are known to state it wrongly, so
their data starts where the fields end, as both readers take it); then
per channel (1ch, then 2ch when it names a kind) `num_frames` frames, each a 32-byte frame
header and `x_pixels` x `y_pixels` little-endian int16 levels, line after line.

AFMReader parses the header and converts levels to nm: volts from the AD range code
(unipolar or bipolar, 1, 2.5 or 5 V over 4096 levels) times the channel's coefficient
(topography TP: z piezo extension (nm/V) x z piezo gain; error ER: -sensor sensitivity (nm/V);
phase PH: -phase sensitivity (deg/V), not a length, so refused as a height). Checked here
against the file's own header before AFMReader reads a frame: the version, the data bits
(AFMReader assumes 12, 4096 levels: other resolutions are refused rather than misread), the
frame-header size (AFMReader reads 32 bytes), the header's fields within `header_length`
for v1/v2, the pixel counts and
scan size, and the file length the frames need. One frame is read (`frame`, 0 first), not
the whole movie. AFMReader returns a frame as an image, its first stored line on top (row 0);
the map's rows run along +y, so the rows are flipped. The pixel size is the scan size (x_nm,
y_nm) over the pixels in each direction (AFMReader gives only x); origin 0 (the frame
headers' offsets are raw scanner levels). The frame time (s), scan size (m), frame count and
scan direction code come through as metadata.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from afm_core.imaging.vendor_common import VendorImage, choose_channel, finite_height

# channel codes (two ASCII letters) -> what a frame holds; only lengths become heights
ASD_KINDS = {"TP": "topography", "ER": "error", "PH": "phase"}
_LENGTH_KINDS = ("TP", "ER")
# AFMReader reads this many bytes of frame header and converts 12-bit levels (4096)
_FRAME_HEADER_BYTES = 32
_AD_BITS = 12
# a frame larger than this is a damaged size field, not a high-speed AFM frame
_MAX_PIXELS = 4096


def _afmreader_asd():
    try:
        from AFMReader import asd
    except ImportError as exc:  # pragma: no cover - pinned in requirements.txt
        raise ImportError(f"reading .asd needs AFMReader ({exc}); run `make setup`") from exc
    from loguru import logger

    # AFMReader logs every field at INFO on stderr; our errors are one line
    logger.disable("AFMReader")
    return asd


def asd_header(path: Path) -> tuple[dict, int]:
    """The header fields (AFMReader's names) and the byte offset where frame data starts;
    ValueError naming the file and the field that is wrong."""
    asd = _afmreader_asd()
    size = os.path.getsize(path)
    readers = {
        0: asd.read_header_file_version_0,
        1: asd.read_header_file_version_1,
        2: asd.read_header_file_version_2,
    }
    with open(path, "rb") as f:
        head = f.read(4)
        if len(head) < 4:
            raise ValueError(f"{path}: not an .asd file (shorter than its version field)")
        version = int.from_bytes(head, "little", signed=True)
        if version not in readers:
            raise ValueError(f"{path}: .asd file version {version} is not read (0, 1, 2 are)")
        try:
            header = readers[version](f)
        except struct.error as exc:  # a short read inside AFMReader
            raise ValueError(f"{path}: truncated .asd v{version} header") from exc
        except (ValueError, TypeError, OverflowError, MemoryError) as exc:
            raise ValueError(f"{path}: damaged .asd v{version} header ({exc})") from exc
        end = f.tell()
    header["version"] = version
    _check_header(path, header, end, size)
    return header, (end if version == 0 else header["header_length"])


def _check_header(path: Path, h: dict, end: int, size: int) -> None:
    v = h["version"]
    if end > size:
        raise ValueError(f"{path}: truncated .asd v{v} header ({size} bytes)")
    if v != 0 and not end <= h["header_length"] <= size:
        raise ValueError(
            f"{path}: header_length={h['header_length']} but the v{v} header's fields end at "
            f"byte {end} and the file has {size}: damaged header"
        )
    end = end if v == 0 else h["header_length"]
    if h["frame_header_length"] != _FRAME_HEADER_BYTES:
        raise ValueError(
            f"{path}: frame_header_length={h['frame_header_length']}: the frame header read "
            f"is {_FRAME_HEADER_BYTES} bytes"
        )
    if h["analogue_digital_data_bits_size"] != _AD_BITS:
        raise ValueError(
            f"{path}: analogue_digital_data_bits_size={h['analogue_digital_data_bits_size']}: "
            f"AFMReader converts {_AD_BITS}-bit levels only"
        )
    for name in ("x_pixels", "y_pixels"):
        if not 0 < h[name] <= _MAX_PIXELS:
            raise ValueError(f"{path}: {name}={h[name]} must be 1 to {_MAX_PIXELS}")
    for name in ("x_nm", "y_nm"):
        if not h[name] > 0:
            raise ValueError(f"{path}: {name}={h[name]} (scan size) must be > 0 nm")
    if not h["num_frames"] > 0:
        raise ValueError(f"{path}: num_frames={h['num_frames']}: the file holds no frame")
    if not asd_channels(h):
        raise ValueError(f"{path}: channel1={h['channel1']!r} is none of {sorted(ASD_KINDS)}")
    needed = end + len(asd_channels(h)) * h["num_frames"] * _frame_bytes(h)
    if size < needed:
        raise ValueError(
            f"{path}: truncated: {size} bytes, the header's {h['num_frames']} frame(s) of "
            f"{len(asd_channels(h))} channel(s) need {needed}"
        )


def _frame_bytes(h: dict) -> int:
    return _FRAME_HEADER_BYTES + 2 * h["x_pixels"] * h["y_pixels"]


def asd_channels(header: dict) -> list[str]:
    """The channel codes holding data, 1ch first (a 2ch code of zeros means one channel)."""
    out = []
    for key in ("channel1", "channel2"):
        code = str(header[key]).strip("\x00")
        if code not in ASD_KINDS:
            break
        out.append(code)
    return out


def asd_frame_count(path: Path) -> int:
    return int(asd_header(path)[0]["num_frames"])


def asd_image(path: Path, channel: int | str = 0, frame: int = 0) -> VendorImage:
    """Frame `frame` (0 first) of channel `channel` (index, or code TP/ER) in metres."""
    header, start = asd_header(path)
    names = asd_channels(header)
    index = choose_channel(path, names, channel)
    code = names[index]
    if code not in _LENGTH_KINDS:
        raise ValueError(f"{path}: channel {code!r} ({ASD_KINDS[code]}) is not a height (deg)")
    count = header["num_frames"]
    if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)):
        raise ValueError(f"frame={frame!r}: must be an index (int)")
    if not 0 <= frame < count:
        raise ValueError(
            f"{path}: frame {frame} does not exist; the file has {count} (0 to {count - 1})"
        )
    nm = _frame_nm(path, header, start + (index * count + int(frame)) * _frame_bytes(header), code)
    where = f"{path} channel {code!r} frame {frame}"
    height = finite_height(nm[::-1] * 1e-9, where)
    meta = {
        "movie_frame": int(frame),
        "movie_frames": int(count),
        "frame_time": float(header["frame_time"]) * 1e-3,  # ms in the file
        "scan_size_x": float(header["x_nm"]) * 1e-9,
        "scan_size_y": float(header["y_nm"]) * 1e-9,
        "scan_direction": int(header["scan_direction"]),
        "asd_version": int(header["version"]),
    }
    return VendorImage(
        height,
        header["x_nm"] * 1e-9 / header["x_pixels"],
        header["y_nm"] * 1e-9 / header["y_pixels"],
        0.0,
        0.0,
        f"{code} ({ASD_KINDS[code]})",
        meta,
    )


def _frame_nm(path: Path, header: dict, offset: int, code: str) -> np.ndarray:
    asd = _afmreader_asd()
    try:
        factor = asd.calculate_scaling_factor(
            channel=code,
            z_piezo_gain=header["z_piezo_gain"],
            z_piezo_extension=header["z_piezo_extension"],
            scanner_sensitivity=header["scanner_sensitivity"],
            phase_sensitivity=header["phase_sensitivity"],
        )
        converter = asd.create_analogue_digital_converter(
            analogue_digital_range=header["analogue_digital_range"], scaling_factor=factor
        )
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
    with open(path, "rb") as f:
        f.seek(offset)
        (frame,) = asd.read_channel_data(
            open_file=f,
            num_frames=1,
            x_pixels=header["x_pixels"],
            y_pixels=header["y_pixels"],
            analogue_digital_converter=converter,
        )
    return np.asarray(frame, dtype=np.float64)
