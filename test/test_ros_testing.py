"""Tests of gcn_match_ros.ros.testing: RosSession publish/collect round trips over DDS, background spinning, close."""
import threading
import time
import uuid

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from std_msgs.msg import String

from gcn_match_msgs.msg import Keypoints
from gcn_match_ros.bags.codec import frame_from_keypoints_msg
from gcn_match_ros.ros.conversions import frame_to_keypoints
from gcn_match_ros.ros.testing import RELIABLE, RosSession, diagnostic_values

from conftest import PermutedScene, domain_id


def unique_namespace() -> str:
    return f"/t{uuid.uuid4().hex[:10]}"


def wait_for(condition, timeout: float = 10.0) -> bool:
    """Poll ``condition`` (another thread spins) until it holds or ``timeout`` seconds pass."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.01)
    return bool(condition())


def test_collect_publisher_spin_until_round_trip():
    ns = unique_namespace()
    with RosSession("tester", namespace=ns, domain_id=domain_id()) as session:
        assert session.node.get_namespace() == ns and session.context.ok()
        texts = session.collect(String, "chatter")
        frames = session.collect(Keypoints, "cam0/keypoints")
        text_pub = session.publisher(String, "chatter")
        kp_pub = session.publisher(Keypoints, "cam0/keypoints")
        assert text_pub.qos_profile.reliability == RELIABLE.reliability and text_pub.qos_profile.depth == 50
        assert session.spin_until(lambda: text_pub.get_subscription_count() > 0
                                  and kp_pub.get_subscription_count() > 0), "discovery timed out"
        frame, _ = PermutedScene(points=40, dim=128, seed=2).frame("cam0", 1_700_000_000.25)
        for k in range(3):
            text_pub.publish(String(data=f"hello {k}"))
        kp_pub.publish(frame_to_keypoints(frame))
        assert session.spin_until(lambda: len(texts) == 3 and len(frames) == 1)
        assert [m.data for m in texts] == ["hello 0", "hello 1", "hello 2"]  # reliable, in order
        got = frame_from_keypoints_msg(frames[0])
        assert (got.camera_id, got.stamp_ns, got.frame_id) == ("cam0", frame.stamp_ns, "cam0_optical_frame")
        np.testing.assert_array_equal(got.keypoints, frame.keypoints)
        np.testing.assert_array_equal(got.descriptors, frame.descriptors)
        # a condition that never holds: False after the timeout
        assert session.spin_until(lambda: len(texts) > 3, timeout=0.2) is False
    assert not session.context.ok()  # closed by the with block


def test_spin_in_background_and_close():
    ns = unique_namespace()
    session = RosSession("bg", namespace=ns, domain_id=domain_id())
    try:
        received = session.collect(String, "numbers")
        pub = session.publisher(String, "numbers")
        main_thread = threading.get_ident()
        threads = set()
        session.node.create_subscription(String, "numbers", lambda m: threads.add(threading.get_ident()), RELIABLE)
        with session.spin_in_background() as same:
            assert same is session
            assert wait_for(lambda: pub.get_subscription_count() >= 2), "discovery timed out"
            for k in range(5):
                pub.publish(String(data=str(k)))
            assert wait_for(lambda: len(received) == 5)
        assert [m.data for m in received] == ["0", "1", "2", "3", "4"]
        assert threads and main_thread not in threads  # the callbacks ran on the spinning thread
        assert session._spinner is None
    finally:
        session.close()
    assert not session.context.ok()
    session.close()  # closing twice is harmless


def test_diagnostic_values_finds_a_nodes_status():
    msg = DiagnosticArray(status=[
        DiagnosticStatus(name="other", hardware_id="/other", values=[KeyValue(key="a", value="1")]),
        DiagnosticStatus(name="m", hardware_id="/ns/matcher_node", level=DiagnosticStatus.WARN,
                         values=[KeyValue(key="windows published", value="3"), KeyValue(key="worker", value="idle")])])
    status, values = diagnostic_values(msg, "/ns/matcher_node")
    assert status.name == "m" and status.level == DiagnosticStatus.WARN
    assert values == {"windows published": "3", "worker": "idle"}
    assert diagnostic_values(msg, "/nobody") is None
    assert diagnostic_values(DiagnosticArray(), "/ns/matcher_node") is None
