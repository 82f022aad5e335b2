"""Keyframe discovery on synthetic 100 Hz demos whose keyframes are known by construction."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hdp_data.keyframes import DEFAULT_STOPPING_DELTA, discover_keyframes, segments

pytestmark = pytest.mark.unit


def piecewise(*pieces, joints=7):
    """(T, joints) velocities from (frames, speed) pieces; speed on every joint."""
    return np.concatenate([np.full((n, joints), speed, dtype=float) for n, speed in pieces])


def gripper(n, closed=()):
    """(n,) open state, closed over the half-open ranges in ``closed``."""
    state = np.ones(n, dtype=bool)
    for start, end in closed:
        state[start:end] = False
    return state


# rest 0-9, move 10-49, rest 50-99, move 100-139, rest 140-169, move 170-189, rest 190-199
REACH = piecewise((10, 0.0), (40, 0.5), (50, 0.0), (40, -0.5), (30, 0.0), (20, 0.3), (10, 0.0))


def test_default_delta_is_hdps():
    assert DEFAULT_STOPPING_DELTA == 0.01


def test_each_rest_gives_one_keyframe_at_its_first_frame():
    assert discover_keyframes(REACH, gripper(200)) == [50, 140, 190, 199]


def test_a_long_rest_is_one_keyframe_whatever_its_length():
    for rest in (6, 50, 500):
        v = piecewise((10, 0.2), (rest, 0.0), (10, 0.2))
        assert discover_keyframes(v, gripper(len(v))) == [10, len(v) - 1]


def test_smooth_motions_with_sensor_noise():
    """Velocity ramps up and down between waypoints; at rest it is noise far below delta."""
    rng = np.random.default_rng(0)
    pieces, expected = [], []
    for move, rest in [(80, 50), (120, 30), (60, 40)]:
        # a sine bump whose first and last samples are still above delta
        bump = np.sin(np.pi * (np.arange(move) + 0.5) / move)
        pieces += [np.repeat(bump[:, None], 7, axis=1), rng.normal(0, 1e-4, (rest, 7))]
        expected.append(sum(map(len, pieces)) - rest)
    v = np.concatenate(pieces)
    assert discover_keyframes(v, gripper(len(v))) == expected + [len(v) - 1]


def test_one_moving_joint_means_not_stopped():
    v = piecewise((10, 0.0), (40, 0.5), (50, 0.0), (20, 0.5), (10, 0.0))
    v[50:100, 3] = 0.2                       # joint 4 keeps moving through the "rest"
    assert discover_keyframes(v, gripper(len(v))) == [120, 129]


def test_gripper_change_during_a_rest_adds_one_keyframe():
    assert discover_keyframes(REACH, gripper(200, closed=[(70, 200)])) == [50, 70, 140, 190, 199]


def test_gripper_change_while_moving():
    assert discover_keyframes(REACH, gripper(200, closed=[(120, 200)])) == [50, 120, 140, 190, 199]


def test_gripper_changes_are_keyframes_even_back_to_back():
    v = piecewise((30, 0.0))
    assert discover_keyframes(v, gripper(30, closed=[(1, 2), (10, 12), (20, 30)])) == [1, 2, 10, 12, 20, 29]


def test_stop_needs_a_steady_gripper_around_it():
    # the arm stops at 50 while the gripper closes at 51: no stop keyframe at 50,
    # and the rest after the change belongs to the change
    assert discover_keyframes(REACH, gripper(200, closed=[(51, 200)])) == [51, 140, 190, 199]


def test_delta_sensitivity_on_a_slow_segment():
    # fast move, rest, slow move at 0.05 rad/s, rest
    v = piecewise((10, 0.0), (40, 0.5), (50, 0.0), (100, 0.05), (50, 0.0))
    g = gripper(len(v))
    assert discover_keyframes(v, g, stopping_delta=0.01) == [50, 200, 249]
    # PerAct's 0.1 takes the slow approach for a rest and misses its end
    assert discover_keyframes(v, g, stopping_delta=0.1) == [50, 249]


def test_refractory_buffer_ignores_blips_just_after_a_keyframe():
    v = piecewise((10, 0.0), (40, 0.5), (50, 0.0))
    v[52] = 0.02                             # noise 2 frames after the stop
    assert discover_keyframes(v, gripper(100)) == [50, 99]
    assert discover_keyframes(v, gripper(100), stopped_buffer=1) == [50, 53, 99]
    v[52], v[60] = 0.0, 0.02                 # outside the buffer it is motion, then a new stop
    assert discover_keyframes(v, gripper(100)) == [50, 61, 99]


def test_never_the_second_to_last_frame():
    v = piecewise((10, 0.0), (40, 0.5), (2, 0.0))            # stops at T-2
    assert discover_keyframes(v, gripper(52)) == [51]
    v = piecewise((60, 0.5))
    assert discover_keyframes(v, gripper(60, closed=[(58, 60)])) == [59]   # gripper changes at T-2


def test_last_frame_always_even_while_moving():
    v = piecewise((10, 0.0), (40, 0.5), (50, 0.0), (30, 0.5))
    assert discover_keyframes(v, gripper(len(v)))[-1] == len(v) - 1


@pytest.mark.parametrize('frames, expected', [(0, []), (1, []), (2, [1]), (3, [2])])
def test_tiny_demos(frames, expected):
    assert discover_keyframes(np.zeros((frames, 7)), gripper(frames, closed=[(1, 2)])) == expected


@pytest.mark.parametrize('velocities, gripper_open, match', [
    (np.zeros((10, 7)), np.ones(9, bool), '10 frames'),
    (np.zeros(10), np.ones(10, bool), 'shapes'),
    (np.zeros((10, 7)), np.ones((10, 1), bool), 'shapes'),
    (np.full((10, 7), np.nan), np.ones(10, bool), 'NaN'),
])
def test_bad_input_is_a_clear_value_error(velocities, gripper_open, match):
    with pytest.raises(ValueError, match=match):
        discover_keyframes(velocities, gripper_open)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 30), st.sampled_from([0.0, 0.005, 0.05, 0.5]),
                          st.booleans()), min_size=1, max_size=12))
def test_invariants(pieces):
    v = piecewise(*[(n, speed) for n, speed, _ in pieces])
    g = np.concatenate([np.full(n, is_open) for n, _, is_open in pieces])
    n = len(g)
    keyframes = discover_keyframes(v, g)
    assert keyframes == sorted(set(keyframes))
    assert 0 not in keyframes and n - 2 not in keyframes
    if n >= 2:
        assert keyframes[-1] == n - 1
    changes = {i for i in range(1, n) if g[i] != g[i - 1]} - {n - 2}
    assert changes <= set(keyframes)
    for k in set(keyframes) - changes - {n - 1}:
        assert np.all(np.abs(v[k]) <= DEFAULT_STOPPING_DELTA)


def test_segments():
    assert segments([50, 140, 199]) == [(0, 50), (50, 140), (140, 199)]
    assert segments([50, 140, 199], include_start=False) == [(50, 140), (140, 199)]
    assert segments([0, 50]) == [(0, 50)]
    assert segments([]) == []
    assert segments(np.array([3, 9])) == [(0, 3), (3, 9)]


@pytest.mark.parametrize('keyframes', [[5, 5], [9, 3], [-1, 4]])
def test_segments_refuse_unordered_keyframes(keyframes):
    with pytest.raises(ValueError, match='strictly increasing'):
        segments(keyframes)
