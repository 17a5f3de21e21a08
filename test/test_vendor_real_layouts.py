"""Layout features of real lab files (the JPK and WSxM samples AFMReader tests with, probed by
hand and compared with AFMReader's and Gwyddion's readings), replicated here by the writers of
vendor_writers.py: the lab files themselves are not part of the repository."""

import math
import warnings

import numpy as np
import pytest
from vendor_writers import write_ibw, write_jpk, write_sxm, write_wsxm

from afm_core.imaging.files import list_channels, load_height_map

ROWS, COLS = 8, 12
# the real NanoWizard height channel: metres per count and metres, of its default slot
JPK_MULTIPLIER, JPK_OFFSET = -1.1577216212539286e-15, 2.486188249421139e-06


def _counts(low: int, high: int, seed: int) -> np.ndarray:
    """Integers spanning exactly low..high, the highest at the bottom-left corner."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(low + 1, high, (ROWS, COLS))
    counts[0, 0], counts[-1, -1] = high, low
    return counts


def test_jpk_reads_the_default_slot_of_the_instruments_slot_chain(tmp_path):
    """A NanoWizard chains four slots (raw, volts, nominal, calibrated: the default, last),
    writes Grid-Reflect 0 on page 0 and the retrace pages first; its heights are the default
    slot's raw * multiplier + offset (AFMReader's sum for its sample, to the last digit)."""
    trace = _counts(-(2**30), 2**30, 1)
    retrace = _counts(-(2**30), 2**30, 2)
    path = tmp_path / "scan.jpk"
    write_jpk(path, [("height", True, retrace, JPK_MULTIPLIER, JPK_OFFSET),
                     ("height", False, trace, JPK_MULTIPLIER, JPK_OFFSET)],
              (COLS * 1.277e-9, ROWS * 1.277e-9), (2.584e-6, 1.623e-6), theta=-0.0,
              reflect=0, chain=True)  # fmt: skip
    assert list_channels(path) == ["height_retrace", "height_trace"]
    hmap = load_height_map(path, "height_trace")
    np.testing.assert_allclose(hmap.height, trace * JPK_MULTIPLIER + JPK_OFFSET, rtol=1e-15)
    assert hmap.height[0, 0] == hmap.height.min()  # first stored row at the bottom
    assert (hmap.pixel_size_x, hmap.pixel_size_y) == pytest.approx((1.277e-9, 1.277e-9))
    assert (hmap.origin_x, hmap.origin_y) == (2.584e-6, 1.623e-6)


@pytest.mark.parametrize("theta", [math.pi / 2, 3 * math.pi / 2, -math.pi / 2, math.pi, 0.3])
def test_jpk_turned_grid_is_refused_or_read_in_its_own_frame(tmp_path, theta):
    """The real sample's grid is turned by exactly pi/2. JPK's convention for the turn (its
    sense, and the corner Grid-x0/-y0 name) is not documented where it could be checked, and
    the sample fits two readings 180 deg apart: it is not put in the scanner frame, but read
    in its own on request, as Gwyddion and AFMReader show it."""
    path = tmp_path / "turned.jpk"
    raw = _counts(-1000, 1000, 3)
    write_jpk(path, [("height", False, raw, JPK_MULTIPLIER, JPK_OFFSET)],
              (COLS * 1e-9, ROWS * 1e-9), (2.584e-6, 1.623e-6), theta=theta)  # fmt: skip
    assert list_channels(path) == ["height_trace"]
    degrees = f"{math.degrees(theta):.6g}"
    with pytest.raises(ValueError, match=f"turned.jpk: Grid-Theta {degrees} deg: ") as error:
        load_height_map(path)
    assert "afm image --scan-frame" in str(error.value)
    own = load_height_map(path, scan_frame=True)
    np.testing.assert_allclose(own.height, raw * JPK_MULTIPLIER + JPK_OFFSET, rtol=1e-15)
    assert (own.origin_x, own.origin_y) == (0.0, 0.0)


def test_jpk_mirrored_grid_is_refused(tmp_path):
    """Grid-Reflect was not read at all: a mirrored grid came in as if it were not."""
    path = tmp_path / "mirrored.jpk"
    write_jpk(path, [("height", False, _counts(-1000, 1000, 4), JPK_MULTIPLIER, JPK_OFFSET)],
              (COLS * 1e-9, ROWS * 1e-9), (0.0, 0.0), reflect=1)  # fmt: skip
    with pytest.raises(ValueError, match="mirrored.jpk: Grid-Reflect 1: a mirrored scan grid"):
        load_height_map(path)


def test_wsxm_scan_saved_as_doubles_and_as_counts_reads_the_same(tmp_path):
    """WSxM saved one scan twice: .stp doubles in nm and .top 'short' DAC counts whose range is
    Z Amplitude (4.53125 nm over 232 counts), sizes in um written with the latin-1 micro sign,
    heights far from 0 (-55.6 .. -51.1 nm). Both read the same absolute heights (AFMReader
    rebases .top to 0 and reads Z Amplitude as its integer part, 4)."""
    counts = _counts(-2848, -2616, 5)
    nm = counts * (4.53125 / 232)
    control = ["Angle: 0", "X Offset: -2697.9 nm", "Y Offset: 1342.13 nm", "Z Gain: 2"]
    for suffix, stored, kind in ((".stp", nm, "double"), (".top", counts, "short")):
        path = tmp_path / f"scan{suffix}"
        write_wsxm(path, stored[:, ::-1], (2, 2), "4.53125 nm", kind, xy_unit="\u00b5m",
                   control=control)  # fmt: skip
        assert b"X Amplitude: 2 \xb5m\r\n" in path.read_bytes()
        hmap = load_height_map(path)
        np.testing.assert_allclose(hmap.height, nm * 1e-9, rtol=1e-12)
        assert hmap.height[0, 0] == hmap.height.max()  # bottom-left: rows along +y
        assert hmap.height.min() == pytest.approx(-2848 * 4.53125 / 232 * 1e-9, rel=1e-12)
        assert (hmap.pixel_size_x, hmap.pixel_size_y) == pytest.approx((2e-6 / COLS, 2e-6 / ROWS))


@pytest.mark.parametrize(
    "values_nm, z_amplitude",
    [
        (np.full((ROWS, COLS), -57.5), "0 nm"),  # flat: no range to stretch (read as 0 m)
        (_counts(-19468, -5073, 6) * 4.150e-3, "59.7449 nm"),  # Z Amplitude rounded
    ],
)
def test_wsxm_doubles_are_heights_in_the_unit_of_z_amplitude(tmp_path, values_nm, z_amplitude):
    """Doubles were stretched so their range was Z Amplitude, as Gwyddion read them until
    2.66 corrected it: a flat image became 0 m and the header's rounding reached the data."""
    path = tmp_path / "scan.stp"
    write_wsxm(path, values_nm[:, ::-1], (500, 500), z_amplitude, "double")
    np.testing.assert_allclose(load_height_map(path).height, values_nm * 1e-9, rtol=1e-14)


def _signalling_nan(path, offset: int, order: str) -> None:
    data = bytearray(path.read_bytes())
    data[offset : offset + 4] = (0x7F800001).to_bytes(4, order)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("suffix", [".sxm", ".stp", ".ibw"])
def test_a_signalling_nan_is_refused_as_a_bad_line_without_a_numpy_warning(tmp_path, suffix):
    """A damaged value that is a signalling NaN made numpy warn 'invalid value encountered in
    cast' on stderr before the refusal (found by test_fuzz_files with warnings as errors)."""
    image = np.arange(ROWS * COLS, dtype=np.float64).reshape(ROWS, COLS) * 1e-10
    path = tmp_path / f"scan{suffix}"
    if suffix == ".sxm":
        write_sxm(path, [("Z", "m", image, None)], (1e-6, 1e-6), (0.0, 0.0))
        _signalling_nan(path, path.read_bytes().index(b"\x1a\x04") + 2, "big")
    elif suffix == ".stp":
        write_wsxm(path, image * 1e9, (100, 100), "1 nm", "float")
        _signalling_nan(path, path.read_bytes().index(b"[Header end]\r\n") + 14, "little")
    else:
        write_ibw(path, image.T[:, :, None], (1e-9, 1e-9), (0.0, 0.0), ["Height"])
        _signalling_nan(path, 64 + 320, "little")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=f"scan{suffix}.*1 line.* NaN or infinite"):
            load_height_map(path)
