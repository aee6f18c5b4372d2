"""rclpy nodes of the live tests (marked ros): each in a Context (a DDS participant) of its own."""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable
from pathlib import Path

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from parproj_ros.core import contract
from parproj_ros.ros.bag import BagReader, BagWriter
from parproj_ros.ros.live import wait_until

#: Navigation kept whole before the first and after the last strip of each view, seconds
#: (:func:`thinned_navigation`).
NAV_AROUND_S = 1.0
#: Navigation kept between the views' strips: one sample every this many seconds.
NAV_BETWEEN_S = 0.5


def thinned_navigation(bag: Path, path: Path, views: tuple[str, ...] = ("left", "right")) -> Path:
    """``bag`` with its navigation thinned to NAV_BETWEEN_S farther than NAV_AROUND_S from every
    view's strips (within the feed's 1 s gap bound): a slow replay of a bag whose scenes lie
    far apart (the fore/aft bag's 38.8 s, mostly navigation) in some 50 s, its pair streamed.
    """
    reader = BagReader(bag)
    spans = []
    for view in views:
        t = [m.log_time_ns for m in reader.messages(topics=[contract.strip_topic(view)])]
        spans.append((min(t) - NAV_AROUND_S * 1e9, max(t) + NAV_AROUND_S * 1e9))
    kept = -math.inf
    with BagWriter(path, overwrite=True) as bw:
        for topic, msgtype in reader.topics().items():
            bw.add_topic(topic, msgtype, reader.qos(topic))
        for m in reader.messages():
            t = m.log_time_ns
            if m.topic == contract.NAVIGATION and not any(a <= t <= b for a, b in spans):
                if t < kept + NAV_BETWEEN_S * 1e9:
                    continue
                kept = t
            bw.write(m.topic, m.msg, t)
    return path


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
