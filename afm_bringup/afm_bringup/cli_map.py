"""`afm map publish`: a lab's scan file into the running graph as its map."""

from __future__ import annotations

import sys

from afm_bringup.cli_errors import INPUT_STATUS
from afm_bringup.units import count_type, length_type, nm, positive_type


def cmd_map_publish(args):
    from afm_bringup.commander import AfmCommander, AfmError
    from afm_core.imaging.cli import raster_scan_of
    from afm_core.imaging.files import load_height_map, mask_note
    from afm_core.imaging.levelling import level

    channel = int(args.channel) if str(args.channel).isdigit() else args.channel
    try:
        hmap = load_height_map(args.file, channel, args.pixel_size, args.frame, args.height_unit)
        if args.level != "none":
            hmap.height, _ = level(hmap.height, args.level, "auto")
    except (ValueError, ImportError) as exc:  # the input's fault: the status afm image gives
        print(f"afm map publish: {exc}", file=sys.stderr)
        return INPUT_STATUS
    note = mask_note(hmap, str(args.file))
    if note:
        print(f"afm map publish: warning: {note}", file=sys.stderr)
    scan = raster_scan_of(hmap, line_rate=args.line_rate, mode=args.mode)
    with AfmCommander("afm_map_publisher") as afm:
        try:
            _, marks = afm.publish_scan(scan, scan_id=args.scan_id, timeout=args.timeout)
        except AfmError as exc:
            sys.exit(f"afm map publish: {exc}")
    print(
        f"published {args.file} ({hmap.title or 'channel ' + str(channel)}, "
        f"{hmap.height.shape[1]} x {hmap.height.shape[0]} px, {nm(hmap.size_x)} x "
        f"{nm(hmap.size_y)} from ({nm(hmap.origin_x)}, {nm(hmap.origin_y)})) as the map: "
        f"{len(marks.landmarks)} landmarks"
    )
    for mark in marks.landmarks:
        print(
            f"  {mark.id:3d} at ({nm(mark.position.x)}, {nm(mark.position.y)}), "
            f"height {nm(mark.height)}"
        )
    return 0


def _add_map(sub) -> None:
    from afm_core.imaging.cli import (
        HEIGHT_UNIT_HELP,
        height_unit,
        level_method,
        line_rate_type,
        pixel_size_type,
    )

    p = sub.add_parser(
        "map",
        help="bring a lab's scan file into the running graph as its map",
        description="Maps from files for the running graph (`afm launch`).",
    )
    maps = p.add_subparsers(dest="map_command", required=True, metavar="STEP")
    p = maps.add_parser(
        "publish",
        help="publish a scan file as the map (the imaging node finds its landmarks)",
        description=(
            "Publish a scan file (.npz, .gwy, .npy, .ibw, .jpk, .spm, .sxm, .stp, .top, .asd; "
            "--frame for a movie) on the driver's scan topic, as a 0 deg scan in scanner "
            "coordinates: the imaging node "
            "publishes it as /afm/map with its landmarks, which the localizer, planner and "
            "nano-hand use. Waits until the imaging node has done so."
        ),
    )
    p.add_argument("file")
    p.add_argument("--channel", default="0", help="channel index or title (default 0)")
    p.add_argument(
        "--frame", type=int, default=0, help="frame of a high-speed .asd movie (default 0)"
    )
    p.add_argument(
        "--pixel-size",
        type=pixel_size_type(length_type("pixel-size")),
        help="for .npy files: pixel size (m, or with a unit: 2nm)",
    )
    p.add_argument("--height-unit", type=height_unit, help=HEIGHT_UNIT_HELP)
    p.add_argument(
        "--level",
        type=level_method,
        default="plane",
        help="level the scan first, features masked: plane (default), median, poly2, a chain "
        "such as median+plane+median, or none (as stored)",
    )
    p.add_argument(
        "--line-rate",
        type=line_rate_type("--line-rate"),
        default=1.0,
        help="lines per second of the scan (Hz, default 1)",
    )
    p.add_argument(
        "--mode", choices=("tapping", "contact"), default="tapping", help="(default tapping)"
    )
    p.add_argument(
        "--scan-id",
        type=count_type("scan-id", 0, 2**32 - 1),  # the message's uint32
        default=0,
        help="scan_id of the message (default 0)",
    )
    p.add_argument(
        "--timeout",
        type=positive_type("timeout"),
        default=30.0,
        help="s to wait for the imaging node (default 30)",
    )
    p.set_defaults(func=cmd_map_publish)
