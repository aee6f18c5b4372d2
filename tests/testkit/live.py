"""rclpy nodes of the live tests (marked ros): each in a Context (a DDS participant) of its own."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from parproj_ros.ros.live import wait_until


def wait(cond: Callable[[], bool], timeout: float, alive: Callable[[], bool] = lambda: True):
    return wait_until(cond, timeout, alive)


class GraphNode:
    """An rclpy node of the test in a Context of its own, spun in a thread (started at once
    unless ``start`` is false: then :meth:`start`)."""

    def __init__(self, name: str, *, start: bool = True) -> None:
        assert os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node(name, context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        if start:
            self.thread.start()

    def start(self) -> None:
        self.thread.start()

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(timeout=5)
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)
