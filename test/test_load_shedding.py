"""Tests of gcn_match_ros.load_shedding.KeypointBudget: down when behind, back up when calm."""
from gcn_match_ros.load_shedding import KeypointBudget


def test_the_budget_falls_when_behind_and_recovers_when_calm():
    b = KeypointBudget(full=1000, floor=200, step=0.75, calm=3)
    assert not b.degraded
    for expected in (750, 562, 421, 315, 236, 200, 200):
        b.behind()
        assert b.current == expected
    # solved with time to spare: back up one step per 3 calm windows
    for _ in range(3):
        b.solved(0.02, 0.1, degraded=True)
    assert b.current == 267 and b.degraded_windows == 3
    # a slow window breaks the calm run
    b.solved(0.09, 0.1, degraded=True)
    b.solved(0.02, 0.1, degraded=True)
    b.solved(0.02, 0.1, degraded=True)
    assert b.current == 267
    for _ in range(200):
        b.solved(0.02, 0.1, degraded=b.degraded)
    assert b.current == 1000 and not b.degraded


def test_a_disabled_budget_never_degrades():
    b = KeypointBudget(full=500, floor=0)
    b.behind()
    assert b.current == 500 and not b.enabled
    b = KeypointBudget(full=500, floor=200)
    b.behind()
    b.reconfigure(800)
    assert b.current == 800 and not b.degraded
