"""Tests of gcn_match_ros.bags.source: BagSource windows as training problems, cycling, scenes, training on bags."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from gcn_match_ros.bags.contents import read_bag
from gcn_match_ros.bags.source import BagSource, bag_scene, check_disjoint_scenes, split_by_scene
from gcn_match_ros.learn.checkpoint import load_checkpoint
from gcn_match_ros.learn.config import TrainConfig
from gcn_match_ros.learn.model import GCNConfig
from gcn_match_ros.learn.objective import make_batch, make_sample, train_step
from gcn_match_ros.learn.sources import ShardedSource
from gcn_match_ros.learn.train import train
from gcn_match_ros.node_features import feature_dim
from gcn_match_ros.windowing import WindowAssembler, WindowConfig, window_problem

from conftest import TINY_BAG_SCENE

D = TINY_BAG_SCENE.descriptor_dim
MODEL = GCNConfig(in_dim=feature_dim(D), widths=(16, 16, 16, 16), out_dim=16, groups=4, skip_layers=(2, 4))


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_torch_thread):
    """Tiny graphs: one intra-op thread is fastest and immune to a busy shared CPU."""


def _same_pairs(gt):
    return (gt[:, None] == gt[None, :]) & (gt[:, None] >= 0)


def test_bag_source_windows_equal_assembler_on_bag_frames(tiny_bags):
    train_bag, _, probs = tiny_bags
    src = BagSource(train_bag, shuffle=False)
    # the node's assembly, by hand: frames in bag order into a WindowAssembler
    contents = read_bag(train_bag)
    asm = WindowAssembler(WindowConfig(cameras=tuple(contents.cameras)))
    windows = [w for f in contents.frames_in_order() for w in asm.add(f)] + asm.flush()
    assert len(src) == len(windows) == len(probs)
    assert [len(w) for w in windows] == [p.n_views for p in probs]  # the 2-view capture stays 2 views
    for k, (w, p, orig) in enumerate(zip(windows, src.problems, probs)):
        assert src.window_frames[k] == (0, [(f.camera_id, f.stamp_ns) for f in w])
        ref = window_problem(w)
        np.testing.assert_array_equal(p.keypoints, ref.keypoints)
        np.testing.assert_array_equal(p.descriptors, ref.descriptors)
        np.testing.assert_array_equal(p.view_offsets, orig.view_offsets)
        # poses from /<cam>/pose (world->camera) and K from camera_info: the epipolar loss applies
        assert p.has_poses
        np.testing.assert_allclose(p.R, orig.R, atol=1e-6)
        np.testing.assert_allclose(p.t, orig.t, atol=1e-5)
        np.testing.assert_allclose(p.K, orig.K)
        np.testing.assert_array_equal(_same_pairs(p.gt_track), _same_pairs(orig.gt_track))
    _, logs = train_step(_tiny_model(), make_batch([make_sample(src.problems[0])]), TrainConfig())
    assert np.isfinite(logs["epipolar"]) and logs["epipolar"] > 0


def _tiny_model():
    from gcn_match_ros.learn.model import GCN

    torch.manual_seed(0)
    return GCN(MODEL)


def test_bag_source_cycles_seeks_and_splits_by_scene(tiny_bags):
    train_bag, val_bag, _ = tiny_bags
    src = BagSource(train_bag, shuffle=True, seed=4)
    seq = [p.name for p, _ in zip(src(), range(13))]
    assert sorted(seq[:6]) == sorted(seq[6:12]) == sorted(p.name for p in src.problems)
    assert [p.name for p, _ in zip(src(7), range(4))] == seq[7:11]  # seekable
    once = BagSource(train_bag, shuffle=False, cycle=False)
    assert [p.name for p in once()] == [f"scene_a:{k}" for k in range(6)]
    # shards of two ranks are disjoint and together the first 2n problems
    r0 = [p.name for p, _ in zip(ShardedSource(src, 0, 2)(1), range(3))]
    r1 = [p.name for p, _ in zip(ShardedSource(src, 1, 2)(1), range(3))]
    assert sorted(r0 + r1) == sorted(seq[2:8]) and r0 == seq[2:8:2]
    # scenes: bags without image sources are named by file; overlap is refused
    assert src.scenes == ["scene_a"]
    val = BagSource(val_bag, cycle=False)
    check_disjoint_scenes(src, val)
    with pytest.raises(ValueError, match="both the training and the validation"):
        check_disjoint_scenes(src, BagSource([val_bag, train_bag], cycle=False))
    tr, va = split_by_scene([train_bag, val_bag], val_scenes=["scene_b"])
    assert (tr, va) == ([train_bag], [val_bag])
    # the shipped sample bags: scene names from their labels; the Strecha bag has poses
    sample_bags = Path(__file__).resolve().parents[1] / "bags"
    fountain, graf = sample_bags / "strecha_fountain_sift.mcap", sample_bags / "oxford_graf_sift.mcap"
    if fountain.is_file() and graf.is_file():
        f, g = BagSource(fountain, cycle=False), BagSource(graf, cycle=False)
        assert (len(f), f.has_poses, f.scenes) == (9, True, ["strecha/fountain-P11"])
        assert (len(g), g.has_poses, bag_scene(graf)) == (4, False, "oxford/graf")
        assert all(p.gt_track is not None and p.n_views == 3 for p in f.problems + g.problems)


def test_training_on_bags_reduces_val_loss_and_resumes(tmp_path, tiny_bags):
    train_bag, val_bag, _ = tiny_bags
    base = dict(lr=5e-3, batch_size=2, val_every=5, val_size=3, checkpoint_every=5, log_every=1,
                epipolar_weight=1.0, progress=False, plot=False)
    src, val = BagSource(train_bag, seed=0), BagSource(val_bag, cycle=False)
    run = tmp_path / "run"
    first = train(MODEL, src, val, TrainConfig(steps=15, **base), run)
    assert [h["step"] for h in first["train"]] == list(range(1, 16))
    _, meta = load_checkpoint(run / "checkpoint.pt")
    assert meta["extra"]["step"] == 15
    hist = train(MODEL, src, val, TrainConfig(steps=30, **dict(base, plot=True)), run, resume=True)
    assert [h["step"] for h in hist["train"]] == list(range(1, 31))  # continues at 16
    assert [h["step"] for h in hist["val"]] == [5, 10, 15, 20, 25, 30]
    vals = [h["loss"] for h in hist["val"]]
    assert min(vals) < 0.93 * vals[0], vals  # 0.83 on this data (seed 0)
    assert hist["best"]["loss"] == min(vals)
    assert np.isfinite(hist["val"][-1]["epipolar"])
    assert json.loads((run / "history.json").read_text())["train"][-1]["step"] == 30
    assert (run / "curves.png").stat().st_size > 10_000
