"""The sim bridge executes and refuses JointTrajectory goals like joint_trajectory_controller."""

import numpy as np
import pytest

from hdp_motion import panda
from hdp_msgs_py import conversions
from hdp_msgs_py.msg import Time
from hdp_sim_bridge.trajectory_follower import accept

pytestmark = pytest.mark.unit

JOINTS = list(panda.ARM_JOINTS)


def trajectory(positions, times, names=JOINTS, velocities=None):
    return conversions.build_joint_trajectory(names, np.asarray(positions), times, velocities)


def test_starts_from_current_state_and_interpolates():
    goal = panda.HOME + 0.2
    active = accept(trajectory([goal], [1.0]), now=10.0, current=panda.HOME)
    assert np.allclose(active.sample(10.0), panda.HOME)
    assert np.allclose(active.sample(10.5), panda.HOME + 0.1)
    assert np.allclose(active.sample(11.0), goal) and np.allclose(active.sample(99.0), goal)
    assert active.end_time == 11.0


def test_joint_order_follows_names():
    names = JOINTS[::-1]
    goal = panda.HOME + np.linspace(0, 0.1, 7)
    active = accept(trajectory([goal[::-1]], [1.0], names=names), 0.0, panda.HOME)
    assert np.allclose(active.sample(1.0), goal)


def test_cubic_when_velocities_given():
    points = [panda.HOME + 0.1, panda.HOME + 0.2]
    active = accept(trajectory(points, [1.0, 2.0], velocities=[np.full(7, 0.1), np.zeros(7)]), 0.0, panda.HOME)
    assert np.allclose(active.sample(1.0), points[0]) and np.allclose(active.sample(2.0), points[1])
    mid = active.sample(1.5)
    assert np.all(mid > points[0]) and np.all(mid < points[1])


def test_future_stamp_waits():
    msg = trajectory([panda.HOME + 0.1], [1.0])
    msg.header.stamp = Time(sec=20, nanosec=0)
    active = accept(msg, now=10.0, current=panda.HOME)
    assert np.allclose(active.sample(15.0), panda.HOME) and np.allclose(active.sample(21.0), panda.HOME + 0.1)


@pytest.mark.parametrize('make, message', [
    (lambda: trajectory([panda.HOME], [1.0], names=JOINTS[:6] + ['elbow']), "unknown: \\['elbow'\\]"),
    (lambda: trajectory([panda.HOME[:6]], [1.0], names=JOINTS[:6]), "missing: \\['panda_joint7'\\]"),
    (lambda: trajectory([panda.UPPER + [0, 0, 0, 0, 0, 0, 0.1]], [10.0]), 'panda_joint7 = 2.9973 rad is above'),
    (lambda: trajectory([panda.HOME + 1.0], [0.1]), 'over its 2.175 rad/s limit'),
    (lambda: trajectory([panda.HOME + 0.1], [0.0]), 'has time_from_start 0 but is 0.100 rad'),
    (lambda: trajectory([panda.HOME, panda.HOME], [1.0, 2.0], velocities=[np.full(7, 3.0), np.zeros(7)]),
     'exceeds'),
])
def test_refuses_what_the_panda_cannot_do(make, message):
    with pytest.raises(ValueError, match=message):
        accept(make(), 0.0, panda.HOME)


def test_refuses_non_increasing_times_and_nan():
    msg = trajectory([panda.HOME + 0.1, panda.HOME + 0.2], [1.0, 2.0])
    msg.points[1].time_from_start = msg.points[0].time_from_start
    with pytest.raises(ValueError, match='strictly increasing'):
        accept(msg, 0.0, panda.HOME)
    msg = trajectory([panda.HOME + 0.1], [1.0])
    msg.points[0].positions[3] = float('nan')
    with pytest.raises(ValueError, match='finite'):
        accept(msg, 0.0, panda.HOME)
    with pytest.raises(ValueError, match='no points'):
        accept(trajectory([panda.HOME], [1.0]).__class__(joint_names=JOINTS), 0.0, panda.HOME)


def test_one_point_at_time_zero_holds_there():
    """joint_trajectory_controller's hold command (set_hold_position): the arm stays at that point."""
    here = panda.HOME + 0.01
    active = accept(trajectory([here], [0.0]), now=5.0, current=panda.HOME)
    assert np.allclose(active.sample(5.0), here) and np.allclose(active.sample(9.0), here)
    assert active.end_time == 5.0
