"""Training from rosbag2 bags (BagSource), resume, plots, and `gcn-match train` end to end."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from gcn_match_ros import cli
from gcn_match_ros.bags.contents import read_bag
from gcn_match_ros.data import synthetic
from gcn_match_ros.bags.make import write_problems_bag
from gcn_match_ros.bags.source import BagSource, bag_scene, check_disjoint_scenes, split_by_scene
from gcn_match_ros.node_features import feature_dim
from gcn_match_ros.learn.checkpoint import load_checkpoint
from gcn_match_ros.learn.model import GCNConfig
from gcn_match_ros.learn.config import TrainConfig
from gcn_match_ros.learn.objective import make_batch, make_sample, train_step
from gcn_match_ros.learn.sources import ShardedSource, data_source
from gcn_match_ros.learn.train import train
from gcn_match_ros.windowing import WindowAssembler, WindowConfig, window_problem

D = 16
MODEL = GCNConfig(in_dim=feature_dim(D), widths=(16, 16, 16, 16), out_dim=16, groups=4, skip_layers=(2, 4))
SCENE = synthetic.rome16k(3, n_points=14, descriptor_dim=D, descriptor_noise=1.0)


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_torch_thread):
    """Tiny graphs: one intra-op thread is fastest and immune to a busy shared CPU."""


def scene_problems(seed, count, two_view_at=()):
    out = []
    for k in range(count):
        p = synthetic.random_scene_problem(SCENE, np.random.default_rng([seed, k]), name=f"s{seed}_{k}")
        out.append(p.subset_views([0, 1]) if k in two_view_at else p)
    return out


@pytest.fixture(scope="module")
def tiny_bags(tmp_path_factory):
    d = tmp_path_factory.mktemp("bags")
    probs = scene_problems(1, 6, two_view_at=(3,))
    train_bag = write_problems_bag(d / "scene_a.mcap", probs)
    val_bag = write_problems_bag(d / "scene_b.mcap", scene_problems(2, 3))
    return train_bag, val_bag, probs


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


def test_gcn_match_train_end_to_end_synth(tmp_path, capsys):
    cfg = tmp_path / "model.json"
    cfg.write_text(json.dumps({"widths": [16, 16, 16, 16], "out_dim": 16, "groups": 4, "skip_layers": [2, 4]}))
    run = tmp_path / "run"
    rc = cli.main(["train", "--train", "synth:easy:3", "--val", "synth:easy:3", "-o", str(run), "--steps", "3",
                   "--batch", "1", "--model-config", str(cfg), "--epipolar-weight", "1"])
    out = capsys.readouterr().out
    assert rc == 0, out
    for name in ("checkpoint.pt", "best.pt", "history.json", "curves.png"):
        assert (run / name).is_file(), name
        if name.endswith(".png"):
            assert str(run / name) in out
    assert str(run / "checkpoint.pt") in out and str(run / "best.pt") in out
    hist = json.loads((run / "history.json").read_text())
    assert [h["step"] for h in hist["train"]] == [1, 2, 3]
    _, meta = load_checkpoint(run / "best.pt")
    assert meta["model_config"].in_dim == feature_dim(128) and meta["model_config"].widths == (16,) * 4
    # --resume continues the run to more steps
    rc = cli.main(["train", "--train", "synth:easy:3", "-o", str(run), "--steps", "4", "--batch", "1",
                   "--model-config", str(cfg), "--resume"])
    assert rc == 0
    assert [h["step"] for h in json.loads((run / "history.json").read_text())["train"]] == [1, 2, 3, 4]


def test_orb_like_generated_scenes_from_cli_and_data_specs(tmp_path, capsys):
    from gcn_match_ros.descriptors import descriptor_kind
    from gcn_match_ros.problem import load_problem

    assert cli.main(["synth", "-o", str(tmp_path), "--preset", "partial", "--descriptor", "binary",
                     "--count", "2"]) == 0
    files = sorted(tmp_path.glob("*.npz"))
    assert len(files) == 2 and all(descriptor_kind(load_problem(f).descriptors) == (256, True) for f in files)
    assert cli.main(["synth", "-o", str(tmp_path), "--descriptor", "orb"]) == 2
    assert "unknown descriptor 'orb'" in capsys.readouterr().err
    src = data_source(["synth:rome16k:4:binary"], train=False)
    problem = next(src())
    assert descriptor_kind(problem.descriptors) == (256, True) and problem.n_views == 4
    assert "binary descriptors" in src.description


def test_gcn_match_train_errors_are_one_line(tmp_path, capsys, tiny_bags):
    train_bag, val_bag, _ = tiny_bags
    cases = [
        (["--train", str(train_bag), "--val", str(train_bag)], "both the training and the validation"),
        (["--train", "synth:nope"], "synth:PRESET"),
        (["--train", "synth:easy:3:orb"], "DESCRIPTOR one of sift, gaussian, binary"),
        (["--train", str(tmp_path / "missing.mcap")], "no such"),
        (["--train", str(tmp_path / "x.txt")], "no such file"),
        (["--train", str(train_bag), "--init", str(tmp_path / "none.pt")], "no such checkpoint"),
    ]
    for extra, msg in cases:
        rc = cli.main(["train", *extra, "-o", str(tmp_path / "r"), "--steps", "1"])
        err = capsys.readouterr().err
        assert rc == 2 and msg in err and err.count("\n") == 1, (extra, err)
    # bag specs: a folder of bags
    src = data_source([str(train_bag.parent)], train=False)
    assert "2 bag(s)" in src.description


def test_gcn_match_train_fine_tunes_the_shipped_model_from_a_bag(tmp_path, capsys):
    """--init the shipped model (edge head included) and train on the posed sample bag: the
    edge head's loss is trained and logged, and the result loads and solves."""
    from gcn_match_ros import solvers
    from gcn_match_ros.solvers.gcn import DEFAULT_CHECKPOINT

    bag = Path(__file__).resolve().parents[1] / "bags" / "strecha_fountain_sift.mcap"
    run = tmp_path / "ft"
    rc = cli.main(["train", "--train", str(bag), "-o", str(run), "--steps", "2", "--batch", "1",
                   "--init", str(DEFAULT_CHECKPOINT), "--lr", "1e-4"])
    assert rc == 0, capsys.readouterr().err
    hist = json.loads((run / "history.json").read_text())
    assert all(np.isfinite(h["edge"]) and np.isfinite(h["epipolar"]) for h in hist["train"])
    model, meta = load_checkpoint(run / "checkpoint.pt")
    assert model.edge_head is not None and meta["config"]["train"]["edge_weight"] == 1.0
    problem = BagSource(bag, cycle=False).problems[0]
    result = solvers.create(f"gcn:checkpoint={run / 'checkpoint.pt'}").solve(problem)
    assert result.track.shape == (problem.n_keypoints,)
