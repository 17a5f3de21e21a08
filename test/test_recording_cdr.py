"""recording.cdr (our CDR encoder, used where no ROS runtime writes a session): rclpy's
deserialize_message reads its bytes back to the message encoded, for every message type a
session holds and for messages with sequences of nested messages and strings. (Bytes are not
compared with serialize_message's: rclpy leaves its padding bytes and a buffer tail
uninitialised.)"""

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sample_messages import force_trace, landmarks, raster_scan

from afm_core.recording.cdr import CdrError, encoder
from afm_core.recording.definitions import full_message_definition
from afm_core.sim2real.session import TYPES


def _same_bytes(msg, type_name: str) -> None:
    encode = encoder(type_name, full_message_definition(type_name))
    data = encode(msg)
    assert deserialize_message(data, type(msg)) == msg
    # the same bytes up to the padding rclpy leaves uninitialised
    reference = bytes(serialize_message(msg))[: len(data)]
    assert len(reference) == len(data)


@pytest.mark.parametrize("i", [0, 1])
def test_cdr_matches_rclpy_on_samples(i):
    _same_bytes(raster_scan(i), "afm_msgs/msg/RasterScan")
    _same_bytes(force_trace(i), "afm_msgs/msg/ForceTrace")
    _same_bytes(landmarks(i), "afm_msgs/msg/LandmarkArray")


@pytest.mark.parametrize("type_name", sorted(TYPES.values()))
def test_cdr_matches_rclpy_on_every_session_type(type_name):
    import importlib

    package, _, name = type_name.split("/")
    cls = getattr(importlib.import_module(f"{package}.msg"), name)
    msg = cls()  # defaults: empty sequences, zero numbers, empty strings
    _same_bytes(msg, type_name)
    # and with every float64[] / string field filled with distinctive values
    rng = np.random.default_rng(7)
    for field, kind in msg.get_fields_and_field_types().items():
        if kind == "sequence<double>":
            setattr(msg, field, list(rng.normal(size=5)))
        elif kind == "string":
            setattr(msg, field, f"{field}-\u00b5")
        elif kind == "double":
            setattr(msg, field, float(rng.normal()))
    _same_bytes(msg, type_name)


def test_cdr_from_dicts_and_errors():
    definition = full_message_definition("geometry_msgs/msg/Point")
    encode = encoder("geometry_msgs/msg/Point", definition)
    from geometry_msgs.msg import Point

    assert deserialize_message(encode({"x": 1.5, "y": -2.0}), Point) == Point(x=1.5, y=-2.0)
    with pytest.raises(CdrError, match="Point.x"):
        encode({"x": "far"})
    encode_scan = encoder(
        "afm_msgs/msg/RasterScan", full_message_definition("afm_msgs/msg/RasterScan")
    )
    with pytest.raises(CdrError, match="line_start_times"):
        encode_scan({"line_start_times": np.zeros((2, 2))})
