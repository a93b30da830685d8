"""Problems solved by the package as it was at an earlier git revision: before/after on the same windows.

A goal such as "generated scenes unchanged or better" compares today's solver with the one of the
day the goal was set. Re-creating that solver from today's code is not possible (its code changed,
not only its model), so :func:`solve_at_revision` takes the revision's own ``gcn_match_ros``
(``git archive``), writes the problems in the problem-format contract (shared/spec/problem-format.md:
keys are added, never changed, so an older package reads today's files), solves them in a separate
Python process that imports that package, and reads the results back. The revision must have the
re-split layout (``solvers.create``, ``problem.load_problem`` / ``save_result``: since issue 10).
Each commit's package is extracted once per process and kept until it exits, so later calls (a
benchmark's second detector) also find the compiled code its first child cached there: two specs at
one recent commit on 12 generated windows 32 -> 22 s (numba's cold start; the filing's commit has no
compiled code).
A core module: it never imports ROS.
"""
from __future__ import annotations

import atexit
import io
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

from .paths import CHECKOUT
from .problem import Problem, Result, load_result, save_problem

__all__ = ["package_tree", "solve_at_revision", "split_revision"]

#: (checkout, commit) -> that commit's package extracted, for the life of this process
_TREES: Dict[Tuple[str, str], Path] = {}

# Runs in the child process, with the revision's package first on sys.path.
_SOLVE = """
import sys, glob, os
import torch
from gcn_match_ros import solvers
from gcn_match_ros.problem import load_problem, save_result
torch.set_num_threads(1)
spec, src, out = sys.argv[1:4]
solver = solvers.create(spec)
files = sorted(glob.glob(os.path.join(src, "*.npz")))
for i, f in enumerate(files):
    name = os.path.join(out, os.path.basename(f))
    try:
        result = solver.solve(load_problem(f))
    except (ValueError, MemoryError) as exc:  # a refused problem, as evaluation records it
        with open(name + ".refused", "w") as refused:
            refused.write(str(exc) or type(exc).__name__)
    else:
        save_result(result, name)
    if (i + 1) % 20 == 0 or i + 1 == len(files):
        print(f"  {spec} at the revision: {i + 1}/{len(files)} problems", file=sys.stderr, flush=True)
"""


def split_revision(method: str) -> Tuple[str, Optional[str]]:
    """``"SPEC@REV"`` -> (SPEC, REV); a method without ``@`` -> (method, None)."""
    spec, at, revision = method.rpartition("@")
    if not at:
        return method, None
    if not spec or not revision:
        raise ValueError(f"'{method}': write SPEC@REVISION, e.g. gcn@a482093")
    return spec, revision


def solve_at_revision(spec: str, revision: str, problems: Sequence[Problem],
                      repo: Union[str, Path] = CHECKOUT) -> List[Union[Result, ValueError]]:
    """Each problem solved by solver ``spec`` of the package at git ``revision`` of ``repo``.

    Args:
        spec: a solver spec as that revision reads it (``solvers.create``), e.g. ``"gcn"``.
        revision: anything git resolves to a commit (a hash, a tag, ``HEAD~3``).
        problems: the windows, in today's :class:`~gcn_match_ros.problem.Problem`.
        repo: the git checkout to take the revision from.

    Returns:
        one :class:`~gcn_match_ros.problem.Result` per problem, in order; a problem the solver refused
        there (ValueError or MemoryError, as :func:`gcn_match_ros.evaluation.evaluate` records a refusal)
        has a ValueError with that message in its place.

    Raises:
        ValueError: ``revision`` is not a commit of ``repo`` (git's message).
        RuntimeError: the revision's solver failed (its exit status; its messages went to stderr).
    """
    tree = package_tree(revision, repo)
    with tempfile.TemporaryDirectory(prefix="gcn_match_revision_") as tmp:
        src, out = (Path(tmp) / d for d in ("problems", "results"))
        for d in (src, out):
            d.mkdir()
        for i, problem in enumerate(problems):
            save_problem(problem, src / f"{i:06d}.npz")
        # cwd and PYTHONPATH put the revision's package before the installed (editable) one
        env = {**os.environ, "PYTHONPATH": os.fspath(tree)}
        run = subprocess.run([sys.executable, "-c", _SOLVE, spec, os.fspath(src), os.fspath(out)], cwd=tree, env=env)
        if run.returncode:
            raise RuntimeError(f"solver '{spec}' at {revision} exited with status {run.returncode}")
        return [_read(out / f"{i:06d}.npz") for i in range(len(problems))]


def package_tree(revision: str, repo: Union[str, Path] = CHECKOUT) -> Path:
    """The directory holding ``gcn_match_ros`` as it was at ``revision`` of ``repo``: extracted
    (``git archive``) on the first call for that commit, the same directory on later ones; removed
    when the process exits.

    Raises:
        ValueError: ``revision`` is not a commit of ``repo``, or has no ``gcn_match_ros`` (git's message).
    """
    found = subprocess.run(["git", "-C", os.fspath(repo), "rev-parse", "--verify", f"{revision}^{{commit}}"],
                           capture_output=True, text=True)
    if found.returncode:
        raise ValueError(f"git rev-parse {revision}: {found.stderr.strip()}")
    key = (os.fspath(Path(repo).resolve()), found.stdout.strip())
    if key not in _TREES:
        archive = subprocess.run(["git", "-C", os.fspath(repo), "archive", "--format=tar", key[1], "gcn_match_ros"],
                                 capture_output=True)
        if archive.returncode:
            raise ValueError(f"git archive {revision}: {archive.stderr.decode(errors='replace').strip()}")
        tree = Path(tempfile.mkdtemp(prefix=f"gcn_match_{key[1][:12]}_"))
        atexit.register(shutil.rmtree, tree, ignore_errors=True)
        with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
            tar.extractall(tree, filter="data")
        _TREES[key] = tree
    return _TREES[key]


def _read(path: Path) -> Union[Result, ValueError]:
    refused = path.with_name(path.name + ".refused")
    return ValueError(refused.read_text()) if refused.exists() else load_result(path)
