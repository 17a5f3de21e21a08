"""`afm scan`: one raster image through the driver, with the lines done as it goes, saved
with what is needed to read it again (pixel size, origin, angle, frame, time)."""

from __future__ import annotations

import sys
from pathlib import Path

from afm_bringup.cli_errors import refuse
from afm_bringup.units import length_type, nm, positive_type
from afm_core import checks

SAVE_SUFFIXES = (".npz", ".gwy", ".npy")


def cmd_scan(args):
    from afm_bringup.commander import AfmCommander, AfmError
    from afm_ros.conversions import image_msg_to_array

    if args.save:
        try:  # before the scan: a file that cannot be written was found only after it
            checks.new_file("--save", args.save)
            if Path(args.save).suffix.lower() not in SAVE_SUFFIXES:
                raise ValueError(
                    f"--save {args.save}: expected a name ending in .npz (pixel size, origin, "
                    "angle, frame and time kept), .gwy (Gwyddion, the same) or .npy (heights only)"
                )
        except ValueError as exc:
            return refuse("scan", exc)
    with AfmCommander() as afm:
        try:
            scan = afm.scan(
                origin=args.origin,
                size=args.size,
                pixels=args.pixels,
                angle_deg=args.angle,
                frame_up=not args.frame_down,
                line_rate=args.line_rate,
                mode=args.mode,
                progress=True,
            )
        except AfmError as exc:
            sys.exit(f"afm scan: {exc}")
        except KeyboardInterrupt:  # the commander has asked the driver to stop the scan
            print("afm scan: cancelled; the driver stops the scan, nothing saved", file=sys.stderr)
            return 130
    height = image_msg_to_array(scan.height)
    print(
        f"scan {scan.scan_id}: {height.shape[1]} x {height.shape[0]} px, "
        f"{nm(scan.size_x)} x {nm(scan.size_y)}, heights {nm(float(height.min()))} .. "
        f"{nm(float(height.max()))}"
    )
    if args.save:
        try:
            save_scan(scan, height, args.save)
        except (OSError, ValueError) as exc:  # a read-only folder, a full disk
            if not isinstance(exc, FileExistsError):  # new_file saw none there: ours, partial
                Path(args.save).unlink(missing_ok=True)
            return refuse("scan", ValueError(f"--save {args.save}: not saved: {exc}"))
    return 0


def save_scan(scan, height, path) -> None:
    """The scan's heights with what they need to be read again: .npz and .gwy keep the pixel
    sizes, the origin and (as metadata) the angle, frame, time and mode; .npy only heights."""
    import numpy as np

    from afm_core.imaging.files import HeightMap, save_height_map

    if Path(path).suffix.lower() == ".npy":
        with open(path, "xb") as handle:  # the name as given (np.save adds .npy to X.NPY)
            np.save(handle, height)
        print(
            f"saved heights (metres) to {path}; a .npy keeps no pixel size or origin "
            "(--save F.npz keeps them)"
        )
        return
    stamp = scan.header.stamp.sec + 1e-9 * scan.header.stamp.nanosec
    hmap = HeightMap(
        np.asarray(height, dtype=np.float64),
        scan.pixel_size_x,
        scan.pixel_size_y,
        scan.origin.x,
        scan.origin.y,
        title=f"scan {scan.scan_id}",
        meta={
            "frame_id": scan.header.frame_id,
            "stamp": stamp,  # s since the epoch, the instrument's clock: the first line's start
            "scan_angle_deg": scan.scan_angle_deg,
            "slow_scan_up": int(scan.slow_scan_up),
            "line_period": scan.line_period,
            "mode": scan.mode,
            "scan_id": int(scan.scan_id),
        },
    )
    save_height_map(path, hmap)
    print(
        f"saved to {path}: heights (m), pixel size {nm(scan.pixel_size_x)} x "
        f"{nm(scan.pixel_size_y)}, origin ({nm(scan.origin.x)}, {nm(scan.origin.y)}) in "
        f"{scan.header.frame_id}, angle {scan.scan_angle_deg:g} deg, time {stamp:.3f} s"
    )


def _add_scan(sub) -> None:
    p = sub.add_parser(
        "scan",
        help="acquire one raster image through the driver",
        description="Acquire a raster image through the running driver (afm launch).",
    )
    p.add_argument(
        "--origin",
        nargs=2,
        required=True,
        type=length_type("origin"),
        metavar=("X", "Y"),
        help="lower-left corner of the area in afm_scanner (m, or with a unit: 54.2um); the "
        "default simulated sample's particles are near (55um, 55um)",
    )
    p.add_argument(
        "--size",
        nargs=2,
        required=True,
        type=length_type("size", positive=True),
        metavar=("W", "H"),
        help="width and height of the area (m, or with a unit: 2um)",
    )
    p.add_argument(
        "--pixels",
        nargs=2,
        type=positive_type("pixels", int),
        default=[256, 256],
        metavar=("NX", "NY"),
        help="columns and rows (default 256 256)",
    )
    p.add_argument(
        "--angle",
        type=float,
        default=0.0,
        choices=[0.0, 90.0],
        help="scan angle in deg: 0 (fast axis x) or 90 (fast axis y); default 0",
    )
    p.add_argument("--frame-down", action="store_true", help="slow axis downwards")
    p.add_argument(
        "--line-rate",
        type=positive_type("line-rate"),
        default=1.0,
        help="lines (trace + retrace) per second, Hz (default 1.0)",
    )
    p.add_argument(
        "--mode", default="tapping", choices=["tapping", "contact"], help="(default tapping)"
    )
    p.add_argument(
        "--save",
        metavar="FILE.npz",
        help="save the image: .npz or .gwy keep the heights (m), pixel size, origin, angle, "
        "frame and time (`afm image ...` reads them); .npy keeps only the heights",
    )
    p.set_defaults(func=cmd_scan)
