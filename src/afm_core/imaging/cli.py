"""`afm image ...`: the imaging algorithms on a lab's own files, no ROS needed.

    afm image drift SCAN0 SCAN90 --line-rate 1 -o corrected.npz
    afm image tip IMAGE --tip-size 41 [--threshold auto|consensus|book|2.5nm] -o tip.npz
    afm image reconstruct IMAGE --tip tip.npz -o surface.npz
    afm image landmarks IMAGE [--min-height 10nm] [--json landmarks.json]
    afm image level IMAGE [--method plane|median|poly2] [--mask auto|none] -o levelled.npz
    afm image channels FILE

Files: .npz (ours), .gwy (Gwyddion), .npy (give --pixel-size), and vendors' scans read only:
.ibw (Asylum), .jpk (JPK), .spm (Bruker), .sxm (Nanonis), .stp/.top (WSxM). Every step takes
--level METHOD to level its input first (a raw scan's tilt and line offsets would otherwise
look like features).
Output never overwrites.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from afm_core import checks
from afm_core.imaging.files import (
    HeightMap,
    count_frames,
    list_channels,
    load_height_map,
    mask_note,
    save_height_map,
)
from afm_core.imaging.levelling import level, parse_method
from afm_core.imaging.vendor_common import length_scale
from afm_core.instrument import RasterScanData


def level_method(text: str) -> str:
    """argparse type of --level / --method: none, plane, median, poly2 or a chain a+b."""
    if text == "none":
        return text
    try:
        parse_method(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def _load(args, path) -> HeightMap:
    """The image at `path`, levelled by --level (with --level-mask) when asked."""
    if str(path).lower().endswith(".npy") and args.pixel_size is None:
        raise ValueError(
            f"{path}: a .npy holds only heights (origin 0); give --pixel-size (e.g. 2nm), or "
            "save the scan as .npz or .gwy (afm scan --save F.npz keeps pixel size and origin)"
        )
    hmap = load_height_map(
        path,
        args.channel,
        args.pixel_size,
        args.frame,
        args.height_unit,
        scan_frame=args.scan_frame,
    )
    note = mask_note(hmap, str(path))
    if note:
        print(f"afm image {args.image_command}: warning: {note}", file=sys.stderr)
    if args.level != "none":
        mask = None if args.level_mask == "none" else "auto"
        hmap.height, _ = level(hmap.height, args.level, mask)
    return hmap


# Lines per second of a lab's scan: a line every few hours to a high-speed AFM's 100 kHz. Beyond,
# the drift fit's times overflow (1e-300 Hz) or its least squares do not converge (1e300 Hz).
LINE_RATE_RANGE = (1e-4, 1e5)
# the 90 deg scan's start at most this many 0 deg scan times after the 0 deg scan's start
MAX_GAP_SCANS = 10
# m: a picometre, far below an atom; a smaller pixel is a unit given twice (2e-9nm)
SMALLEST_PIXEL = 1e-12


def check_line_rate(option: str, rate: float) -> float:
    """`rate` (Hz) when within LINE_RATE_RANGE; else ValueError naming `option` and the range."""
    low, high = LINE_RATE_RANGE
    if not (math.isfinite(rate) and low <= rate <= high):
        raise ValueError(f"{option}={rate}: must be finite and within [{low:g}, {high:g}] Hz")
    return rate


def line_rate_type(option: str):
    """argparse type of a line rate in Hz, refused outside LINE_RATE_RANGE."""

    def convert(text: str) -> float:
        try:
            return check_line_rate(option, float(text))
        except ValueError as exc:
            if option not in str(exc):  # float()'s own words name no option
                exc = ValueError(f"{option}={text!r}: expected a number (Hz)")
            raise argparse.ArgumentTypeError(str(exc)) from None

    return convert


def pixel_size_type(length):
    """argparse type of --pixel-size: a length as `length` reads it, at least SMALLEST_PIXEL."""

    def convert(text: str) -> float:
        try:
            value = length.parse(text, "--pixel-size")
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        if not value >= SMALLEST_PIXEL:
            raise argparse.ArgumentTypeError(
                f"--pixel-size={text!r}: must be at least {SMALLEST_PIXEL:g} m (1pm)"
            )
        return value

    return convert


def raster_scan_of(
    hmap: HeightMap,
    angle: float = 0.0,
    frame_up: bool = True,
    line_rate: float = 1.0,
    start: float = 0.0,
    mode: str = "tapping",
) -> RasterScanData:
    """A height map as the driver's scan record (`afm map publish`, `afm image drift`): lines
    `1 / line_rate` s apart, in frame order, from `start`."""
    lines = hmap.height.shape[0] if angle == 0.0 else hmap.height.shape[1]
    order = np.arange(lines) if frame_up else np.arange(lines)[::-1]
    starts = np.empty(lines)
    starts[order] = np.arange(lines) / line_rate
    return RasterScanData(
        height=hmap.height,
        pixel_size_x=hmap.pixel_size_x,
        pixel_size_y=hmap.pixel_size_y,
        origin_x=hmap.origin_x,
        origin_y=hmap.origin_y,
        scan_angle_deg=angle,
        slow_scan_up=frame_up,
        line_period=1.0 / line_rate,
        line_start_times=starts,
        start_time=start,
        mode=mode,
    )


def _gap(text: str):
    """--gap: seconds, or "auto" (the gap the images imply)."""
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: seconds or 'auto'") from None


def _report_timing(timing, gap_given: bool) -> None:
    """The timing check's findings on stderr (the corrected map is written regardless)."""
    for text in timing.notes:
        print(f"afm image drift: note: {text}", file=sys.stderr)
    for text in timing.warnings:
        if not gap_given:
            # the default gap is a count of line periods, so a wrong --line-rate cannot cause
            # this (every time scales alike): the scan did not start right after
            text = (
                f"--gap: {timing.gap_assumed:.4g} s assumed (the 90 deg scan right after the 0 "
                f"deg one), the images imply {timing.gap_implied:.4g} +- {timing.gap_error:.2g}"
                " s; the drift fitted with the assumed gap is biased (give --gap, or --gap auto)"
            )
        else:
            text = f"--gap / --line-rate: {text}"
        print(f"afm image drift: warning: {text}", file=sys.stderr)


def cmd_drift(args) -> int:
    from afm_core.imaging.drift_compensation import compensate_pair

    check_line_rate("--line-rate", args.line_rate)
    if isinstance(args.gap, float) and not math.isfinite(args.gap):
        raise ValueError(f"--gap={args.gap}: must be finite (s), or auto")
    first = _load(args, args.scan0)
    second = _load(args, args.scan90)
    lines0 = first.height.shape[0]
    given = isinstance(args.gap, float)
    gap = args.gap if given else lines0 / args.line_rate
    if given and not gap >= lines0 / args.line_rate:
        # the tool times the 0 deg scan first; one tip cannot take two scans at once
        raise ValueError(
            f"--gap={args.gap} s: the 90 deg scan must start after the 0 deg one ends "
            f"({lines0} lines at --line-rate={args.line_rate} Hz: >= "
            f"{lines0 / args.line_rate:.4g} s from the start of the 0 deg scan); --gap auto "
            "takes the gap the images imply"
        )
    if given and gap > MAX_GAP_SCANS * lines0 / args.line_rate:
        # the drift spline has a knot every few lines over the whole span, its normal matrix
        # the square of that: a day's gap at 1 Hz asked for 100 GiB (or never finished)
        raise ValueError(
            f"--gap={args.gap} s: at most {MAX_GAP_SCANS} times the 0 deg scan's "
            f"{lines0 / args.line_rate:.4g} s ({lines0} lines at --line-rate={args.line_rate} Hz),"
            f" i.e. <= {MAX_GAP_SCANS * lines0 / args.line_rate:.4g} s: a pair this far apart "
            "cannot be fitted as one drift; take the 90 deg scan sooner after the 0 deg one"
        )

    def compensate(gap: float):
        return compensate_pair(
            raster_scan_of(first, 0.0, not args.down0, args.line_rate, 0.0),
            raster_scan_of(second, 90.0, not args.down90, args.line_rate, gap),
            order=args.order,
        )

    result = compensate(gap)
    if args.gap == "auto":
        if result.timing.checked:
            # the check's implied gap hardly depends on the assumed one: one refit suffices
            gap = result.timing.gap_implied
            print(
                f"afm image drift: --gap auto: {gap:.4g} +- {result.timing.gap_error:.2g} s "
                "implied by the images",
                file=sys.stderr,
            )
            result = compensate(gap)
        else:
            print(
                "afm image drift: --gap auto: the images cannot tell the gap; used right "
                "after the 0 deg scan",
                file=sys.stderr,
            )
    _report_timing(result.timing, given)
    save_height_map(
        args.output,
        HeightMap(
            result.corrected,
            first.pixel_size_x,
            first.pixel_size_y,
            first.origin_x,
            first.origin_y,
            title="drift-corrected",
        ),
    )
    vx, vy = result.velocity
    print(
        f"drift velocity ({vx * 1e9:.4f}, {vy * 1e9:.4f}) nm/s; {len(result.feature_offsets)} "
        f"feature regions; gap {gap:.4g} s; {result.seconds:.2f} s; wrote {args.output}"
    )
    return 0


def _quietly(function, *args, **kwargs):
    """Call with the guard's Python warnings silenced: the commands print the result's own
    warnings list to stderr instead (once each)."""
    from afm_core.imaging.tip_guard import TipGuardWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TipGuardWarning)
        return function(*args, **kwargs)


def _warn(command: str, texts) -> None:
    for text in texts:
        print(f"afm image {command}: warning: {text}", file=sys.stderr)


def cmd_tip(args) -> int:
    from afm_core.imaging.tip_estimation import estimate_tip

    image = _load(args, args.image)
    if image.pixel_size_x != image.pixel_size_y:
        raise ValueError(
            f"{args.image}: blind tip estimation needs square pixels "
            f"({image.pixel_size_x:.3e} x {image.pixel_size_y:.3e} m)"
        )
    threshold = args.threshold  # a rule's name, or metres (threshold_type)
    estimate = _quietly(
        estimate_tip,
        image.height,
        args.tip_size,
        threshold=threshold,
        pixel_size=image.pixel_size_x,
    )
    # reconstruct reads these back from a .npz (a .gwy drops them: it then falls back)
    layers = {"uncertainty": estimate.uncertainty, "unconstrained": estimate.unconstrained}
    save_height_map(
        args.output,
        HeightMap(
            estimate.tip, image.pixel_size_x, image.pixel_size_y, title="tip", layers=layers
        ),
    )
    print(
        f"tip {args.tip_size}x{args.tip_size}: threshold {estimate.threshold * 1e9:.3f} nm, "
        f"{estimate.iterations} iterations, {estimate.seconds:.2f} s; wrote {args.output}"
    )
    print(estimate.constraint.summary(image.pixel_size_x))
    notes = list(estimate.warnings)
    if Path(args.output).suffix.lower() == ".gwy":
        notes.append(
            "a .gwy tip keeps no uncertainty or unconstrained mask; `afm image reconstruct` "
            "will fall back to judging the tip alone (write .npz to keep them)"
        )
    _warn("tip", notes)
    return 0


def cmd_reconstruct(args) -> int:
    from afm_core.imaging.tip_guard import check_reconstruction

    image = _load(args, args.image)
    if str(args.tip).lower().endswith(".npy") and args.pixel_size is None:
        raise ValueError(
            f"--tip {args.tip}: a .npy holds only heights; give --pixel-size (the tip must be on "
            "the image's grid) or write the tip as .npz (afm image tip does)"
        )
    # the image's --height-unit is not the tip's: a tip estimated in metres eroding an image
    # given in nm (or the reverse) flattened it by 1e9 without a word
    tip = load_height_map(
        args.tip,
        pixel_size=args.pixel_size,
        height_unit=args.tip_height_unit,
        unit_option="--tip-height-unit",
    )
    for axis in ("x", "y"):
        tip_pixel = getattr(tip, f"pixel_size_{axis}")
        image_pixel = getattr(image, f"pixel_size_{axis}")
        # pixel sizes are ~1e-9 m: compare relatively only (np.isclose's default atol of 1e-8
        # would call any two pixel sizes equal)
        if not math.isclose(tip_pixel, image_pixel, rel_tol=1e-6):
            raise ValueError(
                f"--tip pixel size in {axis} {tip_pixel * 1e9:.4g} nm differs from the image's "
                f"{image_pixel * 1e9:.4g} nm: erosion needs the tip on the image's grid "
                "(estimate the tip from an image at this pixel size, or resample one of them)"
            )
    started = time.perf_counter()
    check = _quietly(
        check_reconstruction,
        image.height,
        tip.height,
        tip.layers.get("uncertainty"),
        pixel_size=image.pixel_size_x,
        origin=(image.origin_x, image.origin_y),
    )
    surface = check.reconstruction
    save_height_map(
        args.output,
        HeightMap(
            surface,
            image.pixel_size_x,
            image.pixel_size_y,
            image.origin_x,
            image.origin_y,
            title="reconstructed",
        ),
    )
    print(
        f"eroded by the {tip.height.shape[0]}x{tip.height.shape[1]} tip in "
        f"{time.perf_counter() - started:.2f} s; wrote {args.output}"
    )
    _warn("reconstruct", check.warnings)
    return 0


def cmd_landmarks(args) -> int:
    from afm_core.imaging.landmarks import extract_landmarks

    image = _load(args, args.image)
    marks = extract_landmarks(
        image.height,
        image.pixel_size_x,
        image.pixel_size_y,
        image.origin_x,
        image.origin_y,
        min_height=args.min_height,
    )
    frame = image.meta.get("frame_id", "")
    print(
        f"{len(marks)} landmarks in {args.image}; positions in "
        + (f"its frame {frame}" if frame else "the file's coordinates")
        + f" (the area from ({image.origin_x * 1e9:.1f}, {image.origin_y * 1e9:.1f}) nm, "
        f"{image.size_x * 1e9:.1f} x {image.size_y * 1e9:.1f} nm)"
    )
    for m in marks:
        sx, sy = np.sqrt(np.diag(m.covariance))
        print(
            f"  {m.id:3d} {m.kind:6s} at ({m.x * 1e9:10.1f}, {m.y * 1e9:10.1f}) nm  sigma "
            f"({sx * 1e9:.1f}, {sy * 1e9:.1f}) nm  height {m.height * 1e9:.1f} nm"
        )
    if args.json:
        rows = [
            {
                "id": m.id,
                "kind": m.kind,
                "x": m.x,
                "y": m.y,
                "covariance": np.asarray(m.covariance).tolist(),
                "radius": m.radius,
                "height": m.height,
                "length": m.length,
                "orientation": m.orientation,
            }
            for m in marks
        ]
        with open(args.json, "x") as handle:  # never overwrite
            json.dump(rows, handle, indent=2)
        print(f"wrote {args.json} (SI units)")
    return 0


def cmd_level(args) -> int:
    image = load_height_map(
        args.image,
        args.channel,
        args.pixel_size,
        args.frame,
        args.height_unit,
        scan_frame=args.scan_frame,
    )
    mask = None if args.mask == "none" else "auto"
    levelled, used = level(image.height, args.method, mask)
    keeps_mask = Path(args.output).suffix.lower() == ".npz"
    layers = {"feature_mask": used.astype(np.uint8)} if keeps_mask else {}
    save_height_map(
        args.output,
        HeightMap(
            levelled,
            image.pixel_size_x,
            image.pixel_size_y,
            image.origin_x,
            image.origin_y,
            title=f"{image.title} levelled ({args.method})".strip(),
            layers=layers,
            meta=dict(image.meta),
        ),
    )
    background = levelled[~used] if (~used).any() else levelled
    print(
        f"levelled by {args.method}: {used.mean() * 100:.1f} % of the pixels masked as features; "
        f"background rms {np.std(background) * 1e9:.3f} nm, range "
        f"{np.ptp(levelled) * 1e9:.2f} nm; wrote {args.output}"
    )
    return 0


def _turn_of(path, channel, refusal: ValueError) -> tuple[float | None, ValueError]:
    """A channel refused in the scanner frame: its turn if its scan's own frame reads it, or
    the reason it cannot be read even there (a phase channel's unit says more than its turn)."""
    try:
        own = load_height_map(path, channel, scan_frame=True)
    except ValueError as exc:
        return None, exc
    return own.meta.get("scan_frame_turned_deg"), refusal


def cmd_channels(args) -> int:
    # each channel is read, not only listed: a truncated file's header lists its channels
    # as well as a whole one's, and "channels" is how a user checks a file before using it
    readable = 0
    for number, title in enumerate(list_channels(args.image)):
        try:
            load_height_map(args.image, number)
        except ValueError as exc:
            turn, reason = _turn_of(args.image, number, exc)
            if turn is None:
                print(f"{number}: {title} (cannot be used: {reason})")
                continue
            print(f"{number}: {title} (turned {turn:g} deg from the scanner's axes: --scan-frame)")
            readable += 1
            continue
        readable += 1
        print(f"{number}: {title}")
    frames = count_frames(args.image)
    if frames > 1:
        print(f"{frames} frames (--frame 0 to {frames - 1})")
    if not readable:
        raise ValueError(f"{args.image}: no channel can be read as heights")
    return 0


MIN_HEIGHT_HELP = "features lower than this are ignored (m, or with a unit; default 10nm)"
FRAME_HELP = "which frame of a high-speed .asd movie (default 0; afm image channels counts them)"
PIXEL_SIZE_HELP = "for .npy files: pixel size (m, or with a unit: 2nm); other formats carry theirs"
HEIGHT_UNIT_HELP = "for .npy files: the heights' unit (m, um, nm, pm, angstrom; default m)"


def height_unit(text: str) -> float:
    """argparse type of --height-unit: metres per stored value."""
    try:
        return length_scale(text, "--height-unit")
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def threshold_type(length):
    """argparse type of --threshold: a rule's name, or a length as `length` reads it."""

    def convert(text: str):
        from afm_core.imaging.tip_thresholds import RULES

        if text in RULES:
            return text
        try:
            value = length.parse(text, "--threshold")
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"{exc}; or one of {', '.join(RULES)}") from None
        if value < 0:
            raise argparse.ArgumentTypeError(f"--threshold={text!r}: must be >= 0")
        return value

    return convert


def _add_drift(sub, levelling) -> None:
    """The `drift` subcommand (add_subcommands)."""
    p = sub.add_parser(
        "drift",
        help="correct thermal drift from a 0 deg / 90 deg scan pair",
        description=(
            "Thermal-drift compensation from a 0/90 deg pair of the same area (book ch. 3)."
        ),
    )
    p.add_argument("scan0", help="0 deg scan (rows = fast lines)")
    p.add_argument("scan90", help="90 deg scan of the same area (columns = fast lines)")
    p.add_argument(
        "--line-rate",
        type=line_rate_type("--line-rate"),
        required=True,
        help="lines per second of both scans (Hz)",
    )
    p.add_argument("--down0", action="store_true", help="the 0 deg scan was frame-down")
    p.add_argument("--down90", action="store_true", help="the 90 deg scan was frame-down")
    p.add_argument(
        "--gap",
        type=_gap,
        help=(
            "s from the start of the 0 deg scan to the 90 deg one (default: right after it), "
            "or auto: the gap the images imply"
        ),
    )
    p.add_argument(
        "--order", type=int, default=1, choices=[1, 2], help="offset-vector order (default 1)"
    )
    p.add_argument("-o", "--output", required=True, help="corrected map (.npz or .gwy)")
    levelling(p)
    p.set_defaults(image_func=cmd_drift)


def add_subcommands(image_parser: argparse.ArgumentParser, length) -> None:
    """Register `drift`, `tip`, `reconstruct`, `landmarks`, `level`, `channels`; `length` parses
    '10nm'-style values."""
    sub = image_parser.add_subparsers(dest="image_command", required=True, metavar="STEP")

    def common(p):
        p.add_argument(
            "--channel", default=0, help="channel: index or title (default 0; afm image channels)"
        )
        p.add_argument("--frame", type=int, default=0, help=FRAME_HELP)
        p.add_argument("--pixel-size", type=pixel_size_type(length), help=PIXEL_SIZE_HELP)
        p.add_argument("--height-unit", type=height_unit, help=HEIGHT_UNIT_HELP)
        p.add_argument(
            "--scan-frame",
            action="store_true",
            help="read a vendor scan turned from the scanner's axes (scan angle, Grid-Theta) "
            "in its own frame: fast axis along x, origin 0, positions not the scanner's",
        )

    def levelling(p):
        common(p)
        p.add_argument(
            "--level",
            type=level_method,
            default="none",
            help="level the input first: plane, median (line offsets), poly2 (line bows), or "
            "several in order joined by + (median+plane+median); default none",
        )
        p.add_argument(
            "--level-mask",
            choices=("auto", "none"),
            default="auto",
            help="auto (default): leave features out of the levelling fit; none: fit all pixels",
        )

    _add_drift(sub, levelling)

    p = sub.add_parser(
        "tip", help="blind tip estimation", description="Blind tip estimation (book ch. 4)."
    )
    p.add_argument("image")
    p.add_argument("--tip-size", type=int, default=21, help="tip window, odd pixels (default 21)")
    p.add_argument(
        "--threshold",
        default="auto",
        type=threshold_type(length),
        help="denoising threshold (m, or with a unit: 2.5nm), or a rule: auto (default), "
        "consensus (for a characteriser far sharper than the tip), book",
    )
    p.add_argument(
        "-o", "--output", required=True, help="tip (.npz or .gwy), apex 0 at the centre"
    )
    levelling(p)
    p.set_defaults(image_func=cmd_tip)

    p = sub.add_parser("reconstruct", help="erode an image by a tip (remove tip broadening)")
    p.add_argument("image")
    p.add_argument("--tip", required=True, help="tip file from `afm image tip`")
    p.add_argument(
        "--tip-height-unit",
        type=height_unit,
        help="for a .npy tip: its heights' unit (default m; --height-unit is the image's)",
    )
    p.add_argument("-o", "--output", required=True)
    levelling(p)
    p.set_defaults(image_func=cmd_reconstruct)

    p = sub.add_parser("landmarks", help="particles and tubes with centre and covariance")
    p.add_argument("image")
    p.add_argument("--min-height", type=length, default=10e-9, help=MIN_HEIGHT_HELP)
    p.add_argument("--json", help="also write the landmarks to this new JSON file")
    levelling(p)
    p.set_defaults(image_func=cmd_landmarks)

    p = sub.add_parser(
        "level",
        help="level a raw scan: plane, median line alignment or polynomial rows",
        description=(
            "Level a scan as before any analysis: the plane (tilt), each line's median "
            "(line-to-line offsets) or each line's quadratic (bow), fitted to the background "
            "only (features found by a threshold at a 1e-3 false-alarm rate of the noise)."
        ),
    )
    p.add_argument("image")
    p.add_argument(
        "--method",
        type=level_method,
        default="plane",
        help="plane, median, poly2, or several in order joined by + (default plane)",
    )
    p.add_argument(
        "--mask",
        choices=("auto", "none"),
        default="auto",
        help="auto (default): leave features out of the fit; none: fit every pixel",
    )
    p.add_argument(
        "-o", "--output", required=True, help="levelled map (.npz keeps the feature mask, .gwy)"
    )
    common(p)
    p.set_defaults(image_func=cmd_level)

    p = sub.add_parser("channels", help="list a file's channels (index: title)")
    p.add_argument("image")
    p.set_defaults(image_func=cmd_channels, channel=0)


def run(args) -> int:
    if isinstance(args.channel, str) and args.channel.isdigit():
        args.channel = int(args.channel)
    outputs = {}  # option -> the new file it names
    finished, error = False, None
    try:
        if getattr(args, "output", None):
            outputs["-o"] = checks.new_file("-o", args.output, (".npz", ".gwy"))
        if getattr(args, "json", None):
            outputs["--json"] = checks.new_file("--json", args.json)
        code = args.image_func(args)
        finished = True
        return code
    except (ValueError, OSError, ImportError) as exc:
        error = exc
        print(f"afm image {args.image_command}: {_named(exc, outputs)}", file=sys.stderr)
        return 2
    finally:
        # refused, failed or interrupted: what it began is incomplete; a file that appeared
        # meanwhile (FileExistsError: another program's) is not ours to remove
        if not finished and not isinstance(error, FileExistsError):
            _remove_new(outputs)


def _named(exc: BaseException, outputs: dict) -> str:
    """An error writing an output, with the option that names the file (the OS names the file
    only, and /readonly/x.npz said nothing of -o)."""
    if isinstance(exc, OSError) and exc.filename is not None:
        for option, path in outputs.items():
            if Path(exc.filename) == path:
                return f"{option} {path}: cannot write it: {exc.strerror or exc}"
    return str(exc)


def _remove_new(outputs: dict) -> None:
    """The outputs a failed command began: checks.new_file made sure none existed before, so a
    file there now is this run's and incomplete."""
    for path in outputs.values():
        try:
            path.unlink(missing_ok=True)
        except OSError:
            pass
