"""A LandmarkArray from another program is checked as our own (conversions.msg_to_landmarks):
a duplicate id was collapsed to its last entry without a word, and a covariance that is no
covariance, a negative radius or a map in another frame reached the plans."""

import math

import pytest
from std_msgs.msg import Header

from afm_msgs.msg import Landmark, LandmarkArray
from afm_ros.conversions import msg_to_landmarks

pytestmark = pytest.mark.ros


def mark(i, covariance=(4e-18, 0.0, 0.0, 4e-18), radius=100e-9, length=0.0) -> Landmark:
    lm = Landmark(id=i, kind=Landmark.SPHERE, radius=radius, height=200e-9, length=length)
    lm.position.x, lm.position.y = 50e-6 + i * 1e-6, 50e-6
    lm.covariance = list(covariance)
    return lm


def array(marks, frame="afm_task") -> LandmarkArray:
    return LandmarkArray(header=Header(frame_id=frame), landmarks=marks)


def test_a_good_map_reads_with_every_landmark():
    marks = msg_to_landmarks(array([mark(0), mark(1, covariance=(9e-18, 1e-18, 1e-18, 4e-18))]))
    assert [m.id for m in marks] == [0, 1]
    assert marks[1].covariance[0, 1] == marks[1].covariance[1, 0] == 1e-18


@pytest.mark.parametrize(
    "msg, says",
    [
        (array([mark(0)], frame="afm_scanner"), "header.frame_id='afm_scanner'"),
        (array([mark(0)], frame=""), "header.frame_id=''"),
        (array([mark(3), mark(4), mark(3)]), "landmark 3: the id occurs twice"),
        (array([mark(0, radius=-1e-9)]), "landmark 0: radius=-1e-09 m must be > 0"),
        (array([mark(0, radius=0.0)]), "landmark 0: radius=0.0 m must be > 0"),
        (array([mark(0, length=-1e-6)]), "length=-1e-06 m"),
        (array([mark(0, covariance=(4e-18, 0.0, 1e-18, 4e-18))]), "not symmetric"),
        (array([mark(0, covariance=(1e-18, 5e-18, 5e-18, 1e-18))]), "not positive semi-definite"),
        (array([mark(0, covariance=(-1e-18, 0.0, 0.0, 4e-18))]), "not positive semi-definite"),
        (array([mark(0, covariance=(math.nan, 0.0, 0.0, 4e-18))]), "must be finite"),
    ],
)
def test_a_map_that_cannot_be_one_is_refused_naming_the_landmark_and_field(msg, says):
    with pytest.raises(ValueError) as refused:
        msg_to_landmarks(msg)
    assert says in str(refused.value), str(refused.value)
