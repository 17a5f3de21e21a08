"""Which ended actions count as finished for their progress line (commander.succeeded)."""

from types import SimpleNamespace

import pytest
from action_msgs.msg import GoalStatus
from rclpy.task import Future

from afm_bringup.commander import succeeded

pytestmark = pytest.mark.ros


def ended(status, **result) -> Future:
    future = Future()
    future.set_result(SimpleNamespace(status=status, result=SimpleNamespace(**result)))
    return future


@pytest.mark.parametrize(
    "future, finished",
    [
        (ended(GoalStatus.STATUS_SUCCEEDED, success=True), True),
        (ended(GoalStatus.STATUS_SUCCEEDED), True),  # a result without a success field
        (ended(GoalStatus.STATUS_SUCCEEDED, success=False), False),
        (ended(GoalStatus.STATUS_ABORTED, success=True), False),
        (ended(GoalStatus.STATUS_CANCELED, success=False), False),
    ],
)
def test_only_a_succeeded_action_with_its_work_done_is_finished(future, finished):
    assert succeeded(future) is finished


def test_a_failed_wait_is_not_finished():
    future = Future()
    future.set_exception(RuntimeError("the server went away"))
    assert succeeded(future) is False
    future = Future()
    future.cancel()
    assert succeeded(future) is False
