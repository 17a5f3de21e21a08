"""Log time = header stamp: where a message's stamp sits in its CDR bytes, read without
decoding, against the stamp rclpy serialised; and the colour-mapped height images."""

import struct

import numpy as np
import pytest
from geometry_msgs.msg import TransformStamped
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock
from sample_messages import force_trace, raster_scan
from sensor_msgs.msg import Image
from std_msgs.msg import String
from visualization_msgs.msg import Marker, MarkerArray

from afm_core.imaging.colour_map import SCALE_PERCENTILES, afmhot, height_to_rgb
from afm_core.recording import full_message_definition
from afm_core.recording.stamps import DIRECT, FIRST_ELEMENT, stamp_layout, stamp_ns
from afm_msgs.msg import PlannedPath

STAMP = (1_764_000_123, 456_789_012)  # s, ns: a wall-clock epoch plus instrument time
STAMP_NS = STAMP[0] * 10**9 + STAMP[1]


def layout_of(msg) -> str | None:
    module = type(msg).__module__.split(".")[0]
    type_name = f"{module}/msg/{type(msg).__name__}"
    return stamp_layout(type_name, full_message_definition(type_name))


def stamped(header):
    header.stamp.sec, header.stamp.nanosec = STAMP
    return header


def tf_message():
    from tf2_msgs.msg import TFMessage

    first, second = TransformStamped(), TransformStamped()
    stamped(first.header)
    second.header.stamp.sec = 7  # only the first element's stamp is read
    return TFMessage(transforms=[first, second])


def messages():
    scan = raster_scan(3)
    stamped(scan.header)
    path = PlannedPath()
    stamped(path.path.header)
    markers = MarkerArray(markers=[Marker(), Marker()])
    stamped(markers.markers[0].header)
    clock = Clock()
    clock.clock.sec, clock.clock.nanosec = STAMP
    trace = force_trace(1)
    stamped(trace.header)
    return [
        (scan, DIRECT),
        (trace, DIRECT),
        (Image(header=stamped(Image().header)), DIRECT),
        (path, DIRECT),  # nav_msgs/Path first, then its Header
        (clock, DIRECT),  # builtin_interfaces/Time first
        (markers, FIRST_ELEMENT),
        (tf_message(), FIRST_ELEMENT),
    ]


@pytest.mark.parametrize("index", range(7))
def test_the_stamp_is_read_where_rclpy_wrote_it(index):
    msg, layout = messages()[index]
    assert layout_of(msg) == layout
    assert stamp_ns(serialize_message(msg), layout) == STAMP_NS


def test_messages_without_a_stamp_give_none():
    assert layout_of(String(data="x")) is None
    assert stamp_ns(serialize_message(String(data="abcdefghijkl")), None) is None
    from tf2_msgs.msg import TFMessage

    empty = serialize_message(TFMessage())
    assert stamp_ns(empty, FIRST_ELEMENT) is None  # an empty sequence holds no stamp
    unset = serialize_message(raster_scan(0).__class__())
    assert stamp_ns(unset, DIRECT) is None  # a zero stamp was never set
    assert stamp_ns(b"\x00\x01\x00\x00\x01", DIRECT) is None  # too short
    with pytest.raises(ValueError, match="layout='sideways'"):
        stamp_ns(serialize_message(force_trace(0)), "sideways")


def test_big_endian_cdr_is_read_too():
    data = b"\x00\x00\x00\x00" + struct.pack(">iI", *STAMP) + b"rest"
    assert stamp_ns(data, DIRECT) == STAMP_NS


def test_afmhot_is_matplotlibs_in_closed_form():
    np.testing.assert_allclose(
        afmhot(np.array([0.0, 0.25, 0.5, 1.0])), [[0, 0, 0], [0.5, 0, 0], [1, 0.5, 0], [1, 1, 1]]
    )


def test_height_image_is_scaled_per_image_with_y_up():
    y = np.linspace(0.0, 20e-9, 40)
    height = np.repeat(y[:, None], 30, axis=1)  # rises with y (row index)
    height[0, 0] = np.nan
    height[5, 5] = 1e-6  # a spike: clipped, the scale follows the percentiles
    rgb, scale = height_to_rgb(height)
    assert rgb.shape == (40, 30, 3) and rgb.dtype == np.uint8
    finite = height[np.isfinite(height)]
    assert (scale.low, scale.high) == tuple(np.percentile(finite, SCALE_PERCENTILES))
    assert scale.high < 1e-6
    assert rgb[0].mean() > rgb[-1].mean()  # top row: the largest y, the brightest
    np.testing.assert_array_equal(rgb[-1, 0], [0, 0, 0])  # not finite: black
    np.testing.assert_array_equal(rgb[40 - 1 - 5, 5], [255, 255, 255])  # the spike clips
    expected = np.round(afmhot((height[20, 10] - scale.low) / (scale.high - scale.low)) * 255)
    np.testing.assert_array_equal(rgb[40 - 1 - 20, 10], expected)
    assert "nm (black)" in scale.describe()


def test_flat_and_bad_height_images():
    rgb, scale = height_to_rgb(np.full((4, 5), 3e-9))
    assert scale.low == scale.high and np.all(rgb == np.round(afmhot(np.array(0.5)) * 255))
    with pytest.raises(ValueError, match="height: expected a non-empty 2-D image"):
        height_to_rgb(np.zeros(5))
    with pytest.raises(ValueError, match="height: no finite value"):
        height_to_rgb(np.full((3, 3), np.nan))
