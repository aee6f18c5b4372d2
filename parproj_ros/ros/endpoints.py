"""The node's endpoints, made from the interface contract (:mod:`parproj_ros.core.contract`).

One subscription per input row and one publisher per output row, each with the row's QoS as
an rclpy profile; the streamed inputs and every output accept ``qos_overrides.<topic>.*``
parameters (REP 2003 and rclpy's QoS overriding), and latched outputs keep the last
``latched_depth`` messages for subscribers that join late.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace
from typing import Any

from rclpy.node import Node
from rclpy.qos import QoSPolicyKind
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import Image

from ..core import contract
from . import conversions as conv
from .bag import get_message_class
from .startup import StartupError


def message_class(msgtype: str) -> Any:
    """The message class of ``msgtype`` (``pkg/msg/Name``).

    Raises:
        StartupError: not installed (the message packages are built by ``./dev setup``).
    """
    cls = get_message_class(msgtype)
    if cls is None:
        raise StartupError(f"message type {msgtype} is not installed (run ./dev setup)")
    return cls


def subscribe(node: Node, callbacks: Mapping[str, Callable[[Any], None]]) -> dict[str, Any]:
    """Subscribe ``node`` to each input topic of ``callbacks`` (topic -> callback): the subs.

    Navigation and strips (the streamed inputs) take QoS overrides; strips come as CDR bytes
    (``raw``), read by :func:`.cdr.read_image` with the pixels a view on them (rclpy's
    deserialization costs 8.7 ms per full-size strip, GIL held).

    Raises:
        StartupError: a QoS override that cannot be applied.
    """
    overrides = QoSOverridingOptions.with_default_policies()
    views = [v for t in callbacks if (v := contract.view_of(t)) is not None]
    streamed = set(contract.stream_topics(views))
    subs = {}
    for name, callback in callbacks.items():
        row = contract.topic(name)
        cls = message_class(row.msgtype)
        extra: dict[str, Any] = {}
        if name in streamed:
            extra = {"qos_overriding_options": overrides, "raw": cls is Image}
        try:
            subs[name] = node.create_subscription(
                cls, name, callback, conv.qos_profile(row.qos), **extra
            )
        except Exception as err:  # rclpy: RuntimeError or a parameter exception
            raise StartupError(f"QoS override of {name}: {type(err).__name__}: {err}") from err
    return subs


def advertise(node: Node, latched_depth: int) -> dict[str, Any]:
    """A publisher of ``node`` per output topic of the contract (``/diagnostics`` apart).

    Each takes QoS overrides (``qos_overrides.<topic>.publisher.<history|depth|reliability|
    durability>``); a transient-local
    (latched) output keeps its last ``latched_depth`` messages.

    Raises:
        StartupError: a QoS override that cannot be applied.
    """
    # durability too: a latched output may be made volatile, or the reverse (docs/node.md)
    overrides = QoSOverridingOptions(
        policy_kinds=(
            QoSPolicyKind.HISTORY,
            QoSPolicyKind.DEPTH,
            QoSPolicyKind.RELIABILITY,
            QoSPolicyKind.DURABILITY,
        )
    )
    pubs = {}
    for t in contract.OUTPUTS:
        if t.name == contract.DIAGNOSTICS:
            continue
        qos = t.qos
        if qos.durability == "transient_local":
            qos = replace(qos, depth=latched_depth)
        try:
            pubs[t.name] = node.create_publisher(
                message_class(t.msgtype),
                t.name,
                conv.qos_profile(qos),
                qos_overriding_options=overrides,
            )
        except Exception as err:  # rclpy: RuntimeError or a parameter exception
            raise StartupError(f"QoS override of {t.name}: {type(err).__name__}: {err}") from err
    return pubs
