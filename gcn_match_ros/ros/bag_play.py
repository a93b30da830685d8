"""Replay a rosbag2 bag (mcap or sqlite3; a file or a bag directory) onto live topics.

What ``ros2 bag play`` does, for machines without the ros2 CLI::

    bag_play bags/strecha_fountain_sift.mcap --rate 2 --wait-for-subscribers 1
    bag_play BAG --topics /cam0/keypoints /cam1/keypoints --loop --restamp
    bag_play BAG --ros-args -r /cam0/keypoints:=/rig/cam0/keypoints   # remapping works

Messages are published as the raw CDR bytes stored in the bag (``Publisher.publish(bytes)``,
no decoding), each on a publisher of the generated message class named by the bag's type
(``pkg/msg/Name`` -> ``pkg.msg.Name``), in log-time order with the original relative
timing divided by ``--rate``. QoS: reliable, volatile, keep-last ``--qos-depth`` by
default; ``--qos sensor-data`` uses rclpy's ``qos_profile_sensor_data`` (best effort).

``--restamp`` shifts the header stamp of every message whose type starts with a
``std_msgs/Header`` by one constant (wall-clock start minus the bag's first log time,
re-taken at each ``--loop`` pass), so stamps look live (latency measurable, no
``out_of_order`` drops when looping) while their differences, hence the matcher's
windows, stay those of the bag.

Exit status: 0 done or interrupted (Ctrl-C / SIGTERM), 1 unreadable/truncated bag (one
line on stderr), 2 bad arguments.
"""
from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Dict, Optional, Sequence

import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args
from tqdm import tqdm

from ..bags.io import BagError, BagInfo, bag_info, iter_raw, restamp_cdr
from ..bags.typesys import has_header, typestore

NODE_NAME = "bag_play"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bag_play", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", type=Path, help="bag: .mcap / .db3 file or rosbag2 directory")
    p.add_argument("-r", "--rate", type=float, default=1.0, help="playback speed factor (2 = twice as fast)")
    p.add_argument("-l", "--loop", action="store_true", help="play the bag again and again")
    p.add_argument("--topics", nargs="+", metavar="TOPIC", help="play only these topics (exact names)")
    p.add_argument("--qos", choices=("reliable", "sensor-data"), default="reliable",
                   help="publisher QoS (default reliable; sensor-data = best effort)")
    p.add_argument("--qos-depth", type=int, default=10, help="keep-last depth of the reliable profile")
    p.add_argument("--wait-for-subscribers", type=int, default=0, metavar="N",
                   help="before playing, wait until every played topic has N matched subscribers")
    p.add_argument("--wait-timeout", type=float, default=10.0, metavar="S",
                   help="give up waiting after S seconds (then play anyway, with a warning)")
    p.add_argument("--restamp", action="store_true",
                   help="shift header stamps so the bag's start is now (differences kept)")
    p.add_argument("--wait-for-all-acked", type=float, default=0.0, metavar="S",
                   help="at the end, wait up to S seconds until reliable subscribers acknowledged "
                        "everything (acks of small messages can take a heartbeat period, ~3 s)")
    p.add_argument("--delay", type=float, default=0.0, metavar="S", help="sleep S seconds before playing")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def _fail(msg: str, code: int = 1) -> int:
    print(f"bag_play: error: {msg}", file=sys.stderr, flush=True)
    return code


def msg_class(msgtype: str):
    """The generated Python class of ``pkg/msg/Name``.

    Raises:
        ImportError: the message package is not installed/sourced.
    """
    parts = msgtype.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3:
        raise ImportError(f"not a message type name: {msgtype!r}")
    module = importlib.import_module(f"{parts[0]}.{parts[1]}")
    try:
        return getattr(module, parts[2])
    except AttributeError:
        raise ImportError(f"{parts[0]}.{parts[1]} has no message {parts[2]}") from None


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(remove_ros_args(["bag_play"] + argv)[1:])
    if args.rate <= 0 or args.qos_depth < 1 or args.wait_for_subscribers < 0 or args.wait_timeout < 0:
        return _fail("--rate and --qos-depth must be > 0, --wait-for-subscribers and --wait-timeout >= 0", 2)

    # The bag first: a missing/truncated bag fails fast, before any ROS set-up.
    try:
        info = bag_info(args.bag)
    except BagError as exc:
        return _fail(str(exc))
    topics = dict(info.topics)
    if args.topics:
        unknown = [t for t in args.topics if t not in topics]
        if unknown:
            return _fail(f"{args.bag}: no topic(s) {unknown}; the bag has {sorted(topics)}", 2)
        topics = {t: topics[t] for t in args.topics}
    if not topics or info.message_count == 0:
        return _fail(f"{args.bag}: nothing to play (no messages)", 1)

    stop = threading.Event()

    def on_signal(signum, _frame):
        stop.set()

    context = Context()
    rclpy.init(args=["bag_play"] + argv, context=context, signal_handler_options=SignalHandlerOptions.NO)
    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    node = None
    try:
        node = Node(NODE_NAME, context=context)
        log = node.get_logger()
        if args.qos == "sensor-data":
            qos = qos_profile_sensor_data
        else:
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=args.qos_depth,
                             reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
        store = typestore()
        pubs: Dict[str, object] = {}
        restamp: Dict[str, bool] = {}
        for topic, msgtype in sorted(topics.items()):
            try:
                cls = msg_class(msgtype)
            except ImportError as exc:
                log.warning(f"skipping {topic}: no Python message class for {msgtype} ({exc})")
                continue
            pubs[topic] = node.create_publisher(cls, topic, qos)
            restamp[topic] = args.restamp and has_header(msgtype, store)
        if not pubs:
            return _fail(f"{args.bag}: none of the bag's message types can be published here")
        total = sum(info.counts.get(t, 0) for t in pubs)
        log.info(f"playing {args.bag} ({total} messages on {len(pubs)} topics, "
                 f"{(info.end_ns - info.start_ns) * 1e-9:.2f} s of bag time) at rate {args.rate:g}, "
                 f"{args.qos} QoS")

        if args.loop and not args.restamp:
            log.warning("--loop without --restamp repeats the same header stamps each pass "
                        "(a matcher drops them as out of order); add --restamp")
        if args.wait_for_subscribers:
            deadline = time.monotonic() + args.wait_timeout
            while not stop.is_set():
                lacking = [t for t, p in pubs.items() if p.get_subscription_count() < args.wait_for_subscribers]
                if not lacking:
                    break
                if time.monotonic() > deadline:
                    log.warning(f"fewer than {args.wait_for_subscribers} subscriber(s) after "
                                f"{args.wait_timeout:g} s on {lacking}; playing anyway")
                    break
                stop.wait(0.02)
        if args.delay > 0:
            stop.wait(args.delay)
        played = _play(args, info, pubs, restamp, stop, log)
        if stop.is_set():
            log.info(f"interrupted after {played} messages")
        else:
            log.info(f"done: {played} messages")
        if args.wait_for_all_acked > 0 and args.qos != "sensor-data" and not stop.is_set():
            from rclpy.duration import Duration

            deadline = time.monotonic() + args.wait_for_all_acked
            for topic, pub in pubs.items():
                left = max(0.0, deadline - time.monotonic())
                if pub.get_subscription_count() and not pub.wait_for_all_acked(Duration(seconds=left)):
                    log.warning(f"{topic}: not all messages acknowledged within {args.wait_for_all_acked:g} s")
        return 0
    except BagError as exc:
        return _fail(str(exc))
    except KeyboardInterrupt:
        return 0
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


def _play(args, info: BagInfo, pubs: Dict[str, object], restamp: Dict[str, bool],
          stop: threading.Event, log) -> int:
    """Publish the bag (repeatedly with --loop); returns the number of messages published."""
    total = sum(info.counts.get(t, 0) for t in pubs)
    played = 0
    passes = 0
    bar = tqdm(total=total, desc=f"bag_play {args.bag.name}", unit="msg", disable=args.quiet,
               file=sys.stderr, dynamic_ncols=True)
    with bar:
        while not stop.is_set():
            passes += 1
            if passes > 1:
                bar.reset(total=total)
            t0 = time.monotonic()
            offset = time.time_ns() - info.start_ns
            for topic, _, log_ns, raw in iter_raw(args.bag, list(pubs)):
                due = t0 + (log_ns - info.start_ns) * 1e-9 / args.rate
                delay = due - time.monotonic()
                if delay > 0 and stop.wait(delay):
                    break
                if stop.is_set():
                    break
                if restamp[topic]:
                    try:
                        raw = restamp_cdr(raw, offset)
                    except ValueError as exc:
                        log.warning(f"{topic}: not restamped ({exc})", throttle_duration_sec=5.0)
                pubs[topic].publish(bytes(raw))
                played += 1
                bar.update(1)
            if not args.loop:
                break
    return played


if __name__ == "__main__":
    sys.exit(main())
