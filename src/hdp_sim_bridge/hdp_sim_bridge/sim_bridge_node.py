"""sim_bridge_node: announces itself on /hdp/status.

A placeholder in the graph: the PyBullet world is wired in by a later issue.
"""

from hdp_msgs_py import ros
from hdp_msgs_py import topics
from hdp_msgs_py.msg import String


class SimBridgeNode(ros.Node):

    def __init__(self):
        super().__init__('sim_bridge_node')
        self._status = self.create_publisher(String, topics.STATUS, 10)
        # One-shot: give subscribers a moment to match, announce, then cancel.
        self._announce_timer = self.create_timer(0.5, self._announce)

    def _announce(self):
        self._announce_timer.cancel()
        text = 'sim_bridge_node up'
        self.get_logger().info(text)
        self._status.publish(String(data=text))


def main(args=None):
    ros.run(SimBridgeNode, args)


if __name__ == '__main__':
    main()
