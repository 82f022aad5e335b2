"""controller_node: announces itself on /hdp/status.

A placeholder in the graph: the RK-Diffuser policy is wired in by a later issue.
"""

from hdp_msgs_py import ros
from hdp_msgs_py import topics
from hdp_msgs_py.msg import String


class ControllerNode(ros.Node):

    def __init__(self):
        super().__init__('controller_node')
        self._status = self.create_publisher(String, topics.STATUS, 10)
        # One-shot: give subscribers a moment to match, announce, then cancel.
        self._announce_timer = self.create_timer(0.5, self._announce)

    def _announce(self):
        self._announce_timer.cancel()
        text = 'controller_node up'
        self.get_logger().info(text)
        self._status.publish(String(data=text))


def main(args=None):
    ros.run(ControllerNode, args)


if __name__ == '__main__':
    main()
