"""Height images as colour pictures (`sensor_msgs/Image` rgb8) for viewers that show standard
images only; the colour map and its per-image scale are afm_core.imaging.colour_map's."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import Image

from afm_core.imaging.colour_map import ColourScale, height_to_rgb


def height_image_msg(height: np.ndarray, header) -> tuple[Image, ColourScale]:
    """A height image (m, row 0 at the smallest y) -> (rgb8 Image with +y up, its scale)."""
    rgb, scale = height_to_rgb(height)
    image = Image(header=header, encoding="rgb8", is_bigendian=0)
    image.height, image.width = rgb.shape[:2]
    image.step = 3 * image.width
    image.data = rgb.tobytes()
    return image, scale
