"""Where the package's files are, relative to the package itself (one owner for the rule).

:data:`CHECKOUT` is the directory that holds the ``gcn_match_ros`` package: the root of a
source checkout (``setup.py``, ``config/``, ``bags/``, ``msg_defs/`` beside the package, the
datasets in ``../shared`` beside it), or the site directory of an installed package, where
those are absent — a reader checks that the file it wants is there and falls back to the
installed share directory.
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["CHECKOUT"]

CHECKOUT = Path(__file__).resolve().parents[1]
