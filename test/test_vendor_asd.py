"""High-speed AFM .asd movies (imaging.vendor_asd, through AFMReader): files of versions 0, 1
and 2 written byte by byte from the documented structure (vendor_writers.write_asd) come back
as the frame asked for, heights in metres from the header's own scaling (closed form: the
bipolar AD range's volts x the channel's nm/V), rows along +y, the scan size over the pixels,
frame time and scan size as metadata; damaged files and wrong choices are refused by name."""

import json
import subprocess
import sys

import numpy as np
import pytest
from vendor_writers import write_asd

from afm_core.imaging.files import count_frames, list_channels, load_height_map

FRAMES, LINES, PIXELS = 3, 10, 14
SIZE_NM = (280, 150)  # x, y scan size: 20 nm by 15 nm pixels
Z_EXT, Z_GAIN, SENSOR = 10.0, 2.0, 3.0  # nm/V, gain, nm/V
AD_VOLTS, LEVELS = 2.5, 4096  # bipolar 2.5 V, 12 bits


def _nm(levels, coefficient):
    """Bipolar conversion: level 0 is +2.5 V, level 4096 would be -2.5 V."""
    return (AD_VOLTS - 2.0 * levels * AD_VOLTS / LEVELS) * coefficient


def _movie(seed=0):
    levels = np.random.default_rng(seed).integers(0, LEVELS, (FRAMES, LINES, PIXELS))
    levels[:, 0, 0] = 0  # the first stored line's first pixel: the top-left corner, highest
    return levels.astype(np.int16)


@pytest.mark.parametrize("version", [0, 1, 2])
def test_each_frame_of_each_channel_in_metres_rows_along_y(tmp_path, version):
    topo, error = _movie(1), _movie(2)
    path = tmp_path / f"movie{version}.asd"
    write_asd(path, version, [("TP", topo), ("ER", error)], SIZE_NM, 62.5, (Z_EXT, Z_GAIN), SENSOR)
    assert list_channels(path) == ["TP", "ER"] and count_frames(path) == FRAMES
    for frame in range(FRAMES):
        m = load_height_map(path, "TP", frame=frame)
        # stored lines run down the picture; the map's row 0 is its bottom line
        expected = _nm(topo[frame], Z_EXT * Z_GAIN)[::-1] * 1e-9
        np.testing.assert_allclose(m.height, expected, rtol=1e-12, atol=1e-21)
        assert m.height[-1, 0] == pytest.approx(AD_VOLTS * Z_EXT * Z_GAIN * 1e-9)  # top-left
        assert (m.pixel_size_x, m.pixel_size_y) == pytest.approx((20e-9, 15e-9))
        assert (m.origin_x, m.origin_y) == (0.0, 0.0)
        assert m.meta["movie_frame"] == frame and m.meta["movie_frames"] == FRAMES
        assert m.meta["frame_time"] == pytest.approx(0.0625)  # 62.5 ms in the file
        assert (m.meta["scan_size_x"], m.meta["scan_size_y"]) == pytest.approx((280e-9, 150e-9))
    er = load_height_map(path, 1, frame=2)  # the second channel's frames follow the first's
    np.testing.assert_allclose(er.height, _nm(error[2], -SENSOR)[::-1] * 1e-9, rtol=1e-12)


def test_a_one_channel_file_and_the_phase_channel(tmp_path):
    write_asd(tmp_path / "one.asd", 1, [("TP", _movie())], SIZE_NM)
    assert list_channels(tmp_path / "one.asd") == ["TP"]
    with pytest.raises(ValueError, match=r"channel 1 does not exist; channels: 0: 'TP'"):
        load_height_map(tmp_path / "one.asd", 1)
    write_asd(tmp_path / "ph.asd", 1, [("TP", _movie()), ("PH", _movie())], SIZE_NM)
    with pytest.raises(ValueError, match=r"'PH' \(phase\) is not a height"):
        load_height_map(tmp_path / "ph.asd", "PH")


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"bits": 14}, "analogue_digital_data_bits_size=14: AFMReader converts 12-bit"),
        ({"frame_header": 40}, "frame_header_length=40: the frame header read is 32 bytes"),
        ({"ad_range": 0x00000005}, "Analogue to digital range hex value 0x5"),
        ({"size_nm": (0, 150)}, r"x_nm=0 \(scan size\) must be > 0 nm"),
    ],
)
def test_headers_the_conversion_cannot_trust_are_refused(tmp_path, change, message):
    kwargs = {"size_nm": SIZE_NM, **change}
    write_asd(tmp_path / "bad.asd", 1, [("TP", _movie())], **kwargs)
    with pytest.raises(ValueError, match=message):
        load_height_map(tmp_path / "bad.asd")


def test_damaged_files_and_frames_that_do_not_exist(tmp_path):
    write_asd(tmp_path / "ok.asd", 0, [("TP", _movie())], SIZE_NM)
    data = (tmp_path / "ok.asd").read_bytes()
    (tmp_path / "short.asd").write_bytes(data[:-5])
    with pytest.raises(ValueError, match=r"truncated: .* 3 frame\(s\) of 1 channel\(s\) need"):
        load_height_map(tmp_path / "short.asd")
    (tmp_path / "v3.asd").write_bytes(b"\x03\0\0\0" + data[4:])
    with pytest.raises(ValueError, match="file version 3 is not read"):
        load_height_map(tmp_path / "v3.asd")
    (tmp_path / "head.asd").write_bytes(data[:40])
    with pytest.raises(ValueError, match="truncated .asd v0 header"):
        load_height_map(tmp_path / "head.asd")
    with pytest.raises(ValueError, match=r"frame 3 does not exist; the file has 3 \(0 to 2\)"):
        load_height_map(tmp_path / "ok.asd", frame=3)
    np.save(tmp_path / "one.npy", np.zeros((2, 2)))
    with pytest.raises(ValueError, match="holds one frame"):
        load_height_map(tmp_path / "one.npy", pixel_size=1e-9, frame=1)


def _particle_movie(centres_px):
    """Levels of a flat movie with one 12 px wide, 30 nm high cap per frame at (x, y) pixels
    of the map (row 0 at the bottom); stored lines run top to bottom."""
    rows, cols = 48, 64
    yy, xx = np.mgrid[0:rows, 0:cols] + 0.5
    frames = []
    for cx, cy in centres_px:
        nm = np.sqrt(np.clip(36.0 - (xx - cx) ** 2 - (yy - cy) ** 2, 0, None)) * 5.0
        # invert the bipolar conversion for this height, then store top line first
        level = np.round((AD_VOLTS - nm / (Z_EXT * Z_GAIN)) * LEVELS / (2 * AD_VOLTS))
        frames.append(level[::-1])
    return np.asarray(frames, dtype=np.int16)


def test_afm_image_reads_the_frame_asked_for(tmp_path):
    centres = [(16.0, 12.0), (40.0, 30.0)]  # pixels; the particle moves between frames
    path = tmp_path / "hs.asd"
    write_asd(path, 1, [("TP", _particle_movie(centres))], (128, 96))  # 2 nm pixels

    def afm(*args):
        command = [sys.executable, "-m", "afm_bringup.cli", "image", *map(str, args)]
        return subprocess.run(command, capture_output=True, text=True, timeout=300)

    listed = afm("channels", path)
    assert listed.returncode == 0, listed.stderr
    assert listed.stdout.split("\n")[:2] == ["0: TP", "2 frames (--frame 0 to 1)"]
    for frame, (cx, cy) in enumerate(centres):
        out = tmp_path / f"marks{frame}.json"
        done = afm("landmarks", path, "--frame", frame, "--json", out)
        assert done.returncode == 0, done.stderr
        (mark,) = json.loads(out.read_text())
        assert abs(mark["x"] - cx * 2e-9) < 1e-9 and abs(mark["y"] - cy * 2e-9) < 1e-9
    refused = afm("landmarks", path, "--frame", 2)
    assert refused.returncode == 2 and len(refused.stderr.strip().splitlines()) == 1
    assert "frame 2 does not exist; the file has 2" in refused.stderr


def test_map_publish_reads_the_frame_then_needs_the_graph(tmp_path):
    path = tmp_path / "hs.asd"
    write_asd(path, 2, [("TP", _particle_movie([(16.0, 12.0), (40.0, 30.0)]))], (128, 96))
    command = [sys.executable, "-m", "afm_bringup.cli", "map", "publish", str(path)]
    bad = subprocess.run([*command, "--frame", "5"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "frame 5 does not exist" in bad.stderr  # as afm image
    # a readable frame gets as far as the graph: without the imaging node it says so
    done = subprocess.run(
        [*command, "--frame", "1", "--timeout", "2"], capture_output=True, text=True, timeout=60
    )
    assert done.returncode != 0 and "afm_imaging" in done.stderr, done.stderr
