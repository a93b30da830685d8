"""The life cycle every executable node shares: init, start, spin until a signal, clean up."""
from __future__ import annotations

import signal
import subprocess
from typing import Callable, Optional, Tuple, Type

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

__all__ = ["run_node", "stop_node_process"]


def run_node(make_node: Callable[[], Node], name: str, args=None,
             start_errors: Tuple[Type[BaseException], ...] = (Exception,),
             on_shutdown: Optional[Callable[[Node], None]] = None) -> int:
    """Run one node until SIGINT / SIGTERM; returns the process exit status.

    Args:
        make_node: builds the node; ``start_errors`` it raises are logged as
            ``cannot start: ...`` and give status 1 (a node never starts half-working).
        name: logger name for that message.
        args: ROS command-line arguments (``rclpy.init(args=...)``).
        on_shutdown: called with the node before it is destroyed (e.g. join a worker).
    """
    rclpy.init(args=args)
    executor = SingleThreadedExecutor()  # before the node: a signal during start-up is then harmless
    node = None
    try:
        try:
            node = make_node()
        except start_errors as exc:
            if not rclpy.ok():  # interrupted while starting (e.g. loading a model)
                return 0
            rclpy.logging.get_logger(name).fatal(f"cannot start: {type(exc).__name__}: {exc}")
            return 1
        executor.add_node(node)
        if rclpy.ok():
            executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():
            raise
        # A signal shut the context down while the executor was between its checks: rclpy
        # then raises RCLError ("context is not valid") instead of ExternalShutdownException.
    finally:
        if node is not None:
            if on_shutdown is not None:
                on_shutdown(node)
            node.destroy_node()
        executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown()
    return 0


def stop_node_process(proc: subprocess.Popen, timeout: float) -> None:
    """Stop a node running as a child process the way Ctrl-C does (SIGINT: it cleans up and
    exits), killing it when it has not exited after ``timeout`` seconds."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
