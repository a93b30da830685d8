"""Tests of gcn_match_ros.cli: `gcn-match train`, synth, plot, make-bags, match and eval end to end; one-line errors."""
import json
from pathlib import Path

import numpy as np
import pytest

from gcn_match_ros import cli
from gcn_match_ros.bags.source import BagSource
from gcn_match_ros.learn.checkpoint import load_checkpoint
from gcn_match_ros.learn.sources import data_source
from gcn_match_ros.node_features import feature_dim

from conftest import rigid_motion_2d, write_oxford_like_scene


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


# ---------------------------------------------------------------------------
# gcn-match plot, make-bags, match, eval
# ---------------------------------------------------------------------------
TINY_MODEL = {"widths": [16, 16, 16, 16], "out_dim": 16, "groups": 4, "skip_layers": [2, 4]}
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def run_cli(capsys, *argv):
    """(exit status, stdout, stderr) of ``gcn-match argv``."""
    rc = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def assert_one_line_error(rc, err, message):
    assert rc == 2 and err.startswith("gcn-match: error: ") and message in err and err.count("\n") == 1, err


def assert_png_file(path):
    import cv2

    assert path.is_file() and path.read_bytes()[:8] == PNG_MAGIC
    img = cv2.imread(str(path))
    assert img is not None and min(img.shape[:2]) > 50


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A 2-step training run of a tiny GCN on generated scenes (checkpoints, history)."""
    d = tmp_path_factory.mktemp("tiny_run")
    cfg = d / "model.json"
    cfg.write_text(json.dumps(TINY_MODEL))
    run = d / "run"
    rc = cli.main(["train", "--train", "synth:easy:3", "--val", "synth:easy:3", "-o", str(run), "--steps", "2",
                   "--batch", "1", "--model-config", str(cfg)])
    assert rc == 0
    return run


def test_gcn_match_plot_curves_and_figures_of_a_run(tmp_path, capsys, tiny_run):
    figs = {name: tmp_path / "figs" / f"{name}.png" for name in ("curves", "pr", "similarity", "histograms")}
    rc, out, err = run_cli(capsys, "plot", tiny_run, "-o", figs["curves"], "--data", "synth:easy:3", "--count", "2",
                           "--pr", figs["pr"], "--similarity", figs["similarity"], "--histograms", figs["histograms"])
    assert rc == 0, err
    for path in figs.values():
        assert_png_file(path)
        assert str(path) in out.splitlines()  # each figure's path is printed
    # curves only, two runs with names of their own
    rc, out, err = run_cli(capsys, "plot", tiny_run, tiny_run / "history.json", "-o", tmp_path / "two.png",
                           "--labels", "first", "second")
    assert rc == 0 and out.strip() == str(tmp_path / "two.png"), err
    assert_png_file(tmp_path / "two.png")


def test_gcn_match_plot_errors_are_one_line(tmp_path, capsys, tiny_run):
    cases = [
        (["--labels", "a", "b"], "--labels: 2 names for 1 runs"),
        (["--pr", tmp_path / "pr.png"], "--pr, --similarity and --histograms need --data"),
    ]
    for extra, message in cases:
        rc, _, err = run_cli(capsys, "plot", tiny_run, "-o", tmp_path / "c.png", *extra)
        assert_one_line_error(rc, err, message)
    rc, _, err = run_cli(capsys, "plot", tmp_path / "no_run", "-o", tmp_path / "c.png")
    assert_one_line_error(rc, err, "no such history file")
    assert not (tmp_path / "pr.png").exists()


@pytest.fixture
def tiny_data_root(tmp_path):
    """A data root with one 3-image scene in the Oxford layout: homography/tiny."""
    root = tmp_path / "data"
    write_oxford_like_scene(root / "homography" / "tiny", rigid_motion_2d(4, 5, -3), n=3)
    return root


def test_gcn_match_make_bags_writes_a_bag_and_replaces_it_only_with_force(tmp_path, capsys, tiny_data_root):
    from gcn_match_ros.bags.contents import read_bag

    out = tmp_path / "bags"
    args = ["make-bags", "--out", out, "--data-root", tiny_data_root, "--scenes", "homography/tiny",
            "--max-features", "40", "-q"]
    rc, stdout, err = run_cli(capsys, *args)
    assert rc == 0, err
    bag = out / "homography_tiny_sift.mcap"
    assert bag.is_file() and sorted(p.name for p in out.iterdir()) == [bag.name]
    assert stdout.startswith(f"{bag}: ") and ", 3 frames, " in stdout  # 3 cameras, 3 images: one capture
    contents = read_bag(bag, progress=False)
    assert contents.cameras == ["cam0", "cam1", "cam2"] and contents.n_frames == 3
    assert [contents.sources[c] for c in contents.cameras] == [["homography/tiny/img1.png"],
                                                              ["homography/tiny/img2.png"],
                                                              ["homography/tiny/img3.png"]]
    assert all(0 < f.count <= 40 for c in contents.cameras for f in contents.frames[c])
    assert all(len(lab) == f.count for c in contents.cameras for f, lab in zip(contents.frames[c], contents.labels[c]))
    before = bag.read_bytes()
    # an existing bag is kept without --force ...
    rc, _, err = run_cli(capsys, *args)
    assert_one_line_error(rc, err, f"{bag} exists (use --force to replace it)")
    assert bag.read_bytes() == before
    # ... and replaced with it (the same scene and settings give the same bag)
    rc, _, err = run_cli(capsys, *args, "--force")
    assert rc == 0, err
    assert bag.read_bytes() == before
    # a rosbag2 folder (sqlite3) is replaced with --force too
    folder = out / "homography_tiny_sift"
    rc, _, err = run_cli(capsys, *args, "--storage", "sqlite3", "--cameras", "2")
    assert rc == 0 and folder.is_dir(), err
    assert read_bag(folder, progress=False).n_frames == 4  # 2 captures of 2 cameras
    rc, _, err = run_cli(capsys, *args, "--storage", "sqlite3")
    assert_one_line_error(rc, err, "exists (use --force to replace it)")
    rc, _, err = run_cli(capsys, *args, "--storage", "sqlite3", "--force")
    assert rc == 0 and read_bag(folder, progress=False).n_frames == 3, err


def test_gcn_match_make_bags_errors_are_one_line(tmp_path, capsys, tiny_data_root):
    base = ["make-bags", "--out", tmp_path / "bags", "--data-root", tiny_data_root, "--max-features", "40", "-q"]
    cases = [
        (["--scenes", "homography/nope"], "homography/nope: "),
        (["--scenes", "nowhere/x"], "unknown dataset 'nowhere'"),
        (["--scenes", "homography/tiny", "--cameras", "4"], "n_cameras must be in [2, 3]"),
        (["--scenes", "homography/tiny", "--stagger", "0.5"], "stagger"),
        (["--scenes", "homography/tiny", "--detector", "akaze"], "invalid choice: 'akaze'"),
    ]
    for extra, message in cases:
        rc, _, err = run_cli(capsys, *base, *extra)
        assert_one_line_error(rc, err, message)
    assert not list((tmp_path / "bags").glob("*.mcap"))


@pytest.fixture
def synth_problems(tmp_path, capsys):
    """Two generated 3-view problems (SIFT-like descriptors) written by `gcn-match synth`."""
    folder = tmp_path / "problems"
    assert cli.main(["synth", "-o", str(folder), "--preset", "easy", "--count", "2", "--seed", "4"]) == 0
    capsys.readouterr()
    files = sorted(folder.glob("*.npz"))
    assert len(files) == 2
    return files


def test_gcn_match_match_writes_a_result(tmp_path, capsys, synth_problems):
    from gcn_match_ros.problem import load_problem, load_result
    from gcn_match_ros.rounding import is_cycle_consistent

    problem = load_problem(synth_problems[0])
    for method in ("gcn", "nn:graph=mutual"):  # gcn (the shipped model) is the default
        out = tmp_path / f"{method.split(':')[0]}.npz"
        extra = [] if method == "gcn" else ["--method", method]
        rc, stdout, err = run_cli(capsys, "match", synth_problems[0], "-o", out, *extra)
        assert rc == 0, err
        result = load_result(out)
        assert result.track.shape == (problem.n_keypoints,) and is_cycle_consistent(result.track, problem.view_index)
        assert stdout.startswith(f"{problem.name}: {result.method}: ") and stdout.rstrip().endswith(f"-> {out}")
        assert f"{int(result.track.max()) + 1} tracks, {result.pair_rows.size} scored pairs" in stdout
    rc, _, err = run_cli(capsys, "match", tmp_path / "missing.npz", "-o", tmp_path / "r.npz")
    assert_one_line_error(rc, err, "missing.npz")
    rc, _, err = run_cli(capsys, "match", synth_problems[0], "--method", "nope", "-o", tmp_path / "r.npz")
    assert_one_line_error(rc, err, "unknown method 'nope'")
    assert not (tmp_path / "r.npz").exists()


def test_gcn_match_eval_table_json_and_pr_plot(tmp_path, capsys, synth_problems):
    folder = synth_problems[0].parent
    report_path, pr_path = tmp_path / "report.json", tmp_path / "pr.png"
    rc, stdout, err = run_cli(capsys, "eval", str(folder / "*.npz"), "--methods", "nn;matchals:iters=5,max_nodes=100",
                              "--json", report_path, "--pr-plot", pr_path, "-q")
    assert rc == 0, err
    report = json.loads(report_path.read_text())
    assert report["problems"] == [f.stem for f in synth_problems]
    assert list(report["methods"]) == ["nn", "matchals:iters=5,max_nodes=100", "identity", "all-zero"]
    dense = report["methods"]["matchals:iters=5,max_nodes=100"]  # 240 keypoints: over its node limit
    assert dense["per_problem"] == {} and sorted(dense["skipped"]) == report["problems"]
    assert set(report["methods"]["nn"]["per_problem"]) == set(report["problems"])
    lines = stdout.splitlines()
    assert lines[0].startswith("| method | P | R | F1 |")
    assert [line.split("|")[1].strip() for line in lines[2:6]] == ["nn", "matchals:iters=5,max_nodes=100",
                                                                   "identity", "all-zero"]
    assert "matchals:iters=5,max_nodes=100 skipped" in stdout
    assert_png_file(pr_path)
    rc, _, err = run_cli(capsys, "eval", str(tmp_path / "none" / "*.npz"), "--methods", "nn")
    assert_one_line_error(rc, err, "no file matches")
    rc, _, err = run_cli(capsys, "eval", synth_problems[0], "--methods", "nn,bogus", "-q")
    assert_one_line_error(rc, err, "unknown method 'bogus'")


def test_gcn_match_stream_solves_a_bag_as_the_node_does(tmp_path, capsys, tiny_bags):
    """The node's windows of the bag, in order, through one stream state: tracks and landmark ids
    as solve_stream gives them (the node's own answer, test_ros_matcher_node), written per window."""
    from gcn_match_ros import solvers
    from gcn_match_ros.bags.contents import read_bag
    from gcn_match_ros.problem import load_problem, load_result
    from gcn_match_ros.stream import solve_stream

    bag = tiny_bags[0]
    rc, stdout, err = run_cli(capsys, "stream", bag, "--method", "nn", "-o", tmp_path / "out", "-q")
    assert rc == 0, err
    replay = read_bag(bag, progress=False).replay_windows()
    expected = list(solve_stream(solvers.create("nn"), replay.problems, replay.stamps_ns))
    assert len(expected) >= 4 and f"{len(expected)} windows by nn" in stdout
    assert "against the bag's labels: id_precision" in stdout
    for k, (result, landmarks) in enumerate(expected):
        problem = load_problem(tmp_path / "out" / f"window_{k:04d}.npz")
        written = load_result(tmp_path / "out" / f"window_{k:04d}_result.npz")
        extra = np.load(tmp_path / "out" / f"window_{k:04d}_result.npz")
        assert problem.n_keypoints == written.track.size and problem.gt_track is not None
        np.testing.assert_array_equal(written.track, result.track)
        np.testing.assert_array_equal(extra["landmark_ids"], landmarks.ids)
        assert int(extra["stamp_ns"]) == replay.stamps_ns[k]
        ids, ages = extra["landmark_ids"], extra["landmark_ages"]
        assert np.all((ages >= 0) == (ids >= 0))
        for t in np.unique(written.track[written.track >= 0]):  # a track is one landmark
            assert np.unique(ids[written.track == t]).size == 1 and ids[written.track == t][0] >= 0
    assert not (tmp_path / "out" / f"window_{len(expected):04d}.npz").exists()


def test_gcn_match_stream_errors_are_one_line(tmp_path, capsys, tiny_bags):
    bag = tiny_bags[0]
    rc, _, err = run_cli(capsys, "stream", bag, "-q", "--method", "nn", "--cameras", "front", "rear")
    assert_one_line_error(rc, err, "no window of the cameras front, rear")
    rc, _, err = run_cli(capsys, "stream", bag, "-q", "--method", "nn", "--window", "max_keypionts=10")
    assert_one_line_error(rc, err, "expected NAME=VALUE with NAME one of sync_tolerance")
    rc, _, err = run_cli(capsys, "stream", bag, "-q", "--method", "nn", "--window", "max_keypoints=many")
    assert_one_line_error(rc, err, "not a int")
    rc, _, err = run_cli(capsys, "stream", tmp_path / "nothing.mcap", "-q")
    assert_one_line_error(rc, err, "nothing.mcap")
