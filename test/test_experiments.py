"""Tests of gcn_match_ros.experiments: the split of the real scenes, window subsets, results headers, the gcn lead."""
import os
import platform
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from gcn_match_ros import experiments
from gcn_match_ros.data import synthetic
from gcn_match_ros.evaluation import evaluate
from gcn_match_ros.experiments import (command_line, describe_machine, first_pair_tracks, images_of, lead_lines,
                                       pose_windows, problem_files, python_speed, results_header, role, run_note,
                                       speed_note, split, windows, write_results)

from conftest import rigid_motion_2d, write_oxford_like_scene

REPO = Path(__file__).resolve().parents[1]

NAMES = ["oxford_graf_sift_123", "oxford_graf_sift_234", "oxford_graf_sift_345", "oxford_graf_sift_1234",
         "oxford_graf_sift_123456", "strecha_fountain-P11_sift_0-1-2", "strecha_fountain-P11_sift_0-1-2-3",
         "strecha_fountain-P11_sift_3-4-5", "strecha_fountain-P11_sift_4-5-6-7", "strecha_fountain-P11_sift_6-7-8",
         "strecha_fountain-P11_sift_6-7-8-9-10-11", "strecha_castle-P19_orb_12-13-14",
         "strecha_castle-P19_orb_0-1-2", "middlebury_temple_sift_0-1-2", "middlebury_temple_sift_6-7-8"]


def test_images_of_reads_the_window_from_the_name():
    assert images_of("oxford_graf_sift_123") == [1, 2, 3]
    assert images_of("oxford_boat_orb_123456") == [1, 2, 3, 4, 5, 6]
    assert images_of("strecha_fountain-P11_sift_7-8-9-10") == [7, 8, 9, 10]
    assert images_of("strecha_castle-P19_sift_12-13-14") == [12, 13, 14]
    assert images_of("middlebury_temple_orb_0-1-2") == [0, 1, 2]


def test_split_keeps_held_out_scenes_out_and_strecha_windows_on_one_side():
    files = [Path("/data") / f"{n}.npz" for n in NAMES]
    train, val = split(files)
    assert [f.stem for f in train] == ["strecha_fountain-P11_sift_0-1-2", "strecha_fountain-P11_sift_0-1-2-3",
                                       "strecha_fountain-P11_sift_3-4-5", "middlebury_temple_sift_0-1-2",
                                       "middlebury_temple_sift_6-7-8"]
    assert [f.stem for f in val] == ["strecha_fountain-P11_sift_6-7-8", "strecha_fountain-P11_sift_6-7-8-9-10-11"]
    assert all(f.parent == Path("/data") for f in train + val)
    assert split([]) == ([], [])


def test_role_of_each_problem():
    roles = {n: role(n) for n in NAMES}
    assert {n for n, r in roles.items() if r == "test"} == {n for n in NAMES if n.startswith("oxford") or "castle" in n}
    assert roles["strecha_fountain-P11_sift_3-4-5"] == "train"
    assert roles["strecha_fountain-P11_sift_6-7-8"] == "val"
    assert roles["strecha_fountain-P11_sift_4-5-6-7"] == "train/val overlap"
    # the roles of the Oxford and Strecha windows agree with split()
    named = [n for n in NAMES if not n.startswith("middlebury")]
    train, val = split([Path(f"{n}.npz") for n in named])
    assert {f.stem for f in train} == {n for n in named if roles[n] == "train"}
    assert {f.stem for f in val} == {n for n in named if roles[n] == "val"}


def test_windows_quick_and_full():
    assert windows(NAMES, quick=True) == ["oxford_graf_sift_123", "strecha_fountain-P11_sift_0-1-2",
                                          "strecha_castle-P19_orb_0-1-2", "middlebury_temple_sift_0-1-2"]
    assert windows(NAMES, quick=False) == [
        "oxford_graf_sift_123", "oxford_graf_sift_234", "oxford_graf_sift_1234", "oxford_graf_sift_123456",
        "strecha_fountain-P11_sift_0-1-2", "strecha_fountain-P11_sift_0-1-2-3", "strecha_fountain-P11_sift_6-7-8",
        "strecha_fountain-P11_sift_6-7-8-9-10-11", "strecha_castle-P19_orb_12-13-14", "strecha_castle-P19_orb_0-1-2",
        "middlebury_temple_sift_0-1-2", "middlebury_temple_sift_6-7-8"]
    assert windows(list(reversed(NAMES)), quick=True) == list(reversed(windows(NAMES, quick=True)))  # order kept


def test_first_pair_tracks_counts_tracks_in_both_first_views():
    gt = np.array([0, 1, 2, -1, 2, 1, 3, -2, -1, 0, 1])  # view 0: 4, view 1: 4, then a third view
    assert first_pair_tracks(gt, 4, 4) == 2  # tracks 1 and 2 (0 is only in the third view)
    assert first_pair_tracks(gt, 4, 0) == 0
    assert first_pair_tracks(np.full(6, -1), 3, 3) == 0


def test_problem_files_lists_an_existing_folder_without_converting(tmp_path):
    for name in ("b.npz", "a.npz", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    assert problem_files(tmp_path, tmp_path / "no-data-root", "sift") == [tmp_path / "a.npz", tmp_path / "b.npz"]


def test_pose_windows_reads_each_image_once_and_skips_windows_past_the_scene(tmp_path, monkeypatch):
    write_oxford_like_scene(tmp_path / "homography" / "tiny", rigid_motion_2d(5, 4, -3), n=3)
    reads = []
    real_read = experiments.read_gray
    monkeypatch.setattr(experiments, "read_gray", lambda p: reads.append(Path(p).name) or real_read(p))
    got = list(pose_windows(tmp_path, ["homography/tiny"], [(0, 1, 2), (1, 2), (1, 2, 3)], "sift", 40))
    assert [(name, win) for name, _, win, _ in got] == [("homography/tiny", [0, 1, 2]), ("homography/tiny", [1, 2])]
    assert sorted(reads) == ["img1.png", "img2.png", "img3.png"]
    _, scene, _, views = got[0]
    assert scene.n_views == 3
    for features, image in views:
        assert 0 < features.keypoints.shape[0] <= 40 and features.descriptors.shape[1] == 128
        assert image.dtype == np.uint8 and image.shape == (180, 240)
    assert got[1][3][0][0] is views[1][0]  # view 1's features, extracted once


def test_command_line_and_results_header(monkeypatch):
    script = REPO / "benchmarks" / "some_bench.py"
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    assert command_line(script, ["--quick", "a b"]) == ".venv/bin/python benchmarks/some_bench.py --quick 'a b'"
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "1")
    assert command_line(script, [], launcher="./run.sh python", env=("OPENBLAS_NUM_THREADS", "UNSET_VAR_X")) == \
        "OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/some_bench.py"
    monkeypatch.setattr(sys, "argv", ["some_bench.py", "--seed", "3"])
    with pytest.raises(ValueError, match="variable names"):
        command_line(script, [], env=("OPENBLAS_NUM_THREADS=1",))
    assert command_line("/elsewhere/tool.py").endswith(" /elsewhere/tool.py --seed 3")  # outside: as given
    header = results_header("My results", script, ["-q"], torch_threads=1)
    assert len(header) == 3
    assert header[0] == "# My results\n"
    assert header[1] == "Command: `.venv/bin/python benchmarks/some_bench.py -q`  "
    assert header[2].startswith("Machine: nproc=") and header[2].endswith("torch threads 1  ")


def test_describe_machine_shape():
    import torch

    plain = describe_machine()
    parts = plain.split(", ")
    assert parts[0].startswith("nproc=") and parts[1].startswith("CPU: ") and len(parts[1]) > len("CPU: ")
    assert parts[2] == f"Python {platform.python_version()}" and "torch" not in plain
    full = describe_machine("1 per run", extra=["load 0.5"])
    assert full.startswith(plain) and full.endswith(f", torch {torch.__version__}, torch threads 1 per run, load 0.5")
    assert experiments.cpu_name()


def test_resident_memory_follows_what_the_process_touches_and_is_nan_for_no_process():
    before = experiments.resident_memory_mb()
    block = np.ones(64 * 2**20 // 8)  # 64 MB, every page written
    assert experiments.resident_memory_mb() - before > 50
    del block
    assert experiments.resident_memory_mb(os.getpid()) > 0
    assert np.isnan(experiments.resident_memory_mb(2**22 + 12345))  # above Linux's pid limit


@pytest.fixture(scope="module")
def lead_report(one_torch_thread):
    scene = synthetic.rome16k(3, n_points=20)
    problems = [synthetic.random_scene_problem(scene, np.random.default_rng([11, k]), name=f"w{k}") for k in range(3)]
    return problems, evaluate(problems, ["nn", "gcn"], progress=False)


def test_lead_lines_of_gcn_over_the_best_other_method(lead_report):
    problems, report = lead_report
    lines = lead_lines(report, problems, {"first two": ["w0", "w1"], "none": []})
    assert lines[0].startswith("\nF1 lead of gcn:model=shipped over the best other method, nn ")
    assert [line.split(":")[0] for line in lines[1:]] == ["- all", "- first two"]  # empty subsets left out
    f1 = {spec: [report["methods"][spec]["per_problem"][p.name]["F1"] for p in problems] for spec in ("gcn", "nn")}
    mean = np.mean(np.subtract(f1["gcn"], f1["nn"]))
    assert lines[1].startswith(f"- all: {mean:+.3f} [") and ", 3 windows, 180 labelled true pairs" in lines[1]
    assert ", 2 windows, 120 labelled true pairs" in lines[2]
    # no gcn method, or nothing to compare with: no lines
    assert lead_lines({"methods": {"nn": report["methods"]["nn"]}}, problems, {}) == []
    assert lead_lines({"methods": {k: report["methods"][k] for k in ("gcn", "identity", "all-zero")}}, problems,
                      {}) == []


def test_speed_note_states_the_loop_before_and_after():
    """Timing tables state the machine's speed: a fixed pure-Python loop, measured (positive,
    and well under a minute on any machine that runs the suite), before and after the run."""
    seconds = python_speed()
    assert 0 < seconds < 60
    assert speed_note(1.0449, 1.184) == ("A fixed pure-Python loop (experiments.python_speed) took 1.04 s before "
                                         "the run and 1.18 s after it (lower is faster).")


def test_run_note_says_when_how_long_and_the_speed():
    note = run_note(61.4, 0.5)
    assert re.fullmatch(r"Run \d{4}-\d\d-\d\d \d\d:\d\d, 61 s\. A fixed pure-Python loop \(experiments\.python_speed\) "
                        r"took 0\.50 s before the run and \d+\.\d\d s after it \(lower is faster\)\.", note), note


def test_write_results_makes_the_folder_and_appends_below_a_rule(tmp_path, capsys):
    out = tmp_path / "new" / "table.md"
    assert write_results(out, "# first\n\n| a |\n", append=True) == out  # nothing to append to: no rule
    assert out.read_text() == "# first\n\n| a |\n"
    write_results(str(out), "# second\n", append=True)
    assert out.read_text() == "# first\n\n| a |\n\n---\n\n# second\n"
    write_results(out, "# third\n")
    assert out.read_text() == "# third\n"
    assert capsys.readouterr().out.count(f"written to {out}") == 3


def test_solved_at_revision_returns_every_result_or_stops_naming_a_refusal(monkeypatch):
    problems = [synthetic.random_scene_problem(synthetic.preset("easy", 3, "sift"), np.random.default_rng(s))
                for s in range(3)]
    calls = []

    def fake(spec, revision, ps):
        calls.append((spec, revision, len(ps)))
        return [ValueError("too many keypoints") if p is problems[1] and spec == "refuse" else f"{spec}:{p.n_keypoints}"
                for p in ps]

    monkeypatch.setattr(experiments, "solve_at_revision", fake)
    assert experiments.solved_at_revision("gcn:threshold=0.3@a482093", problems) == \
        [f"gcn:threshold=0.3:{p.n_keypoints}" for p in problems]
    with pytest.raises(SystemExit, match="refuse@HEAD refused 1 of 3 windows: too many keypoints"):
        experiments.solved_at_revision("refuse@HEAD", problems)
    assert calls == [("gcn:threshold=0.3", "a482093", 3), ("refuse", "HEAD", 3)]
