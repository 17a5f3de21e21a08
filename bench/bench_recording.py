"""Recording throughput: afm_core's RecordingWriter ("ours") against a plain mcap Writer.

What is measured
----------------
Two payloads, each a list of ROS 2 messages serialized once up front to CDR bytes, so both
writers write exactly the same bytes:

- scans:  afm_msgs/msg/RasterScan, a 512x512 32FC1 height image (smooth topography with
          particles and measurement noise, metres) and 512 line_start_times, ~1 MiB each;
- traces: afm_msgs/msg/ForceTrace, 0.1 s of 10 kHz samples (1000 per array, 6 float64
          arrays with noise), ~48 kB each; 10 messages = 1 s of 10 kHz data.

- commands: afm_msgs/msg/TipCommand, ~200 B each at 50 Hz: the small messages of a session.

Writers, same compression (zstd) and chunk size (4 MiB):

- ours:  afm_core.recording.RecordingWriter with default settings: `.part` file created
         exclusively, free-space check every 8 MiB, QoS metadata per channel, a rosbag2
         metadata record, flush + fsync at close and a link to the final name; its 1 s
         flush_interval is on the wall clock, so writing faster than real time it hardly ever
         closes a chunk early (a recorder catching up with a burst);
- live:  the same, with the flush_interval (1 s) measured on the recording's clock, i.e. chunks
         closed as a recorder closes them when the messages arrive at their recorded pace (a
         scan every 10 s, a force trace every 0.1 s, a command every 20 ms): the price of
         losing at most 1 s to a kill -9, in time and in file size, is live against ours;
- plain: mcap.writer.Writer on a plain file, `finish()` and nothing else (no fsync: its data
         may still sit in the page cache when the clock stops).

Each case (payload x writer x repetition) runs in a fresh process ('spawn'), so cases are
independent and the case's peak memory is that process's own (VmHWM from /proc; its
ru_maxrss is not usable: a spawned child starts with the parent's). The clock (perf_counter)
runs from writer creation through close()/finish(), fsync included for ours. Writers are
interleaved, the order rotating each repetition (ours, plain, live, then plain, live, ours,
...), after one discarded warm-up round; os.sync() runs before each case, untimed, so no case pays
for the previous one's dirty pages. After every case the file is opened with RecordingReader
and must hold exactly N messages, so a broken writer cannot look fast.

How to read the ratio
---------------------
ratio = ours throughput / plain throughput, the median of the per-pair ratios (a pair is the
two runs of one repetition); live/ours likewise, and the file-size ratio live/ours. 1.00
means no overhead; 0.80 means ours writes at 80 % of plain's speed, i.e. takes 1/0.80 =
1.25x as long. The same ratio "without close()/finish()"
leaves out ours' fsync; the "close s" column is the close()/finish() time alone.

Run: `make bench` (default, < 3 min on 2 cores) or `... bench/bench_recording.py --quick`.
Results: bench/results/recording.json and recording.md (recording-quick.* for --quick).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import resource
import shutil
import statistics
import struct
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from importlib.metadata import version
from pathlib import Path

import numpy as np
from machine import command_line, cpu_model

RESULTS_DIR = Path(__file__).resolve().parent / "results"
CHUNK_SIZE = 4 * 1024 * 1024
WRITERS = ("ours", "plain", "live")
MB = 1e6
MIB = 2**20


@dataclass(frozen=True)
class Payload:
    name: str
    topic: str
    type_name: str
    count: int
    period_ns: int  # log-time spacing between messages
    file: str = ""  # serialized messages, length-prefixed (see save_payload)
    total_bytes: int = 0


@dataclass(frozen=True)
class Case:
    payload: Payload
    writer: str
    repetition: int
    output: str


# -- payloads (parent process only) ---------------------------------------------------------
def smooth_noise(rng: np.random.Generator, n: int, correlation_px: float) -> np.ndarray:
    """n x n gaussian-correlated noise with unit standard deviation."""
    white = rng.standard_normal((n, n))
    k = np.fft.fftfreq(n)
    k2 = k[:, None] ** 2 + np.fft.rfftfreq(n)[None, :] ** 2
    field = np.fft.irfft2(
        np.fft.rfft2(white) * np.exp(-k2 * (np.pi * correlation_px) ** 2), s=(n, n)
    )
    return field / field.std()


def sample_surface(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A substrate (rough, tilted) and particle positions/heights/widths (rows: y, x, h, sigma)."""
    yy, xx = np.mgrid[0:n, 0:n] / n
    substrate = 4e-9 * smooth_noise(rng, n, 25) + 1e-9 * smooth_noise(rng, n, 3)
    substrate += rng.uniform(-5e-9, 5e-9) * xx + rng.uniform(-5e-9, 5e-9) * yy
    particles = np.column_stack(
        [
            rng.uniform(0, n, 6),
            rng.uniform(0, n, 6),
            rng.uniform(20e-9, 150e-9, 6),
            rng.uniform(4, 12, 6),
        ]
    )
    return substrate, particles


def scan_heights(
    rng: np.random.Generator,
    substrate: np.ndarray,
    particles: np.ndarray,
    drift_px: tuple[int, int],
) -> np.ndarray:
    """One scan of a surface: drifted substrate, gaussian particles, 0.2 nm noise;
    ~1e-9..2e-7 m."""
    n = substrate.shape[0]
    height = np.roll(substrate, drift_px, axis=(0, 1))
    yy, xx = np.mgrid[0:n, 0:n]
    for y, x, h, sigma in particles:
        height = height + h * np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2 * sigma**2))
    height += 0.2e-9 * rng.standard_normal((n, n))
    return np.clip(height - height.min() + 1e-9, 1e-9, 2e-7).astype(np.float32)


def stamp(ns: int):
    from builtin_interfaces.msg import Time

    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def make_scans(payload: Payload, seed: int = 1) -> list[bytes]:
    """Scans of a few samples; within one sample the tip pushes particles and the scanner
    drifts."""
    from rclpy.serialization import serialize_message

    from afm_msgs.msg import RasterScan
    from afm_ros.conversions import array_to_image

    rng = np.random.default_rng(seed)
    out = []
    for i in range(payload.count):
        if i % 25 == 0:
            substrate, particles = sample_surface(rng, 512)
        particles[:, :2] += rng.normal(0, 3, (len(particles), 2))  # pushed particles move
        msg = RasterScan()
        msg.header.stamp = stamp(i * payload.period_ns)
        msg.header.frame_id = "afm_scanner"
        heights = scan_heights(rng, substrate, particles, (i % 25 // 5, i % 25 // 3))
        msg.height = array_to_image(heights, msg.header)
        msg.pixel_size_x = msg.pixel_size_y = 2e-6 / 512
        msg.size_x = msg.size_y = 2e-6
        msg.line_period = payload.period_ns * 1e-9 / 512
        msg.line_start_times = (np.arange(512) * msg.line_period).tolist()
        msg.slow_scan_up = True
        msg.mode = "tapping"
        msg.scan_id = i
        out.append(bytes(serialize_message(msg)))
    return out


def trace_signals(rng: np.random.Generator, samples: int, rate: float) -> dict[str, np.ndarray]:
    """Continuous push signals: 0.5 s straight pushes, deflection with load bursts, stick-slip."""
    t = np.arange(samples) / rate
    knots = np.arange(0, samples + 5000, 5000)
    path_x = np.interp(np.arange(samples), knots, rng.uniform(0, 2e-6, len(knots)))
    path_y = np.interp(np.arange(samples), knots, rng.uniform(0, 2e-6, len(knots)))
    z = np.repeat(100e-9 + rng.uniform(-5e-9, 5e-9, len(knots)), 5000)[:samples]
    load = np.convolve(rng.random(samples) < 2e-4, np.hanning(800), mode="same")
    deflection = (
        2e-9
        + 3e-9 * load
        + 2e-11 * np.sin(2 * np.pi * 50 * t)
        + 1e-10 * rng.standard_normal(samples)
    )
    torsion = 1e-4 * ((t * 37.0) % 1.0) * (load > 0.1) + 5e-6 * rng.standard_normal(samples)
    return {
        "commanded_x": path_x + 2e-10 * rng.standard_normal(samples),
        "commanded_y": path_y + 2e-10 * rng.standard_normal(samples),
        "commanded_z": z + 5e-11 * rng.standard_normal(samples),
        "vertical_deflection": deflection,
        "lateral_torsion": torsion,
    }


def make_traces(
    payload: Payload, seed: int = 2, per_message: int = 1000, rate: float = 10_000.0
) -> list[bytes]:
    from array import array

    from rclpy.serialization import serialize_message

    from afm_msgs.msg import ForceTrace

    signals = trace_signals(np.random.default_rng(seed), payload.count * per_message, rate)
    times = array("d", (np.arange(per_message) / rate).tobytes())
    out = []
    for i in range(payload.count):
        part = slice(i * per_message, (i + 1) * per_message)
        msg = ForceTrace()
        msg.header.stamp = stamp(i * payload.period_ns)
        msg.header.frame_id = "afm_scanner"
        msg.times = times
        for field, values in signals.items():
            setattr(msg, field, array("d", np.ascontiguousarray(values[part]).tobytes()))
        msg.normal_spring_constant = 0.2
        msg.lateral_spring_constant = 1e-9
        msg.sample_rate = rate
        msg.task = "push"
        msg.object_id = i // 5
        out.append(bytes(serialize_message(msg)))
    return out


def make_commands(payload: Payload, seed: int = 3) -> list[bytes]:
    """Tip commands of a push session: short contact moves between random points."""
    from rclpy.serialization import serialize_message

    from afm_msgs.msg import TipCommand

    rng = np.random.default_rng(seed)
    out = []
    for i in range(payload.count):
        msg = TipCommand()
        msg.header.stamp = stamp(i * payload.period_ns)
        msg.header.frame_id = "afm_scanner"
        msg.kind = int(rng.integers(0, 5))
        msg.start.x, msg.start.y, msg.end.x, msg.end.y = rng.uniform(0, 100e-6, 4)
        msg.speed = float(rng.uniform(0.1e-6, 5e-6))
        msg.duration = payload.period_ns * 1e-9
        msg.start_voltage = rng.uniform(-10, 10, 3).tolist()
        msg.end_voltage = rng.uniform(-10, 10, 3).tolist()
        out.append(bytes(serialize_message(msg)))
    return out


def save_payload(messages: list[bytes], path: Path) -> int:
    with open(path, "wb") as f:
        for data in messages:
            f.write(struct.pack("<Q", len(data)))
            f.write(data)
    return sum(len(m) for m in messages)


def load_payload(path: str) -> list[bytes]:
    """Read message by message (no whole-file buffer), so memory peaks at the payload itself."""
    out = []
    with open(path, "rb") as f:
        while header := f.read(8):
            out.append(f.read(struct.unpack("<Q", header)[0]))
    return out


def prepare_payloads(counts: dict[str, int], workdir: Path) -> list[Payload]:
    specs = [
        Payload("scans", "/afm/scan", "afm_msgs/msg/RasterScan", counts["scans"], 10 * 10**9),
        Payload("traces", "/afm/force_trace", "afm_msgs/msg/ForceTrace", counts["traces"], 10**8),
        Payload(
            "commands",
            "/afm/tip_command",
            "afm_msgs/msg/TipCommand",
            counts["commands"],
            2 * 10**7,
        ),
    ]
    makers = {"scans": make_scans, "traces": make_traces, "commands": make_commands}
    ready = []
    for spec in specs:
        t0 = time.perf_counter()
        file = workdir / f"{spec.name}.payload"
        total = save_payload(makers[spec.name](spec), file)
        ready.append(Payload(**{**asdict(spec), "file": str(file), "total_bytes": total}))
        print(
            f"payload {spec.name}: {spec.count} messages, {total / MIB:.1f} MiB "
            f"({total / spec.count / 1024:.1f} KiB each), "
            f"built in {time.perf_counter() - t0:.1f} s",
            flush=True,
        )
    return ready


# -- the measured writers (child process) -----------------------------------------------------
def write_ours(path: str, payload: Payload, messages: list[bytes], live: bool = False) -> float:
    """Returns the time spent in close() (summary, metadata, flush, fsync, link). live: the
    flush interval runs on the recording's clock, with the recorder's flush timer."""
    from afm_core.recording import QosDescription, RecordingWriter

    now = [0.0]
    rec = RecordingWriter(path, clock=(lambda: now[0]) if live else time.monotonic)
    channel = rec.add_channel(payload.topic, payload.type_name, [QosDescription()])
    next_poll = 0.0
    for i, data in enumerate(messages):
        now[0] = i * payload.period_ns * 1e-9
        while live and next_poll <= now[0]:  # the recorder's timer, between messages
            rec.flush_if_due()
            next_poll += rec.poll_period
        rec.write(channel, i * payload.period_ns, data)
    t0 = time.perf_counter()
    rec.close()
    return time.perf_counter() - t0


def write_live(path: str, payload: Payload, messages: list[bytes]) -> float:
    return write_ours(path, payload, messages, live=True)


def write_plain(path: str, payload: Payload, messages: list[bytes]) -> float:
    """Returns the time spent in finish() (last chunk, summary, indexes)."""
    from mcap.writer import CompressionType, Writer

    from afm_core.recording import full_message_definition

    with open(path, "wb") as stream:
        writer = Writer(stream, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD)
        writer.start(profile="ros2")
        schema = writer.register_schema(
            payload.type_name, "ros2msg", full_message_definition(payload.type_name).encode()
        )
        channel = writer.register_channel(payload.topic, "cdr", schema, metadata={})
        for i, data in enumerate(messages):
            writer.add_message(
                channel,
                log_time=i * payload.period_ns,
                data=data,
                publish_time=i * payload.period_ns,
            )
        t0 = time.perf_counter()
        writer.finish()
        return time.perf_counter() - t0


def max_rss_kib() -> int:
    """ru_maxrss (KiB). In a spawned child it starts at the parent's RSS: fork copies it, exec
    keeps it."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def proc_status_kib(field: str) -> int:
    """VmRSS (current) or VmHWM (peak since exec or since the last reset_peak_rss) in KiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def reset_peak_rss() -> None:
    """Set VmHWM to the current RSS (Linux >= 4.0), so the next VmHWM is the peak from now on."""
    Path("/proc/self/clear_refs").write_text("5")


def run_case(case: Case) -> dict:
    """Runs in a fresh process: load payload, time one writer, verify the file, delete it."""
    from afm_core.recording import RecordingReader

    write = {"ours": write_ours, "plain": write_plain, "live": write_live}[case.writer]
    messages = load_payload(case.payload.file)
    peak_before = proc_status_kib("VmHWM")
    reset_peak_rss()
    rss_before = proc_status_kib("VmRSS")
    t0 = time.perf_counter()
    close_s = write(case.output, case.payload, messages)
    seconds = time.perf_counter() - t0
    write_peak = proc_status_kib("VmHWM")
    with RecordingReader(case.output) as reader:
        count = reader.message_count
    if count != len(messages):
        raise RuntimeError(
            f"{case.writer}/{case.payload.name}: file holds {count} messages, "
            f"wrote {len(messages)}"
        )
    file_bytes = os.path.getsize(case.output)
    with RecordingReader(case.output) as reader:
        chunks = len(reader.summary.chunk_indexes)
    os.unlink(case.output)
    return {
        "payload": case.payload.name,
        "writer": case.writer,
        "repetition": case.repetition,
        "messages": len(messages),
        "payload_bytes": case.payload.total_bytes,
        "seconds": seconds,
        "close_seconds": close_s,
        "file_bytes": file_bytes,
        "chunks": chunks,
        "messages_per_s": len(messages) / seconds,
        "mb_per_s": case.payload.total_bytes / MB / seconds,
        "compression_ratio": case.payload.total_bytes / file_bytes,
        "rss_before_kib": rss_before,
        "peak_rss_kib": max(peak_before, write_peak),
        "writer_rss_kib": write_peak - rss_before,
        "ru_maxrss_kib": max_rss_kib(),
    }


def run_in_fresh_process(case: Case) -> dict:
    os.sync()  # untimed: start with no dirty pages from the previous case
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        return pool.apply(run_case, (case,))


# -- running and reporting (parent) ----------------------------------------------------------
def pair_order(rep: int) -> tuple[str, ...]:
    """ours, plain, live | plain, live, ours | ...: interleaved, no writer always first."""
    shift = rep % len(WRITERS)
    return WRITERS[shift:] + WRITERS[:shift]


def run_all(payloads: list[Payload], repetitions: int, warmups: int, workdir: Path) -> list[dict]:
    """Repetitions numbered from -warmups; runs with rep < 0 are warm-ups, left out of the
    summary."""
    results = []
    for payload in payloads:
        for rep in range(-warmups, repetitions):
            for writer in pair_order(rep):
                output = str(workdir / f"{payload.name}-{writer}-{rep}.mcap")
                result = run_in_fresh_process(Case(payload, writer, rep, output)) | {
                    "warmup": rep < 0
                }
                label = "warm-up" if rep < 0 else f"rep {rep}"
                print(
                    f"  {payload.name:6} {label:7} {writer:5}: {result['seconds']:6.2f} s "
                    f"(close {result['close_seconds']:.3f} s), {result['mb_per_s']:6.1f} MB/s, "
                    f"peak RSS {result['peak_rss_kib'] / 1024:.0f} MiB",
                    flush=True,
                )
                results.append(result)
    return results


def summarize(results: list[dict]) -> dict:
    results = [r for r in results if not r["warmup"]]
    summary = {}
    for name in dict.fromkeys(r["payload"] for r in results):
        rows = {
            w: [r for r in results if r["payload"] == name and r["writer"] == w] for w in WRITERS
        }
        per_writer = {}
        for writer, runs in rows.items():
            med = lambda key: statistics.median(r[key] for r in runs)  # noqa: E731
            per_writer[writer] = {
                "repetitions": len(runs),
                "messages": runs[0]["messages"],
                "payload_bytes": runs[0]["payload_bytes"],
                "seconds": med("seconds"),
                "close_seconds": med("close_seconds"),
                "messages_per_s": med("messages_per_s"),
                "mb_per_s": med("mb_per_s"),
                "min_seconds": min(r["seconds"] for r in runs),
                "max_seconds": max(r["seconds"] for r in runs),
                "file_bytes": med("file_bytes"),
                "chunks": med("chunks"),
                "compression_ratio": med("compression_ratio"),
                "peak_rss_kib": max(r["peak_rss_kib"] for r in runs),
                "writer_rss_kib": statistics.median(r["writer_rss_kib"] for r in runs),
            }
        pairs = list(zip(rows["ours"], rows["plain"]))  # same repetition = adjacent runs
        ratios = [p["seconds"] / o["seconds"] for o, p in pairs]  # = ours msg/s / plain msg/s
        no_close = [
            (p["seconds"] - p["close_seconds"]) / (o["seconds"] - o["close_seconds"])
            for o, p in pairs
        ]
        live_pairs = list(zip(rows["ours"], rows["live"]))
        live_ratios = [o["seconds"] / v["seconds"] for o, v in live_pairs]
        summary[name] = {
            **per_writer,
            "ratio_ours_over_plain": statistics.median(ratios),
            "pair_ratios": ratios,
            "ratio_ours_over_plain_excluding_close": statistics.median(no_close),
            "ratio_live_over_ours": statistics.median(live_ratios),
            "live_pair_ratios": live_ratios,
            "file_ratio_live_over_ours": per_writer["live"]["file_bytes"]
            / per_writer["ours"]["file_bytes"],
        }
    return summary


def machine_info() -> dict:
    return {
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)),
        "cpu_model": cpu_model(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "load_average_at_start": os.getloadavg(),
        "packages": {p: version(p) for p in ("mcap", "zstandard", "numpy")},
    }


def table(summary: dict) -> list[str]:
    head = (
        "| payload | writer | msgs | payload MB | time s (median) | close s | msg/s | MB/s "
        "| file MB | chunks | compr. | peak RSS MiB | writer +RSS MiB |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, entry in summary.items():
        for writer in WRITERS:
            s = entry[writer]
            lines.append(
                f"| {name} | {writer} | {s['messages']} | {s['payload_bytes'] / MB:.1f} "
                f"| {s['seconds']:.2f} "
                f"({s['min_seconds']:.2f}-{s['max_seconds']:.2f}) | {s['close_seconds']:.3f} "
                f"| {s['messages_per_s']:.0f} | {s['mb_per_s']:.1f} | {s['file_bytes'] / MB:.1f} "
                f"| {s['chunks']:.0f} | {s['compression_ratio']:.2f} "
                f"| {s['peak_rss_kib'] / 1024:.0f} | {s['writer_rss_kib'] / 1024:.0f} |"
            )
    return lines


def ratio_lines(summary: dict) -> list[str]:
    return [
        f"- {name}: ours/plain throughput = **{e['ratio_ours_over_plain']:.3f}** "
        f"(per pair: {', '.join(f'{r:.3f}' for r in e['pair_ratios'])}); "
        f"without close()/finish(): {e['ratio_ours_over_plain_excluding_close']:.3f}; "
        f"live/ours (1 s flush at the recorded pace): throughput "
        f"**{e['ratio_live_over_ours']:.3f}** "
        f"(per pair: {', '.join(f'{r:.3f}' for r in e['live_pair_ratios'])}), "
        f"file size **{e['file_ratio_live_over_ours']:.3f}**"
        for name, e in summary.items()
    ]


def notes(settings: dict) -> list[str]:
    return [
        f"Writers: zstd, {CHUNK_SIZE // MIB} MiB chunks; {settings['repetitions']} repetitions "
        f"each after {settings['warmups']} discarded warm-up round(s), interleaved (ours, plain, "
        "live, then plain, live, ours, ...); live closes a chunk once its oldest message is "
        "0.75 s old on the recording's clock (the 1 s flush_interval); each case in a fresh "
        "spawned process, os.sync() before each case (untimed).",
        "Time = writer creation through close()/finish(); ours includes flush + fsync + link at "
        "close, plain has no fsync (its data may still be in the page cache). 'close s' = "
        "close()/finish() alone.",
        "MB = 1e6 bytes of serialized CDR payload. compr. = payload bytes / file bytes. "
        "Peak RSS = peak of the case's own process (VmHWM), payload held in memory included; "
        "writer +RSS = peak during the timed write minus RSS just before it (the writer's own "
        "memory). (A spawned child's ru_maxrss starts at the parent's RSS, so it is kept in the "
        "JSON only.)",
        "ratio = median over pairs of (ours msg/s / plain msg/s); < 1 means ours is slower. "
        "'without close()/finish()' compares the time before close, i.e. leaves out ours' fsync.",
    ]


def write_reports(report: dict, stem: str) -> tuple[Path, Path]:
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    json_path, md_path = RESULTS_DIR / f"{stem}.json", RESULTS_DIR / f"{stem}.md"
    json_path.write_text(json.dumps(report, indent=2) + "\n")
    m = report["machine"]
    md = [
        f"# Recording throughput ({'quick' if report['settings']['quick'] else 'default'} run)",
        "",
        f"Measured {report['date']} on {m['cpu_count']} CPUs ({m['cpu_model']}), "
        f"Python {m['python']}, {m['platform']}; load average at start "
        f"{', '.join(f'{x:.2f}' for x in m['load_average_at_start'])}.",
        "",
        f"Command: `{command_line()}`",
        "",
        *table(report["summary"]),
        "",
        *ratio_lines(report["summary"]),
        "",
        *(f"- {n}" for n in notes(report["settings"])),
        "- Benchmark process peak RSS (payload building): "
        f"{report['process_peak_rss_kib'] / 1024:.0f} MiB; "
        f"total wall time {report['wall_seconds']:.0f} s.",
        "",
    ]
    md_path.write_text("\n".join(md))
    return json_path, md_path


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--quick", action="store_true", help="smoke run: few messages, 2 repetitions"
    )
    parser.add_argument(
        "--repetitions", type=int, help="runs per writer and payload (default 5, quick 2)"
    )
    parser.add_argument(
        "--warmups", type=int, help="discarded pairs before them (default 1, quick 0)"
    )
    parser.add_argument("--scans", type=int, help="raster scans per run (default 300, quick 20)")
    parser.add_argument(
        "--traces",
        type=int,
        help="force-trace messages per run (default 4000 = 400 s at 10 kHz, quick 200)",
    )
    parser.add_argument(
        "--commands",
        type=int,
        help="tip commands per run (default 20000 = 400 s at 50 Hz, quick 1000)",
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    defaults = (
        {"repetitions": 2, "warmups": 0, "scans": 20, "traces": 200, "commands": 1000}
        if args.quick
        else {"repetitions": 5, "warmups": 1, "scans": 300, "traces": 4000, "commands": 20000}
    )
    settings = {
        k: v if getattr(args, k) is None else getattr(args, k) for k, v in defaults.items()
    }
    settings["quick"] = args.quick
    started, t0 = datetime.now(timezone.utc), time.perf_counter()
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    workdir = Path(
        tempfile.mkdtemp(prefix="run-", suffix=".tmp", dir=RESULTS_DIR)
    )  # same disk; git-ignored
    try:
        payloads = prepare_payloads(
            {k: settings[k] for k in ("scans", "traces", "commands")}, workdir
        )
        results = run_all(payloads, settings["repetitions"], settings["warmups"], workdir)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    report = {
        "date": started.isoformat(timespec="seconds"),
        "machine": machine_info(),
        "settings": settings,
        "process_peak_rss_kib": max_rss_kib(),
        "wall_seconds": time.perf_counter() - t0,
        "summary": summarize(results),
        "runs": results,
    }
    print(
        "\n"
        + "\n".join(
            [*table(report["summary"]), "", *ratio_lines(report["summary"]), "", *notes(settings)]
        )
    )
    paths = write_reports(report, "recording-quick" if args.quick else "recording")
    print(
        f"\nbenchmark process peak RSS {report['process_peak_rss_kib'] / 1024:.0f} MiB; "
        f"wall time {report['wall_seconds']:.0f} s; wrote {paths[0]} and {paths[1]}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
