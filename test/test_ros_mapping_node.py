"""The example mapping node: MatchWindows with landmark ids + keypoints + camera poses -> a
PointCloud2 of triangulated landmarks near the true points; without poses, statistics only."""
import contextlib
import uuid

import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import PointCloud2

from conftest import domain_id
from gcn_match_msgs.msg import Keypoints, MatchWindow
from gcn_match_ros import solvers
from gcn_match_ros.data.rig_sequence import RigSequenceConfig, rig_sequence
from gcn_match_ros.geometry import rt_to_pose
from gcn_match_ros.landmark_map import LandmarkMap
from gcn_match_ros.ros.conversions import frame_to_keypoints, result_to_match_window
from gcn_match_ros.ros.mapping_node import MappingNode
from gcn_match_ros.ros.testing import RosSession
from gcn_match_ros.stamps import ns_to_sec_nanosec
from gcn_match_ros.stream import solve_stream
from gcn_match_ros.windowing import Frame

CFG = RigSequenceConfig(n_cameras=3, n_windows=4, n_points=800)


def _true_points(seed):
    rng = np.random.default_rng(seed)  # rig_sequence draws the scene first
    return np.stack([rng.uniform(-2.0, CFG.length_m, CFG.n_points),
                     rng.uniform(-CFG.half_width_m, CFG.half_width_m, CFG.n_points),
                     rng.uniform(0.0, CFG.height_m, CFG.n_points)], 1)


def _pose(R, t, stamp_ns):
    pos, q = rt_to_pose(R, t)
    msg = PoseStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = ns_to_sec_nanosec(stamp_ns)
    msg.header.frame_id = "world"
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = pos.tolist()
    msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z, msg.pose.orientation.w = q.tolist()
    return msg


@contextlib.contextmanager
def _mapping_session(cameras):
    """A MappingNode in a namespace of its own, with publishers of every camera's keypoints and
    pose and of the matches, and the landmark clouds it publishes."""
    ns = f"/t{uuid.uuid4().hex[:10]}"
    with RosSession("tester", namespace=ns, domain_id=domain_id()) as session:
        node = session.add_node(MappingNode(context=session.context, namespace=ns))
        pubs = {c: (session.publisher(Keypoints, f"{c}/keypoints"), session.publisher(PoseStamped, f"{c}/pose"))
                for c in cameras}
        matches = session.publisher(MatchWindow, "matches")
        clouds = session.collect(PointCloud2, "mapping_node/landmarks")
        assert session.spin_until(lambda: matches.get_subscription_count() > 0
                                  and all(k.get_subscription_count() > 0 for k, _ in pubs.values()))
        yield session, node, pubs, matches, clouds


def _publish_window(session, node, pubs, matches, problem, solved, stamp, pose=None):
    """One window: every view's keypoints and pose (``pose(view, message)`` may change the pose
    first), then — once the node holds them — its MatchWindow."""
    result, landmarks = solved
    frames = [Frame(camera_id=c, stamp_ns=stamp, keypoints=problem.keypoints[problem.view_slice(v)],
                    descriptors=problem.descriptors[problem.view_slice(v)], K=problem.K[v], image_size=(640, 480))
              for v, c in enumerate(problem.camera_ids)]
    for v, f in enumerate(frames):
        message = _pose(problem.R[v], problem.t[v], stamp)
        if pose is not None:
            pose(v, message)
        pubs[f.camera_id][0].publish(frame_to_keypoints(f))
        pubs[f.camera_id][1].publish(message)
    # the keypoints and poses arrive first (waited for: a busy machine may take longer than a guess)
    assert session.spin_until(lambda: all(node._keypoints.find(c, stamp) is not None
                                          and node._poses.find(c, stamp) is not None for c in pubs), timeout=10)
    matches.publish(result_to_match_window(frames, result, landmark_ids=landmarks.ids, landmark_ages=landmarks.ages_s))


def test_the_map_holds_the_landmarks_near_the_true_points():
    problems, truth, stamps = rig_sequence(CFG, rng=3)
    X = _true_points(3)
    solved = list(solve_stream(solvers.create("gcn"), problems, stamps))
    with _mapping_session(problems[0].camera_ids) as (session, node, pubs, matches, clouds):
        for k, (p, window, stamp) in enumerate(zip(problems, solved, stamps)):
            _publish_window(session, node, pubs, matches, p, window, stamp)
            assert session.spin_until(lambda: len(clouds) == k + 1, timeout=10)
        cloud = clouds[-1]
        assert cloud.header.frame_id == "world" and cloud.point_step == 20 and cloud.width > 50
        data = np.frombuffer(bytes(cloud.data), np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                                          ("id", "<u4"), ("sightings", "<u4")]))
        # every mapped landmark against the true point its keypoints show in the last window
        last_ids, last_truth = solved[-1][1].ids, truth[-1]
        errors = []
        for row in data:
            sel = (last_ids == row["id"]) & (last_truth >= 0)
            if sel.any():
                errors.append(np.linalg.norm(np.array([row["x"], row["y"], row["z"]]) -
                                             X[np.bincount(last_truth[sel]).argmax()]))
        assert len(errors) > 50 and np.median(errors) < 0.5, np.median(errors)
        assert node.counts["maps published"] == 4 and node.counts["windows without poses"] == 0
        # the map predicted the later windows' sightings of its landmarks (held out when predicted)
        held_out = np.asarray(node.held_out_px)
        assert held_out.size > 100 and np.median(held_out) < 3.0, (held_out.size, np.median(held_out))


def test_a_landmark_map_refuses_points_that_do_not_reproject():
    K = np.array([[400.0, 0, 320], [0, 400, 240], [0, 0, 1]])
    R = np.eye(3)
    ts = [np.zeros(3), np.array([-0.5, 0, 0])]
    X = np.array([0.3, -0.2, 5.0])
    xy = [K @ (R @ X + t) for t in ts]
    xy = np.array([v[:2] / v[2] for v in xy])
    m = LandmarkMap()
    mapped = m.add_window(np.array([7, 7]), xy, np.array([0, 1]), np.stack([K, K]), np.stack([R, R]), np.stack(ts), 0)
    assert mapped == [7] and np.allclose(m.points[7], X, atol=1e-6)
    bad = xy.copy()
    bad[1, 1] += 30.0  # off the epipolar line: no point explains both sightings
    m2 = LandmarkMap()
    assert m2.add_window(np.array([3, 3]), bad, np.array([0, 1]), np.stack([K, K]), np.stack([R, R]), np.stack(ts), 0) == []
    # landmarks unseen for max_age are dropped
    m.add_window(np.array([-1]), xy[:1], np.array([0]), K[None], R[None], ts[0][None], int(10e9))
    assert 7 not in m.points


def test_held_out_errors_predict_a_new_view_from_the_map():
    K = np.array([[400.0, 0, 320], [0, 400, 240], [0, 0, 1]])
    R = np.eye(3)
    ts = [np.zeros(3), np.array([-0.5, 0, 0]), np.array([-1.0, 0, 0])]
    X = np.array([0.3, -0.2, 5.0])
    xy = np.array([(K @ (R @ X + t))[:2] / (K @ (R @ X + t))[2] for t in ts])
    m = LandmarkMap()
    # nothing mapped yet: nothing predicted
    assert m.held_out_errors(np.array([7]), xy[:1], np.array([0]), K[None], R[None], ts[0][None]).size == 0
    m.add_window(np.array([7, 7]), xy[:2], np.array([0, 1]), np.stack([K, K]), np.stack([R, R]), np.stack(ts[:2]), 0)
    # the third view, not used to map: the right sighting lands on it, one 8 px off misses by 8 px,
    # an unmapped id and a keypoint without landmark are not scored
    third = np.array([xy[2], xy[2] + [0.0, 8.0], xy[2], xy[2]])
    err = m.held_out_errors(np.array([7, 7, 9, -1]), third, np.zeros(4, int), K[None], R[None], ts[2][None])
    np.testing.assert_allclose(err, [0.0, 8.0], atol=1e-6)
    # a camera the point is behind: inf
    behind = m.held_out_errors(np.array([7]), xy[2:], np.array([0]), K[None], np.diag([1.0, -1, -1])[None],
                               ts[2][None])
    assert np.isinf(behind).all()


def test_a_window_with_a_pose_that_is_none_is_counted_not_mapped():
    problems, _, stamps = rig_sequence(CFG, rng=4)
    solved = list(solve_stream(solvers.create("nn"), problems[:2], stamps[:2]))

    def unknown_orientation(view, message):  # a driver's all-zero "orientation unknown", in the first window
        if view == 1:
            o = message.pose.orientation
            o.x = o.y = o.z = o.w = 0.0

    with _mapping_session(problems[0].camera_ids) as (session, node, pubs, matches, clouds):
        for k, (p, window, stamp) in enumerate(zip(problems, solved, stamps)):
            _publish_window(session, node, pubs, matches, p, window, stamp, unknown_orientation if k == 0 else None)
            assert session.spin_until(lambda: sum(node.counts.values()) >= k + 1, timeout=10)
        assert session.spin_until(lambda: len(clouds) == 1, timeout=10)
        assert node.counts["windows with an invalid pose"] == 1 and node.counts["maps published"] == 1
