"""Tests of gcn_match_ros.load_shedding.KeypointBudget: down when behind, back up when calm."""
from gcn_match_ros.load_shedding import KeypointBudget


def test_the_budget_falls_when_behind_and_recovers_when_calm():
    b = KeypointBudget(full=1000, floor=200, step=0.75, calm=3)
    assert not b.degraded
    for expected in (750, 562, 421, 315, 236, 200, 200):  # each slow solve let a window be superseded
        b.behind()
        assert b.current == expected
        b.solved(0.15, 0.1, degraded=True)
    # solved with time to spare: back up one step per 3 calm windows
    for _ in range(3):
        b.solved(0.02, 0.1, degraded=True)
    assert b.current == 267 and b.degraded_windows == 10
    # a slow window breaks the calm run (a quarter of 3 windows: none may be slow)
    b.solved(0.09, 0.1, degraded=True)
    b.solved(0.02, 0.1, degraded=True)
    b.solved(0.02, 0.1, degraded=True)
    assert b.current == 267
    for _ in range(200):
        b.solved(0.02, 0.1, degraded=b.degraded)
    assert b.current == 1000 and not b.degraded


def test_the_budget_recovers_through_periodic_slow_windows_but_not_under_load():
    """A stream's periodic slow windows (a camera pair without a trusted model re-fitted every
    eighth window: rig_memory's back-off) must not keep the budget down; a load where slow windows
    are common must."""
    b = KeypointBudget(full=1000, floor=200, calm=20)
    b.behind()
    assert b.current == 750
    for k in range(20):  # one window in eight slow: 3 of these 20
        b.solved(0.13 if k % 8 == 2 else 0.03, 0.1, degraded=True)
    assert b.current == 1000
    b.behind()
    for k in range(100):  # one in three slow
        b.solved(0.09 if k % 3 == 0 else 0.03, 0.1, degraded=True)
    assert b.current == 750


def test_a_disabled_budget_never_degrades():
    b = KeypointBudget(full=500, floor=0)
    b.behind()
    assert b.current == 500 and not b.enabled
    b = KeypointBudget(full=500, floor=200)
    b.behind()
    b.reconfigure(800)
    assert b.current == 800 and not b.degraded


def test_windows_superseded_during_one_solve_cut_the_budget_once():
    """A stream's first window fits every camera pair's model (~0.3 s at 8 x 500): the two or three
    windows superseded meanwhile are one overload, not three; the next slow solve cuts again."""
    b = KeypointBudget(full=1024, floor=200, step=0.75, calm=20)
    for _ in range(3):
        b.behind()
    assert b.current == 768
    b.solved(0.3, 0.1, degraded=False)
    b.behind()
    b.behind()
    assert b.current == 576
    b.reconfigure(800)  # a new maximum starts over: its first overload cuts at once
    b.behind()
    assert b.current == 600
