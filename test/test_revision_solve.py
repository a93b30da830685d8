"""Tests of gcn_match_ros.revision_solve: problems solved by the package of an earlier git revision."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gcn_match_ros.data import synthetic
from gcn_match_ros.revision_solve import package_tree, solve_at_revision, split_revision

PROBLEM_MODULE = Path(__file__).resolve().parents[1] / "gcn_match_ros" / "problem.py"

# A stand-in package: each revision's solver marks its results with its version, the spec it was
# created with and the problem's size, so a test sees which package solved what.
FAKE_SOLVERS = '''
import numpy as np
from .problem import Result
VERSION = "{version}"
class _Solver:
    def __init__(self, spec):
        if spec == "broken":
            raise ValueError("no such solver")
        self.spec = spec
    def solve(self, problem):
        n = problem.n_keypoints
        if self.spec == "refuse-large" and n > 300:
            raise ValueError(f"{{n}} keypoints are too many")
        return Result(track=np.full(n, -1), pair_rows=np.array([0]), pair_cols=np.array([n - 1]),
                      pair_scores=np.array([0.5], np.float32), method=f"{{VERSION}}:{{self.spec}}:{{n}}")
def create(spec):
    return _Solver(spec)
'''


def _git(repo: Path, *args: str) -> None:
    subprocess.run(["git", "-C", str(repo), "-c", "user.name=test", "-c", "user.email=test@example.org", *args],
                   check=True, capture_output=True)


@pytest.fixture(scope="module")
def fake_repo(tmp_path_factory):
    """A git repository whose package changed between its two commits (v1, then v2)."""
    repo = tmp_path_factory.mktemp("fake_repo")
    package = repo / "gcn_match_ros"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "problem.py").write_text(PROBLEM_MODULE.read_text())  # the contract both sides read
    _git(repo, "init", "-q")
    for version in ("v1", "v2"):
        (package / "solvers.py").write_text(FAKE_SOLVERS.format(version=version))
        _git(repo, "add", "-A")
        _git(repo, "commit", "-q", "-m", version)
    return repo


def _problems():
    return [synthetic.random_scene_problem(synthetic.preset("rome16k", views, "sift"), np.random.default_rng(views))
            for views in (3, 4)]


def test_split_revision_reads_spec_at_revision():
    assert split_revision("gcn@a482093") == ("gcn", "a482093")
    assert split_revision("gcn:threshold=0.3,verify=false@HEAD~2") == ("gcn:threshold=0.3,verify=false", "HEAD~2")
    assert split_revision("gcn:threshold=0.3") == ("gcn:threshold=0.3", None)
    for bad in ("@HEAD", "gcn@"):
        with pytest.raises(ValueError, match="SPEC@REVISION"):
            split_revision(bad)


def test_each_revision_solves_with_its_own_package(fake_repo):
    problems = _problems()
    for revision, version in (("HEAD", "v2"), ("HEAD~1", "v1")):
        results = solve_at_revision("gcn:x=1", revision, problems, repo=fake_repo)
        assert [r.method for r in results] == [f"{version}:gcn:x=1:{p.n_keypoints}" for p in problems]
        for r, p in zip(results, problems):  # the problems arrived whole, results came back in order
            assert r.pair_cols.tolist() == [p.n_keypoints - 1] and r.track.shape == (p.n_keypoints,)


def test_unknown_revision_and_failing_solver_are_named(fake_repo):
    with pytest.raises(ValueError, match="git rev-parse no-such-revision"):
        solve_at_revision("gcn", "no-such-revision", _problems(), repo=fake_repo)
    with pytest.raises(RuntimeError, match="solver 'broken' at HEAD exited with status 1"):
        solve_at_revision("broken", "HEAD", _problems(), repo=fake_repo)


def test_a_problem_refused_at_the_revision_comes_back_as_its_error(fake_repo):
    small, large = _problems()  # 240 and 320 keypoints
    solved, refused = solve_at_revision("refuse-large", "HEAD", [small, large], repo=fake_repo)
    assert solved.method == f"v2:refuse-large:{small.n_keypoints}"
    assert isinstance(refused, ValueError) and str(refused) == "320 keypoints are too many"


def test_a_commit_is_extracted_once_per_process_and_removed_at_exit(fake_repo):
    head = subprocess.run(["git", "-C", str(fake_repo), "rev-parse", "HEAD"], capture_output=True, text=True,
                          check=True).stdout.strip()
    tree = package_tree("HEAD", fake_repo)
    assert package_tree(head, fake_repo) == tree  # the same commit by another name: not extracted again
    assert 'VERSION = "v2"' in (tree / "gcn_match_ros" / "solvers.py").read_text()
    older = package_tree("HEAD~1", fake_repo)
    assert older != tree and 'VERSION = "v1"' in (older / "gcn_match_ros" / "solvers.py").read_text()
    # a process's trees go when it exits
    child = subprocess.run([sys.executable, "-c", "import sys; from gcn_match_ros.revision_solve import package_tree; "
                            "print(package_tree('HEAD', sys.argv[1]))", str(fake_repo)],
                           capture_output=True, text=True, check=True)
    assert child.stdout.strip() and not Path(child.stdout.strip()).exists()
