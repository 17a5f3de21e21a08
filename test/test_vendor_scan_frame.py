"""Scans turned from the scanner's axes (a scan angle): refused by default, since their pixels
are not at the scanner positions the map's axes stand for, and read in their own frame on
request (`scan_frame`, `afm image --scan-frame`), which is how Gwyddion and AFMReader show them.
Before 2026-11-29 an Asylum scan's ScanAngle was not read at all: a turned .ibw came in as if
it were not turned."""

import math
import subprocess
import sys

import numpy as np
import pytest
from vendor_writers import write_ibw, write_jpk, write_spm, write_sxm, write_wsxm

from afm_core.imaging.files import load_height_map

ROWS, COLS = 8, 12
DX, DY = 2e-9, 3e-9


def _image(seed: int) -> np.ndarray:
    """Heights (m, float32-exact) with a corner that tells up from down and left from right."""
    rng = np.random.default_rng(seed)
    z = np.round(rng.normal(0.0, 100.0, (ROWS, COLS))).astype(np.float32) * np.float32(1e-10)
    z[0, 0] = np.float32(50e-9)
    return z.astype(np.float64)


def _ibw(path, z, angle):
    note = f"FastScanSize: {COLS * DX}\rSlowScanSize: {ROWS * DY}\rScanAngle: {angle}\r"
    write_ibw(path, z.T[:, :, None], (DX, DY), (1e-6, 2e-6), ["HeightTrace"], note)


def _jpk(path, z, angle):
    write_jpk(path, [("height", False, np.round(z / 1e-12).astype(np.int32), 1e-12, 0.0)],
              (COLS * DX, ROWS * DY), (1e-6, 2e-6), theta=math.radians(angle))  # fmt: skip


def _sxm(path, z, angle):
    write_sxm(path, [("Z", "m", z, None)], (COLS * DX, ROWS * DY), (1e-6, 2e-6), angle=angle)


def _wsxm(path, z, angle):
    # WSxM stores the picture turned by 180 deg (vendor_files)
    write_wsxm(path, z[:, ::-1] * 1e9, (COLS * DX * 1e9, ROWS * DY * 1e9), "1 nm",
               control=[f"Angle: {angle}"])  # fmt: skip


# (writer, suffix, the header field the refusal names)
FORMATS = [
    (_ibw, ".ibw", "ScanAngle"),
    (_jpk, ".jpk", "Grid-Theta"),
    (_sxm, ".sxm", "SCAN_ANGLE"),
    (_wsxm, ".stp", "Control / Angle"),
]


@pytest.mark.parametrize("write, suffix, field", FORMATS, ids=[f[1] for f in FORMATS])
@pytest.mark.parametrize("angle", [90.0, 30.0, -45.0])
def test_a_turned_scan_is_refused_naming_the_field_or_read_in_its_own_frame(
    tmp_path, write, suffix, field, angle
):
    z = _image(5)
    straight, turned = tmp_path / f"straight{suffix}", tmp_path / f"turned{suffix}"
    write(straight, z, 0)
    write(turned, z, angle)
    with pytest.raises(ValueError, match=f"turned{suffix}: {field} {angle:g} deg: ") as error:
        load_height_map(turned)
    assert "--scan-frame" in str(error.value)
    reference = load_height_map(straight)
    assert "scan_frame_turned_deg" not in reference.meta
    own = load_height_map(turned, scan_frame=True)
    np.testing.assert_allclose(own.height, reference.height, rtol=1e-12, atol=1e-15)
    assert own.height[0, 0] == own.height.max()  # not turned by the reading
    assert (own.pixel_size_x, own.pixel_size_y) == pytest.approx((DX, DY), rel=1e-9)
    assert (own.origin_x, own.origin_y) == (0.0, 0.0)  # no scanner position claimed
    assert own.meta["scan_frame_turned_deg"] == pytest.approx(angle)
    # a straight scan reads the same with or without the option
    again = load_height_map(straight, scan_frame=True)
    np.testing.assert_array_equal(again.height, reference.height)
    assert (again.origin_x, again.origin_y) == (reference.origin_x, reference.origin_y)


def test_a_turned_spm_scan_is_read_in_its_own_frame_on_request(tmp_path):
    raw = np.arange(ROWS * COLS, dtype=np.int16).reshape(ROWS, COLS)
    write_spm(tmp_path / "straight.spm", [("Height", raw, False)], (1, 1))
    write_spm(tmp_path / "turned.spm", [("Height", raw, False)], (1, 1), rotate=90.0)
    with pytest.raises(ValueError, match="turned.spm: Rotate Ang. 90 deg: .*--scan-frame"):
        load_height_map(tmp_path / "turned.spm")
    own = load_height_map(tmp_path / "turned.spm", scan_frame=True)
    np.testing.assert_array_equal(own.height, load_height_map(tmp_path / "straight.spm").height)
    assert own.meta["scan_frame_turned_deg"] == 90.0


def test_an_unreadable_scan_angle_is_refused_by_name(tmp_path):
    _ibw(tmp_path / "odd.ibw", _image(6), "n/a")
    with pytest.raises(ValueError, match=r"odd.ibw channel 'HeightTrace': the note's ScanAngle"):
        load_height_map(tmp_path / "odd.ibw")


def test_afm_image_lists_and_levels_a_turned_scan_with_scan_frame(tmp_path):
    _sxm(tmp_path / "turned.sxm", _image(7), 90.0)
    out = tmp_path / "level.npz"
    command = [
        sys.executable,
        "-m",
        "afm_bringup.cli",
        "image",
        "level",
        str(tmp_path / "turned.sxm"),
    ]
    refused = subprocess.run([*command, "-o", str(out)], capture_output=True, text=True)
    assert refused.returncode == 2 and "--scan-frame" in refused.stderr and not out.exists()
    done = subprocess.run(
        [*command, "--scan-frame", "-o", str(out)], capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    assert load_height_map(out).meta["scan_frame_turned_deg"] == 90.0
    listed = subprocess.run(
        [
            sys.executable,
            "-m",
            "afm_bringup.cli",
            "image",
            "channels",
            str(tmp_path / "turned.sxm"),
        ],
        capture_output=True,
        text=True,
    )
    assert listed.returncode == 0, listed.stderr
    assert "0: Z (turned 90 deg from the scanner's axes: --scan-frame)" in listed.stdout
