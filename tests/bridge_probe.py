"""Drive a running sim_bridge_node from another process and print what happened as JSON.

    python bridge_probe.py
"""

import json
import sys
import time

import numpy as np
import rclpy

from hdp_motion import panda
from hdp_msgs_py import conversions, topics
from hdp_ros import ros
from hdp_msgs_py.msg import Bool, CameraInfo, Clock, Image, JointState, JointTrajectory, String, TFMessage


class Probe(ros.Node):
    def __init__(self):
        super().__init__('bridge_probe')
        self.seen = {'joint_stamps': [], 'status': [], 'episodes': [], 'success': [], 'clock': [],
                     'images': {}, 'tf': [], 'tf_moving': {}, 'robot_description': []}
        self.joints = None
        self.create_subscription(JointState, topics.JOINT_STATES, self._on_joints, 50)
        self.create_subscription(String, topics.STATUS, lambda m: self.seen['status'].append(m.data),
                                 topics.STATUS_QOS)
        self.create_subscription(String, topics.SIM_EPISODE, lambda m: self.seen['episodes'].append(json.loads(m.data)),
                                 topics.LATCHED_QOS)
        self.create_subscription(Bool, topics.SIM_SUCCESS, lambda m: self.seen['success'].append(m.data), 10)
        self.create_subscription(Clock, topics.CLOCK, lambda m: self.seen['clock'].append(
            conversions.time_to_seconds(m.clock)), topics.SENSOR_QOS)
        self.create_subscription(TFMessage, topics.TF_STATIC, lambda m: self.seen['tf'].extend(
            t.child_frame_id for t in m.transforms), topics.TF_STATIC_QOS)
        self.create_subscription(TFMessage, topics.TF, lambda m: self.seen['tf_moving'].update(
            {t.child_frame_id: t.header.frame_id for t in m.transforms}), topics.TF_QOS)
        self.create_subscription(String, topics.ROBOT_DESCRIPTION, lambda m: self.seen['robot_description'].append(
            m.data), topics.LATCHED_QOS)
        for topic, kind in ((topics.color_image('front'), Image), (topics.depth_image('side'), Image),
                            (topics.camera_info('front'), CameraInfo)):
            self.create_subscription(kind, topic, lambda m, t=topic: self.seen['images'].__setitem__(t, (
                m.encoding, m.width, m.height) if hasattr(m, 'encoding') else ('info', m.width, m.height)),
                topics.SENSOR_QOS)
        self.arm = self.create_publisher(JointTrajectory, topics.ARM_TRAJECTORY, 10)
        self.gripper = self.create_publisher(JointTrajectory, topics.GRIPPER_TRAJECTORY, 10)
        self.reset = self.create_publisher(String, topics.SIM_RESET, 10)

    def _on_joints(self, msg):
        self.seen['joint_stamps'].append(conversions.time_to_seconds(msg.header.stamp))
        self.joints = np.asarray(msg.position[:7], dtype=float)

    def spin_for(self, seconds, until=lambda: False):
        end = time.monotonic() + seconds
        while time.monotonic() < end and not until():
            rclpy.spin_once(self, timeout_sec=0.02)


def main():
    ros.init(args=sys.argv)
    probe = Probe()
    facts = {}
    probe.spin_for(30, until=lambda: probe.joints is not None and probe.seen['episodes']
                   and len(probe.seen['images']) == 3 and len(set(probe.seen['tf'])) >= 6
                   and probe.seen['tf_moving'] and probe.seen['robot_description']
                   and all(p.get_subscription_count() for p in (probe.arm, probe.gripper, probe.reset)))
    facts['first_episode'] = probe.seen['episodes'][-1]
    start = probe.joints.copy()

    # A trajectory that breaks a joint limit: refused, nothing moves.
    bad = conversions.build_joint_trajectory(list(panda.ARM_JOINTS), [panda.UPPER + 0.3], [2.0])
    probe.arm.publish(bad)
    probe.spin_for(1.5)
    facts['moved_after_bad'] = float(np.max(np.abs(probe.joints - start)))
    unknown = conversions.build_joint_trajectory(list(panda.ARM_JOINTS[:6]) + ['elbow'], [panda.HOME], [2.0])
    probe.arm.publish(unknown)
    probe.spin_for(1.0)

    # A good one: the arm gets there.
    goal = panda.HOME + np.array([0.3, -0.2, 0.1, 0.2, 0.0, -0.2, 0.4])
    probe.arm.publish(conversions.build_joint_trajectory(list(panda.ARM_JOINTS), [goal], [1.5]))
    probe.spin_for(15, until=lambda: np.max(np.abs(probe.joints - goal)) < 0.01)
    facts['error_after_good'] = float(np.max(np.abs(probe.joints - goal)))

    probe.reset.publish(String(data=json.dumps({'task': 'open_drawer', 'seed': 5, 'variation': 2})))
    probe.spin_for(10, until=lambda: probe.seen['episodes'][-1]['task'] == 'open_drawer')
    probe.reset.publish(String(data='{"task": "make_tea"}'))
    probe.spin_for(2.0)
    # A variation the task does not have: refused before the scene is touched; the bridge carries on.
    probe.reset.publish(String(data=json.dumps({'task': 'open_drawer', 'seed': 6, 'variation': 999})))
    probe.spin_for(1.0)
    reports = len(probe.seen['success'])
    probe.spin_for(2.0)
    facts['success_reports_after_bad_variation'] = len(probe.seen['success']) - reports

    stamps = np.array(probe.seen['joint_stamps'])
    rising = np.diff(stamps)
    facts.update(
        last_episode=probe.seen['episodes'][-1],
        joint_state_hz=float(1.0 / np.median(rising[rising > 0])),
        clock_advances=bool(len(probe.seen['clock']) > 10 and probe.seen['clock'][-1] > probe.seen['clock'][0]),
        images=probe.seen['images'], tf=sorted(set(probe.seen['tf'])), tf_moving=probe.seen['tf_moving'],
        robot_description=probe.seen['robot_description'][-1][:2000] if probe.seen['robot_description'] else '',
        status=probe.seen['status'], success_reports=len(probe.seen['success']))
    print(json.dumps(facts), flush=True)
    probe.destroy_node()
    rclpy.try_shutdown()


if __name__ == '__main__':
    main()
