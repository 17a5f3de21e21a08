"""User image files (afm_core.imaging.files): .npz (native), .npy and Gwyddion .gwy."""

import shutil
import subprocess
import sys

import gwyfile
import numpy as np
import pytest
from gwyfile.objects import GwyContainer, GwyDataField

from afm_core.imaging.files import (
    HeightMap,
    ImageFileNotFound,
    list_channels,
    load_height_map,
    save_height_map,
)
from afm_core.imaging.landmarks import extract_landmarks


def sample_map(title="topography", ny=30, nx=40, seed=0) -> HeightMap:
    rng = np.random.default_rng(seed)
    height = rng.normal(0.0, 2e-9, (ny, nx))
    height[0, :] += 50e-9  # row 0 (the bottom, smallest y) stands out
    return HeightMap(
        height, pixel_size_x=2.5e-9, pixel_size_y=4e-9, origin_x=12e-6, origin_y=-3e-6, title=title
    )


def assert_same(a: HeightMap, b: HeightMap):
    np.testing.assert_array_equal(a.height, b.height)
    assert a.height.dtype == np.float64
    for name in ("pixel_size_x", "pixel_size_y", "origin_x", "origin_y"):
        assert getattr(a, name) == pytest.approx(getattr(b, name), rel=1e-12, abs=0)
    assert a.title == b.title


def write_gwy(path, fields: dict):
    """A .gwy file made with gwyfile directly, as another program would: {title: GwyDataField}."""
    container = GwyContainer()
    for number, (title, field) in enumerate(fields.items()):
        container[f"/{number}/data"] = field
        container[f"/{number}/data/title"] = title
    container.tofile(str(path))


# -- .npz ------------------------------------------------------------------------------------


def test_npz_round_trip(tmp_path):
    original = sample_map()
    path = tmp_path / "scan.npz"
    save_height_map(path, original)
    assert_same(load_height_map(path), original)
    assert_same(load_height_map(str(path), channel="topography"), original)
    assert list_channels(path) == ["topography"]


def test_saving_never_overwrites(tmp_path):
    path = tmp_path / "scan.npz"
    save_height_map(path, sample_map(seed=1))
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="already exists"):
        save_height_map(path, sample_map(seed=2))
    assert path.read_bytes() == before
    gwy = tmp_path / "scan.gwy"
    save_height_map(gwy, sample_map())
    with pytest.raises(FileExistsError, match="not overwriting"):
        save_height_map(gwy, sample_map())


def test_npy_needs_the_pixel_size(tmp_path):
    path = tmp_path / "plain.npy"
    height = np.random.default_rng(4).normal(0, 1e-9, (16, 24)).astype(np.float32)
    np.save(path, height)
    with pytest.raises(ValueError, match="pixel_size"):
        load_height_map(path)
    hmap = load_height_map(path, pixel_size=3e-9)
    np.testing.assert_array_equal(hmap.height, height.astype(np.float64))
    assert (hmap.pixel_size_x, hmap.pixel_size_y, hmap.origin_x, hmap.origin_y) == (
        3e-9,
        3e-9,
        0.0,
        0.0,
    )
    assert hmap.title == "plain"
    with pytest.raises(ValueError, match="cannot hold the pixel size"):
        save_height_map(tmp_path / "out.npy", hmap)


# -- .gwy ------------------------------------------------------------------------------------


def test_gwy_round_trip_with_several_channels(tmp_path):
    maps = [sample_map("Height", seed=5), sample_map("Height retrace", seed=6)]
    path = tmp_path / "scan.gwy"
    save_height_map(path, maps)
    assert list_channels(path) == ["Height", "Height retrace"]
    assert_same(load_height_map(path), maps[0])
    assert_same(load_height_map(path, channel=1), maps[1])
    assert_same(load_height_map(path, channel="Height retrace"), maps[1])
    single = tmp_path / "one.gwy"
    save_height_map(single, maps[0])
    assert_same(load_height_map(single, channel="Height"), maps[0])


def test_gwy_rows_go_top_to_bottom_and_ours_bottom_to_top(tmp_path):
    """Gwyddion's first data row is the top of its picture; our row 0 is the bottom (origin_y).
    What we write, Gwyddion shows with our row 0 at the bottom; what it holds at the top of the
    picture comes to us as the last row (largest y)."""
    hmap = sample_map()
    path = tmp_path / "rows.gwy"
    save_height_map(path, hmap)
    field = gwyfile.load(str(path))["/0/data"]
    np.testing.assert_array_equal(field.data[-1], hmap.height[0])
    np.testing.assert_array_equal(field.data[0], hmap.height[-1])
    assert field["si_unit_xy"]["unitstr"] == "m" and field["si_unit_z"]["unitstr"] == "m"
    assert field["xreal"] == pytest.approx(40 * 2.5e-9) and field["yreal"] == pytest.approx(
        30 * 4e-9
    )
    assert (field["xoff"], field["yoff"]) == (12e-6, -3e-6)

    picture = np.zeros((20, 30))
    picture[2, 5] = 7.0  # near the top-left corner of the Gwyddion picture
    other = tmp_path / "other.gwy"
    write_gwy(
        other, {"Z": GwyDataField(picture, xreal=3e-7, yreal=2e-7, si_unit_xy="m", si_unit_z="nm")}
    )
    loaded = load_height_map(other)
    row, col = np.unravel_index(np.argmax(loaded.height), loaded.height.shape)
    assert (row, col) == (20 - 1 - 2, 5)  # high y in our frame
    assert loaded.height[row, col] == pytest.approx(7e-9)


@pytest.mark.parametrize(
    "unit, scale",
    [("nm", 1e-9), ("m", 1.0), ("um", 1e-6), ("\u00b5m", 1e-6), ("pm", 1e-12), ("\u00c5", 1e-10)],
)
def test_gwy_z_units_are_converted_to_metres(tmp_path, unit, scale):
    values = (np.arange(12.0).reshape(3, 4) + 1.0) * 1e-9 / scale  # 1-12 nm in `unit`
    path = tmp_path / "units.gwy"
    write_gwy(
        path,
        {
            "Height": GwyDataField(
                values, xreal=4.0, yreal=3.0, xoff=1.0, yoff=2.0, si_unit_xy="um", si_unit_z=unit
            )
        },
    )
    hmap = load_height_map(path)
    np.testing.assert_allclose(hmap.height, values[::-1] * scale, rtol=1e-12)
    assert hmap.pixel_size_x == pytest.approx(1e-6) and hmap.pixel_size_y == pytest.approx(1e-6)
    assert hmap.origin_x == pytest.approx(1e-6) and hmap.origin_y == pytest.approx(2e-6)
    assert hmap.title == "Height"


def test_gwy_channel_by_title_and_missing_channels_listed(tmp_path):
    path = tmp_path / "multi.gwy"
    write_gwy(
        path,
        {
            "Amplitude": GwyDataField(
                np.ones((4, 4)), xreal=1e-6, yreal=1e-6, si_unit_xy="m", si_unit_z="V"
            ),
            "Height": GwyDataField(
                np.full((4, 4), 5.0), xreal=1e-6, yreal=1e-6, si_unit_xy="m", si_unit_z="nm"
            ),
        },
    )
    assert list_channels(path) == ["Amplitude", "Height"]
    assert np.all(load_height_map(path, channel="Height").height == pytest.approx(5e-9))
    with pytest.raises(
        ValueError, match=r"'Phase' does not exist; channels: 0: 'Amplitude', 1: 'Height'"
    ):
        load_height_map(path, channel="Phase")
    with pytest.raises(ValueError, match="channel 2 does not exist.*'Amplitude'.*'Height'"):
        load_height_map(path, channel=2)
    with pytest.raises(ValueError, match="'V' is not a length"):
        load_height_map(path, channel="Amplitude")


def test_gwy_channel_index_is_the_position_not_gwyddions_number(tmp_path):
    container = GwyContainer()
    for number, value in ((3, 1.0), (7, 2.0)):
        container[f"/{number}/data"] = GwyDataField(
            np.full((2, 3), value), xreal=3e-9, yreal=2e-9, si_unit_xy="m", si_unit_z="m"
        )
        container[f"/{number}/data/title"] = f"ch{number}"
    path = tmp_path / "gaps.gwy"
    container.tofile(str(path))
    assert list_channels(path) == ["ch3", "ch7"]
    assert load_height_map(path, channel=1).height[0, 0] == 2.0


def test_gwy_bad_content_is_rejected(tmp_path):
    nan = np.ones((3, 3))
    nan[1, 1] = np.nan
    path = tmp_path / "nan.gwy"
    write_gwy(
        path, {"Height": GwyDataField(nan, xreal=1e-6, yreal=1e-6, si_unit_xy="m", si_unit_z="m")}
    )
    with pytest.raises(ValueError, match="NaN"):
        load_height_map(path)
    no_unit = tmp_path / "nounit.gwy"
    write_gwy(
        no_unit, {"Height": GwyDataField(np.ones((3, 3)), xreal=1e-6, yreal=1e-6, si_unit_xy="m")}
    )
    with pytest.raises(ValueError, match="no height .*unit"):
        load_height_map(no_unit)
    junk = tmp_path / "junk.gwy"
    junk.write_bytes(b"this is not a gwyddion file")
    with pytest.raises(ValueError, match="not a Gwyddion"):
        load_height_map(junk)
    truncated = tmp_path / "truncated.gwy"
    save_height_map(tmp_path / "whole.gwy", sample_map())
    truncated.write_bytes((tmp_path / "whole.gwy").read_bytes()[:200])
    with pytest.raises(ValueError, match="malformed"):
        load_height_map(truncated)
    with pytest.raises(ValueError, match="disagrees"):
        load_height_map(tmp_path / "whole.gwy", pixel_size=1e-9)


def test_a_gwy_channel_s_mask_is_kept_and_named_not_applied(tmp_path):
    """Gwyddion's importers fill pixels that held no data and mask them; a .sxm with those
    lines is refused, the same scan saved by Gwyddion was read without a word."""
    from afm_core.imaging.files import GWYDDION_MASK, mask_note

    stored = np.random.default_rng(2).normal(0, 1e-9, (8, 6))
    marked = np.zeros((8, 6))
    marked[:3] = 1.0  # Gwyddion's top three rows: our last three
    container = GwyContainer()
    container["/0/data"] = GwyDataField(stored, xreal=6e-8, yreal=8e-8, si_unit_xy="m",
                                        si_unit_z="m")  # fmt: skip
    container["/0/data/title"] = "Z (forward)"
    container["/0/mask"] = GwyDataField(marked, xreal=6e-8, yreal=8e-8)
    container.tofile(str(tmp_path / "aborted.gwy"))
    hmap = load_height_map(tmp_path / "aborted.gwy")
    np.testing.assert_array_equal(hmap.layers[GWYDDION_MASK], marked[::-1].astype(np.uint8))
    assert "mask over 18 of 48 pixels; it is not applied" in mask_note(hmap, "aborted.gwy")
    done = subprocess.run([sys.executable, "-m", "afm_bringup.cli", "image", "landmarks",
                           str(tmp_path / "aborted.gwy")], capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    assert done.returncode == 0 and "Gwyddion mask over 18 of 48" in done.stderr, done.stderr
    assert mask_note(sample_map(), "x") == ""


@pytest.mark.skipif(shutil.which("gwyddion") is None, reason="Gwyddion itself is not installed")
def test_gwyddion_itself_reads_what_we_write(tmp_path):
    """Gwyddion loads our file and writes it again as its own; that reads back the same."""
    maps = [sample_map("Height", seed=8), sample_map("Phase-free height", seed=9)]
    ours, theirs = tmp_path / "ours.gwy", tmp_path / "theirs.gwy"
    save_height_map(ours, maps)
    run = subprocess.run(
        ["gwyddion", "--no-log-to-file", "--convert-to-gwy=" + str(theirs), str(ours)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0 and theirs.is_file(), run.stderr
    assert list_channels(theirs) == ["Height", "Phase-free height"]
    for number, original in enumerate(maps):
        assert_same(load_height_map(theirs, channel=number), original)


def test_a_clear_error_without_gwyfile(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "gwyfile", None)  # import gwyfile now fails
    with pytest.raises(ImportError, match="pip install gwyfile"):
        save_height_map(tmp_path / "x.gwy", sample_map())
    assert not (tmp_path / "x.gwy").exists()


# -- errors common to all formats --------------------------------------------------------------


def test_unknown_suffix_and_missing_file(tmp_path):
    with pytest.raises(ValueError, match="unknown image file suffix '.tif'"):
        load_height_map(tmp_path / "scan.tif")
    with pytest.raises(ValueError, match="unknown image file suffix"):
        save_height_map(tmp_path / "scan.png", sample_map())
    with pytest.raises(ImageFileNotFound, match="no such image file") as caught:
        load_height_map(tmp_path / "absent.gwy")
    assert isinstance(caught.value, ValueError) and isinstance(caught.value, FileNotFoundError)
    with pytest.raises(ValueError, match="no such image file"):
        list_channels(tmp_path / "absent.npz")


def test_non_finite_data_is_rejected(tmp_path):
    bad = sample_map()
    bad.height[3, 4] = np.inf
    with pytest.raises(ValueError, match="NaN or infinite"):
        save_height_map(tmp_path / "bad.npz", bad)
    with pytest.raises(ValueError, match="NaN or infinite"):
        save_height_map(tmp_path / "bad.gwy", bad)
    assert not (tmp_path / "bad.npz").exists() and not (tmp_path / "bad.gwy").exists()
    height = np.zeros((4, 4))
    height[0, 0] = np.nan
    np.save(tmp_path / "nan.npy", height)
    with pytest.raises(ValueError, match="NaN"):
        load_height_map(tmp_path / "nan.npy", pixel_size=1e-9)
    np.savez(tmp_path / "nan.npz", height=height, pixel_size_x=1e-9, pixel_size_y=1e-9)
    with pytest.raises(ValueError, match="NaN"):
        load_height_map(tmp_path / "nan.npz")


def test_bad_maps_and_archives_are_rejected_by_name(tmp_path):
    with pytest.raises(ValueError, match="pixel_size_y"):
        save_height_map(tmp_path / "a.npz", HeightMap(np.zeros((3, 3)), 1e-9, 0.0))
    with pytest.raises(ValueError, match="2-D"):
        save_height_map(tmp_path / "b.npz", HeightMap(np.zeros(3), 1e-9, 1e-9))
    with pytest.raises(ValueError, match="one height map"):
        save_height_map(tmp_path / "c.npz", [sample_map(), sample_map()])
    np.savez(tmp_path / "nosize.npz", height=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="pixel_size_x or pixel_size_y"):
        load_height_map(tmp_path / "nosize.npz")
    assert load_height_map(tmp_path / "nosize.npz", pixel_size=2e-9).pixel_size_y == 2e-9
    with pytest.raises(ValueError, match="channel 1 does not exist"):
        load_height_map(tmp_path / "nosize.npz", channel=1, pixel_size=2e-9)
    # another format renamed: numpy's own message suggested allow_pickle, i.e. loading a pickle
    save_height_map(tmp_path / "scan.gwy", sample_map())
    (tmp_path / "renamed.npz").write_bytes((tmp_path / "scan.gwy").read_bytes())
    with pytest.raises(ValueError, match=r"renamed.npz: not a .npz archive") as refused:
        load_height_map(tmp_path / "renamed.npz")
    assert "pickle" not in str(refused.value)


def test_landmarks_are_where_they_were_after_a_gwy_round_trip(tmp_path):
    """The frame survives the file: a particle near the top of the area stays at the same
    (x, y)."""
    px = 4e-9
    rows, cols = np.indices((80, 100))
    x, y = 5e-6 + (cols + 0.5) * px, 7e-6 + (rows + 0.5) * px
    r, cx, cy = 40e-9, 5e-6 + 130e-9, 7e-6 + 230e-9
    d2 = (x - cx) ** 2 + (y - cy) ** 2
    height = np.where(d2 < r * r, r + np.sqrt(np.clip(r * r - d2, 0, None)), 0.0)
    hmap = HeightMap(height, px, px, 5e-6, 7e-6, "Height")
    path = tmp_path / "particle.gwy"
    save_height_map(path, hmap)
    loaded = load_height_map(path)
    before = extract_landmarks(hmap.height, px, px, hmap.origin_x, hmap.origin_y)
    after = extract_landmarks(
        loaded.height, loaded.pixel_size_x, loaded.pixel_size_y, loaded.origin_x, loaded.origin_y
    )
    assert len(before) == len(after) == 1
    assert after[0].x == pytest.approx(cx, abs=0.5e-9) and after[0].y == pytest.approx(
        cy, abs=0.5e-9
    )
    assert (after[0].x, after[0].y) == pytest.approx((before[0].x, before[0].y), abs=1e-15)


def test_how_the_scan_was_taken_survives_npz_and_gwy(tmp_path):
    """`afm scan --save` keeps the angle, frame and time beside pixel size and origin."""
    original = sample_map()
    original.meta = {
        "frame_id": "afm_scanner",
        "stamp": 1764236400.123456,
        "scan_angle_deg": 90.0,
        "scan_id": 7,
    }
    for name in ("scan.npz", "scan.gwy"):
        save_height_map(tmp_path / name, original)
        back = load_height_map(tmp_path / name)
        assert_same(back, original)
        assert back.meta == original.meta, name  # numbers to the last bit, 7 as 7.0
    bad = sample_map()
    bad.meta = {"stamp": float("nan")}
    with pytest.raises(ValueError, match="meta stamp"):
        save_height_map(tmp_path / "bad.npz", bad)


SPHERES_NM = np.array([[0.0, 1.5, 20.0], [3.0, 0.5, 12.0], [0.2, 7.0, 1.0]])  # heights in nm


def test_heights_not_in_metres_are_refused_with_the_fix_and_an_npy_unit_is_applied(tmp_path):
    """A map in nm read as metres is 1e9 times too tall: everything after it is nonsense in
    silence, so the loader refuses a span beyond any AFM's z range and names the fix."""
    npy = tmp_path / "nm.npy"
    np.save(npy, SPHERES_NM)
    with pytest.raises(ValueError, match=r"heights span 20 m, .*--height-unit nm"):
        load_height_map(npy, pixel_size=2e-9)
    loaded = load_height_map(npy, pixel_size=2e-9, height_unit=1e-9)
    np.testing.assert_allclose(loaded.height, SPHERES_NM * 1e-9, rtol=1e-12)

    npz = tmp_path / "nm.npz"
    save_height_map(npz, HeightMap(SPHERES_NM * 1e-9, 2e-9, 2e-9))
    assert load_height_map(npz).height.max() == pytest.approx(20e-9)
    with pytest.raises(ValueError, match="height_unit is for .npy files only"):
        load_height_map(npz, height_unit=1e-9)

    gwy = tmp_path / "counts.gwy"  # raw counts stored as metres by a careless exporter
    field = GwyDataField(SPHERES_NM * 1000, xreal=6e-9, yreal=6e-9, si_unit_xy="m", si_unit_z="m")
    write_gwy(gwy, {"Z": field})
    with pytest.raises(ValueError, match=r"heights span 2e\+04 m, .*not read as metres"):
        load_height_map(gwy)


@pytest.mark.parametrize("bad", [2.0, 1e-3])
def test_a_pixel_size_no_afm_has_is_refused_naming_the_limit(tmp_path, bad):
    npy = tmp_path / "m.npy"
    np.save(npy, SPHERES_NM * 1e-9)
    with pytest.raises(ValueError, match=rf"pixel_size={bad!r} m: must be <= 0.0001 m"):
        load_height_map(npy, pixel_size=bad)
    assert load_height_map(npy, pixel_size=1e-4).pixel_size_x == 1e-4  # the limit itself


def test_an_unfinished_scan_is_refused_with_the_rows_to_keep(tmp_path):
    """A scan aborted at row 7 of 10 stores its last rows as NaN; one more pixel is lost at
    row 2: the refusal names the empty rows and the longest run of complete ones."""
    height = np.zeros((10, 8))
    height[7:] = np.nan
    height[2, 3] = np.inf
    path = tmp_path / "aborted.npy"
    np.save(path, height)
    with pytest.raises(ValueError, match=r"25 NaN .* 3 of 10 rows hold no value .* e\.g\. 3-6"):
        load_height_map(path, pixel_size=1e-9)
