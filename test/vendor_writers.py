"""Minimal vendor scan files written byte by byte from the formats' documented structure,
for the reader tests (none of these formats has a writer we could use)."""

import struct

import numpy as np


def write_ibw(path, layers, spacing, first, labels, note="", data_units="m", dim_units="m"):
    """An Igor binary wave version 5 (Igor Technical Note 003), little endian, float32:
    `layers` (x, y, channel); `spacing`, `first` = sfA, sfB of dimensions 0 and 1."""
    data = np.asarray(layers, dtype="<f4")
    nx, ny, nch = data.shape
    payload = data.tobytes(order="F")  # Igor stores dimension 0 fastest
    note_bytes = note.encode("latin-1")
    label_bytes = b"".join(n.encode().ljust(32, b"\0") for n in [""] + list(labels))
    wave_header = struct.pack(
        "<IIIihh6sh32slI4i4d4d4s16shhddI4I4II16ihhhccIihhII",
        0, 0, 0, nx * ny * nch, 2, 0, b"", 1, b"scan", 0, 0,
        nx, ny, nch, 0,
        spacing[0], spacing[1], 1.0, 1.0,
        first[0], first[1], 0.0, 0.0,
        data_units.encode().ljust(4, b"\0"),
        dim_units.encode().ljust(4, b"\0") * 2 + b"\0" * 8,
        0, 0, 0.0, 0.0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0,
        *[0] * 16, 0, 0, 0, b"\0", b"\0", 0, 0, 0, 0, 0, 0,
    )  # fmt: skip
    assert len(wave_header) == 320
    bin_header = struct.pack(
        "<hhllll4l4llll",
        5, 0, 320 + len(payload), 0, len(note_bytes), 0, 0, 0, 0, 0,
        0, 0, len(label_bytes), 0, 0, 0, 0,
    )  # fmt: skip
    assert len(bin_header) == 64
    words = np.frombuffer(bin_header + wave_header, dtype="<i2")
    checksum = (-int(words.astype(np.int64).sum())) % 65536  # the header words sum to 0
    bin_header = bin_header[:2] + struct.pack("<H", checksum) + bin_header[4:]
    with open(path, "xb") as f:
        f.write(bin_header + wave_header + payload + note_bytes + label_bytes)


def write_sxm(path, channels, size, centre, direction="up", angle=0.0, truncate=0):
    """A Nanonis .sxm: `channels` = [(name, unit, forward, backward or None)], each image with
    rows along +y as the map should read; stored as scanned (big-endian float32)."""
    lines, columns = np.shape(channels[0][2])
    table = "\tChannel\tName\tUnit\tDirection\tCalibration\tOffset\n"
    blocks = []
    for number, (name, unit, forward, backward) in enumerate(channels):
        both = backward is not None
        table += f"\t{number}\t{name}\t{unit}\t{'both' if both else 'forward'}\t1.0E+0\t0.0E+0\n"
        for image, mirrored in ((forward, False), (backward, True)):
            if image is None:
                continue
            stored = np.asarray(image)[:, ::-1] if mirrored else np.asarray(image)
            stored = stored[::-1] if direction == "down" else stored
            blocks.append(stored.astype(">f4").tobytes())
    header = (
        ":NANONIS_VERSION:\n2\n"
        ":SCANIT_TYPE:\n              FLOAT            MSBFIRST\n"
        f":SCAN_PIXELS:\n       {columns}       {lines}\n"
        f":SCAN_RANGE:\n           {size[0]:.6E}           {size[1]:.6E}\n"
        f":SCAN_OFFSET:\n           {centre[0]:.6E}         {centre[1]:.6E}\n"
        f":SCAN_ANGLE:\n            {angle:.3E}\n"
        f":SCAN_DIR:\n{direction}\n"
        f":DATA_INFO:\n{table}\n"
        ":SCANIT_END:\n\n\n"
    )
    data = header.encode("latin-1") + b"\x1a\x04" + b"".join(blocks)
    with open(path, "xb") as f:
        f.write(data[: len(data) - truncate])


def write_wsxm(
    path, stored, size_nm, z_amplitude, data_type="double", channel="Topography",
    xy_unit="nm", control=(),
):  # fmt: skip
    """A WSxM image file as Gwyddion exports one: `stored` already in file order; `size_nm`
    the X and Y Amplitude in `xy_unit` (latin-1: "\xb5m" as WSxM writes um); `control`:
    further [Control] lines ("Angle: 0", "X Offset: -2697.9 nm", as the instrument adds)."""
    rows, columns = np.shape(stored)
    text = (
        "WSxM file copyright UAM\r\nSxM Image file\r\nImage header size: 99999\r\n\r\n"
        "[Control]\r\n\r\n"
        + "".join(f"    {line}\r\n" for line in control)
        + f"    X Amplitude: {size_nm[0]} {xy_unit}\r\n"
        f"    Y Amplitude: {size_nm[1]} {xy_unit}\r\n\r\n"
        "[General Info]\r\n\r\n"
        f"    Image Data Type: {data_type}\r\n    Acquisition channel: {channel}\r\n"
        f"    Number of columns: {columns}\r\n    Number of rows: {rows}\r\n"
        f"    Z Amplitude: {z_amplitude}\r\n\r\n"
        "[Header end]\r\n"
    )
    text = text.replace("99999", f"{len(text):5d}")
    dtype = {"double": "<f8", "float": "<f4", "integer": "<i2", "short": "<i2"}[data_type]
    with open(path, "xb") as f:
        f.write(text.encode("latin-1") + np.asarray(stored).astype(dtype).tobytes())


def write_jpk(path, channels, size, corner, theta=0.0, slot_unit="m", reflect=None, chain=False):
    """A JPK image TIFF (JPKImageSpec 2.0 tags, as in the instrument's files): a thumbnail page
    with the grid (and Grid-Reflect when `reflect` is given, as a NanoWizard writes it there),
    then one int32 page per channel [(name, retrace, raw, multiplier, offset)], each with a
    raw slot and a default 'calibrated' LinearScaling slot. `chain`: the slots a NanoWizard
    writes, raw, volts, nominal, calibrated (the default, last), each LinearScaling from raw
    counts, so only the default one gives the heights."""
    import tifffile

    lines, columns = np.shape(channels[0][2])
    grid = [
        (32832, "d", 1, corner[0], True), (32833, "d", 1, corner[1], True),
        (32834, "d", 1, size[0], True), (32835, "d", 1, size[1], True),
        (32836, "d", 1, theta, True), (32838, "I", 1, columns, True),
        (32839, "I", 1, lines, True), (32848, "s", 0, "thumbnail", True),
    ]  # fmt: skip
    if reflect is not None:
        grid.append((32837, "I", 1, int(reflect), True))
    with tifffile.TiffWriter(path) as tif:
        tif.write(np.zeros((4, 4), np.uint8), extratags=grid)
        for name, retrace, raw, multiplier, offset in channels:
            scalings = [("calibrated", slot_unit, multiplier, offset)]
            if chain:  # volts and nominal metres per count: other numbers than the default's
                nominal = ("nominal", "m", multiplier * 1.31, offset * 0.77)
                scalings = [("volts", "V", 2.3283e-08, 50.0), nominal, *scalings]
            tags = [
                (32848, "s", 0, name, True), (32849, "I", 1, int(retrace), True),
                (32896, "I", 1, 1 + len(scalings), True), (32897, "s", 0, "calibrated", True),
                (32912, "s", 0, "raw", True), (32931, "s", 0, "NullScaling", True),
            ]  # fmt: skip
            for k, (slot, unit, times, plus) in enumerate(scalings, start=1):
                base = 32912 + 48 * k
                tags += [
                    (base, "s", 0, slot, True), (base + 18, "s", 0, unit, True),
                    (base + 19, "s", 0, "LinearScaling", True), (base + 20, "d", 1, times, True),
                    (base + 21, "d", 1, plus, True),
                ]  # fmt: skip
            tif.write(np.asarray(raw, dtype=np.int32), extratags=tags)


def write_spm(path, images, size_um, sens=15.068, full_scale=439.9866, bpp=2, rotate=0.0):
    """A Bruker NanoScope (v5.31) file: `images` = [(name, raw integers rows x columns,
    retrace)], stored as they are (the first row is the bottom line); heights are raw x
    full_scale / 2^(8 bpp) x `sens` nm/V for a channel scaled by 'Sens. Zscan'."""
    header_size = 8192
    text = [
        "\\*File list", "\\Version: 0x05310001", f"\\Data length: {header_size}",
        "\\*Scanner list", f"\\@Sens. Zscan: V {sens} nm/V", "\\@Sens. Deflection: V 1.000000 ",
        "\\*Ciao scan list", f"\\Scan size: {size_um[0] * 1000} nm", f"\\Rotate Ang.: {rotate}",
    ]  # fmt: skip
    offset, blocks = header_size, []
    for name, raw, retrace in images:
        raw = np.asarray(raw, dtype=f"<i{bpp}")
        sensitivity = "Zscan" if name == "Height" else name
        text += [
            "\\*Ciao image list", f"\\Data offset: {offset}",
            f"\\Data length: {raw.size * bpp}", f"\\Bytes/pixel: {bpp}",
            f"\\Samps/line: {raw.shape[1]}", f"\\Number of lines: {raw.shape[0]}",
            f"\\Scan Size: {size_um[0]} {size_um[1]} ~m",
            f"\\Line Direction: {'Retrace' if retrace else 'Trace'}",
            f'\\@2:Image Data: S [{name}] "{name}"',
            f"\\@2:Z scale: V [Sens. {sensitivity}] ({full_scale / 2 ** (8 * bpp):.9g} V/LSB) "
            f"{full_scale} V",
        ]  # fmt: skip
        offset += raw.size * bpp
        blocks.append(raw.tobytes())
    header = ("\r\n".join(text) + "\r\n\\*File list end\r\n").encode("latin-1")
    with open(path, "xb") as f:
        f.write(header.ljust(header_size, b"\0") + b"".join(blocks))


# .asd AD range codes (bipolar 2.5 V: levels 0..4095 span +2.5 V .. -2.5 V) and their volts
ASD_BIPOLAR_2_5V = 0x00020000


def write_asd(
    path, version, channels, size_nm, frame_time_ms=50.0, z_nm_per_v=(10.0, 2.0),
    sensor_nm_per_v=3.0, ad_range=ASD_BIPOLAR_2_5V, bits=12, frame_header=32,
):  # fmt: skip
    """A high-speed AFM .asd movie (file version 0, 1 or 2) as libasd and AFMReader describe
    it, little endian: `channels` = [(code "TP"/"ER"/"PH", int16 levels (frames, lines,
    pixels), lines in stored order)], at most two, the same shape; `z_nm_per_v` = (z piezo
    extension nm/V, z piezo gain). v2 is written as libasd reads it (a 1-byte feed-forward
    flag), with no colour anchor points; `header_length` counts from the file's start."""
    frames, lines, pixels = np.asarray(channels[0][1]).shape
    codes = [c.encode() for c, _ in channels] + [b""] * (2 - len(channels))
    name, comment = b"afm", b"written by the tests"
    z_ext, z_gain = z_nm_per_v
    if version == 0:
        fixed = struct.calcsize("<i2s2s5i4h3fIi?ihh6Bff3i3ih")
        length = fixed + len(name) + struct.calcsize("<ffi") + len(comment)
        header = struct.pack(
            "<i2s2s5i4h3fIi?ihh6Bff3i3ih", 0, codes[0], codes[1], length, frame_header,
            len(name), 0, len(comment), pixels, lines, size_nm[0], size_nm[1],
            frame_time_ms, z_ext, z_gain, ad_range, bits, False, 0, 0, 2026, 11, 27, 12,
            0, 0, 0, 4000.0, 4000.0, 0, 0, 0, frames, frames, 1, 7,
        ) + name + struct.pack("<ffi", sensor_nm_per_v, 1.0, 1) + comment  # fmt: skip
    else:
        body = struct.pack(
            "<4s4s4i4i?i6i2i3fi12xiIi6f", codes[0], codes[1], frames, frames, 1, 7,
            pixels, lines, size_nm[0], size_nm[1], False, 0, 2026, 11, 27, 12, 0, 0, 0, 0,
            frame_time_ms, sensor_nm_per_v, 1.0, 0, 1, ad_range, bits, 4000.0, 4000.0,
            1.0, 1.0, z_ext, z_gain,
        ) + name + comment  # fmt: skip
        if version == 2:
            body += struct.pack("<i?id5i", frames, False, 0, 0.0, 255, 0, 0, 0, 0)
        length = 4 + struct.calcsize("<5i") + len(body)
        header = struct.pack("<6i", version, length, frame_header, 65001, len(name), len(comment))
        header += body
    assert len(header) == length
    data = b""
    for _, levels in channels:
        for k, frame in enumerate(np.asarray(levels, dtype="<i2")):
            head = struct.pack("<ihhhhff?bhii", k, int(frame.max()), int(frame.min()), 0, 0,
                               0.0, 0.0, False, 0, 0, 0, 0)  # fmt: skip
            data += head.ljust(frame_header, b"\0") + frame.tobytes()
    with open(path, "xb") as f:
        f.write(header + data)
