"""Damaged input files: every reader a user reaches refuses them with one clean line.

Seeded mutations (truncated, bit-flipped, overwritten with random bytes, random bytes whole) of
a valid file of each kind: height maps (.npz, .npy, .gwy) through `afm image landmarks`, MCAP
recordings through `afm info`, both in-process (afm_bringup.cli.main); simulator
configurations, localization and DAQ calibrations (YAML) through the core loaders the nodes
and `afm calibrate` call, which a node turns into exit status 2 (test_node_parameters). The
assertion for every file: exit status 0 (the damage left a valid file) or 2 with one line on
stderr; no traceback, no hang (each file has a time limit).

MCAP: this checks the command line only (no traceback, no hang, exit 2). That the reader
detects changed message contents (its CRCs) is the recorder's test (issue 30, item 2).
"""

from __future__ import annotations

import contextlib
import signal
import time

import numpy as np
import pytest
import yaml
from cli_runs import run_cli

from afm_core.daq import load_calibration as load_daq_calibration
from afm_core.imaging.files import HeightMap, save_height_map
from afm_core.localization.calibration.model import (
    Calibration,
    load_calibration,
    save_calibration,
)
from afm_core.sim.config import dump_config, load_config

SEED = 30
PER_KIND = 100  # mutated files of each of the 13 kinds: 1300 in all
PER_FILE_LIMIT_S = 10.0  # a reader that takes longer on a 1-40 kB file is hanging
TOTAL_LIMIT_S = 60.0  # the whole test on two loaded cores (4-6 s measured, 8 seeds)


class Hang(BaseException):
    """Not an Exception: a reader's `except Exception` must not turn a hang into a refusal."""


def mutations(data: bytes, rng: np.random.Generator, count: int):
    """(name, bytes): a quarter each truncated, bit-flipped (1-16 bits), a span overwritten
    with random bytes, random bytes of a random length."""
    for k in range(count):
        kind = k % 4
        if kind == 0:
            yield "truncated", data[: int(rng.integers(0, len(data)))]
        elif kind == 1:
            out = bytearray(data)
            for _ in range(int(rng.integers(1, 17))):
                bit = int(rng.integers(0, 8 * len(out)))
                out[bit // 8] ^= 1 << (bit % 8)
            yield "bit-flipped", bytes(out)
        elif kind == 2:
            out = bytearray(data)
            start = int(rng.integers(0, len(out)))
            span = int(rng.integers(1, 65))
            out[start : start + span] = rng.bytes(len(out[start : start + span]))
            yield "overwritten", bytes(out)
        else:
            yield "random", rng.bytes(int(rng.integers(0, 2 * len(data) + 1)))


@contextlib.contextmanager
def time_limit(seconds: float):
    def expire(_signum, _frame):
        raise Hang()

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def run_loader(load, path) -> tuple[int, str]:
    """A core loader as a node uses it: ValueError is the clean refusal (exit 2)."""
    try:
        load(path)
    except ValueError as exc:
        return 2, " ".join(str(exc).split()) + "\n"
    return 0, ""


def seeds(folder) -> dict:
    """kind -> (suffix, valid bytes, how to read a file of that kind)."""
    rng = np.random.default_rng(SEED)
    height = rng.normal(0.0, 1e-9, (24, 24))
    height[8:14, 8:14] += 20e-9  # a particle, so landmarks finds something
    hmap = HeightMap(height, 10e-9, 10e-9, 1e-6, 2e-6, "fuzz")
    save_height_map(folder / "seed.npz", hmap)
    save_height_map(folder / "seed.gwy", hmap)
    np.save(folder / "seed.npy", height)
    (folder / "seed_sim.yaml").write_text(dump_config(load_config()))
    save_calibration(Calibration(), folder / "seed_cal.yaml")
    (folder / "seed_daq.yaml").write_text(
        yaml.safe_dump(
            {
                "x_volts_per_metre": 0.18e6,
                "x_volts_limits": [-10.0, 10.0],
                "x_hysteresis": {"thresholds": [0.0, 1e-6], "weights": [1.0, 0.1]},
            }
        )
    )
    vendor_seeds(folder, height)
    landmarks = ["image", "landmarks"]
    kinds = {
        "npz": (".npz", landmarks, []),
        "gwy": (".gwy", landmarks, []),
        "npy": (".npy", landmarks, ["--pixel-size", "1e-8"]),
        "sim_config": ("_sim.yaml", load_config, None),
        "calibration": ("_cal.yaml", load_calibration, None),
        "daq_calibration": ("_daq.yaml", load_daq_calibration, None),
        **{suffix[1:]: (suffix, landmarks, []) for suffix in VENDOR},
    }
    out = {k: (s, (folder / f"seed{s}").read_bytes(), r, x) for k, (s, r, x) in kinds.items()}
    out["mcap"] = (".mcap", mcap_seed(folder / "seed.mcap"), ["info"], [])
    return out


VENDOR = (".ibw", ".sxm", ".stp", ".jpk", ".spm", ".asd")  # a lab's own scans (issue 31)


def vendor_seeds(folder, height) -> None:
    """The same map in each vendor format the readers take (test/vendor_writers.py)."""
    from vendor_writers import write_asd, write_ibw, write_jpk, write_spm, write_sxm, write_wsxm

    rows, columns = height.shape
    write_ibw(folder / "seed.ibw", height.T[:, :, None], (10e-9, 10e-9), (1e-6, 2e-6), ["Height"])
    size = (columns * 10e-9, rows * 10e-9)
    write_sxm(folder / "seed.sxm", [("Z", "m", height, None)], size, (1.1e-6, 2.1e-6))
    nm = np.round(height / 1e-10)  # 0.1 nm units
    span = f"{float(nm.max() - nm.min()) * 0.1!r} nm"
    write_wsxm(folder / "seed.stp", nm[:, ::-1] * 0.1, (columns * 10, rows * 10), span)
    write_jpk(folder / "seed.jpk", [("height", False, nm, 1e-10, 0.0)], size, (1e-6, 2e-6))
    write_spm(folder / "seed.spm", [("Height", nm, False)], (size[0] * 1e6, size[1] * 1e6))
    # two frames of the height in bipolar 2.5 V levels (20 nm/V: 0.024 nm a level)
    levels = np.round((2.5 - height[::-1] / 20e-9) * 4096 / 5.0).astype(np.int16)
    write_asd(folder / "seed.asd", 1, [("TP", np.stack([levels, levels]))], (240, 240))


def mcap_seed(path) -> bytes:
    from sample_messages import cdr, force_trace, landmarks

    from afm_core.recording import QosDescription, RecordingWriter

    with RecordingWriter(path, chunk_size=4 * 1024) as rec:
        traces = rec.add_channel("/afm/force_trace", "afm_msgs/msg/ForceTrace", [QosDescription()])
        marks = rec.add_channel("/afm/landmarks", "afm_msgs/msg/LandmarkArray", [QosDescription()])
        for i in range(6):
            rec.write(traces, 1_000_000_000 * (i + 1), cdr(force_trace(i)))
            rec.write(marks, 1_000_000_000 * (i + 1) + 1, cdr(landmarks(i)))
    return path.read_bytes()


def test_the_seed_files_are_read(tmp_path):
    """Each valid file is read (exit 0): the mutations start from files the readers accept."""
    for kind, (suffix, data, reader, extra) in seeds(tmp_path).items():
        path = tmp_path / f"valid{suffix}"
        path.write_bytes(data)
        if callable(reader):
            code, err = run_loader(reader, path)
        else:
            code, err = run_cli([*reader, path, *extra])
        assert code == 0, (kind, err)


def test_damaged_files_get_one_clean_line_and_exit_status_2(tmp_path):
    rng = np.random.default_rng(SEED)
    started = time.monotonic()
    outcomes: dict[str, dict[int, int]] = {}
    failures = []
    for kind, (suffix, data, reader, extra) in seeds(tmp_path).items():
        outcomes[kind] = {}
        for k, (how, damaged) in enumerate(mutations(data, rng, PER_KIND)):
            path = tmp_path / f"{kind}-{k}{suffix}"
            path.write_bytes(damaged)
            try:
                with time_limit(PER_FILE_LIMIT_S):
                    if callable(reader):
                        code, err = run_loader(reader, path)
                    else:
                        code, err = run_cli([*reader, path, *extra])
            except Hang:
                failures.append(f"{path.name} ({how}): no answer in {PER_FILE_LIMIT_S} s")
                continue
            except Exception as exc:  # noqa: BLE001 - the point of the test: a traceback
                failures.append(f"{path.name} ({how}): {type(exc).__name__}: {exc}")
                continue
            outcomes[kind][code] = outcomes[kind].get(code, 0) + 1
            lines = err.strip().splitlines()
            if code not in (0, 2) or (code == 2 and len(lines) != 1):
                failures.append(f"{path.name} ({how}): exit {code}, stderr {err!r}")
            path.unlink()
    elapsed = time.monotonic() - started
    total = len(outcomes) * PER_KIND
    assert not failures, f"{len(failures)} of {total}:\n" + "\n".join(failures[:20])
    assert sum(sum(c.values()) for c in outcomes.values()) == total >= 500
    # the damage was seen: most files of every kind were refused, not read as if valid
    for kind, codes in outcomes.items():
        assert codes.get(2, 0) >= PER_KIND // 2, (kind, codes)
    assert elapsed < TOTAL_LIMIT_S, f"{elapsed:.0f} s"


@pytest.mark.parametrize("suffix", [".npz", ".gwy", ".npy", ".mcap"])
def test_a_missing_file_and_a_folder_are_refused_the_same_way(tmp_path, suffix):
    command = ["info"] if suffix == ".mcap" else ["image", "landmarks"]
    extra = ["--pixel-size", "1e-8"] if suffix == ".npy" else []
    for path in (tmp_path / f"missing{suffix}", tmp_path):
        code, err = run_cli([*command, path, *extra])
        assert code == 2 and len(err.strip().splitlines()) == 1, err
