"""The `replay` node: plays rosbag2 recordings into the ROS graph."""
import rclpy
from rclpy.node import Node


class Replay(Node):
    def __init__(self) -> None:
        super().__init__('vlp_replay')
        self.declare_parameter('bag', '')


def main(args: list[str] | None = None) -> None:
    rclpy.init(args=args)
    node = Replay()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
