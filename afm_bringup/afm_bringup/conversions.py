"""Message <-> core-type conversions shared by the nodes (SI units both sides)."""
from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from sensor_msgs.msg import Image

from afm_core.recording.reader import image_to_array
from afm_core.sim.instrument import RasterScanData

FRAME_SCANNER = "afm_scanner"
FRAME_TASK = "afm_task"
FRAME_IMAGE = "afm_image"


def array_to_image(array: np.ndarray, header=None) -> Image:
    """2-D float32 array -> sensor_msgs/Image 32FC1 (little-endian, row-major)."""
    array = np.ascontiguousarray(array, dtype="<f4")
    image = Image()
    if header is not None:
        image.header = header
    image.height, image.width = array.shape
    image.encoding = "32FC1"
    image.is_bigendian = 0
    image.step = 4 * image.width
    image.data = array.tobytes()
    return image


def image_msg_to_array(image: Image) -> np.ndarray:
    return image_to_array(image)


def seconds_to_time(seconds: float) -> Time:
    sec, nsec = divmod(int(round(seconds * 1e9)), 1_000_000_000)
    return Time(sec=sec, nanosec=nsec)


def raster_scan_to_msg(scan: RasterScanData, header, scan_id: int = 0, pair_id: str = ""):
    from afm_msgs.msg import RasterScan
    msg = RasterScan()
    msg.header = header
    msg.height = array_to_image(scan.height, header)
    msg.pixel_size_x = float(scan.pixel_size_x)
    msg.pixel_size_y = float(scan.pixel_size_y)
    msg.origin.x, msg.origin.y = float(scan.origin_x), float(scan.origin_y)
    msg.size_x = float(scan.pixel_size_x * scan.height.shape[1])
    msg.size_y = float(scan.pixel_size_y * scan.height.shape[0])
    msg.scan_angle_deg = float(scan.scan_angle_deg)
    msg.slow_scan_up = bool(scan.slow_scan_up)
    msg.line_period = float(scan.line_period)
    msg.line_start_times = [float(t) for t in scan.line_start_times]
    msg.mode = scan.mode
    msg.scan_id = int(scan_id)
    msg.pair_id = pair_id
    return msg


def msg_to_raster_scan(msg) -> RasterScanData:
    """RasterScan -> core type; ValueError naming the field when the message is inconsistent."""
    height = image_msg_to_array(msg.height).astype(np.float32)
    lines = height.shape[0] if msg.scan_angle_deg == 0 else height.shape[1]
    if len(msg.line_start_times) != lines:
        raise ValueError(f"line_start_times has {len(msg.line_start_times)} entries, the image has {lines} lines")
    if not (msg.pixel_size_x > 0 and msg.pixel_size_y > 0):
        raise ValueError(f"pixel_size_x/pixel_size_y = {msg.pixel_size_x}/{msg.pixel_size_y}: must be > 0")
    stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
    return RasterScanData(height=height, pixel_size_x=msg.pixel_size_x, pixel_size_y=msg.pixel_size_y,
                          origin_x=msg.origin.x, origin_y=msg.origin.y, scan_angle_deg=msg.scan_angle_deg,
                          slow_scan_up=msg.slow_scan_up, line_period=msg.line_period,
                          line_start_times=np.asarray(msg.line_start_times), start_time=stamp, mode=msg.mode)
