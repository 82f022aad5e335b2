"""planner_node: the high-level agent's place in the graph.

For now it acknowledges each instruction on /hdp/status; the next-best-pose
agent is wired in by a later issue.
"""

from hdp_msgs_py import ros
from hdp_msgs_py import topics
from hdp_msgs_py.msg import String


class PlannerNode(ros.Node):

    def __init__(self):
        super().__init__('planner_node')
        self._status = self.create_publisher(String, topics.STATUS, 10)
        self.create_subscription(String, topics.INSTRUCTION, self._on_instruction, 10)

    def _on_instruction(self, msg):
        text = (f'planner_node: received instruction {msg.data!r}; '
                'no high-level agent is wired yet')
        self.get_logger().info(text)
        self._status.publish(String(data=text))


def main(args=None):
    ros.run(PlannerNode, args)


if __name__ == '__main__':
    main()
