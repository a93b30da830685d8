"""Training losses of the GCN, computed without ever forming an N × N matrix.

Both losses compare the embedding similarity S = EEᵀ with a target over the
N² keypoint pairs of one problem (one graph; for a block-diagonal batch call them
on each graph's rows):

- :func:`reconstruction_loss`: the paper's D(A + I, EEᵀ), mean |·| (L1) or mean (·)² (L2)
  over all N² entries. L2 in closed form from the edges and the d × d Gram matrix
  EᵀE; L1 one view-pair block (n_a × n_b) at a time.
- :func:`epipolar_loss`: the paper's geometric term mean(S ∘ G) over cross-view pairs,
  with G the epipolar residual of the two keypoints under the known poses; one
  view-pair block at a time.
- :func:`edge_loss`: the edge head's label-free loss on candidate edges of a posed problem.
- :func:`distillation_loss`: a student edge head's logits against a teacher's probabilities.

All functions are differentiable in E, work in float32 and float64, and accept
``view_offsets`` as a tensor, array or list of V+1 ints.
"""
from __future__ import annotations

from typing import List, Optional, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry import essential_from_poses

__all__ = ["reconstruction_loss", "epipolar_loss", "edge_loss", "distillation_loss"]

Offsets = Union[Tensor, Sequence[int]]


def _offsets(view_offsets: Offsets, num_nodes: int) -> List[int]:
    vo = [int(v) for v in (view_offsets.tolist() if hasattr(view_offsets, "tolist") else view_offsets)]
    if len(vo) < 2 or vo[0] != 0 or vo[-1] != num_nodes or any(b < a for a, b in zip(vo[:-1], vo[1:])):
        raise ValueError(f"view_offsets: expected (V+1,) non-decreasing offsets from 0 to N={num_nodes}, got {vo}")
    return vo


def _check_embedding(E: Tensor, num_nodes: Optional[int] = None) -> None:
    if E.dim() != 2 or (num_nodes is not None and E.shape[0] != num_nodes):
        want = f"({'N' if num_nodes is None else num_nodes}, d)"
        raise ValueError(f"E: expected shape {want}, got {tuple(E.shape)}")


def _view_index(vo: List[int], device) -> Tensor:
    sizes = torch.tensor([b - a for a, b in zip(vo[:-1], vo[1:])], device=device)
    return torch.repeat_interleave(torch.arange(len(vo) - 1, device=device), sizes)


def _target_entries(edge_index: Tensor, edge_weight: Tensor, num_nodes: int, view: Tensor,
                    include_identity: bool, include_within_view: bool, dtype) -> Tuple[Tensor, Tensor, Tensor]:
    """Coalesced non-zeros (rows, cols, values) of the counted part of the target T."""
    if edge_index.dim() != 2 or edge_index.shape[0] != 2:
        raise ValueError(f"edge_index: expected shape (2, E), got {tuple(edge_index.shape)}")
    if edge_weight.dim() != 1 or edge_weight.shape[0] != edge_index.shape[1]:
        raise ValueError(f"edge_weight: expected shape ({edge_index.shape[1]},), got {tuple(edge_weight.shape)}")
    r, c = edge_index[0].long(), edge_index[1].long()
    w = edge_weight.to(dtype)
    if not include_within_view:
        keep = view[r] != view[c]
        r, c, w = r[keep], c[keep], w[keep]
    if include_identity:
        nodes = torch.arange(num_nodes, device=r.device)
        r, c = torch.cat([r, nodes]), torch.cat([c, nodes])
        w = torch.cat([w, torch.ones(num_nodes, dtype=dtype, device=w.device)])
    # sum duplicates so that sum(T²) is right
    key = r * num_nodes + c
    uniq, inv = torch.unique(key, return_inverse=True)
    vals = torch.zeros(uniq.shape[0], dtype=dtype, device=w.device).index_add(0, inv, w)
    return uniq // num_nodes, uniq % num_nodes, vals


def reconstruction_loss(E: Tensor, edge_index: Tensor, edge_weight: Tensor, num_nodes: int,
                        view_offsets: Offsets, kind: str = "l1", include_identity: bool = True,
                        include_within_view: bool = True) -> Tensor:
    r"""Mean discrepancy between the target T = A (+ I) and S = EEᵀ.

    .. math::
        L_1 = \frac{1}{|M|}\sum_{(i,j)\in M} |T_{ij} - (EE^\top)_{ij}|, \qquad
        L_2 = \frac{1}{|M|}\sum_{(i,j)\in M} (T_{ij} - (EE^\top)_{ij})^2

    M is the set of counted entries: all N² (the paper) when ``include_within_view``,
    else only pairs in different views (plus the diagonal when ``include_identity``).

    L2 is evaluated in closed form, O(E·d + N·d²):
    ``Σ_M T² − 2 Σ_edges T_ij (EEᵀ)_ij + Σ_M (EEᵀ)²`` with ``Σ_all (EEᵀ)² = ‖EᵀE‖_F²``
    (within-view blocks ``‖E_vᵀE_v‖_F²`` subtracted when masked, the diagonal
    ``Σ‖e_i‖⁴`` added back). L1 is evaluated one view-pair block at a time, memory
    O(max n_a n_b); it assumes A is symmetric (as :class:`graph.CorrespondenceGraph` is)
    and counts each off-diagonal block twice.

    Args:
        E: (N, d) embeddings.
        edge_index: (2, E) int64 non-zeros of A (both directions of every edge).
        edge_weight: (E,) their weights.
        num_nodes: N.
        view_offsets: (V+1,) node offsets of the views.
        kind: "l1" or "l2".
        include_identity: target A + I (the paper) instead of A.
        include_within_view: count the within-view blocks (the paper), where the
            target is 0 off the diagonal.

    Returns:
        () scalar loss in E's dtype.

    Shapes:
        E (N, d), edge_index (2, E), edge_weight (E,), view_offsets (V+1,) -> ().
    """
    _check_embedding(E, num_nodes)
    if kind not in ("l1", "l2"):
        raise ValueError(f"reconstruction_loss: kind must be 'l1' or 'l2', got {kind!r}")
    vo = _offsets(view_offsets, num_nodes)
    n = num_nodes
    if n == 0:
        return E.sum() * 0.0
    view = _view_index(vo, E.device)
    rows, cols, vals = _target_entries(edge_index.to(E.device), edge_weight.to(E.device), n, view,
                                       include_identity, include_within_view, E.dtype)
    sizes = [b - a for a, b in zip(vo[:-1], vo[1:])]
    if include_within_view:
        count = n * n
    else:
        count = n * n - sum(s * s for s in sizes) + (n if include_identity else 0)
    if count == 0:
        return E.sum() * 0.0

    if kind == "l2":
        s_on_t = (E[rows] * E[cols]).sum(dim=1)
        gram = E.t() @ E
        s_sq = gram.square().sum()
        if not include_within_view:
            for a, b in zip(vo[:-1], vo[1:]):
                Ev = E[a:b]
                s_sq = s_sq - (Ev.t() @ Ev).square().sum()
            if include_identity:
                s_sq = s_sq + E.square().sum(dim=1).square().sum()
        total = vals.square().sum() - 2.0 * (vals * s_on_t).sum() + s_sq
        return total / count

    # L1, block by block
    V = len(vo) - 1
    vr, vc = view[rows], view[cols]
    total = E.new_zeros(())
    for a in range(V):
        a0, a1 = vo[a], vo[a + 1]
        if a1 == a0:
            continue
        for b in range(a, V):
            b0, b1 = vo[b], vo[b + 1]
            if b1 == b0:
                continue
            sel = (vr == a) & (vc == b)
            if a == b and not include_within_view:
                if include_identity:  # only the diagonal is counted
                    diag = E[a0:a1].square().sum(dim=1)
                    total = total + (1.0 - diag).abs().sum()
                continue
            T = E.new_zeros(a1 - a0, b1 - b0)
            T[rows[sel] - a0, cols[sel] - b0] = vals[sel]
            block = (T - E[a0:a1] @ E[b0:b1].t()).abs().sum()
            total = total + (block if a == b else 2.0 * block)
    return total / count


# ---------------------------------------------------------------------------
# Geometric losses (poses at training time only)
# ---------------------------------------------------------------------------
def epipolar_loss(E: Tensor, X: Tensor, R: Tensor, t: Tensor, view_offsets: Offsets,
                  clamp_negative: bool = True, normalize_rays: bool = False) -> Tensor:
    r"""The paper's geometric loss: mean over cross-view pairs of (EEᵀ)_ij · G_ij.

    .. math::
        L = \frac{1}{\sum_{a<b} n_a n_b} \sum_{a<b} \sum_{i\in a, j\in b} s_{ij} G_{ij},
        \qquad G_{ij} = |x_i^\top R_a [\hat b_{ab}]_\times R_b^\top x_j|

    for world→camera poses (R_v, t_v) (``x ~ K (R X + t)``, camera centre C = −Rᵀt,
    camera→world rotation Rᵀ, unit baseline direction b̂_ab = (C_b − C_a)/‖C_b − C_a‖,
    which makes the loss independent of the scene's scale); see
    :func:`gcn_match_ros.geometry.essential_from_poses`. The authors wrote the same residual with
    camera→world rotations and camera centres. The mean over unordered pairs equals
    the mean over ordered ones (both S and G are symmetric). Computed one view-pair
    block at a time.

    A matched pair (same scene point) has G = 0, so the loss penalises similarity
    between keypoints whose rays cannot meet. ``clamp_negative`` uses
    s_ij = max((EEᵀ)_ij, 0): otherwise an embedding could lower the loss by making
    geometrically impossible pairs *negatively* similar (EEᵀ of unit rows lies in [-1, 1]).

    Args:
        E: (N, d) embeddings.
        X: (N, 3) calibrated homogeneous keypoints (:func:`gcn_match_ros.node_features.calibrated_points`).
        R: (V, 3, 3) world→camera rotations.
        t: (V, 3) world→camera translations.
        view_offsets: (V+1,) node offsets of the views.

    Returns:
        () scalar loss in E's dtype (0 with fewer than two non-empty views).

    Shapes:
        E (N, d), X (N, 3), R (V, 3, 3), t (V, 3), view_offsets (V+1,) -> ().
    """
    _check_embedding(E)
    n = E.shape[0]
    vo = _offsets(view_offsets, n)
    V = len(vo) - 1
    if X.shape != (n, 3):
        raise ValueError(f"X: expected shape ({n}, 3), got {tuple(X.shape)}")
    if R.shape != (V, 3, 3):
        raise ValueError(f"R: expected shape ({V}, 3, 3), got {tuple(R.shape)}")
    if t.shape != (V, 3):
        raise ValueError(f"t: expected shape ({V}, 3), got {tuple(t.shape)}")
    X = X.to(device=E.device, dtype=E.dtype)
    R = R.to(device=E.device, dtype=E.dtype)
    t = t.to(device=E.device, dtype=E.dtype)
    if normalize_rays:
        X = X / X.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    total, count = E.new_zeros(()), 0
    for a in range(V):
        a0, a1 = vo[a], vo[a + 1]
        for b in range(a + 1, V):
            b0, b1 = vo[b], vo[b + 1]
            if a1 == a0 or b1 == b0:
                continue
            G = (X[a0:a1] @ essential_from_poses(R[a], t[a], R[b], t[b]) @ X[b0:b1].t()).abs()
            S = E[a0:a1] @ E[b0:b1].t()
            if clamp_negative:
                S = S.clamp(min=0.0)
            total = total + (S * G).sum()
            count += (a1 - a0) * (b1 - b0)
    return total / count if count else total


def edge_loss(logits: Tensor, residual_px: Tensor, tol_px: float = 1.0, span_px: float = 2.0,
              epipolar_weight: float = 9.0) -> Tensor:
    r"""Label-free loss of the edge head on the candidate edges of a posed problem.

    .. math::
        L = \frac{1}{M}\sum_m \mathrm{softplus}(-z_m) + \lambda\, g_m\, \mathrm{softplus}(z_m),
        \qquad g_m = \mathrm{clip}((d_m - \tau)/\sigma, 0, 1)

    The first term reconstructs the candidate adjacency (every candidate is an edge of A,
    target 1); the second is the epipolar term: an edge whose Sampson distance d under the
    true poses exceeds τ + σ pixels is pushed to sigmoid(z) = 1/(1+λ). No match labels.
    """
    g = ((residual_px - tol_px) / span_px).clamp(0.0, 1.0).to(logits.dtype)
    return (F.softplus(-logits) + epipolar_weight * g * F.softplus(logits)).mean()


def distillation_loss(logits: Tensor, teacher_logits: Tensor) -> Tensor:
    r"""Binary cross-entropy of a student's edge logits against a teacher's probabilities.

    .. math::
        L = -\frac{1}{M}\sum_m p_m \log \sigma(z_m) + (1 - p_m) \log(1 - \sigma(z_m)),
        \qquad p_m = \sigma(t_m)

    Its gradient in z is (σ(z) − p) / M: zero where the student scores as the teacher, so the
    minimum (the teacher's mean binary entropy) is reached by copying the teacher's scores,
    calibration included. The teacher gets no gradient.

    Shapes: logits (M,), teacher_logits (M,) -> ().
    """
    if logits.shape != teacher_logits.shape:
        raise ValueError(f"distillation_loss: logits {tuple(logits.shape)} and teacher_logits "
                         f"{tuple(teacher_logits.shape)} differ in shape")
    target = torch.sigmoid(teacher_logits.detach().to(logits.dtype))
    return F.binary_cross_entropy_with_logits(logits, target)
