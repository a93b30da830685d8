"""Record live topics into a rosbag2 bag (mcap by default), without the ros2 CLI.

    bag_record -o run1.mcap --topics /cam0/keypoints /cam1/keypoints /matcher/matches
    bag_record -o run1 --all --duration 30           # a rosbag2 directory, every topic
    bag_record -o run1.mcap --topics /a --count 100  # stop after 100 messages

Each topic is subscribed with ``raw=True`` (the CDR bytes are written as received, no
decoding) once it appears in the ROS graph (its type is taken from there). The bag stores
each type's message definition (standard types and gcn_match_msgs from the rosbags Jazzy
type store; other types from ``share/<pkg>/msg/*.msg`` on AMENT_PREFIX_PATH), so any
rosbags reader can decode it. Log time = receive time (ROS clock), as ``ros2 bag record``.

QoS: ``auto`` (default) subscribes best effort when any publisher of the topic is best
effort, else reliable; ``reliable`` / ``sensor-data`` force one. Stops on Ctrl-C,
SIGTERM, ``--duration`` or ``--count``; the bag is then finalised (index, metadata) and
moved into place: a path ending in ``.mcap`` gives a single mcap file, another path a
rosbag2 directory (``--storage mcap|sqlite3``). Exit status: 0 bag written, 1 error.
"""
from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Dict, Optional, Sequence

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from ..bags.io import STORAGES, BagError, BagWriter
from ..bags.typesys import ensure_type
from .bag_play import msg_class

NODE_NAME = "bag_record"
_IGNORED = ("/rosout", "/parameter_events")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bag_record", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-o", "--output", required=True, type=Path,
                   help="bag to create: NAME.mcap (single file) or a directory name (rosbag2 bag)")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--topics", nargs="+", metavar="TOPIC", help="topics to record")
    what.add_argument("-a", "--all", action="store_true",
                      help="every topic that appears (except /rosout, /parameter_events)")
    p.add_argument("-s", "--storage", choices=STORAGES, default="mcap", help="storage of a bag directory")
    p.add_argument("--qos", choices=("auto", "reliable", "sensor-data"), default="auto")
    p.add_argument("--qos-depth", type=int, default=100, help="keep-last depth of the subscriptions")
    p.add_argument("-d", "--duration", type=float, default=0.0, metavar="S",
                   help="stop S seconds after starting (0: until Ctrl-C / SIGTERM)")
    p.add_argument("-n", "--count", type=int, default=0, metavar="N", help="stop after N messages (0: no limit)")
    p.add_argument("--no-compress", action="store_true", help="no zstd chunk compression (mcap)")
    return p


def _fail(msg: str, code: int = 1) -> int:
    print(f"bag_record: error: {msg}", file=sys.stderr, flush=True)
    return code


class Recorder:
    """Subscribes to topics as they appear and writes every message to the bag."""

    def __init__(self, node, writer, args) -> None:
        self.node = node
        self.writer = writer
        self.args = args
        self.wanted = list(args.topics or [])
        self.subs: Dict[str, object] = {}
        self.skipped: set = set()
        self.count = 0
        self.per_topic: Dict[str, int] = {}
        self.error: Optional[str] = None

    def _qos(self, topic: str):
        if self.args.qos == "sensor-data":
            return qos_profile_sensor_data
        reliability = ReliabilityPolicy.RELIABLE
        if self.args.qos == "auto":
            infos = self.node.get_publishers_info_by_topic(topic)
            if any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos):
                reliability = ReliabilityPolicy.BEST_EFFORT
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.args.qos_depth,
                          reliability=reliability, durability=DurabilityPolicy.VOLATILE)

    def discover(self) -> None:
        """Subscribe to wanted topics that have appeared in the graph since the last call."""
        log = self.node.get_logger()
        for topic, types in self.node.get_topic_names_and_types():
            if topic in self.subs or topic in self.skipped:
                continue
            if self.wanted and topic not in self.wanted:
                continue
            if not self.wanted and (topic in _IGNORED or topic.endswith("/_action/status")):
                continue
            if not self.node.get_publishers_info_by_topic(topic):
                continue  # only subscribers so far: wait for a publisher (its QoS decides ours)
            msgtype = types[0]
            if len(types) > 1:
                log.warning(f"{topic} has several types {types}; recording {msgtype}")
            try:
                cls = msg_class(msgtype)
                ensure_type(self.writer.store, msgtype)
                self.writer.connection(topic, msgtype)
            except (ImportError, BagError) as exc:
                log.error(f"cannot record {topic} [{msgtype}]: {exc}")
                self.skipped.add(topic)
                continue
            qos = self._qos(topic)
            self.subs[topic] = self.node.create_subscription(
                cls, topic, lambda raw, t=topic, m=msgtype: self._on_message(t, m, raw), qos, raw=True)
            self.per_topic[topic] = 0
            log.info(f"recording {topic} [{msgtype}] ({qos.reliability.name.lower()})")

    def _on_message(self, topic: str, msgtype: str, raw: bytes) -> None:
        if self.args.count and self.count >= self.args.count:
            return
        try:
            self.writer.write_raw(topic, msgtype, self.node.get_clock().now().nanoseconds, raw)
        except Exception as exc:  # noqa: BLE001 - report once, stop recording
            self.error = f"writing {topic}: {type(exc).__name__}: {exc}"
            return
        self.count += 1
        self.per_topic[topic] += 1


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(remove_ros_args(["bag_record"] + argv)[1:])
    if args.duration < 0 or args.count < 0 or args.qos_depth < 1:
        return _fail("--duration and --count must be >= 0, --qos-depth >= 1", 2)
    if args.output.suffix == ".mcap" and args.storage != "mcap":
        return _fail(f"{args.output}: a .mcap output needs --storage mcap", 2)
    if args.output.exists():
        return _fail(f"{args.output}: exists already, not overwriting", 2)

    stop = threading.Event()

    def on_signal(signum, _frame):
        stop.set()

    try:
        writer = BagWriter(args.output, args.storage, compress=not args.no_compress)
    except (BagError, OSError, ValueError) as exc:
        return _fail(str(exc))
    context = Context()
    rclpy.init(args=["bag_record"] + argv, context=context, signal_handler_options=SignalHandlerOptions.NO)
    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    node = None
    executor = None
    finished = False
    try:
        node = Node(NODE_NAME, context=context)
        log = node.get_logger()
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        rec = Recorder(node, writer, args)
        what = "all topics" if args.all else " ".join(args.topics)
        log.info(f"recording {what} into {args.output}"
                 + (f" for {args.duration:g} s" if args.duration else "")
                 + (f", at most {args.count} messages" if args.count else ""))
        t_end = time.monotonic() + args.duration if args.duration else None
        next_discovery = 0.0
        while not stop.is_set() and context.ok():
            now = time.monotonic()
            if t_end is not None and now >= t_end:
                break
            if args.count and rec.count >= args.count:
                break
            if rec.error:
                break
            if now >= next_discovery:
                rec.discover()
                next_discovery = now + (0.05 if len(rec.subs) < len(rec.wanted) or args.all else 0.5)
            executor.spin_once(timeout_sec=0.05)
        # take what has already arrived (e.g. a SIGTERM right after the publisher finished):
        # spin until three rounds in a row bring nothing new (at most 2 s)
        quiet, drain_end = 0, time.monotonic() + 2.0
        while quiet < 3 and time.monotonic() < drain_end and not rec.error \
                and not (args.count and rec.count >= args.count):
            before = rec.count
            executor.spin_once(timeout_sec=0.02)
            quiet = quiet + 1 if rec.count == before else 0
        missing = [t for t in rec.wanted if t not in rec.subs]
        if missing:
            log.warning(f"never saw a publisher on {missing}: not in the bag")
        for sub in list(rec.subs.values()):
            node.destroy_subscription(sub)
        writer.close()
        finished = True
        if rec.error:
            return _fail(f"{args.output}: {rec.error} (bag closed with {rec.count} messages)")
        log.info(f"wrote {args.output}: {rec.count} messages "
                 + ", ".join(f"{t} {n}" for t, n in sorted(rec.per_topic.items())))
        return 0
    except KeyboardInterrupt:
        return 0
    except Exception as exc:  # noqa: BLE001 - one line, bag aborted
        return _fail(f"{args.output}: {type(exc).__name__}: {exc}")
    finally:
        if not finished:
            try:
                writer.close()  # keep what was recorded
            except Exception:  # noqa: BLE001
                writer.abort()
        for s, h in old.items():
            signal.signal(s, h)
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


if __name__ == "__main__":
    sys.exit(main())
