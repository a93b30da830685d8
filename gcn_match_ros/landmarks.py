"""Landmark ids that persist across windows: the same 3-D point keeps its id while any camera
sees it, and a new id is born only for a new point.

:class:`LandmarkTracker` follows one stream of solved windows (one per node, one per offline
replay; :class:`gcn_match_ros.stream.StreamState`). Each window's *units* — its tracks (one 3-D
point seen by several cameras, cycle-consistent by construction) and the keypoints in no track
— are associated with the live landmarks:

- a landmark is summarised by a running mean of its (unit) descriptors and, per camera, where
  it was last seen (and at the sighting before);
- a unit scores a landmark by the best cosine between one of its members and the summary; a
  member of a camera that saw the landmark at its last sighting must lie within ``gate_px`` of
  one of its last sightings (the rig moves little between windows; any camera's, because a
  camera's image can move to another camera's place — the sample bags slide a "rig" along one
  image sequence), a member of a camera that did not see it needs ``cross_similarity``;
- the best landmark of each unit is accepted when it clears ``min_similarity`` and Lowe's
  ratio against the unit's second best, and (``verify_motion``) when its members moved like the
  other continuations between the same two frames (a two-view model fitted per pair of frames,
  pose-free: repetitive structure passes the descriptor and gate tests but not this one; a
  landmark re-found after a gap is checked through the continuations that saw its frame);
  units then take landmarks one-to-one, best score first
  (a landmark continues at most one unit, so a window never gives two points one id);
- a track left without a landmark founds a new one (ids count up, never reused); a keypoint
  in no track only continues landmarks (one sighting of a new point is no landmark yet);
- landmarks not seen for ``max_age_s`` are retired: the state stays bounded on endless streams.

The cost: one descriptor product (keypoints x landmarks), then one compiled pass that keeps each
keypoint's two best landmarks, visiting only the landmarks its camera did not see and the
sightings in the grid cells around it (the gate), in chunks of keypoints that both threads take.
That search needs no tracks (:meth:`LandmarkTracker.search`): in a stream it runs on the second
thread while the solver finishes the window, and the solving thread takes the chunks still left
once it is done (:func:`gcn_match_ros.stream.solve_window`); only the rest
(:meth:`LandmarkTracker.associate`) follows the solve;
every later step works on those pairs (``test_landmarks`` checks them against the rule written
as dense matrices). A still 4 x 500 window with 445 landmarks: 6.7 ms (11.6 ms on one thread
with the earlier sort-based best per unit; benchmarks/results/stage_breakdown.md).

Shapes are per window: N keypoints, views in ``camera_ids`` order.
"""
from __future__ import annotations

import collections
import dataclasses
import functools
import math
import threading
from typing import Dict, Iterator, NamedTuple, Optional, Sequence, Tuple

import cv2
import numba
import numba.extending
import numpy as np

from .descriptors import cosine_distance
from .edges.verify import MIN_SEEDS, RANSAC_PX, PairModel, fit_pair, matrix_residuals, model_matrices, trusted_support
from .rounding import track_members
from .threads import SharedTasks, alongside

__all__ = ["LandmarkConfig", "LandmarkTracker", "WindowSearch", "PerCameraNNLinker"]

#: a continuation agrees with the motion model within this many times the model's tolerance
MOTION_SLACK = 2.0
#: continuations are mostly right (inlier shares ~0.9): USAC without local optimisation finds the
#: same inliers at half the cost of the solver's estimator (~0.9 vs 1.9 ms a fit)
MOTION_ESTIMATOR = cv2.USAC_FAST
#: a frame pair's model is fitted on at most this many of its pairs (the cost of a fit grows
#: with them; ~0.8 ms for F at 128)
MOTION_FIT_PAIRS = 128
#: RANSAC iterations of a frame pair's fit: enough for the inlier shares of continuations
#: (~0.9: a few dozen), bounded where most of a frame pair's continuations are wrong (then no
#: model is found and they stay unchecked)
MOTION_MAX_ITERS = 200
#: last window's motion model of a camera pair is used again while the share of the pairs it
#: explains is at most this much below its share when it was fitted (else refined, else re-fitted): a model
#: kept while it explained an absolute 0.8 drifted from the moving rig over windows and dropped
#: right continuations (landmark_eval: 1.24 vs 0.71 id switches per 100 on 2 cameras, seed 10)
MOTION_REUSE_DROP = 0.02
#: ... or by more than this many standard errors of a share of that many pairs: a right model's
#: share of ~90 continuations varies by ~0.02 from window to window, so at 0.02 alone half of the
#: refined models of node_latency's moving 2 x 250 rig were re-fitted (52 of its 60 fits in 118
#: windows; with 2 standard errors 32 fits, landmark_eval's ids within +-0.02 on every metric)
MOTION_REUSE_SIGMAS = 2.0
#: motion models are remembered for frames up to this many windows apart (a landmark re-found
#: after a gap is checked on the motion since its last sighting, which a steady rig repeats too)
MOTION_MEMORY_WINDOWS = 8
#: the motion is checked with H when H explains at least this share of F's pairs
MOTION_PLANAR_RATIO = 0.95
#: A window's landmark search is cut into chunks of keypoints of about this many (keypoint,
#: landmark) similarities, each taken by whichever thread is free (:class:`LandmarkSearch`): ~0.7
#: ms a chunk on a still 4 x 500 window (445 landmarks), small enough that the thread done first
#: takes over most of what is left, and above the size where handing a chunk to the second
#: thread costs more than it saves. A window below it is one chunk.
SEARCH_CHUNK_PRODUCTS = 100_000
#: keypoints a chunk holds at least: a product of a few rows costs a call of its own for little
#: work. Whether a chunk's product is bitwise the window's depends on the CPU's BLAS kernels (on
#: some, from a few rows on; on an AMD EPYC VM's OpenBLAS no row slice is); the chunks are fixed by
#: the window, so a window's result does not depend on who takes them either way.
SEARCH_CHUNK_ROWS = 64
#: and at most this many chunks: each costs a call and a product of its own (~30 us), and two
#: threads finishing within one of 16 chunks of each other waste little
SEARCH_CHUNKS = 16
_NO_PAIRS = np.zeros((0, 2))


@dataclasses.dataclass(frozen=True)
class LandmarkConfig:
    """See the module docstring; similarities are cosines of L2-normalised descriptors."""

    # generated rig sequences (seed 1, 3 cameras; benchmarks/landmark_eval.py scores other seeds):
    # same-point cosines between windows have median 0.66 at the calibrated descriptor noise, so
    # the image gate does most of the work (displacements: median 7 px, 99 % under 40 px)
    min_similarity: float = 0.45
    cross_similarity: float = 0.75
    ratio: float = 0.95
    gate_px: float = 40.0
    summary_weight: float = 0.3   # weight of a new sighting in the running-mean descriptor
    max_age_s: float = 2.0
    verify_motion: bool = True


class WindowSearch(NamedTuple):
    """One window's keypoints as :meth:`LandmarkTracker.search` leaves them for
    :meth:`LandmarkTracker.associate`.

    Shapes: column (N,) int64 camera column; keypoints (N, 2); desc (N, D) float32 L2-normalised;
    candidates: (keypoint, landmark, score) (K,) each, K <= 2N: each keypoint's best and second-best
    landmark that pass the gate (:func:`_two_best_landmarks`); None when there were no landmarks or
    keypoints.
    """

    column: np.ndarray
    keypoints: np.ndarray
    desc: np.ndarray
    stamp_ns: int
    candidates: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]]


class LandmarkSearch:
    """One window's :meth:`LandmarkTracker.search`, by whichever threads take part
    (:class:`gcn_match_ros.threads.SharedTasks`): the first :meth:`help` sets the search up
    (retires the landmarks unseen too long, notes the window's cameras), then every helper
    scores chunks of keypoints against the landmarks until none is left; :meth:`result` helps,
    waits for the chunks others took and puts them together. The chunks are fixed by the window
    and the tracker, not by who ran them: the result is the same on one thread or two.
    Made by :meth:`LandmarkTracker.search_job`.
    """

    def __init__(self, tracker: "LandmarkTracker", camera_ids: Sequence[str], view_offsets: np.ndarray,
                 keypoints: np.ndarray, descriptors: np.ndarray, stamp_ns: int) -> None:
        self._tracker = tracker
        self._args = (camera_ids, view_offsets, keypoints, descriptors, int(stamp_ns))
        self._lock = threading.Lock()
        self._set_up: Optional[Tuple[WindowSearch, SharedTasks]] = None

    @property
    def chunks(self) -> int:
        """How many chunks the keypoints are scored in (sets the search up)."""
        return len(self._tasks()[1])

    def help(self) -> None:
        """Score chunks not yet taken, on this thread, until none is left."""
        self._tasks()[1].help()

    def result(self) -> WindowSearch:
        """The search (:class:`WindowSearch`; a chunk's error re-raised), helping meanwhile; the
        tracker's next call must be :meth:`LandmarkTracker.associate` with it."""
        searched, tasks = self._tasks()
        if len(tasks):
            first, second, first_score, second_score = (np.concatenate(parts) for parts in zip(*tasks.results()))
            rows = np.arange(first.size)
            member = np.concatenate([rows, rows])
            lm, best = np.concatenate([first, second]), np.concatenate([first_score, second_score])
            keep = np.isfinite(best)
            searched = searched._replace(candidates=(member[keep], lm[keep], best[keep]))
        self._tracker._searched = searched
        return searched

    def _tasks(self) -> Tuple[WindowSearch, SharedTasks]:
        with self._lock:
            if self._set_up is None:
                self._set_up = self._tracker._search_tasks(*self._args)
            return self._set_up


class LandmarkTracker:
    """Persistent landmark ids over a stream of windows (module docstring).

    Attributes:
        born, retired: landmarks founded and retired so far; ``len()``: live landmarks.
    """

    def __init__(self, config: LandmarkConfig = LandmarkConfig()) -> None:
        self.config = config
        self._next_id = 0
        self._ids = np.zeros(0, np.int64)
        self._desc = np.zeros((0, 0), np.float32)
        self._born_ns = np.zeros(0, np.int64)
        self._seen_ns = np.zeros(0, np.int64)
        self._cams: Dict[str, int] = {}  # camera id -> column of _xy
        self._xy = np.zeros((0, 0, 2))   # (L, cameras, 2): where each camera saw it last (NaN: not)
        self._xy_before = np.zeros((0, 0, 2))  # (L, cameras, 2): the same at the sighting before
        self._before_ns = np.zeros(0, np.int64)  # time of that sighting (-1: none)
        # (last camera column, camera column, windows between the frames) -> (motion model, share
        # explained when fitted)
        self._motion_models = {}
        self._recent_ns = collections.deque(maxlen=MOTION_MEMORY_WINDOWS)  # the last windows' times, newest first
        self._searched: Optional[WindowSearch] = None  # the search associate() takes next
        self.born = 0
        self.retired = 0

    def __len__(self) -> int:
        return int(self._ids.size)

    def update(self, camera_ids: Sequence[str], view_offsets: np.ndarray, keypoints: np.ndarray,
               descriptors: np.ndarray, track: np.ndarray, stamp_ns: int) -> Tuple[np.ndarray, np.ndarray]:
        """Associate one solved window; returns (N,) landmark id per keypoint (-1: none) and
        (N,) the landmark's age in nanoseconds (since it was born; -1: none).
        :meth:`search` then :meth:`associate`."""
        return self.associate(self.search(camera_ids, view_offsets, keypoints, descriptors, stamp_ns), track)

    def search(self, camera_ids: Sequence[str], view_offsets: np.ndarray, keypoints: np.ndarray,
               descriptors: np.ndarray, stamp_ns: int) -> WindowSearch:
        """The first half of :meth:`update`, which needs no tracks: retire the landmarks unseen
        too long, then find each keypoint's candidate landmarks. A window of several chunks
        (:data:`SEARCH_CHUNK_PRODUCTS`) is shared with the second thread
        (:func:`gcn_match_ros.threads.alongside`): the descriptor product and the compiled pass
        release the GIL. The next call on this tracker must be :meth:`associate` with its result.
        In a stream the search runs while the window is solved instead (:meth:`search_job`)."""
        job = self.search_job(camera_ids, view_offsets, keypoints, descriptors, stamp_ns)
        with alongside(job.help, parallel=job.chunks > 1):
            return job.result()

    def search_job(self, camera_ids: Sequence[str], view_offsets: np.ndarray, keypoints: np.ndarray,
                   descriptors: np.ndarray, stamp_ns: int) -> "LandmarkSearch":
        """:meth:`search` as a :class:`LandmarkSearch` that threads take part in, made without
        work: :func:`gcn_match_ros.stream.solve_window` hands it to the second thread while the
        window is solved, and the solving thread helps with what is left once it is done. Until
        its result is taken the tracker must not be used otherwise."""
        return LandmarkSearch(self, camera_ids, view_offsets, keypoints, descriptors, stamp_ns)

    def _search_tasks(self, camera_ids: Sequence[str], view_offsets: np.ndarray, keypoints: np.ndarray,
                      descriptors: np.ndarray, stamp_ns: int) -> Tuple[WindowSearch, SharedTasks]:
        """A search's set-up, on the first thread that takes part: retire, note the cameras,
        normalise. Returns the search without candidates and the tasks that find them, chunks of
        keypoints each giving :func:`_two_best_landmarks` of its rows (none without landmarks or
        keypoints)."""
        n = keypoints.shape[0]
        view = np.repeat(np.arange(len(camera_ids)), np.diff(view_offsets))
        desc = descriptors.astype(np.float32)
        desc = desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        if self._desc.shape[1] != desc.shape[1]:
            self._reset(desc.shape[1])
        self._retire(stamp_ns)
        self._camera_columns(camera_ids)
        column = np.array([self._cams[c] for c in camera_ids], np.int64)[view]   # (N,) camera column
        searched = WindowSearch(column, keypoints, desc, stamp_ns, None)
        if not (self._ids.size and n):
            return searched, SharedTasks([])
        cfg = self.config
        points = np.asarray(keypoints, np.float64)
        landmarks, xy = self._desc, self._xy  # as they are now: the tracker is not changed until associate()
        gate = np.float64(cfg.gate_px)
        unseen_lists, grid = _unseen_by_camera(xy), _sighting_grid(xy, gate)

        def two_best(lo: int, hi: int):
            return _two_best_landmarks(desc[lo:hi] @ landmarks.T, column[lo:hi], points[lo:hi], xy, unseen_lists,
                                       grid, gate, np.float32(cfg.min_similarity), np.float32(cfg.cross_similarity))

        chunks = max(1, min(n * self._ids.size // SEARCH_CHUNK_PRODUCTS, n // SEARCH_CHUNK_ROWS, SEARCH_CHUNKS))
        bounds = np.linspace(0, n, chunks + 1).astype(np.int64)
        return searched, SharedTasks([functools.partial(two_best, int(lo), int(hi))
                                      for lo, hi in zip(bounds[:-1], bounds[1:])])

    def associate(self, searched: WindowSearch, track: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """The second half of :meth:`update`: the window's units (from ``track`` (N,)) take
        landmarks or found new ones. ``searched``: this tracker's last :meth:`search`.

        Raises:
            ValueError: ``searched`` is not the last search, or was associated already; ``track``
                is not one entry per keypoint of the search.
        """
        if searched is not self._searched:
            raise ValueError("associate() takes the tracker's last search() result, once")
        if len(track) != searched.keypoints.shape[0]:
            raise ValueError(f"track has {len(track)} entries for {searched.keypoints.shape[0]} keypoints")
        self._searched = None
        cfg = self.config
        column, keypoints, desc, stamp_ns = searched.column, searched.keypoints, searched.desc, searched.stamp_ns
        n = keypoints.shape[0]
        units = _Units(track)
        sizes = units.sizes
        best_lm = np.full(sizes.size, -1)
        best_score = np.zeros(sizes.size)
        if searched.candidates is not None:
            member, lm, score = searched.candidates
            best_lm, best_score = _best_per_unit(units.of_keypoint[member], lm, score, sizes.size, cfg.ratio)
        order = np.argsort(-best_score, kind="stable")   # the units, best score first
        if searched.candidates is not None and cfg.verify_motion:
            claimed = _one_to_one(best_lm, order) >= 0
            best_lm = self._motion_checked(best_lm, claimed, units, column, keypoints)
        # units take landmarks one-to-one, best score first; a track left without one is a new point
        best_lm = _one_to_one(best_lm, order)
        winners = best_lm[order] >= 0
        continued = order[winners]
        founders = order[~winners & (sizes[order] >= 2)]
        landmark = np.full(n, -1, np.int64)   # per keypoint: its landmark's index (-1: none)
        if continued.size:
            members = units.members(continued)
            self._sighted(best_lm[continued], members, sizes[continued], column, keypoints, desc, stamp_ns)
            landmark[members] = np.repeat(best_lm[continued], sizes[continued])
        if founders.size:
            members = units.members(founders)
            first = self._found(members, sizes[founders], column, keypoints, desc, stamp_ns)
            landmark[members] = np.repeat(first + np.arange(founders.size), sizes[founders])
        has = landmark >= 0
        ids, ages = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
        ids[has], ages[has] = self._ids[landmark[has]], stamp_ns - self._born_ns[landmark[has]]
        self._recent_ns.appendleft(stamp_ns)
        return ids, ages

    @property
    def _previous_ns(self):
        """The last window's time (None before the first)."""
        return self._recent_ns[0] if self._recent_ns else None

    def _windows_back(self, stamp_ns: int):
        """How many windows ago the frame of ``stamp_ns`` was (1: the last window); None when it
        is older than the remembered windows."""
        for back, ns in enumerate(self._recent_ns, 1):
            if ns == stamp_ns:
                return back
        return None

    def _motion_checked(self, best_lm, claimed, units, column, keypoints):
        """The continuations that agree with the image motion since the last sightings.

        Each continuation pairs a member's pixel with its landmark's last sighting in a camera;
        the pairs of all continuations between the same two frames (last camera at the time of
        the last sighting, current camera) share one motion. A frame pair whose image held still
        is checked against the identity; the others, where a continuation is still unchecked,
        fit a two-view model (:func:`gcn_match_ros.edges.verify.fit_pair`; H unless F explains
        clearly more pairs) and count only with the support of a trusted one (``edges.verify``).
        The models are fitted on (and a frame pair is fitted only for) the continuations of the
        units that keep their landmark if it passes (``claimed``, (U,) bool: first in the
        one-to-one claims): a unit outscored for its landmark is mostly a wrong continuation, and
        a static 2-camera scene's lone keypoints made 70% of the fitted pairs wrong (every fit
        untrusted, four a window); every continuation is still checked against the models.
        The frames of a camera pair as many windows apart as a frame pair of last window (up to
        ``MOTION_MEMORY_WINDOWS``) re-check that pair's model first; when it explains a share of
        the pairs more than :func:`_reuse_drop` below its share when fitted, it is refined by
        least squares on the pairs it still explains, and re-fitted only when that falls short
        too, as the rig memory does for camera pairs: a rig moving steadily is not re-fitted
        every window.
        A continuation most of whose checked pairs disagree is dropped (one wrong member of a
        track does not undo the track's continuation): what descriptors and the image gate
        cannot tell apart on repetitive structure, the motion of the other points can.
        A landmark re-found after windows unseen was last seen in an older frame, which few
        other continuations share: too few pairs to fit that frame pair's motion. The
        continuations from the last window bridge it (:func:`_motion_pairs`: their sighting before
        the last one was in that frame), so the re-found ones are checked with a model fitted
        on their pairs and the bridges'. A continuation that nothing checks is dropped when it
        is a lone keypoint's or a re-finding after a gap (on the sample bags such re-findings
        were mostly wrong; fountain's held-out reprojection within 3 px 0.934 -> 0.958); a
        track's continuation from the last window stays unchecked (refusing those fragmented
        the generated rigs' landmarks, 1.1 -> 1.25 per point).
        """
        cont = np.flatnonzero(best_lm >= 0)
        if cont.size == 0:
            return best_lm
        sizes = units.sizes
        rows = units.members(cont)
        (unit, xa, xb, fitted, moved, starts, ends, cam_a, cam_b, frame_ns, still, bridge_bounds, bridge_xa,
         bridge_xb) = _motion_pairs(rows, np.repeat(cont, sizes[cont]), best_lm, claimed, column, keypoints,
                                    self._xy, self._seen_ns, self._xy_before, self._before_ns,
                                    self._previous_ns, MIN_SEEDS, RANSAC_PX)
        votes = np.zeros(sizes.size, np.int64)   # per unit: pairs that agree minus pairs that do not
        checked = np.zeros(sizes.size, np.int64)  # per unit: pairs under a trusted model
        # frame pairs whose image held still first (a standing robot; on the sample bags an image
        # seen again by the next camera): the identity is their model, exact and free, and F
        # would be degenerate there
        _vote_still(unit, fitted, moved, starts, ends, still, votes, checked)
        # then models, only where a continuation is still unchecked (docstring): the frame pairs
        # their remembered model serves are voted in one compiled pass, which stops at one whose
        # model must be refined or fitted; that one is done here, then the pass goes on
        keys = [self._remembered_as(int(a), int(b), int(ns)) for a, b, ns in zip(cam_a, cam_b, frame_ns)]
        remembered = [self._motion_models.get(key, (None, 0.0)) for key in keys]
        known, matrices, has_h, has_f, thresholds, shares = _packed_models(remembered)
        g = -1
        while True:
            g = _vote_remembered(g + 1, unit, xa, xb, fitted, starts, ends, still, bridge_bounds, bridge_xa,
                                 bridge_xb, known, matrices, has_h, has_f, thresholds, shares, votes, checked)
            if g == starts.size:
                break
            sel = slice(starts[g], ends[g])
            bridge = None
            if bridge_bounds[g + 1] > bridge_bounds[g]:
                at = slice(bridge_bounds[g], bridge_bounds[g + 1])
                bridge = bridge_xa[at], bridge_xb[at]
            fitted_model = _refitted(remembered[g], xa[sel], xb[sel], fitted[sel], bridge)
            if fitted_model is None:
                continue
            model, fitted_share, checks = fitted_model
            if keys[g] is not None:
                self._motion_models[keys[g]] = (model, fitted_share)
            _add_votes(votes, checked, unit[sel], *checks.residuals, checks.uses_h, model.px, model.epipolar_px)
        gap = np.zeros(sizes.size, bool)
        gap[cont] = self._seen_ns[best_lm[cont]] != self._previous_ns
        return np.where((votes < 0) | ((checked == 0) & ((sizes == 1) | gap)), -1, best_lm)

    def _remembered_as(self, cam_a: int, cam_b: int, frame_ns: int):
        """The key of a frame pair's remembered motion model: (camera then, camera now, windows
        back), None for a frame older than the remembered windows."""
        back = self._windows_back(frame_ns)
        return None if back is None else (cam_a, cam_b, back)

    # -- state ---------------------------------------------------------------------------
    def _reset(self, dim: int) -> None:
        self._ids = np.zeros(0, np.int64)
        self._desc = np.zeros((0, dim), np.float32)
        self._born_ns = np.zeros(0, np.int64)
        self._seen_ns = np.zeros(0, np.int64)
        self._xy = np.zeros((0, len(self._cams), 2))
        self._xy_before = np.zeros((0, len(self._cams), 2))
        self._before_ns = np.zeros(0, np.int64)

    def _camera_columns(self, camera_ids: Sequence[str]) -> None:
        new = [c for c in camera_ids if c not in self._cams]
        for c in new:
            self._cams[c] = len(self._cams)
        if new:
            self._xy = np.concatenate([self._xy, np.full((self._xy.shape[0], len(new), 2), np.nan)], 1)
            self._xy_before = np.concatenate([self._xy_before, np.full((self._xy.shape[0], len(new), 2), np.nan)], 1)

    def _retire(self, now_ns: int) -> None:
        keep = (now_ns - self._seen_ns) <= self.config.max_age_s * 1e9
        if keep.all():
            return
        self.retired += int((~keep).sum())
        self._ids, self._desc = self._ids[keep], self._desc[keep]
        self._born_ns, self._seen_ns = self._born_ns[keep], self._seen_ns[keep]
        self._xy, self._xy_before, self._before_ns = self._xy[keep], self._xy_before[keep], self._before_ns[keep]

    def _sighted(self, js, rows, sizes, column, keypoints, desc, stamp_ns) -> None:
        """Update the landmarks ``js`` (K,) with their units at once: the units' members one
        unit after another in ``rows``, ``sizes`` (K,) members each."""
        _blend_summaries(self._desc, js, rows, sizes, desc, self.config.summary_weight)
        _move_sightings(self._xy, self._xy_before, self._seen_ns, self._before_ns, js, rows, sizes, column,
                        keypoints, stamp_ns)

    def _found(self, rows, sizes, column, keypoints, desc, stamp_ns) -> int:
        """New landmarks for K tracks, ids in their order: their members one track after another
        in ``rows``, ``sizes`` (K,) members each. Returns the first new landmark's index."""
        k = sizes.size
        summary = _unit_summaries(rows, sizes, desc)
        xy = np.full((k, len(self._cams), 2), np.nan)
        xy[np.repeat(np.arange(k), sizes), column[rows]] = keypoints[rows]   # a track has one keypoint per camera
        first = self._ids.size
        self._ids = np.concatenate([self._ids, self._next_id + np.arange(k)])
        self._desc = np.concatenate([self._desc, summary])
        self._born_ns = np.concatenate([self._born_ns, np.full(k, stamp_ns, np.int64)])
        self._seen_ns = np.concatenate([self._seen_ns, np.full(k, stamp_ns, np.int64)])
        self._xy = np.concatenate([self._xy, xy])
        self._xy_before = np.concatenate([self._xy_before, np.full_like(xy, np.nan)])
        self._before_ns = np.concatenate([self._before_ns, np.full(k, -1, np.int64)])
        self._next_id += k
        self.born += k
        return first


@numba.njit(cache=True)
def _motion_pairs(rows, unit_of_row, best_lm, claimed, column, keypoints, xy, seen_ns, xy_before, before_ns,
                  previous_ns, min_seeds, still_px):
    """:meth:`LandmarkTracker._motion_checked`'s pairs and frame pairs, compiled (numpy and a
    dict of bridges took ~1.5 ms a window at 2 x 500).

    A pair per continuing keypoint (``rows`` (R,), its unit ``unit_of_row``) and earlier sighting
    of its landmark (``best_lm`` of the unit) in a camera: (that sighting, the keypoint now).
    Pairs are grouped by frame pair (camera then, camera now, time then), the groups in that
    order, a group's pairs in row order then camera order. A frame pair older than the last window
    takes its bridge pairs: the continuations from the last window (rows ascending) whose sighting
    before the last one was in that frame, in that camera, with their keypoint in the same camera
    now. Only frame pairs with at least ``min_seeds`` fitted pairs (those of ``claimed`` units)
    and bridge pairs are kept; "still" where the median motion of their fitted pairs is at most
    ``still_px``.

    Shapes: xy, xy_before (L, cameras, 2) float64; seen_ns, before_ns (L,). Returns the sorted
    pairs (P,): unit, xa, xb (P, 2) float64, fitted (bool), moved (|xb - xa|); per kept frame
    pair (G,): start, end into the pairs, camera then, camera now, time then, still (bool); then
    the bridge pairs of every kept frame pair one after another, ``bridge_bounds`` (G + 1,),
    bridge_xa, bridge_xb (B, 2) float64.
    """
    n_cams = xy.shape[1]
    pair_row = np.empty(rows.size * n_cams, np.int64)
    pair_cam = np.empty(rows.size * n_cams, np.int64)
    pair_ns = np.empty(rows.size * n_cams, np.int64)
    n_pairs = 0
    for r in range(rows.size):
        lm = best_lm[unit_of_row[r]]
        for c in range(n_cams):
            if not np.isnan(xy[lm, c, 0]):
                pair_row[n_pairs], pair_cam[n_pairs], pair_ns[n_pairs] = r, c, seen_ns[lm]
                n_pairs += 1
    pair_row, pair_cam, pair_ns = pair_row[:n_pairs], pair_cam[:n_pairs], pair_ns[:n_pairs]
    # the frames' times, few: ranked by a scan, the pairs then put in key order by a counting sort
    # (stable: row order, then camera order, within a group)
    times = np.empty(n_pairs, np.int64)
    n_times = 0
    for p in range(n_pairs):
        known = False
        for k in range(n_times):
            if times[k] == pair_ns[p]:
                known = True
                break
        if not known:
            times[n_times] = pair_ns[p]
            n_times += 1
    times = np.sort(times[:n_times])
    key = (pair_cam * n_cams + column[rows[pair_row]]) * times.size + np.searchsorted(times, pair_ns)
    count = np.zeros(n_cams * n_cams * times.size + 1, np.int64)
    for p in range(n_pairs):
        count[key[p] + 1] += 1
    count = np.cumsum(count)
    order = np.empty(n_pairs, np.int64)
    for p in range(n_pairs):
        order[count[key[p]]] = p
        count[key[p]] += 1
    unit = np.empty(n_pairs, np.int64)
    xa = np.empty((n_pairs, 2))
    xb = np.empty((n_pairs, 2))
    fitted = np.empty(n_pairs, np.bool_)
    moved = np.empty(n_pairs)
    for i in range(n_pairs):
        q = order[i]
        r, c = pair_row[q], pair_cam[q]
        unit[i] = unit_of_row[r]
        xa[i, 0], xa[i, 1] = xy[best_lm[unit[i]], c, 0], xy[best_lm[unit[i]], c, 1]
        xb[i, 0], xb[i, 1] = np.float64(keypoints[rows[r], 0]), np.float64(keypoints[rows[r], 1])
        fitted[i] = claimed[unit[i]]
        dx, dy = xb[i, 0] - xa[i, 0], xb[i, 1] - xa[i, 1]
        moved[i] = np.sqrt(dx * dx + dy * dy)
    # every frame pair's bridge rows at once, by the frame pair's key (a scan of the rows per frame
    # pair cost ~5 us each, and a window has ~36 of them at 2 x 500, most with too few pairs to keep)
    bridge_start, bridges = _bridge_rows(rows, unit_of_row, best_lm, column, seen_ns, before_ns, xy_before,
                                         previous_ns, times)
    # the frame pairs, kept where they have enough pairs to fit on
    starts = np.empty(n_pairs, np.int64)
    ends = np.empty(n_pairs, np.int64)
    cam_a = np.empty(n_pairs, np.int64)
    cam_b = np.empty(n_pairs, np.int64)
    frame_ns = np.empty(n_pairs, np.int64)
    still = np.empty(n_pairs, np.bool_)
    bridge_bounds = np.zeros(n_pairs + 1, np.int64)
    bridge_row = np.empty(bridges.size, np.int64)   # a frame pair's key is its own: each bucket once
    n_groups = 0
    i = 0
    while i < n_pairs:
        j = i + 1
        while j < n_pairs and key[order[j]] == key[order[i]]:
            j += 1
        first = order[i]
        ca, cb, t = pair_cam[first], column[rows[pair_row[first]]], pair_ns[first]
        n_fit = 0
        for k in range(i, j):
            n_fit += fitted[k]
        b0, b1 = bridge_start[key[first]], bridge_start[key[first] + 1]
        if n_fit + b1 - b0 >= min_seeds:
            starts[n_groups], ends[n_groups] = i, j
            cam_a[n_groups], cam_b[n_groups], frame_ns[n_groups] = ca, cb, t
            if n_fit:
                m = np.empty(n_fit)
                f = 0
                for k in range(i, j):
                    if fitted[k]:
                        m[f] = moved[k]
                        f += 1
                m.sort()
                still[n_groups] = 0.5 * (m[(n_fit - 1) // 2] + m[n_fit // 2]) <= still_px
            else:
                still[n_groups] = False
            at = bridge_bounds[n_groups]
            bridge_row[at:at + b1 - b0] = bridges[b0:b1]
            bridge_bounds[n_groups + 1] = at + b1 - b0
            n_groups += 1
        i = j
    bridge_row = bridge_row[:bridge_bounds[n_groups]]
    bridge_xa = np.empty((bridge_row.size, 2))
    bridge_xb = np.empty((bridge_row.size, 2))
    for g in range(n_groups):
        for k in range(bridge_bounds[g], bridge_bounds[g + 1]):
            r = bridge_row[k]
            lm = best_lm[unit_of_row[r]]
            bridge_xa[k, 0], bridge_xa[k, 1] = xy_before[lm, cam_a[g], 0], xy_before[lm, cam_a[g], 1]
            bridge_xb[k, 0], bridge_xb[k, 1] = np.float64(keypoints[rows[r], 0]), np.float64(keypoints[rows[r], 1])
    return (unit, xa, xb, fitted, moved, starts[:n_groups], ends[:n_groups], cam_a[:n_groups], cam_b[:n_groups],
            frame_ns[:n_groups], still[:n_groups], bridge_bounds[:n_groups + 1], bridge_xa, bridge_xb)


@numba.njit(cache=True, inline="always")
def _bridge_rows(rows, unit_of_row, best_lm, column, seen_ns, before_ns, xy_before, previous_ns, times):
    """The rows that bridge each frame pair of :func:`_motion_pairs` (camera then at a time of
    ``times``, camera now): continuations from the last window, their keypoint in the camera now,
    whose landmark's sighting before the last one was in the camera then at that time; none for
    a frame of the last window itself. By the frame pairs' key ((camera then x cameras + camera
    now) x times + the time's rank), rows ascending within one: (keys + 1,) bucket starts and the
    rows, bucket after bucket."""
    n_cams = xy_before.shape[1]
    key = np.full(rows.size * n_cams, -1, np.int64)   # per (row, camera then)
    start = np.zeros(n_cams * n_cams * times.size + 1, np.int64)
    for r in range(rows.size):
        lm = best_lm[unit_of_row[r]]
        t = before_ns[lm]
        if seen_ns[lm] != previous_ns or t == previous_ns:
            continue
        rank = np.searchsorted(times, t)
        if rank == times.size or times[rank] != t:
            continue   # no continuation's frame pair at that time
        for c in range(n_cams):
            if not np.isnan(xy_before[lm, c, 0]):
                key[r * n_cams + c] = (c * n_cams + column[rows[r]]) * times.size + rank
                start[key[r * n_cams + c] + 1] += 1
    start = np.cumsum(start)
    fill = start[:-1].copy()
    bridges = np.empty(start[-1], np.int64)
    for k in range(key.size):
        if key[k] >= 0:
            bridges[fill[key[k]]] = k // n_cams
            fill[key[k]] += 1
    return start, bridges


@numba.njit(cache=True)
def _move_sightings(xy, xy_before, seen_ns, before_ns, js, rows, sizes, column, keypoints, stamp_ns) -> None:
    """In place: landmark ``js[u]``'s last sightings become its sightings before, and unit u's
    members (``rows``, one unit after another, ``sizes`` (K,) each) its last ones, at ``stamp_ns``.
    Compiled (numpy's gathers and scatters took ~0.1 ms at 2 x 500).

    Shapes: xy, xy_before (L, cameras, 2); seen_ns, before_ns (L,); js (K,) distinct; column
    (N,) each keypoint's camera column; keypoints (N, 2)."""
    r = 0
    for u in range(js.size):
        j = js[u]
        before_ns[j], seen_ns[j] = seen_ns[j], stamp_ns
        for c in range(xy.shape[1]):
            xy_before[j, c, 0], xy_before[j, c, 1] = xy[j, c, 0], xy[j, c, 1]
            xy[j, c, 0], xy[j, c, 1] = np.nan, np.nan
        for k in range(r, r + sizes[u]):
            row = rows[k]
            xy[j, column[row], 0], xy[j, column[row], 1] = keypoints[row, 0], keypoints[row, 1]
        r += sizes[u]


@numba.njit(cache=True, inline="always")
def _member_mean(mean, total, rows, start, size, desc) -> None:
    """Into ``mean`` (D,) float64: the mean descriptor of the ``size`` members
    ``rows[start:start + size]`` of ``desc`` (N, D) float32, summed in float32 in member order
    in ``total`` (D,) float32 (scratch). One owner of a unit's mean for :func:`_unit_summaries`
    and :func:`_blend_summaries`."""
    total[:] = 0
    for r in range(start, start + size):
        row = rows[r]
        for k in range(total.size):
            total[k] += desc[row, k]
    for k in range(total.size):
        mean[k] = np.float64(total[k]) / size


@numba.njit(cache=True, inline="always")
def _unit_norm(v) -> float:
    """The Euclidean norm of ``v`` (D,), at least 1e-12 (a zero mean stays zero)."""
    square = 0.0
    for k in range(v.size):
        square += v[k] * v[k]
    return max(np.sqrt(square), 1e-12)


@numba.njit(cache=True)
def _unit_summaries(rows: np.ndarray, sizes: np.ndarray, desc: np.ndarray) -> np.ndarray:
    """(K, D) float32: the summary a new landmark starts from for each of K units whose members
    are ``rows``, one unit after another, ``sizes`` (K,) each: the unit vector along the members'
    mean descriptor. Compiled (the numpy mean, norm and cast took 0.15 ms at 2 x 500)."""
    d = desc.shape[1]
    out = np.empty((sizes.size, d), np.float32)
    total = np.empty(d, np.float32)
    mean = np.empty(d, np.float64)
    r = 0
    for u in range(sizes.size):
        _member_mean(mean, total, rows, r, sizes[u], desc)
        r += sizes[u]
        norm = _unit_norm(mean)
        for k in range(d):
            out[u, k] = mean[k] / norm
    return out


@numba.njit(cache=True)
def _blend_summaries(summaries: np.ndarray, js: np.ndarray, rows: np.ndarray, sizes: np.ndarray,
                     desc: np.ndarray, weight: float) -> None:
    """In place: landmark ``js[u]``'s summary becomes the unit vector along
    (1 - weight) x its summary + weight x the mean descriptor of unit u, whose members are
    ``rows``, one unit after another, ``sizes`` (K,) each. Compiled: the gather, blend, norm and
    scatter in numpy took 0.5 ms at 2 x 500, this 0.13 ms.

    Shapes: summaries (L, D) float32, js (K,) distinct, desc (N, D) float32."""
    d = summaries.shape[1]
    total = np.empty(d, np.float32)
    mixed = np.empty(d, np.float64)
    keep = np.float32(1.0 - weight)
    r = 0
    for u in range(js.size):
        _member_mean(mixed, total, rows, r, sizes[u], desc)
        r += sizes[u]
        j = js[u]
        for k in range(d):   # the summary's share in float32, as numpy scales a float32 array
            mixed[k] = np.float64(keep * summaries[j, k]) + weight * mixed[k]
        norm = _unit_norm(mixed)
        for k in range(d):
            summaries[j, k] = mixed[k] / norm


class _Units:
    """A window's units: its tracks (members in view order, tracks by id) and then every keypoint
    in no track, alone; stored as one (N,) array of members, unit after unit.

    Attributes:
        sizes: (U,) members per unit; of_keypoint: (N,) each keypoint's unit.
    """

    def __init__(self, track: np.ndarray) -> None:
        track = np.asarray(track, np.int64)
        self._members, self._starts, self.of_keypoint = _unit_layout(track, *track_members(track))
        self.sizes = np.diff(self._starts)

    def __len__(self) -> int:
        return int(self.sizes.size)

    def __iter__(self) -> Iterator[np.ndarray]:
        """Each unit's members."""
        return iter(np.split(self._members, self._starts[1:-1]))

    def members(self, units: np.ndarray) -> np.ndarray:
        """The members of ``units`` (K,), one unit after another: (sizes[units].sum(),)."""
        sizes = self.sizes[units]
        first = np.repeat(self._starts[units] - np.cumsum(sizes) + sizes, sizes)
        return self._members[first + np.arange(first.size)]


@numba.njit(cache=True)
def _unit_layout(track, tracked, starts):
    """:class:`_Units`' arrays from the tracks' members ``tracked`` (K,) and their starts (T + 1,)
    (:func:`gcn_match_ros.rounding.track_members`), compiled (numpy's concatenations and scatter
    took ~0.1 ms a 2 x 500 window): the members, the tracks' then every keypoint in no track,
    ascending; where each unit starts among them; each keypoint's unit.

    Shapes: track (N,) int64, -1 = none -> (N,), (U + 1,), (N,) int64.
    """
    n = track.size
    members = np.empty(n, np.int64)
    members[:tracked.size] = tracked
    unit_starts = np.empty(n + 1, np.int64)
    units = starts.size - 1
    unit_starts[:units] = starts[:units]
    k = tracked.size
    for i in range(n):
        if track[i] < 0:
            members[k] = i
            unit_starts[units] = k
            units += 1
            k += 1
    unit_starts[units] = n
    of_keypoint = np.empty(n, np.int64)
    for u in range(units):
        for k in range(unit_starts[u], unit_starts[u + 1]):
            of_keypoint[members[k]] = u
    return members, unit_starts[:units + 1], of_keypoint


def _best_per_unit(unit: np.ndarray, lm: np.ndarray, score: np.ndarray, n_units: int, ratio: float):
    """Each unit's best landmark if it clears Lowe's ratio against the unit's second best.

    A unit scores a landmark by its best member; the second best is the best score of any other
    landmark.

    Args:
        unit, lm, score: (K,) candidate (unit, landmark) rows, a row per member, float32 scores.
        n_units: U.
    Returns:
        (U,) landmark index (-1: none) and (U,) float32 its score (0: none). Ties go to the lower
        landmark index.
    """
    best_lm, first, second = _two_best_per_unit(np.asarray(unit, np.int64), np.asarray(lm, np.int64),
                                                np.asarray(score, np.float32), n_units)
    second = np.where(np.isfinite(second), second, -1.0)
    ok = np.isfinite(first) & ((cosine_distance(first) < ratio * cosine_distance(second)) | (second < 0))
    return np.where(ok, best_lm, -1), np.where(ok, first, 0.0)


@numba.njit(cache=True, nogil=True)
def _two_best_per_unit(unit, lm, score, n_units):
    """Per unit the landmark of its best row (the lower index on ties), that row's score, and
    the best score of any other landmark, in one pass over the rows: the two best distinct
    landmarks so far are kept with their best scores (a landmark outside them scored at most the
    second's). Shapes: (K,) rows -> (U,) int64 (-1: none), (U,) float32 twice (-inf: none)."""
    best = np.full(n_units, -1, np.int64)
    runner = np.full(n_units, -1, np.int64)
    first = np.full(n_units, -np.inf, np.float32)
    second = np.full(n_units, -np.inf, np.float32)
    for r in range(unit.size):
        u, l, s = unit[r], lm[r], score[r]
        if l == best[u]:
            first[u] = max(first[u], s)
        elif l == runner[u]:
            second[u] = max(second[u], s)
            if second[u] > first[u] or (second[u] == first[u] and l < best[u]):
                best[u], runner[u] = l, best[u]
                first[u], second[u] = second[u], first[u]
        elif s > first[u] or (s == first[u] and l < best[u]):
            runner[u], second[u] = best[u], first[u]
            best[u], first[u] = l, s
        elif s > second[u]:
            runner[u], second[u] = l, s
    return best, first, second


@numba.njit(cache=True)
def _one_to_one(best_lm: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Each landmark to the first unit in ``order`` that takes it (the units by descending score,
    ties in unit order: the one that scores it highest, the first on ties); the other units'
    landmark becomes -1. Compiled: one pass (a sort and np.unique took 0.1 ms a call, twice a
    window).

    Shapes: best_lm (U,) landmark index (-1: none), order (U,) a permutation -> (U,).
    """
    out = np.full(best_lm.size, -1, np.int64)
    if best_lm.size == 0:
        return out
    taken = np.zeros(best_lm.max() + 1, np.bool_)
    for u in order:
        lm = best_lm[u]
        if lm >= 0 and not taken[lm]:
            taken[lm] = True
            out[u] = lm
    return out


@numba.extending.register_jitable
def _reuse_drop(share: float, n: int) -> float:
    """How far below ``share`` (the share a remembered motion model explained when fitted) its
    share of a new frame pair's n pairs may fall before it is refined or re-fitted:
    ``MOTION_REUSE_DROP``, or ``MOTION_REUSE_SIGMAS`` standard errors of a share of n pairs
    where that is more (the share of a model that is still right varies that much from window
    to window)."""
    p = (share * n + 1.0) / (n + 2.0)  # not 0 or 1: a share of 1.0 fitted on 90 pairs is not exact
    return max(MOTION_REUSE_DROP, MOTION_REUSE_SIGMAS * math.sqrt(p * (1.0 - p) / n))


@numba.extending.register_jitable
def _enough_support(share: float, n: int) -> float:
    """The support a remembered motion model needs on a frame pair's n pairs to be used as it is:
    its ``share`` when fitted, less :func:`_reuse_drop`, of them."""
    return (share - _reuse_drop(share, n)) * n


@numba.extending.register_jitable
def _uses_h(support_h: int, support_f: int) -> bool:
    """Whether a motion check goes by H (:attr:`_MotionChecks.uses_h`)."""
    return support_h >= MOTION_PLANAR_RATIO * support_f


@numba.njit(cache=True, nogil=True)
def _model_support(xa, xb, fitted, bridge_xa, bridge_xb, H, Hi, F, has_h, has_f, px, fit_px):
    """:class:`_MotionChecks`' arithmetic (the matrices as :func:`gcn_match_ros.edges.verify.model_matrices`
    gives them): residuals (M,) twice on xa <-> xb (M, 2), and whether each pair the model is
    fitted on (those of ``fitted`` (M,), then the bridge pairs (B, 2)) lies within H's threshold
    ``px`` and within F's fit threshold ``fit_px``."""
    rh, rf = matrix_residuals(xa, xb, H, Hi, F, has_h, has_f)
    bh, bf = matrix_residuals(bridge_xa, bridge_xb, H, Hi, F, has_h, has_f)
    n = 0
    for m in range(rh.size):
        n += fitted[m]
    in_h = np.empty(n + bh.size, np.bool_)
    in_f = np.empty(n + bh.size, np.bool_)
    k = 0
    for m in range(rh.size):
        if fitted[m]:
            in_h[k], in_f[k] = rh[m] <= px, rf[m] <= fit_px
            k += 1
    for m in range(bh.size):
        in_h[k], in_f[k] = bh[m] <= px, bf[m] <= fit_px
        k += 1
    return rh, rf, in_h, in_f


@numba.njit(cache=True, nogil=True)
def _add_votes(votes, checked, unit, rh, rf, uses_h, px, epipolar_px) -> None:
    """In place: each pair's unit (``unit`` (M,)) gets a vote for (+1) or against (-1) its
    continuation, by whether the pair agrees with the motion model (residuals ``rh``, ``rf``
    (M,), H's when ``uses_h``, within MOTION_SLACK times its tolerance), and a check."""
    for m in range(unit.size):
        agree = rh[m] <= MOTION_SLACK * px if uses_h else rf[m] <= MOTION_SLACK * epipolar_px
        votes[unit[m]] += 1 if agree else -1
        checked[unit[m]] += 1


@numba.njit(cache=True, nogil=True)
def _vote_still(unit, fitted, moved, starts, ends, still, votes, checked) -> None:
    """In place: the votes and checks of the frame pairs whose image held still (``still``
    (G,)), under the identity: their pairs agree when they moved (``moved`` (P,)) at most
    MOTION_SLACK x RANSAC_PX, counted when the identity explains the fitted pairs with trusted
    support (:func:`_motion_pairs`' pairs and frame pairs)."""
    for g in range(starts.size):
        if not still[g]:
            continue
        inliers, n = 0, 0
        for m in range(starts[g], ends[g]):
            if fitted[m]:
                n += 1
                inliers += moved[m] <= RANSAC_PX
        if trusted_support(inliers, n):
            for m in range(starts[g], ends[g]):
                votes[unit[m]] += 1 if moved[m] <= MOTION_SLACK * RANSAC_PX else -1
                checked[unit[m]] += 1


@numba.njit(cache=True, nogil=True)
def _vote_remembered(g, unit, xa, xb, fitted, starts, ends, still, bridge_bounds, bridge_xa, bridge_xb, known,
                     matrices, has_h, has_f, thresholds, shares, votes, checked) -> int:
    """In place: the votes and checks of the frame pairs from ``g`` on (moving ones with a
    continuation not yet checked) that their remembered motion model serves as it is (support at
    least :func:`_enough_support`; counted where that is trusted support). Returns the first frame
    pair whose model must be refined or fitted instead (no remembered model, or too little
    support), or G when none is left.

    Shapes: :func:`_motion_pairs`' pairs (P,) and frame pairs (G,); the remembered models as
    :func:`_packed_models` packs them.
    """
    while g < starts.size:
        a, b, c, d = starts[g], ends[g], bridge_bounds[g], bridge_bounds[g + 1]
        unchecked = False
        for m in range(a, b):
            if fitted[m] and checked[unit[m]] == 0:
                unchecked = True
                break
        if still[g] or not unchecked:
            g += 1
            continue
        if not known[g]:
            return g
        rh, rf, in_h, in_f = _model_support(xa[a:b], xb[a:b], fitted[a:b], bridge_xa[c:d], bridge_xb[c:d],
                                            matrices[g, 0], matrices[g, 1], matrices[g, 2], has_h[g], has_f[g],
                                            thresholds[g, 0], thresholds[g, 2])
        support_h, support_f = in_h.sum(), in_f.sum()
        if max(support_h, support_f) < _enough_support(shares[g], in_h.size):
            return g
        if trusted_support(max(support_h, support_f), in_h.size):
            _add_votes(votes, checked, unit[a:b], rh, rf, _uses_h(support_h, support_f), thresholds[g, 0],
                       thresholds[g, 1])
        g += 1
    return g


def _packed_models(remembered):
    """Remembered motion models ((model or None, share when fitted) per frame pair) as arrays
    for :func:`_vote_remembered`: known (G,) bool; matrices (G, 3, 3, 3) float64 (H, H⁻¹, F;
    :func:`gcn_match_ros.edges.verify.model_matrices`); has_h, has_f (G,) bool; thresholds (G, 3)
    (px, epipolar_px, epipolar_fit_px); shares (G,)."""
    n = len(remembered)
    known, has_h, has_f = np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, bool)
    matrices, thresholds, shares = np.zeros((n, 3, 3, 3)), np.zeros((n, 3)), np.zeros(n)
    for g, (model, share) in enumerate(remembered):
        if model is not None:
            known[g], shares[g] = True, share
            matrices[g, 0], matrices[g, 1], matrices[g, 2], has_h[g], has_f[g] = model_matrices(model)
            thresholds[g] = model.px, model.epipolar_px, model.epipolar_fit_px
    return known, matrices, has_h, has_f, thresholds, shares


def _refined(model: PairModel, checks: "_MotionChecks", xa: np.ndarray, xb: np.ndarray) -> Optional[PairModel]:
    """``model`` with the motion its check uses (:attr:`_MotionChecks.uses_h`) re-estimated by
    least squares (DLT, normalised 8-point) on the pairs it was fitted on, xa <-> xb (M, 2), that
    ``checks`` found within its fit threshold; the other motion is kept as it was (the check
    chooses between them again on the new counts; H's DLT with OpenCV's refinement costs 0.3 ms,
    and a moving rig's check mostly uses F). None when the model lacks that motion, when it has
    fewer than MIN_SEEDS such pairs, or when the fit fails."""
    planar = checks.uses_h
    on = checks.inliers[0] if planar else checks.inliers[1]
    if (model.H if planar else model.F) is None or on.sum() < MIN_SEEDS:
        return None
    try:
        if planar:
            H, F = cv2.findHomography(xa[on], xb[on], 0)[0], model.F
        else:
            H, F = model.H, cv2.findFundamentalMat(xa[on], xb[on], cv2.FM_8POINT)[0]
    except cv2.error:
        return None
    if (H is None) if planar else (F is None or F.shape != (3, 3)):
        return None
    return dataclasses.replace(model, H=H, F=F)


def _refitted(remembered, xa, xb, fitted, bridge):
    """The model of a frame pair whose remembered model (``remembered``: (model or None,
    share explained when fitted)) explains too few of its pairs (:func:`_enough_support`):
    that model refined by least squares on the pairs it still explains (a steady rig's motion
    drifts slowly, and a re-fit costs several times as much), else a new fit on an even
    spread of at most MOTION_FIT_PAIRS of the pairs it is fitted on (``fitted`` (M,) of
    xa <-> xb (M, 2), then the ``bridge`` pairs), checked on all of them.

    Returns:
        (model, share explained when fitted, its :class:`_MotionChecks`), or None when no
        model with trusted support is found.
    """
    model, fitted_share = remembered
    fa, fb = xa[fitted], xb[fitted]
    if bridge is not None:
        fa, fb = np.concatenate([fa, bridge[0]]), np.concatenate([fb, bridge[1]])
    enough = _enough_support(fitted_share, fa.shape[0])
    checks = None
    if model is not None:
        refined = _refined(model, _MotionChecks(model, xa, xb, fitted, bridge), fa, fb)
        if refined is not None:
            model, checks = refined, _MotionChecks(refined, xa, xb, fitted, bridge)
    if checks is None or max(checks.support) < enough:
        fit = np.linspace(0, fa.shape[0] - 1, min(fa.shape[0], MOTION_FIT_PAIRS)).astype(np.int64)
        model = fit_pair(fa[fit], fb[fit], estimator=MOTION_ESTIMATOR, max_iters=MOTION_MAX_ITERS)
        if model is None:
            return None
        checks = _MotionChecks(model, xa, xb, fitted, bridge)
        fitted_share = max(checks.support) / fa.shape[0]
    if not trusted_support(max(checks.support), fa.shape[0]):
        return None
    return model, fitted_share, checks


class _MotionChecks:
    """A motion model's residuals on a frame pair's pairs xa <-> xb (M, 2) and its support on
    the pairs it is fitted on: those of ``fitted`` (M,) bool, then the ``bridge`` pairs (or None).

    Attributes:
        residuals: (H's, F's) (M,) each (:func:`gcn_match_ros.edges.verify.residuals`);
        inliers: (within H's threshold, within F's) (F,) bool each, of the F pairs it is fitted on;
        support: their counts;
        uses_h: whether the check goes by H: H unless F explains clearly more pairs (fewer than
            MOTION_PLANAR_RATIO of F's), counted by the residuals the check uses — a small rig
            motion makes H almost as good as F by the estimators' counts, yet near points move
            off it by tens of pixels; on a plane F is degenerate and absorbs outliers.
    """

    def __init__(self, model, xa: np.ndarray, xb: np.ndarray, fitted: np.ndarray, bridge) -> None:
        bridge_xa, bridge_xb = bridge if bridge is not None else (_NO_PAIRS, _NO_PAIRS)
        rh, rf, in_h, in_f = _model_support(np.ascontiguousarray(xa, np.float64), np.ascontiguousarray(xb, np.float64),
                                            np.ascontiguousarray(fitted, np.bool_),
                                            np.ascontiguousarray(bridge_xa, np.float64),
                                            np.ascontiguousarray(bridge_xb, np.float64), *model_matrices(model),
                                            model.px, model.epipolar_fit_px)
        self.residuals = rh, rf
        self.inliers = in_h, in_f
        self.support = int(in_h.sum()), int(in_f.sum())
        self.uses_h = bool(_uses_h(*self.support))


class PerCameraNNLinker:
    """The baseline: ids linked window to window by per-camera mutual nearest neighbours.

    Each keypoint is linked to the previous window's keypoint of the same camera that is its
    mutual nearest neighbour (and passes Lowe's ``ratio``); a unit (track, or lone keypoint)
    takes the id of its first linked member, one unit per id; an unlinked track gets a new id.
    """

    def __init__(self, ratio: float = 0.8) -> None:
        self.ratio = ratio
        self._next_id = 0
        self._previous: Dict[str, Tuple[np.ndarray, np.ndarray]] = {}  # camera -> (descriptors, ids)

    def update(self, camera_ids: Sequence[str], view_offsets: np.ndarray, descriptors: np.ndarray,
               track: np.ndarray) -> np.ndarray:
        """(N,) ids of one solved window (-1: none)."""
        n = descriptors.shape[0]
        desc = descriptors / np.maximum(np.linalg.norm(descriptors, axis=1, keepdims=True), 1e-12)
        linked = np.full(n, -1, np.int64)
        for v, cam in enumerate(camera_ids):
            rows = np.arange(int(view_offsets[v]), int(view_offsets[v + 1]))
            prev_desc, prev_ids = self._previous.get(cam, (np.zeros((0, 1)), None))
            if prev_desc.shape[0] < 2 or rows.size < 2:
                continue
            sim = desc[rows] @ prev_desc.T
            best = sim.argmax(1)
            back = sim.argmax(0)
            top2 = np.sort(sim, axis=1)[:, -2:]
            ok = (back[best] == np.arange(rows.size)) & (cosine_distance(top2[:, 1])
                                                         < self.ratio * cosine_distance(top2[:, 0]))
            linked[rows[ok]] = prev_ids[best[ok]]
        ids = np.full(n, -1, np.int64)
        used = set()
        for members in _Units(track):
            cand = [int(linked[m]) for m in members if linked[m] >= 0 and int(linked[m]) not in used]
            if cand:
                ids[members] = cand[0]
                used.add(cand[0])
            elif members.size >= 2:
                ids[members] = self._next_id
                self._next_id += 1
        self._previous = {cam: (desc[int(view_offsets[v]):int(view_offsets[v + 1])],
                                ids[int(view_offsets[v]):int(view_offsets[v + 1])])
                          for v, cam in enumerate(camera_ids)}
        return ids


@numba.njit(cache=True, nogil=True)
def _two_best_landmarks(sim, column, keypoints, xy, unseen_lists, grid, gate_px, min_similarity, cross_similarity):
    """Per keypoint its best and second-best landmark (-1 and -inf where none) by the rule of
    the module docstring: a landmark its camera saw counts at ``sim`` >= ``min_similarity`` when
    the keypoint lies within ``gate_px`` of one of its last sightings (any camera's), one its
    camera did not see at ``sim`` >= ``cross_similarity``. The lower landmark index on ties, as
    argmax. Compiled, no (N, L) temporaries: the sightings are binned on a grid of cells at
    least ``gate_px`` wide, so a keypoint visits only the sightings of the 3 x 3 cells around it
    and the landmarks its camera did not see (a pass over every landmark of every keypoint took
    as long as the descriptor product on a moving rig: 0.9 -> 0.2 ms for 482 keypoints x 524
    landmarks); where the sightings around a keypoint are dense (a still scene that every camera
    sees), that one pass in landmark order, which is then cheaper.

    ``unseen_lists`` (:func:`_unseen_by_camera`) and ``grid`` (:func:`_sighting_grid`, at
    ``gate_px``) are of ``xy``, made once for all chunks of a window's keypoints.

    Shapes: sim (N, L) float32; column (N,); keypoints (N, 2); xy (L, cameras, 2), NaN where
    unseen -> (N,) int64 twice, (N,) float32 twice.
    """
    n, n_lm = sim.shape
    n_cams = xy.shape[1]
    gate2 = gate_px * gate_px
    first = np.full(n, -1, np.int64)
    second = np.full(n, -1, np.int64)
    first_score = np.full(n, -np.inf, np.float32)
    second_score = np.full(n, -np.inf, np.float32)
    unseen, unseen_start = unseen_lists
    x0, y0, cell, nx, ny, cell_start, sighting_lm, sighting_xy = grid
    passed_lm = np.empty(sighting_lm.size, np.int64)   # one keypoint's sightings that pass
    passed_score = np.empty(sighting_lm.size, np.float32)
    for i in range(n):
        c = column[i]
        x, y = keypoints[i, 0], keypoints[i, 1]
        # the 3 x 3 cells around it, clipped to the grid (none: off the grid or not finite)
        lo_x, hi_x, lo_y, hi_y = 0, -1, 0, -1
        if nx and np.isfinite(x) and np.isfinite(y):
            gx, gy = np.floor((x - x0) / cell), np.floor((y - y0) / cell)
            if max(gx - 1, 0.0) <= min(gx + 1, nx - 1.0) and max(gy - 1, 0.0) <= min(gy + 1, ny - 1.0):
                lo_x, hi_x = int(max(gx - 1, 0.0)), int(min(gx + 1, nx - 1.0))
                lo_y, hi_y = int(max(gy - 1, 0.0)), int(min(gy + 1, ny - 1.0))
        visits = 0
        for ix in range(lo_x, hi_x + 1):
            visits += cell_start[ix * ny + hi_y + 1] - cell_start[ix * ny + lo_y]
        if 2 * visits + unseen_start[c + 1] - unseen_start[c] > n_lm:
            # dense sightings around it (e.g. every camera saw every landmark): one pass in
            # landmark order is cheaper than visiting them cell by cell (a grid visit reads
            # sim out of order, about twice the cost)
            for lm in range(n_lm):
                s = sim[i, lm]
                if not s >= second_score[i]:
                    continue
                if np.isnan(xy[lm, c, 0]):
                    if s >= cross_similarity:
                        _enter_two_best(i, lm, s, first, second, first_score, second_score)
                elif s >= min_similarity:
                    for k in range(n_cams):
                        dx, dy = x - xy[lm, k, 0], y - xy[lm, k, 1]
                        if dx * dx + dy * dy <= gate2:  # NaN (unseen) compares False
                            _enter_two_best(i, lm, s, first, second, first_score, second_score)
                            break
            continue
        for at in range(unseen_start[c], unseen_start[c + 1]):
            lm = unseen[at]
            s = sim[i, lm]
            if s >= cross_similarity and s >= second_score[i]:
                _enter_two_best(i, lm, s, first, second, first_score, second_score)
        # the sightings that pass first, without a branch per test (which pass is unpredictable:
        # branching on each cost ~20 ns a visit, twice the reads), then the two best among them
        passed = 0
        for ix in range(lo_x, hi_x + 1):
            for at in range(cell_start[ix * ny + lo_y], cell_start[ix * ny + hi_y + 1]):
                lm = sighting_lm[at]
                s = sim[i, lm]
                dx, dy = x - sighting_xy[at, 0], y - sighting_xy[at, 1]
                passed_lm[passed], passed_score[passed] = lm, s
                # its camera saw it (NaN: did not, the cross rule above), and within the gate
                passed += (s >= min_similarity) & (xy[lm, c, 0] == xy[lm, c, 0]) & (dx * dx + dy * dy <= gate2)
        for k in range(passed):
            if passed_score[k] >= second_score[i]:
                _enter_two_best(i, passed_lm[k], passed_score[k], first, second, first_score, second_score)
    return first, second, first_score, second_score


@numba.njit(cache=True, nogil=True, inline="always")
def _enter_two_best(i, lm, s, first, second, first_score, second_score):
    """Landmark ``lm`` at similarity ``s`` into keypoint i's two best (higher similarity first,
    then the lower index), once however often it is offered."""
    if lm == first[i] or lm == second[i]:
        return
    if s > first_score[i] or (s == first_score[i] and lm < first[i]):
        second[i], second_score[i] = first[i], first_score[i]
        first[i], first_score[i] = lm, s
    elif s > second_score[i] or (s == second_score[i] and lm < second[i]):
        second[i], second_score[i] = lm, s


@numba.njit(cache=True, nogil=True)
def _unseen_by_camera(xy):
    """Per camera the landmarks it did not see, ascending: camera c's are
    ``unseen[unseen_start[c]:unseen_start[c + 1]]``. Shapes: xy (L, cameras, 2) -> (L * cameras,),
    (cameras + 1,) int64."""
    n_lm, n_cams = xy.shape[0], xy.shape[1]
    unseen = np.empty(n_lm * n_cams, np.int64)
    unseen_start = np.zeros(n_cams + 1, np.int64)
    for c in range(n_cams):
        at = unseen_start[c]
        for lm in range(n_lm):
            if np.isnan(xy[lm, c, 0]):
                unseen[at] = lm
                at += 1
        unseen_start[c + 1] = at
    return unseen, unseen_start


@numba.njit(cache=True, nogil=True)
def _sighting_grid(xy, gate_px):
    """Every finite sighting binned on a grid of square cells at least ``gate_px`` wide (and at
    most 256 x 256 of them), column-major by cell x: cell (ix, iy) holds
    ``sighting_lm / sighting_xy[cell_start[ix * ny + iy]:cell_start[ix * ny + iy + 1]]``, so the
    cells iy = lo..hi of one ix are one slice.

    Returns: x0, y0 (the grid's corner), cell (its width), nx, ny (0, 0: no sighting),
    cell_start (nx * ny + 1,) int64, sighting_lm (S,) int64, sighting_xy (S, 2).
    """
    n_lm, n_cams = xy.shape[0], xy.shape[1]
    sighting_lm = np.empty(n_lm * n_cams, np.int64)
    sighting_xy = np.empty((n_lm * n_cams, 2))
    count = 0
    x0, y0, x1, y1 = np.inf, np.inf, -np.inf, -np.inf
    for lm in range(n_lm):
        for k in range(n_cams):
            sx, sy = xy[lm, k, 0], xy[lm, k, 1]
            if np.isfinite(sx) and np.isfinite(sy):
                sighting_lm[count], sighting_xy[count, 0], sighting_xy[count, 1] = lm, sx, sy
                x0, y0, x1, y1 = min(x0, sx), min(y0, sy), max(x1, sx), max(y1, sy)
                count += 1
    if count == 0:
        return 0.0, 0.0, 1.0, 0, 0, np.zeros(1, np.int64), sighting_lm[:0], sighting_xy[:0]
    cell = max(gate_px, (x1 - x0) / 256.0, (y1 - y0) / 256.0, 1.0)
    nx, ny = int((x1 - x0) / cell) + 1, int((y1 - y0) / cell) + 1
    of = np.empty(count, np.int64)
    cell_start = np.zeros(nx * ny + 1, np.int64)
    for at in range(count):
        of[at] = int((sighting_xy[at, 0] - x0) / cell) * ny + int((sighting_xy[at, 1] - y0) / cell)
        cell_start[of[at] + 1] += 1
    for g in range(nx * ny):
        cell_start[g + 1] += cell_start[g]
    fill = cell_start[:-1].copy()
    binned_lm = np.empty(count, np.int64)
    binned_xy = np.empty((count, 2))
    for at in range(count):
        g = of[at]
        binned_lm[fill[g]] = sighting_lm[at]
        binned_xy[fill[g]] = sighting_xy[at]
        fill[g] += 1
    return x0, y0, cell, nx, ny, cell_start, binned_lm, binned_xy
