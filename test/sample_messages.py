"""Messages with distinctive values for round-trip tests (every field type we use)."""

import numpy as np
from rclpy.serialization import serialize_message

from afm_msgs.msg import ForceTrace, Landmark, LandmarkArray, RasterScan
from afm_ros.conversions import array_to_image


def raster_scan(i: int) -> RasterScan:
    rng = np.random.default_rng(i)
    msg = RasterScan()
    msg.header.frame_id = "afm_scanner"
    msg.header.stamp.sec = 100 + i
    msg.height = array_to_image((rng.normal(size=(24, 32)) * 1e-9).astype(np.float32))
    msg.pixel_size_x, msg.pixel_size_y = 3.1e-9 + i * 1e-12, 2.9e-9
    msg.origin.x, msg.origin.y = 1e-6 * i, 2e-6
    msg.scan_angle_deg = 90.0 if i % 2 else 0.0
    msg.line_period = 0.5
    msg.line_start_times = list(np.arange(24 if i % 2 == 0 else 32) * 0.5)
    msg.mode, msg.scan_id, msg.pair_id = "tapping", i, f"pair-{i // 2}"
    return msg


def force_trace(i: int) -> ForceTrace:
    t = np.arange(1000) / 10_000.0
    msg = ForceTrace(sample_rate=10_000.0, task="push", object_id=i, normal_spring_constant=0.2)
    msg.header.stamp.sec = 200 + i
    msg.times = list(t)
    msg.commanded_x = list(1e-6 + 1e-7 * t * i)
    msg.commanded_y = list(np.full_like(t, 2e-6))
    msg.vertical_deflection = list(np.sin(2 * np.pi * 50 * t) * 1e-9 * (i + 1))
    msg.lateral_torsion = list(np.cos(2 * np.pi * 50 * t) * 1e-3)
    return msg


def landmarks(i: int) -> LandmarkArray:
    msg = LandmarkArray()
    msg.header.frame_id = "afm_task"
    for k in range(3):
        lm = Landmark(id=k + 10 * i, kind=Landmark.SPHERE, radius=100e-9, height=200e-9)
        lm.position.x, lm.position.y = 1e-6 * k, 2e-6 + 1e-9 * i
        lm.covariance = [25e-18, 1e-18, 1e-18, 20e-18]
        msg.landmarks.append(lm)
    return msg


def cdr(msg) -> bytes:
    return serialize_message(msg)


def dict_message_writer(writer, types: dict):
    """A channel per topic on an open RecordingWriter, and write(topic, log_ns, message) for
    messages given as plain dicts (CDR-encoded from the full definition of `types[topic]`)."""
    from afm_core.recording.cdr import encoder
    from afm_core.recording.definitions import full_message_definition

    channels, encode = {}, {}
    for topic, type_name in types.items():
        definition = full_message_definition(type_name)
        channels[topic] = writer.add_channel(topic, type_name, [], definition=definition)
        encode[topic] = encoder(type_name, definition)

    def write(topic: str, log_ns: int, message: dict) -> None:
        writer.write(channels[topic], log_ns, encode[topic](message))

    return write
