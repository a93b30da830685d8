"""Tests of gcn_match_ros.evaluation: evaluate() reports (scores, skips, reference rows) and format_table."""
import dataclasses
import json

import numpy as np
import pytest

from gcn_match_ros import solvers
from gcn_match_ros.data import synthetic
from gcn_match_ros.evaluation import evaluate, format_table
from gcn_match_ros.geometric_metrics import score_geometric
from gcn_match_ros.metrics import SCORE_KEYS, count_pairs
from gcn_match_ros.problem import save_problem

from conftest import permuted_views_problem

EASY_SCENE = synthetic.easy(3, n_points=20)  # SIFT-like 128-D descriptors: the shipped gcn model takes them


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_torch_thread):
    """Tiny graphs: one intra-op thread is fastest and immune to a busy shared CPU."""


def easy_problems(count=2):
    return [synthetic.random_scene_problem(EASY_SCENE, np.random.default_rng([7, k]), name=f"easy{k}")
            for k in range(count)]


def named_permuted(name, n_points, seed):
    return dataclasses.replace(permuted_views_problem(n_points=n_points, seed=seed), name=name)


@pytest.fixture(scope="module")
def nn_gcn_report():
    problems = easy_problems()
    return problems, evaluate(problems, ["nn", "gcn"], progress=False)


def test_report_lists_problems_methods_and_per_problem_scores(nn_gcn_report):
    problems, report = nn_gcn_report
    names = [p.name for p in problems]
    assert report["problems"] == names == ["easy0", "easy1"]
    assert list(report["methods"]) == ["nn", "gcn", "identity", "all-zero"]
    json.loads(json.dumps(report))  # JSON-able as documented
    for spec in ("nn", "gcn"):
        entry = report["methods"][spec]
        posed = {"geometric"} if all(p.has_poses for p in problems) else set()
        assert set(entry) == {"describe", "per_problem", "mean", "skipped", "pr"} | posed
        assert entry["skipped"] == {} and "reference" not in entry
        assert list(entry["per_problem"]) == names
        for scores in entry["per_problem"].values():
            assert set(SCORE_KEYS) <= set(scores)
            assert 0.0 <= scores["P"] <= 1.0 and 0.0 <= scores["R"] <= 1.0 and 0.0 <= scores["F1"] <= 1.0
            assert scores["seconds"] > 0
        rows = list(entry["per_problem"].values())
        # mean of every score over the problems; seconds is the median
        for key in ("P", "R", "F1", "AP", "L1"):
            assert entry["mean"][key] == pytest.approx(np.mean([r[key] for r in rows]))
        assert entry["mean"]["seconds"] == pytest.approx(np.median([r["seconds"] for r in rows]))
        # pooled precision-recall: equally long, within [0, 1], recall rising to 1 (unlisted pairs score 0)
        pr = entry["pr"]
        assert len(pr["precision"]) == len(pr["recall"]) >= 2
        assert all(0.0 <= x <= 1.0 for x in pr["precision"] + pr["recall"])
        assert np.all(np.diff(pr["recall"]) >= 0) and pr["recall"][-1] == pytest.approx(1.0)
    assert report["methods"]["nn"]["describe"] == "nn"
    assert report["methods"]["gcn"]["describe"] == "gcn:model=shipped"
    # the shipped model matches these easy scenes almost perfectly, and at least as well as nn
    assert report["methods"]["gcn"]["mean"]["F1"] > 0.9
    assert report["methods"]["gcn"]["mean"]["F1"] >= report["methods"]["nn"]["mean"]["F1"]


def test_reference_rows_score_the_trivial_answers(nn_gcn_report):
    problems, report = nn_gcn_report
    # every easy problem: 20 points seen by all 3 views, no distractors
    n = problems[0].n_keypoints
    n_pairs, n_true = count_pairs(problems[0].gt_track, problems[0].view_index)
    assert (n, n_true, n_pairs) == (60, 60, 1200)
    for row in ("identity", "all-zero"):
        entry = report["methods"][row]
        assert entry["reference"] is True and entry["describe"] == row
        assert entry["per_problem"] == {} and entry["skipped"] == {} and "pr" not in entry
        mean = entry["mean"]
        assert (mean["P"], mean["R"], mean["F1"]) == (0.0, 0.0, 0.0)
        assert mean["AP"] == pytest.approx(n_true / n_pairs)  # every pair at score 0
    # S = I misses every true pair twice (both triangles); S = 0 also misses the N diagonal entries
    assert report["methods"]["identity"]["mean"]["L1"] == pytest.approx(2 * n_true / n ** 2)
    assert report["methods"]["all-zero"]["mean"]["L1"] == pytest.approx((2 * n_true + n) / n ** 2)
    assert report["methods"]["all-zero"]["mean"]["L2"] == pytest.approx((2 * n_true + n) / n ** 2)
    without = evaluate(problems[:1], ["nn"], progress=False, with_reference_rows=False)
    assert list(without["methods"]) == ["nn"]


def test_a_refused_problem_is_recorded_as_skipped_with_its_reason():
    small, big = named_permuted("small", 12, 0), named_permuted("big", 16, 1)  # 36 and 48 keypoints
    report = evaluate([small, big], ["nn", "matchals:max_nodes=40", "gcn"], progress=False)
    assert list(report["methods"]["nn"]["per_problem"]) == ["small", "big"]
    dense = report["methods"]["matchals:max_nodes=40"]
    assert dense["describe"] == "matchals:max_nodes=40"
    assert list(dense["per_problem"]) == ["small"]
    assert list(dense["skipped"]) == ["big"]
    assert "48 keypoints exceed this dense method's node limit max_nodes=40" in dense["skipped"]["big"]
    assert dense["mean"]["F1"] == dense["per_problem"]["small"]["F1"] == pytest.approx(1.0)
    # the shipped gcn models take no 16-D descriptors: every problem is refused, nothing scored
    refused = report["methods"]["gcn"]
    assert refused["per_problem"] == {} and refused["mean"] == {}
    assert sorted(refused["skipped"]) == ["big", "small"]
    assert all("no shipped gcn model takes 16-D" in r for r in refused["skipped"].values())
    assert refused["pr"] == {"precision": [], "recall": []}
    table = format_table(report)
    assert "| matchals:max_nodes=40 |" in table and "| 1/2 |" in table and "| 0/2 |" in table
    assert "matchals:max_nodes=40 skipped big: matchals: 48 keypoints" in table
    assert "gcn skipped small: no shipped gcn model" in table


def test_problem_files_are_loaded_and_problems_without_ground_truth_refused(tmp_path):
    problem = named_permuted("labelled", 10, 2)
    save_problem(problem, tmp_path / "p.npz")
    report = evaluate([tmp_path / "p.npz", str(tmp_path / "p.npz")], ["nn"], progress=False)
    assert report["problems"] == ["p", "p"]  # a loaded problem is named by its file stem
    assert report["methods"]["nn"]["mean"]["F1"] == pytest.approx(1.0)  # noiseless descriptors
    unlabelled = dataclasses.replace(problem, gt_track=None, name="unlabelled")
    with pytest.raises(ValueError, match="'unlabelled' has neither gt_track nor cameras"):
        evaluate([problem, unlabelled], ["nn"], progress=False)
    empty = evaluate([], ["nn"], progress=False)
    assert empty["problems"] == [] and list(empty["methods"]) == ["nn"]
    assert empty["methods"]["nn"]["per_problem"] == {} and empty["methods"]["nn"]["mean"] == {}


def _row_names(table):
    return [line.split("|")[1].strip() for line in table.splitlines()[2:] if line.startswith("| ")]


def test_format_table_sorts_by_f1_with_reference_rows_last():
    def entry(describe, f1, reference=False, solved=1):
        mean = {k: 0.5 for k in SCORE_KEYS}
        mean["F1"] = f1
        e = {"describe": describe, "per_problem": {f"p{i}": {} for i in range(solved)}, "mean": mean,
             "skipped": {} if solved == 2 else {"p1": "too big"}}
        if reference:
            e["reference"] = True
        return e

    report = {"problems": ["p0", "p1"],
              "methods": {"identity": entry("identity", 0.0, reference=True), "low": entry("low", 0.2),
                          "all-zero": entry("all-zero", 0.9, reference=True), "high": entry("high", 0.8, solved=2),
                          "mid": entry("mid", 0.5)}}
    table = format_table(report)
    lines = table.splitlines()
    assert lines[0] == "| method | P | R | F1 | AP | same | diff | L1 | L2 | median s | solved |"
    assert lines[1] == "|" + "---|" * 11
    # by F1, highest first; the reference rows last even when their F1 is higher
    assert _row_names(table) == ["high", "mid", "low", "all-zero", "identity"]
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
            for line in lines[2:] if line.startswith("| ")}
    assert rows["high"] == ["0.500", "0.500", "0.800", "0.500", "0.500", "0.5000", "0.5000", "0.5000", "0.5000",
                            "2/2"]
    assert rows["mid"][-1] == "1/2"
    assert rows["identity"][-2:] == ["–", "–"]  # no runtime, no solved count for a reference row
    assert "\nlow skipped p1: too big" in table and "\nhigh skipped" not in table


def test_format_table_of_an_evaluation(nn_gcn_report):
    _, report = nn_gcn_report
    table = format_table(report)
    assert _row_names(table) == ["gcn:model=shipped", "nn", "identity", "all-zero"]  # gcn F1 1.0 > nn
    assert table.count("| 2/2 |") == 2 and "skipped" not in table


def test_posed_problems_get_geometric_scores_over_every_predicted_pair(nn_gcn_report):
    problems, report = nn_gcn_report
    for spec in ("nn", "gcn"):
        geo = report["methods"][spec]["geometric"]
        summaries = [score_geometric(p, solvers.create(spec).solve(p)).summary() for p in problems]
        assert geo["pairs"] == sum(s["pairs"] for s in summaries)
        assert geo["consistent"] == sum(s["consistent"] for s in summaries)
        assert geo["precision"] == pytest.approx(geo["consistent"] / geo["pairs"])
        assert 0.0 < geo["pooled_recall"] <= 1.0
    # the union of both methods' consistent pairs holds each method's
    total = report["methods"]["nn"]["geometric"]["pooled_recall"] + report["methods"]["gcn"]["geometric"]["pooled_recall"]
    assert total >= 1.0
    table = format_table(report)
    assert "P geo" in table and "R pool" in table


def test_posed_problems_without_labels_are_scored_geometrically_only():
    problem = dataclasses.replace(easy_problems(1)[0], gt_track=None, name="posed")
    report = evaluate([problem], ["nn"], progress=False, with_reference_rows=False)
    entry = report["methods"]["nn"]
    assert "F1" not in entry["mean"] and entry["geometric"]["pairs"] > 0
    assert entry["geometric"]["pooled_recall"] == pytest.approx(1.0)  # the only method: the whole union
    assert "| nn |" in format_table(report)


def test_a_method_at_a_git_revision_is_scored_beside_todays():
    """``SPEC@REVISION`` is solved by that revision's package (revision_solve): the committed ``nn`` of
    HEAD, in its own process, scores exactly as today's does in this one, in the same report."""
    problems = easy_problems()
    report = evaluate(problems, ["nn", "nn@HEAD", "nn"], progress=False, with_reference_rows=False)
    assert list(report["methods"]) == ["nn", "nn@HEAD"]  # a row a method
    today, past = report["methods"]["nn"], report["methods"]["nn@HEAD"]
    assert past["describe"] == "nn@HEAD" and not past["skipped"]
    for p in problems:
        for key in ("P", "R", "F1", "AP"):
            assert past["per_problem"][p.name][key] == today["per_problem"][p.name][key]


def test_a_problem_refused_at_a_revision_is_skipped_with_its_reason(monkeypatch):
    problems = easy_problems()
    solved_today = solvers.create("nn").solve(problems[1])
    monkeypatch.setattr("gcn_match_ros.evaluation.solve_at_revision",
                        lambda spec, revision, ps: [ValueError("too large there"), solved_today])
    entry = evaluate(problems, ["nn@v1"], progress=False, with_reference_rows=False)["methods"]["nn@v1"]
    assert entry["skipped"] == {problems[0].name: "too large there"}
    assert list(entry["per_problem"]) == [problems[1].name]
