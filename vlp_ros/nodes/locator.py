"""The `locator` node: camera images in, camera poses out."""
import rclpy
from rclpy.node import Node


class Locator(Node):
    def __init__(self) -> None:
        super().__init__('vlp_locator')
        self.declare_parameter('map_frame', 'map')


def main(args: list[str] | None = None) -> None:
    rclpy.init(args=args)
    node = Locator()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
