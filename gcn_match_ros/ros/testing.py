"""A private ROS session for whoever drives a node from Python: tests, the demo, the benchmarks.

:class:`RosSession` owns an rclpy context of its own (its domain, no signal handlers: the
caller's Ctrl-C stays the caller's), an executor and a helper node to publish and
subscribe with. Nodes made in ``session.context`` can be added to the same executor, so a
test runs a :class:`~gcn_match_ros.ros.matcher_node.MatcherNode` and its publishers in one
thread (:meth:`RosSession.spin_until`), and a benchmark spins in the background
(:meth:`RosSession.spin_in_background`) while it publishes at a fixed rate.
"""
from __future__ import annotations

import contextlib
import threading
import time
from typing import Callable, Dict, Iterator, List, Optional, Tuple

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

__all__ = ["RELIABLE", "RosSession", "diagnostic_values"]

#: Reliable, keep-last 50: nothing a test sends or receives is lost to a slow reader.
RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.RELIABLE)


def diagnostic_values(msg: DiagnosticArray, hardware_id: str) -> Optional[Tuple[DiagnosticStatus, Dict[str, str]]]:
    """The status of ``hardware_id`` (a node's fully qualified name) in a ``/diagnostics`` message
    and its values as a dict; None if the message has none."""
    for st in msg.status:
        if st.hardware_id == hardware_id:
            return st, {kv.key: kv.value for kv in st.values}
    return None


class RosSession:
    """A context, an executor and a helper node (``self.node``); close it (or use ``with``).

    Args:
        name, namespace: of the helper node.
        domain_id: ROS domain (None: ``ROS_DOMAIN_ID`` or 0, as rclpy does).
    """

    def __init__(self, name: str = "harness", namespace: str = "", domain_id: Optional[int] = None) -> None:
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
        try:
            self.node = rclpy.create_node(name, context=self.context, namespace=namespace)
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
        except BaseException:
            rclpy.try_shutdown(context=self.context)
            raise
        self._spinner: Optional[threading.Thread] = None

    def add_node(self, node: Node) -> Node:
        """Spin ``node`` (made with ``context=session.context``) with the helper node."""
        self.executor.add_node(node)
        return node

    def collect(self, msg_type, topic: str, qos: QoSProfile = RELIABLE) -> List:
        """Subscribe ``topic``; every message is appended to the returned list."""
        received: List = []
        self.node.create_subscription(msg_type, topic, received.append, qos)
        return received

    def publisher(self, msg_type, topic: str, qos: QoSProfile = RELIABLE):
        return self.node.create_publisher(msg_type, topic, qos)

    def spin_until(self, condition: Callable[[], bool], timeout: float = 10.0) -> bool:
        """Spin until ``condition()`` holds or ``timeout`` seconds pass; returns the condition."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if condition():
                return True
            self.executor.spin_once(timeout_sec=0.01)
        return bool(condition())

    @contextlib.contextmanager
    def spin_in_background(self) -> Iterator["RosSession"]:
        """Spin in a thread of its own while the ``with`` block runs."""
        self._spinner = threading.Thread(target=self.executor.spin, name="ros-session", daemon=True)
        self._spinner.start()
        try:
            yield self
        finally:
            self.executor.shutdown(timeout_sec=1.0)
            self._spinner.join(2.0)
            self._spinner = None

    def close(self) -> None:
        """Destroy every node of the executor and shut the context down."""
        try:
            nodes = self.executor.get_nodes()
            self.executor.shutdown(timeout_sec=1.0)
            for n in nodes:
                n.destroy_node()
        finally:
            rclpy.try_shutdown(context=self.context)

    def __enter__(self) -> "RosSession":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
