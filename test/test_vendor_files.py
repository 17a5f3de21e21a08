"""Vendor scan files (imaging.vendor_files through files.load_height_map): files written byte
by byte from each format's documented structure (vendor_writers.py) come back in metres,
with rows along +y, the pixel size and position the header states, and damaged or
unsupported files are refused naming the file and the problem."""

import numpy as np
import pytest
from vendor_writers import write_ibw, write_jpk, write_spm, write_sxm, write_wsxm

from afm_core.imaging.files import list_channels, load_height_map

ROWS, COLS = 12, 16


def _image(seed: int) -> np.ndarray:
    """Heights (m, float32-exact) with a corner that tells up from down and left from right."""
    rng = np.random.default_rng(seed)
    z = np.round(rng.normal(0.0, 100.0, (ROWS, COLS))).astype(np.float32) * np.float32(1e-10)
    z[0, 0] = np.float32(50e-9)  # bottom-left corner (row 0 = lowest y, col 0 = lowest x)
    return z.astype(np.float64)


def test_ibw_reads_channels_in_metres_with_rows_along_y(tmp_path):
    trace, retrace = _image(1), _image(2)
    layers = np.stack([trace.T, retrace.T], axis=2)  # Igor: (x, y, channel)
    dx, dy, x0, y0 = 2e-9, 3e-9, 1e-6, -2e-6
    note = f"ScanSize: {COLS * dx}\rFastScanSize: {COLS * dx}\rSlowScanSize: {ROWS * dy}\r"
    path = tmp_path / "scan.ibw"
    write_ibw(path, layers, (dx, dy), (x0, y0), ["HeightTrace", "HeightRetrace"], note)
    assert list_channels(path) == ["HeightTrace", "HeightRetrace"]
    hmap = load_height_map(path, "HeightRetrace")
    np.testing.assert_array_equal(hmap.height, retrace)
    assert hmap.height[0, 0] == load_height_map(path).height[0, 0] == trace[0, 0]
    assert (hmap.pixel_size_x, hmap.pixel_size_y) == (dx, dy)
    # Igor's point positions are pixel centres: the area starts half a pixel before
    assert (hmap.origin_x, hmap.origin_y) == (x0 - dx / 2, y0 - dy / 2)
    assert hmap.title == "HeightRetrace"


def test_ibw_units_are_converted_and_checked(tmp_path):
    z = _image(3)
    path = tmp_path / "nm.ibw"
    write_ibw(path, z.T[:, :, None] * 1e9, (2.0, 2.0), (0.0, 0.0), ["Height"], "",
              data_units="nm", dim_units="nm")  # fmt: skip
    hmap = load_height_map(path)
    np.testing.assert_allclose(hmap.height, z, rtol=1e-6)
    assert hmap.pixel_size_x == pytest.approx(2e-9)
    write_ibw(tmp_path / "volts.ibw", z.T[:, :, None], (1e-9, 1e-9), (0, 0), ["Phase"],
              data_units="V")  # fmt: skip
    with pytest.raises(ValueError, match=r"volts.ibw channel 'Phase' \(data units\).*'V'"):
        load_height_map(tmp_path / "volts.ibw")
    write_ibw(tmp_path / "note.ibw", z.T[:, :, None], (1e-9, 1e-9), (0, 0), ["Height"],
              f"FastScanSize: {2 * COLS * 1e-9}\r")  # fmt: skip
    with pytest.raises(ValueError, match="FastScanSize.*disagrees"):
        load_height_map(tmp_path / "note.ibw")
    with pytest.raises(ValueError, match="channel 'Amplitude' does not exist.*0: 'Height'"):
        load_height_map(path.with_name("note.ibw"), "Amplitude")
    (tmp_path / "cut.ibw").write_bytes((tmp_path / "nm.ibw").read_bytes()[:200])
    with pytest.raises(ValueError, match="cut.ibw: not a readable Igor binary wave"):
        load_height_map(tmp_path / "cut.ibw")


@pytest.mark.parametrize("direction", ["up", "down"])
def test_sxm_reads_both_directions_and_scan_orders(tmp_path, direction):
    forward, backward = _image(4), _image(5)
    current = _image(6) * 1e-3
    path = tmp_path / f"{direction}.sxm"
    size, centre = (COLS * 2e-9, ROWS * 2.5e-9), (3e-7, -1e-7)
    write_sxm(path, [("Z", "m", forward, backward), ("Current", "A", current, None)], size,
              centre, direction)  # fmt: skip
    assert list_channels(path) == ["Z", "Z backward", "Current"]
    z = load_height_map(path)
    np.testing.assert_array_equal(z.height, forward)
    np.testing.assert_array_equal(load_height_map(path, "Z backward").height, backward)
    assert (z.pixel_size_x, z.pixel_size_y) == pytest.approx((2e-9, 2.5e-9), rel=1e-6)
    # SCAN_OFFSET is the frame's centre
    assert (z.origin_x, z.origin_y) == pytest.approx((3e-7 - size[0] / 2, -1e-7 - size[1] / 2))
    with pytest.raises(ValueError, match=r"channel 'Current'.*unit 'A' is not a length"):
        load_height_map(path, "Current")


def test_sxm_damaged_and_unsupported_files_are_refused_by_name(tmp_path):
    z = _image(7)
    write_sxm(tmp_path / "cut.sxm", [("Z", "m", z, None)], (1e-7, 1e-7), (0, 0), truncate=9)
    with pytest.raises(ValueError, match=r"cut.sxm: truncated: \d+ data bytes"):
        load_height_map(tmp_path / "cut.sxm")
    write_sxm(tmp_path / "turned.sxm", [("Z", "m", z, None)], (1e-7, 1e-7), (0, 0), angle=30)
    with pytest.raises(ValueError, match="turned.sxm: SCAN_ANGLE 30 deg"):
        load_height_map(tmp_path / "turned.sxm")
    stopped = z.copy()
    stopped[-3:] = np.nan  # Nanonis leaves the lines of an interrupted scan NaN
    write_sxm(tmp_path / "stopped.sxm", [("Z", "m", stopped, None)], (1e-7, 1e-7), (0, 0))
    with pytest.raises(ValueError, match="stopped.sxm channel 'Z': 3 line"):
        load_height_map(tmp_path / "stopped.sxm")
    (tmp_path / "other.sxm").write_bytes(b"not a scan")
    with pytest.raises(ValueError, match="other.sxm: not a Nanonis .sxm file"):
        load_height_map(tmp_path / "other.sxm")


@pytest.mark.parametrize("suffix, data_type", [(".stp", "double"), (".top", "integer")])
def test_wsxm_reads_counts_scaled_to_z_amplitude_and_doubles_in_its_unit(
    tmp_path, suffix, data_type
):
    raw = np.round(np.random.default_rng(8).normal(0, 300, (ROWS, COLS)))
    raw[0, 0] = 2000  # bottom-left corner of the picture
    quantum = 0.05  # nm per count; doubles are nm
    stored = raw[:, ::-1]  # WSxM stores columns right to left, the bottom row first
    stored = stored * quantum if data_type == "double" else stored
    path = tmp_path / f"scan{suffix}"
    z_amplitude = f"{float(raw.max() - raw.min()) * quantum!r} nm"
    write_wsxm(path, stored, (COLS * 2, ROWS * 3), z_amplitude, data_type)
    hmap = load_height_map(path)
    np.testing.assert_allclose(hmap.height, raw * quantum * 1e-9, rtol=1e-12, atol=1e-22)
    assert hmap.height[0, 0] == hmap.height.max()
    assert (hmap.pixel_size_x, hmap.pixel_size_y) == pytest.approx((2e-9, 3e-9))
    assert list_channels(path) == ["Topography"]
    data = path.read_bytes()
    (tmp_path / f"cut{suffix}").write_bytes(data[: data.index(b"[Header end]")])
    with pytest.raises(ValueError, match=f"cut{suffix}: WSxM header without"):
        load_height_map(tmp_path / f"cut{suffix}")
    (tmp_path / f"short{suffix}").write_bytes(data[:-10])
    with pytest.raises(ValueError, match=f"short{suffix}: truncated"):
        load_height_map(tmp_path / f"short{suffix}")


def test_vendor_formats_are_read_only(tmp_path):
    from afm_core.imaging.files import HeightMap, save_height_map

    with pytest.raises(ValueError, match="supported for writing"):
        save_height_map(tmp_path / "x.sxm", HeightMap(np.zeros((2, 2)), 1e-9, 1e-9))


def _tilted_scan_with_a_particle(centre_xy, origin, pixel):
    """A 10 nm tilt across the map, noise, and a 20 nm round particle at centre_xy (m)."""
    rows, cols = 64, 64
    rng = np.random.default_rng(9)
    y = origin[1] + (np.arange(rows) + 0.5) * pixel
    x = origin[0] + (np.arange(cols) + 0.5) * pixel
    xx, yy = np.meshgrid(x, y)
    r2 = (xx - centre_xy[0]) ** 2 + (yy - centre_xy[1]) ** 2
    particle = np.sqrt(np.clip((10e-9) ** 2 - r2, 0, None)) * 2.0  # 20 nm high cap
    tilt = 10e-9 * (xx - origin[0]) / (cols * pixel) + 4e-9 * (yy - origin[1]) / (rows * pixel)
    return particle, particle + tilt + rng.normal(0.0, 0.1e-9, xx.shape)


def test_cli_levels_and_finds_a_particle_where_a_down_scan_put_it(tmp_path):
    import json
    import subprocess
    import sys

    pixel, origin, centre = 2e-9, (1.0e-6, 2.0e-6), (1.0e-6 + 40e-9, 2.0e-6 + 90e-9)
    particle, raw = _tilted_scan_with_a_particle(centre, origin, pixel)
    size = (64 * pixel, 64 * pixel)
    scan = tmp_path / "lab.sxm"
    write_sxm(scan, [("Z", "m", raw, None)], size,
              (origin[0] + size[0] / 2, origin[1] + size[1] / 2), "down")  # fmt: skip

    def afm(*args):
        command = [sys.executable, "-m", "afm_bringup.cli", "image", *map(str, args)]
        return subprocess.run(command, capture_output=True, text=True, timeout=300)

    listed = afm("channels", scan)
    assert listed.returncode == 0 and listed.stdout.strip() == "0: Z", listed.stderr
    # a truncated copy lists the same channel but cannot be read: "channels" says so
    (tmp_path / "cut.sxm").write_bytes(scan.read_bytes()[:-100])
    cut = afm("channels", tmp_path / "cut.sxm")
    assert (
        cut.returncode == 2 and "0: Z (cannot be used:" in cut.stdout and "truncated" in cut.stdout
    )
    levelled = afm("level", scan, "--method", "plane", "-o", tmp_path / "flat.npz")
    assert levelled.returncode == 0, levelled.stderr
    flat = load_height_map(tmp_path / "flat.npz")
    # the particle stands on a levelled background (noise 0.1 nm, fit error far below it)
    assert np.max(np.abs(flat.height - particle)) < 0.6e-9
    marks = afm("landmarks", scan, "--level", "plane", "--json", tmp_path / "marks.json")
    assert marks.returncode == 0, marks.stderr
    found = json.loads((tmp_path / "marks.json").read_text())
    assert len(found) == 1
    # where the scan put it, in the file's own coordinates, to a fraction of a pixel
    assert (
        abs(found[0]["x"] - centre[0]) < pixel / 2 and abs(found[0]["y"] - centre[1]) < pixel / 2
    )


def test_jpk_reads_the_default_calibration_in_metres(tmp_path):
    rng = np.random.default_rng(10)
    trace = rng.integers(-(2**30), 2**30, (ROWS, COLS))
    trace[0, 0] = 2**31 - 1  # bottom-left: the first stored row is the bottom line
    retrace = rng.integers(-(2**30), 2**30, (ROWS, COLS))
    multiplier, offset = -1.1577e-15, 2.486e-6  # m per count and m, as a NanoWizard writes
    path = tmp_path / "scan.jpk"
    write_jpk(path, [("height", False, trace, multiplier, offset),
                     ("height", True, retrace, multiplier, offset)],
              (COLS * 5e-9, ROWS * 4e-9), (2.5e-6, 1.6e-6))  # fmt: skip
    assert list_channels(path) == ["height_trace", "height_retrace"]
    hmap = load_height_map(path, "height_retrace")
    np.testing.assert_allclose(hmap.height, retrace * multiplier + offset, rtol=1e-15)
    trace_map = load_height_map(path)
    assert trace_map.height[0, 0] == trace_map.height.min()  # the negative multiplier
    assert (hmap.pixel_size_x, hmap.pixel_size_y) == pytest.approx((5e-9, 4e-9))
    assert (hmap.origin_x, hmap.origin_y) == (2.5e-6, 1.6e-6)


def test_jpk_refuses_rotated_grids_and_non_lengths(tmp_path):
    raw = np.zeros((ROWS, COLS), dtype=np.int32)
    write_jpk(tmp_path / "turned.jpk", [("height", False, raw, 1e-15, 0.0)], (1e-7, 1e-7),
              (0.0, 0.0), theta=np.pi / 2)  # fmt: skip
    with pytest.raises(ValueError, match="turned.jpk: Grid-Theta 90 deg"):
        load_height_map(tmp_path / "turned.jpk")
    write_jpk(tmp_path / "volts.jpk", [("error", False, raw, 1e-9, 0.0)], (1e-7, 1e-7),
              (0.0, 0.0), slot_unit="V")  # fmt: skip
    with pytest.raises(ValueError, match=r"volts.jpk channel 'error_trace' \(slot unit\)"):
        load_height_map(tmp_path / "volts.jpk")
    (tmp_path / "bad.jpk").write_bytes(b"not a TIFF at all")
    with pytest.raises(ValueError, match="bad.jpk: not a readable JPK TIFF"):
        load_height_map(tmp_path / "bad.jpk")


@pytest.mark.parametrize("bpp", [2, 4])
def test_spm_heights_from_the_scale_and_sensitivity(tmp_path, bpp):
    rng = np.random.default_rng(11)
    top = 2 ** (8 * bpp - 2)
    trace = rng.integers(-top, top, (ROWS, COLS))
    trace[0, 0] = 2 * top - 1  # the first stored row is the bottom line
    retrace = rng.integers(-top, top, (ROWS, COLS))
    path = tmp_path / "scan.spm"
    write_spm(path, [("Height", trace, False), ("Height", retrace, True),
                     ("Deflection", trace, False)], (1.6, 1.2), bpp=bpp)  # fmt: skip
    assert list_channels(path) == ["Height", "Height retrace", "Deflection"]
    metres_per_count = 439.9866 / 2 ** (8 * bpp) * 15.068e-9
    hmap = load_height_map(path)
    np.testing.assert_allclose(hmap.height, trace * metres_per_count, rtol=1e-12)
    assert hmap.height[0, 0] == hmap.height.max()
    np.testing.assert_allclose(
        load_height_map(path, "Height retrace").height, retrace * metres_per_count, rtol=1e-12
    )
    assert (hmap.pixel_size_x, hmap.pixel_size_y) == pytest.approx((1.6e-6 / COLS, 1.2e-6 / ROWS))
    with pytest.raises(ValueError, match=r"channel 'Deflection'.*Sens. Deflection"):
        load_height_map(path, "Deflection")


def test_spm_damaged_and_rotated_files_are_refused_by_name(tmp_path):
    raw = np.zeros((ROWS, COLS), dtype=np.int16)
    write_spm(tmp_path / "turned.spm", [("Height", raw, False)], (1, 1), rotate=30.0)
    with pytest.raises(ValueError, match="turned.spm: Rotate Ang. 30 deg"):
        load_height_map(tmp_path / "turned.spm")
    write_spm(tmp_path / "whole.spm", [("Height", raw, False)], (1, 1))
    data = (tmp_path / "whole.spm").read_bytes()
    (tmp_path / "cut.spm").write_bytes(data[:-2])
    with pytest.raises(ValueError, match="cut.spm: truncated"):
        load_height_map(tmp_path / "cut.spm")
    (tmp_path / "header.spm").write_bytes(data[:200])
    with pytest.raises(ValueError, match="header.spm: NanoScope header without"):
        load_height_map(tmp_path / "header.spm")
    (tmp_path / "other.spm").write_bytes(b"PK\x03\x04 not a scan")
    with pytest.raises(ValueError, match="other.spm: not a Bruker NanoScope file"):
        load_height_map(tmp_path / "other.spm")


def test_header_numbers_that_are_not_numbers_and_twin_titles_are_refused_by_name(tmp_path):
    """A header edited by hand or written by another software version gave Python's bare
    'could not convert string to float'; of two channels titled alike the first was read."""
    raw = np.zeros((ROWS, COLS), dtype=np.int16)
    write_spm(tmp_path / "angle.spm", [("Height", raw, False)], (1, 1), rotate="n/a")
    with pytest.raises(ValueError, match=r"angle.spm: Rotate Ang. 'n/a' is not a number"):
        load_height_map(tmp_path / "angle.spm")
    write_spm(tmp_path / "sens.spm", [("Height", raw, False)], (1, 1), sens="abc")
    with pytest.raises(ValueError, match=r"sens.spm channel 'Height': @Sens. Zscan 'abc' is not"):
        load_height_map(tmp_path / "sens.spm")
    write_spm(tmp_path / "twins.spm", [("Height", raw, False), ("Height", raw + 1, False)], (1, 1))
    assert list_channels(tmp_path / "twins.spm") == ["Height", "Height"]
    with pytest.raises(ValueError, match=r"twins.spm: 2 channels are titled 'Height'; choose one"):
        load_height_map(tmp_path / "twins.spm", "Height")
    assert load_height_map(tmp_path / "twins.spm", 1).height.max() > 0
    write_wsxm(tmp_path / "z.stp", np.ones((ROWS, COLS)), (COLS, ROWS), "1.2.3 nm")
    with pytest.raises(ValueError, match=r"z.stp: General Info / Z Amplitude '1.2.3' is not a"):
        load_height_map(tmp_path / "z.stp")
