"""The managed matcher (matcher_node.LifecycleMatcherNode), driven through its lifecycle
services as a lifecycle manager would: configure loads the model (a bad parameter leaves it
unconfigured), activate matches, deactivate stops matching and keeps the model, cleanup
releases it, and it can be configured and activated again."""
import time
import uuid

import numpy as np
import torch
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.parameter import Parameter

from conftest import PROCESS_CPUS, PermutedScene, domain_id, needs_two_cpus, second_thread_cpus
from gcn_match_msgs.msg import Keypoints, MatchWindow
from gcn_match_ros.ros.conversions import frame_to_keypoints
from gcn_match_ros.ros.matcher_node import PER_WINDOW, LifecycleMatcherNode
from gcn_match_ros.ros.testing import RosSession

CAMS = ["cam0", "cam1", "cam2"]


class _Manager:
    """Calls a node's lifecycle services from the session's own node."""

    def __init__(self, session, fqn):
        self.session = session
        self.change = session.node.create_client(ChangeState, f"{fqn}/change_state")
        self.get = session.node.create_client(GetState, f"{fqn}/get_state")
        assert session.spin_until(lambda: self.change.service_is_ready() and self.get.service_is_ready())

    def _call(self, client, request):
        future = client.call_async(request)
        assert self.session.spin_until(future.done, timeout=30), "service call timed out"
        return future.result()

    def transition(self, transition_id: int) -> bool:
        return self._call(self.change, ChangeState.Request(transition=Transition(id=transition_id))).success

    def state(self) -> int:
        return self._call(self.get, GetState.Request()).current_state.id


def _publish_window(session, pubs, scene):
    t = time.time()
    for i, cam in enumerate(CAMS):
        pubs[cam].publish(frame_to_keypoints(scene.frame(cam, t - 0.002 * i)[0]))


def test_lifecycle_transitions_through_the_services():
    ns = f"/t{uuid.uuid4().hex[:10]}"
    with RosSession("tester", namespace=ns, domain_id=domain_id()) as session:
        node = session.add_node(LifecycleMatcherNode(context=session.context, namespace=ns, parameter_overrides=[
            Parameter("solver", value="nn"), Parameter("max_age", value=3.0)]))
        manager = _Manager(session, node.get_fully_qualified_name())
        windows = session.collect(MatchWindow, "matcher_node/matches")
        pubs = {c: session.publisher(Keypoints, f"{c}/keypoints") for c in CAMS}
        scene = PermutedScene(points=30, dim=64, seed=5)
        assert manager.state() == State.PRIMARY_STATE_UNCONFIGURED and not node.solver_loaded

        assert manager.transition(Transition.TRANSITION_CONFIGURE)
        assert manager.state() == State.PRIMARY_STATE_INACTIVE and node.solver_loaded
        assert not node._subs  # configured, not yet matching

        assert manager.transition(Transition.TRANSITION_ACTIVATE)
        assert manager.state() == State.PRIMARY_STATE_ACTIVE
        assert session.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()))
        _publish_window(session, pubs, scene)
        assert session.spin_until(lambda: len(windows) == 1)

        assert manager.transition(Transition.TRANSITION_DEACTIVATE)
        assert manager.state() == State.PRIMARY_STATE_INACTIVE and node.solver_loaded
        assert session.spin_until(lambda: all(p.get_subscription_count() == 0 for p in pubs.values()))
        _publish_window(session, pubs, scene)
        session.spin_until(lambda: False, timeout=0.5)
        assert len(windows) == 1  # not matching while inactive

        assert manager.transition(Transition.TRANSITION_ACTIVATE)  # the model is still loaded
        assert session.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()))
        _publish_window(session, pubs, scene)
        assert session.spin_until(lambda: len(windows) == 2)
        assert np.all(np.asarray(windows[-1].track) >= -1)

        assert manager.transition(Transition.TRANSITION_DEACTIVATE)
        assert manager.transition(Transition.TRANSITION_CLEANUP)
        assert manager.state() == State.PRIMARY_STATE_UNCONFIGURED and not node.solver_loaded
        assert manager.transition(Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)
        assert manager.state() == State.PRIMARY_STATE_FINALIZED


def test_a_bad_parameter_leaves_it_unconfigured():
    ns = f"/t{uuid.uuid4().hex[:10]}"
    with RosSession("tester", namespace=ns, domain_id=domain_id()) as session:
        node = session.add_node(LifecycleMatcherNode(context=session.context, namespace=ns, parameter_overrides=[
            Parameter("solver", value="nope")]))
        manager = _Manager(session, node.get_fully_qualified_name())
        assert not manager.transition(Transition.TRANSITION_CONFIGURE)
        assert manager.state() == State.PRIMARY_STATE_UNCONFIGURED and not node.solver_loaded
        assert manager.transition(Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)


@needs_two_cpus
def test_pinned_solve_threads_follow_activation():
    """cpu_affinity: the worker pins the solve's threads while active and gives them back when
    deactivated (so an inactive node leaves its process's threads as they were), then again."""
    allowed = PROCESS_CPUS
    torch_threads = torch.get_num_threads()
    second_before = second_thread_cpus()
    ns = f"/t{uuid.uuid4().hex[:10]}"
    with RosSession("tester", namespace=ns, domain_id=domain_id()) as session:
        node = session.add_node(LifecycleMatcherNode(context=session.context, namespace=ns, parameter_overrides=[
            Parameter("solver", value="nn"), Parameter("cpu_affinity", value=allowed[0])]))
        manager = _Manager(session, node.get_fully_qualified_name())
        assert manager.transition(Transition.TRANSITION_CONFIGURE)
        pinned = f"{allowed[0]}, {allowed[1]}"
        for _ in range(2):
            assert manager.transition(Transition.TRANSITION_ACTIVATE)
            assert session.spin_until(lambda: node._solve_cpus == pinned)
            assert second_thread_cpus() == {allowed[1]}
            assert manager.transition(Transition.TRANSITION_DEACTIVATE)
            assert node._solve_cpus == PER_WINDOW and torch.get_num_threads() == torch_threads
            assert second_thread_cpus() == second_before
        assert manager.transition(Transition.TRANSITION_CLEANUP)
