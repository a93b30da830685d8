"""The visualiser node: MatchWindow + the cameras' keypoints and images -> one picture on
~/image, tracks drawn; windows it cannot draw in time are skipped and counted, never queued."""
import time
import uuid

import numpy as np
from rclpy.parameter import Parameter
from sensor_msgs.msg import CompressedImage, Image

import cv2

from conftest import PermutedScene, domain_id
from gcn_match_msgs.msg import Keypoints, MatchWindow
from gcn_match_ros.problem import Result
from gcn_match_ros.ros.conversions import frame_to_keypoints, result_to_match_window
from gcn_match_ros.ros.testing import RosSession
from gcn_match_ros.ros.visualizer_node import VisualizerNode, image_to_bgr
from gcn_match_ros.stamps import ns_to_sec_nanosec
from gcn_match_ros.track_image import TITLE_PX

CAMS = ["cam0", "cam1", "cam2"]


def _image_msg(stamp_ns, value):
    img = np.full((480, 640, 3), value, np.uint8)
    msg = Image(height=480, width=640, encoding="bgr8", is_bigendian=0, step=640 * 3, data=img.tobytes())
    msg.header.stamp.sec, msg.header.stamp.nanosec = ns_to_sec_nanosec(stamp_ns)
    return msg


def _send_window(session, pubs, image_pubs, matches_pub, scene, t):
    frames, gts = [], []
    for i, cam in enumerate(CAMS):
        f, gt = scene.frame(cam, t)
        frames.append(f)
        gts.append(gt)
        pubs[cam].publish(frame_to_keypoints(f))
        image_pubs[cam].publish(_image_msg(f.stamp_ns, 100 + 40 * i))
    gt = np.concatenate(gts)
    result = Result(track=np.where(gt >= 0, gt, -1), pair_rows=np.zeros(0, np.int64), pair_cols=np.zeros(0, np.int64),
                    pair_scores=np.zeros(0, np.float32))  # the true tracks
    matches_pub.publish(result_to_match_window(frames, result, method="truth"))
    return frames


def test_the_visualizer_draws_windows_and_skips_rather_than_lags():
    ns = f"/t{uuid.uuid4().hex[:10]}"
    with RosSession("tester", namespace=ns, domain_id=domain_id()) as session:
        node = session.add_node(VisualizerNode(context=session.context, namespace=ns, parameter_overrides=[
            Parameter("height", value=120), Parameter("max_rate", value=2.0)]))
        pubs = {c: session.publisher(Keypoints, f"{c}/keypoints") for c in CAMS}
        image_pubs = {c: session.publisher(Image, f"{c}/image") for c in CAMS}
        matches_pub = session.publisher(MatchWindow, "matches")
        images = session.collect(Image, "visualizer_node/image")
        assert session.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs.values())
                                  and matches_pub.get_subscription_count() > 0)
        scene = PermutedScene(points=20, dim=32, distractors=2, seed=3)
        _send_window(session, pubs, image_pubs, matches_pub, scene, time.time())
        assert session.spin_until(lambda: len(images) == 1, timeout=10)
        img = images[0]
        assert img.encoding == "bgr8" and img.height == TITLE_PX + 120 and img.width > 3 * 160
        pixels = np.frombuffer(bytes(img.data), np.uint8).reshape(img.height, img.width, 3)
        assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 10  # images, grey dots, coloured tracks
        # ten windows in a burst: drawn at most twice a second, the rest skipped, nothing queued
        for k in range(10):
            _send_window(session, pubs, image_pubs, matches_pub, scene, time.time() + 0.01 * k)
        # every window of the burst drawn or skipped (waited for, not guessed), and the drawn ones received
        assert session.spin_until(lambda: node.counts["windows skipped"] + node.counts["images published"] == 11
                                  and len(images) == node.counts["images published"], timeout=10)
        assert node.counts["windows skipped"] >= 5 and len(images) <= 4
        assert node.counts["views without image"] == 0 and node.counts["windows without keypoints"] == 0


def test_image_conversion_handles_the_usual_encodings_and_refuses_others():
    rgb = Image(height=2, width=3, encoding="rgb8", step=9, data=bytes(range(18)))
    assert image_to_bgr(rgb)[0, 0].tolist() == [2, 1, 0]
    assert image_to_bgr(Image(height=2, width=3, encoding="mono8", step=4, data=bytes(8))).shape == (2, 3)
    ok, png = cv2.imencode(".png", np.zeros((4, 5, 3), np.uint8))
    assert image_to_bgr(CompressedImage(format="png", data=png.tobytes())).shape == (4, 5, 3)
    for bad in (Image(height=2, width=3, encoding="32FC1", step=12, data=bytes(24)),
                Image(height=2, width=3, encoding="bgr8", step=9, data=bytes(10)),
                CompressedImage(format="jpeg", data=b"not an image")):
        try:
            image_to_bgr(bad)
        except ValueError:
            continue
        raise AssertionError(f"accepted {bad.encoding if isinstance(bad, Image) else bad.format}")
