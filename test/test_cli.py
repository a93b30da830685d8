"""Tests of gcn_match_ros.cli: `gcn-match train` and `gcn-match synth` end to end, one-line errors."""
import json
from pathlib import Path

import numpy as np
import pytest

from gcn_match_ros import cli
from gcn_match_ros.bags.source import BagSource
from gcn_match_ros.learn.checkpoint import load_checkpoint
from gcn_match_ros.learn.sources import data_source
from gcn_match_ros.node_features import feature_dim


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_torch_thread):
    """Tiny graphs: one intra-op thread is fastest and immune to a busy shared CPU."""


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
