"""What a lab user may type wrong on the `afm` command line, found by fuzzing the subcommands
that need no running graph (and those that refuse before starting one): each is refused with
exit status 2, one line naming the option and its limit, no traceback and no file left behind.
In-process (afm_bringup.cli.main); nothing here starts a DDS participant or a Dask cluster."""

from __future__ import annotations

import os

import numpy as np
import pytest
from cli_runs import run_cli

from afm_bringup.cli import build_parser
from afm_core.imaging.files import HeightMap, save_height_map


@pytest.fixture(autouse=True)
def same_environment():
    """The ROS commands set the DDS environment of this process (exposure.apply)."""
    saved = dict(os.environ)
    yield
    os.environ.clear()
    os.environ.update(saved)


@pytest.fixture
def image(tmp_path):
    rng = np.random.default_rng(7)
    height = rng.normal(0.0, 1e-9, (24, 24))
    height[8:14, 8:14] += 20e-9
    path = tmp_path / "scan.npz"
    save_height_map(path, HeightMap(height, 10e-9, 10e-9, 1e-6, 2e-6, "fuzz"))
    return path


def run(*argv) -> tuple[int, str]:
    """Exit status and stderr of `afm ARGV` (cli_runs.run_cli)."""
    return run_cli(argv)


def refused(code: int, err: str, *words: str) -> bool:
    last = err.strip().splitlines()[-1] if err.strip() else ""
    return code == 2 and "Traceback" not in err and all(w in last for w in words)


def test_an_option_given_twice_with_two_values_is_refused(image, tmp_path):
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    code, err = run("image", "level", image, "-o", a, "-o", b)
    assert refused(code, err, "-o/--output", "given twice", "give it once"), err
    assert not a.exists() and not b.exists()
    # the same value twice, in two spellings, is one value
    code, err = run("image", "landmarks", image, "--min-height", "10nm", "--min-height", "1e-8")
    assert code == 0, err
    with pytest.raises(SystemExit):
        build_parser().parse_args(["batch", "evaluate", "x", "-o", "o", "--tolerance", "5nm",
                                   "--tolerance", "6nm"])  # fmt: skip


@pytest.mark.parametrize("value", ["-inf", "-nan", "-1GiB"])
def test_a_negative_non_number_reaches_its_option_check(image, value):
    """'-inf' was read as an unknown option: 'expected one argument'."""
    code, err = run("image", "landmarks", image, "--min-height", value)
    assert refused(code, err, "--min-height", repr(value)), err
    assert "expected one argument" not in err


@pytest.mark.parametrize(
    "extra, words",
    [
        # 1e300 Hz: 'SVD did not converge'; 1e-300 Hz: '(34, Numerical result out of range)'
        (["--line-rate", "1e300"], ["--line-rate=1e+300", "within [0.0001, 100000] Hz"]),
        (["--line-rate", "1e-300"], ["--line-rate=1e-300", "within [0.0001, 100000] Hz"]),
        # a day at 1 Hz asked for 116 GiB; 1e300 s: 'Python int too large to convert to C long'
        (["--line-rate", "1", "--gap", "1e5"], ["--gap=100000.0", "at most 10 times", "240 s"]),
        (["--line-rate", "1", "--gap", "1e300"], ["--gap=1e+300", "at most 10 times"]),
    ],
    ids=["rate-1e300", "rate-1e-300", "gap-a-day", "gap-1e300"],
)
def test_drift_refuses_times_beyond_its_fit(image, tmp_path, extra, words):
    output = tmp_path / "d.npz"
    code, err = run("image", "drift", image, image, *extra, "-o", output)
    assert refused(code, err, *words), err
    assert not output.exists()


def test_a_pixel_size_below_a_picometre_is_refused(tmp_path):
    npy = tmp_path / "heights.npy"
    np.save(npy, np.zeros((8, 8)))
    code, err = run("image", "landmarks", npy, "--pixel-size", "2e-9nm")
    assert refused(code, err, "--pixel-size", "at least 1e-12 m"), err


def test_an_output_that_cannot_be_written_is_named_and_not_left(image, tmp_path, monkeypatch):
    from afm_core.imaging import cli as image_cli

    output = tmp_path / "levelled.npz"

    def half_written(path, hmap):  # a read-only folder or a full disk, half way through
        with open(path, "wb") as handle:
            handle.write(b"PK\x03\x04")
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(image_cli, "save_height_map", half_written)
    code, err = run("image", "level", image, "-o", output)
    assert refused(code, err, f"-o {output}", "cannot write it", "Permission denied"), err
    assert not output.exists()


def test_a_landmarks_json_interrupted_is_not_left(image, tmp_path, monkeypatch):
    from afm_core.imaging import cli as image_cli

    target = tmp_path / "marks.json"

    def full_disk(rows, handle, **kwargs):
        handle.write("[")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(image_cli.json, "dump", full_disk)
    code, err = run("image", "landmarks", image, "--json", target)
    assert refused(code, err, "No space left"), err
    assert not target.exists()


@pytest.mark.parametrize(
    "argv, words",
    [
        (["map", "publish", "f.npz", "--timeout", "nan"], ["--timeout", "must be above 0"]),
        (["map", "publish", "f.npz", "--timeout", "-1"], ["--timeout", "must be above 0"]),
        (["map", "publish", "f.npz", "--scan-id", "-1"], ["--scan-id", "[0, 4294967295]"]),
        (["map", "publish", "f.npz", "--line-rate", "1e-300"], ["--line-rate", "0.0001"]),
        (["map", "publish", "f.npz", "--pixel-size", "1e-300"], ["--pixel-size", "1e-12 m"]),
        (["push", "--particle", "-5", "--goal", "0", "0"], ["--particle", "[0, 2147483647]"]),
        (["push", "--at", "0", "0", "--goal", "0", "0", "--timeout", "inf"], ["must be finite"]),
        (["calibrate", "-o", "c.yaml", "--seed", "-5"], ["--seed", "-1 for the configuration"]),
        (["batch", "push", "--seeds", "0", "-o", "o", "--goal-distance", "0"], ["above 0"]),
    ],
)
def test_values_refused_before_anything_starts(argv, words, capsys):
    with pytest.raises(SystemExit) as stopped:
        build_parser().parse_args(argv)
    err = capsys.readouterr().err
    assert stopped.value.code == 2 and all(w in err.splitlines()[-1] for w in words), err


def test_launch_refuses_a_log_dir_that_is_a_file_before_any_node(tmp_path):
    """It was a FileExistsError traceback from Graph's mkdir."""
    log = tmp_path / "log.txt"
    log.write_text("")
    code, err = run("launch", "--nodes", "teleop", "--log-dir", log)
    assert refused(code, err, f"--log-dir {log}", "cannot use it"), err
    code, err = run("launch", "--nodes", "bogus")  # was exit status 1
    assert refused(code, err, "--nodes ['bogus']", "expected names from"), err


def test_scan_checks_its_save_file_before_the_scan(tmp_path):
    """A missing folder was found only after the scan (a traceback); each refusal is status 2."""
    for save, words in (
        (tmp_path / "missing" / "s.npz", ["--save", "does not exist"]),
        (tmp_path / "s.png", ["--save", "expected a name ending in .npz"]),
        (tmp_path, ["--save", "a folder"]),
    ):
        code, err = run("scan", "--origin", "0", "0", "--size", "1um", "1um", "--save", save)
        assert refused(code, err, *words), err


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--strategy", "centre"], ["--strategy: montecarlo does not use it (only push)"]),
        (["--mode", "direct"], ["--mode: montecarlo does not use it"]),
        (["--model", "m.yaml"], ["--model: montecarlo does not use it"]),
        (["--scheduler", "nonsense"], ["--scheduler 'nonsense'", "tcp://HOST:PORT"]),
    ],
)
def test_batch_refuses_options_before_any_cluster(tmp_path, extra, words):
    output = tmp_path / "out"
    code, err = run("batch", "montecarlo", "--seeds", "0", "-o", output, "--workers", "1", *extra)
    assert refused(code, err, *words), err
    assert not output.exists()  # the scheduler's refusal left results.csv


def test_batch_reads_a_shared_file_once_before_the_items(tmp_path):
    """A calibration that is no YAML failed every seed, each with the worker's traceback."""
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1\n")
    output = tmp_path / "out"
    code, err = run("batch", "localize", "--seeds", "0", "-o", output, "--calibration", bad)
    assert refused(code, err, "is not valid YAML"), err
    assert not output.exists()
    afile = tmp_path / "afile"
    afile.write_text("")
    code, err = run("batch", "localize", "--seeds", "0", "-o", afile, "--workers", "1")
    assert refused(code, err, f"--output {afile}", "a file; name a folder"), err


@pytest.mark.parametrize("value", ["creep.step=nan", "motion_noise.distances=1e-7,inf"])
def test_calibrate_refuses_a_non_finite_setting_before_the_instrument(tmp_path, value):
    """It ran the experiments before it and wrote a file with nothing measured (exit 1)."""
    output = tmp_path / "c.yaml"
    code, err = run("calibrate", "-o", output, "--set", value)
    assert refused(code, err, "--set", "must be finite"), err
    assert not output.exists()


def test_channels_of_another_format_renamed_npz_says_so_without_numpys_pickle_hint(tmp_path):
    """numpy's message for it invites loading the file as a pickle, which is never safe."""
    from afm_core.imaging.files import list_channels

    renamed = tmp_path / "scan.npz"
    renamed.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    with pytest.raises(ValueError, match="not a .npz archive.*another format renamed") as error:
        list_channels(renamed)
    assert "pickle" not in str(error.value)
