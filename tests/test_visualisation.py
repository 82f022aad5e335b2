"""The next-best pose as RViz and Foxglove draw it: a TF frame and an arrow ending at the pose."""

import numpy as np
import pytest

from hdp_msgs_py import conversions
from hdp_msgs_py.msg import JointState, Marker, Time
from hdp_planner import visualisation

pytestmark = pytest.mark.unit


def test_the_nbp_frame_and_arrow_follow_the_pose_and_the_gripper_goal():
    stamp = Time(sec=12, nanosec=5)
    hand_down = np.array([1.0, 0.0, 0.0, 0.0])            # x, y, z, w: z axis pointing down
    nbp = conversions.xyz_quat_to_pose_stamped([0.5, 0.1, 0.9], hand_down, 'world', stamp)
    tf = visualisation.nbp_transform(nbp)
    assert (tf.header.frame_id, tf.child_frame_id, tf.header.stamp) == ('world', 'hdp_next_best_pose', stamp)
    assert np.allclose([tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z],
                       [0.5, 0.1, 0.9])
    marker = visualisation.nbp_marker(nbp, visualisation.opens(JointState(position=[0.08])))
    tail, tip = ([p.x, p.y, p.z] for p in marker.points)
    assert marker.type == Marker.ARROW and marker.header.frame_id == 'world'
    assert np.allclose(tip, [0.5, 0.1, 0.9]) and np.allclose(tail, [0.5, 0.1, 1.0])     # from above, down
    assert marker.color.g > marker.color.r                                             # opens: green
    closing = visualisation.nbp_marker(nbp, visualisation.opens(JointState(position=[0.0])))
    assert closing.color.r > closing.color.g


def test_a_cloud_goes_out_as_pcl_xyz_rgb_and_reads_back():
    from hdp_msgs_py.msg import Header
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-1, 1, (50, 3)).astype(np.float32)
    colours = rng.integers(0, 256, (50, 3), dtype=np.uint8)
    msg = conversions.cloud_to_pointcloud2(xyz, colours, Header(frame_id='world'))
    assert [f.name for f in msg.fields] == ['x', 'y', 'z', 'rgb'] and msg.width == 50 and msg.height == 1
    assert len(msg.data) == msg.row_step == 50 * 16
    # rgb as PCL packs it: the float32 whose bytes are 0x00RRGGBB
    first = np.frombuffer(bytes(msg.data[12:16]), '<u4')[0]
    assert first == (int(colours[0, 0]) << 16) | (int(colours[0, 1]) << 8) | int(colours[0, 2])
    back_xyz, back_colours = conversions.pointcloud2_to_cloud(msg)
    assert np.array_equal(back_xyz, xyz) and np.array_equal(back_colours, colours)
    with pytest.raises(ValueError, match='points but'):
        conversions.cloud_to_pointcloud2(xyz, colours[:3], Header())
