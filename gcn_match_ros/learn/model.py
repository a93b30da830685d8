"""The graph convolutional network of Phillips & Daniilidis (arXiv 1901.02078).

The network maps the keypoints of a window of views (the nodes of the
correspondence graph, :mod:`graph`) to unit embeddings E so that EEᵀ approximates
the cycle-consistent match matrix. As in the authors' code, every layer is a graph
convolution with a linear self-skip,

    H' = relu(Â H W + b) + H U + c,        Â = (D+I)^-½ (A+I) (D+I)^-½,

followed by group norm (layers 1 … L-1); the *skip layers* (default the 7th and the
12th) also receive a linear projection of the input features and of the previous
skip layer's output; an output linear layer and row L2 normalisation give E.

Everything is sparse: Â is a CSR matrix with N + E entries, so a forward pass costs
O(N·d² + E·d) per layer and never forms an N × N matrix. Several graphs of
different sizes run in one pass as one block-diagonal graph (:func:`collate`).

Typical inference::

    model, meta = load_checkpoint("default.pt")      # .checkpoint
    E, graph = embed_problem(model, problem, meta["graph_config"], meta["feature_config"])
"""
from __future__ import annotations

import dataclasses
import warnings
from typing import Any, Dict, Optional, Sequence, Tuple, Union

import numba
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..buckets import sort_buckets
from ..configs import JsonConfig
from ..graph import CorrespondenceGraph, GraphConfig, build_graph
from ..node_features import FeatureConfig, node_features
from ..problem import Problem

__all__ = ["GCNConfig", "GCN", "GraphSkipConv", "GraphGroupNorm", "gcn_norm", "normalized_adjacency",
           "graph_tensors", "collate", "embed_problem"]

#: Candidate edges scored at a time at inference (:meth:`GCN.score_edges`): 4096 x 64 hidden
#: floats (1 MiB) stay in cache; at 4 x 500 2048 was slower (3.6 ms), 8192 the same (3.1 ms).
EDGE_CHUNK = 4096


# ---------------------------------------------------------------------------
# Shape checks
# ---------------------------------------------------------------------------
def _fmt(shape) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ")"


def _check_2d(t: Tensor, name: str, cols: Optional[int] = None, rows: Optional[int] = None) -> None:
    ok = t.dim() == 2 and (cols is None or t.shape[1] == cols) and (rows is None or t.shape[0] == rows)
    if not ok:
        want = _fmt(("N" if rows is None else rows, "*" if cols is None else cols))
        raise ValueError(f"{name}: expected shape {want}, got {_fmt(tuple(t.shape))}")


def _check_edges(edge_index: Tensor, edge_weight: Tensor, num_nodes: int) -> None:
    if edge_index.dim() != 2 or edge_index.shape[0] != 2:
        raise ValueError(f"edge_index: expected shape (2, E), got {_fmt(tuple(edge_index.shape))}")
    if edge_index.dtype not in (torch.int64, torch.int32):
        raise ValueError(f"edge_index: expected an integer dtype, got {edge_index.dtype}")
    e = edge_index.shape[1]
    if edge_weight.dim() != 1 or edge_weight.shape[0] != e:
        raise ValueError(f"edge_weight: expected shape ({e},) to match edge_index (2, {e}), "
                         f"got {_fmt(tuple(edge_weight.shape))}")
    if e:
        lo, hi = (int(v) for v in torch.aminmax(edge_index))
        if lo < 0 or hi >= num_nodes:
            raise ValueError(f"edge_index: node indices must lie in [0, {num_nodes}), got [{lo}, {hi}]")


def _check_ptr(node_ptr: Tensor, num_nodes: int) -> None:
    if node_ptr.dim() != 1 or node_ptr.shape[0] < 2:
        raise ValueError(f"node_ptr: expected shape (B+1,) with B >= 1, got {_fmt(tuple(node_ptr.shape))}")
    if int(node_ptr[0]) != 0 or int(node_ptr[-1]) != num_nodes or bool((node_ptr[1:] < node_ptr[:-1]).any()):
        raise ValueError(f"node_ptr: must start at 0, be non-decreasing and end at N={num_nodes}, "
                         f"got {node_ptr.tolist()}")


# ---------------------------------------------------------------------------
# Normalisation of the adjacency (pure functions)
# ---------------------------------------------------------------------------
def gcn_norm(edge_index: Tensor, edge_weight: Tensor, num_nodes: int) -> Tuple[Tensor, Tensor]:
    r"""Symmetric GCN normalisation with self loops (Kipf & Welling 2017).

    .. math::
        \hat A = (D + I)^{-1/2} (A + I) (D + I)^{-1/2}, \qquad D_{ii} = \sum_j A_{ij}

    i.e. for every entry (i, j) of A + I: :math:`\hat a_{ij} = a_{ij} / \sqrt{d_i d_j}`
    with :math:`d_i = 1 + \sum_j A_{ij}`. Self loops already in the input are folded
    into the added identity (their weight is added to 1), so the output has exactly
    one entry per node on the diagonal. Degrees are row sums; for the symmetric
    correspondence graphs they equal the column sums.

    Args:
        edge_index: (2, E) int64 ``[rows; cols]`` of the non-zeros of A.
        edge_weight: (E,) float, their values.
        num_nodes: N.

    Returns:
        ``(edge_index', weight')``: the non-zeros of Â, the E' = E - (#self loops) + N
        entries, input edges first (in input order) then the N diagonal entries.

    Shapes:
        edge_index (2, E), edge_weight (E,) -> (2, E'), (E',).
    """
    _check_edges(edge_index, edge_weight, num_nodes)
    edge_index = edge_index.long()
    row, col = edge_index[0], edge_index[1]
    loop = row == col
    diag = torch.ones(num_nodes, dtype=edge_weight.dtype, device=edge_weight.device)
    if bool(loop.any()):
        diag = diag.index_add(0, row[loop], edge_weight[loop])
        keep = ~loop
        row, col, edge_weight = row[keep], col[keep], edge_weight[keep]
    deg = diag.index_add(0, row, edge_weight)
    inv_sqrt = deg.clamp(min=1e-12).rsqrt()
    nodes = torch.arange(num_nodes, device=row.device)
    out_index = torch.stack([torch.cat([row, nodes]), torch.cat([col, nodes])])
    # index_select, not inv_sqrt[row]: the same values, ~5x faster on the CPU for these gathers
    out_weight = torch.cat([inv_sqrt.index_select(0, row) * edge_weight * inv_sqrt.index_select(0, col),
                            diag * inv_sqrt * inv_sqrt])
    return out_index, out_weight


def normalized_adjacency(edge_index: Tensor, edge_weight: Tensor, num_nodes: int) -> Tensor:
    """Â of :func:`gcn_norm` as a sparse CSR tensor (the propagation operator).

    CSR is used because, measured on a 2-core CPU at N = 2000 with 20 edges per node
    and d = 128, ``csr @ H`` takes 0.3–0.4 ms (1.5 ms with backward) against 1.2 ms
    (4.5 ms) for COO ``torch.sparse.mm`` and 4 ms (30 ms) for gather + ``index_add``.
    At inference on the CPU (float32, no gradient) Â is built by one compiled pass,
    :func:`_normalized_csr`, bit for bit the tensor the torch ops below give (a 4 x 500
    window's ~40 k entries: 0.59 -> 0.26 ms alone; in the solve, beside the candidate edges'
    thread, the network 0.65 ms sooner: one call instead of ~20 that each wait for the GIL).

    Shapes: edge_index (2, E), edge_weight (E,) -> (N, N) sparse CSR, dtype of edge_weight.
    """
    if (edge_weight.device.type == "cpu" and edge_weight.dtype == torch.float32
            and not (torch.is_grad_enabled() and edge_weight.requires_grad)):
        _check_edges(edge_index, edge_weight, num_nodes)
        crow, col, weight = _normalized_csr(edge_index[0].long().numpy(), edge_index[1].long().numpy(),
                                            edge_weight.numpy(), num_nodes)
        crow, col, weight = torch.from_numpy(crow), torch.from_numpy(col), torch.from_numpy(weight)
    else:
        index, weight = gcn_norm(edge_index, edge_weight, num_nodes)
        row, col = index[0], index[1]
        key = row * num_nodes + col  # unique: any sort gives the (row, col) order
        # numpy's stable sort (timsort) on the CPU: the graphs come sorted by (row, col) (graph.build_graph,
        # collate) and the diagonal after them, two runs it merges in linear time (4 x 500 window's 39 k
        # keys: 0.08 ms; numpy's default sort 0.7, torch.argsort 1.6)
        order = (torch.from_numpy(np.argsort(key.numpy(), kind="stable")) if key.device.type == "cpu"
                 else torch.argsort(key))
        counts = torch.bincount(row, minlength=num_nodes)
        crow = torch.zeros(num_nodes + 1, dtype=torch.int64, device=row.device)
        crow[1:] = torch.cumsum(counts, 0)
        col, weight = col.index_select(0, order), weight.index_select(0, order)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*Sparse CSR tensor support is in beta.*")
        return torch.sparse_csr_tensor(crow, col, weight, (num_nodes, num_nodes), check_invariants=False)


@numba.njit(cache=True, nogil=True)
def _normalized_csr(rows, cols, weights, n):
    """Â of :func:`gcn_norm` in CSR order, float32, as :func:`normalized_adjacency`'s torch ops
    compute it: self loops folded into the diagonal and the degrees summed in edge order, the
    entries ``inv_sqrt[r] * w * inv_sqrt[c]`` (the diagonal's ``d * inv_sqrt * inv_sqrt``), each
    row's entries by column, equal columns in edge order (a stable sort; the graphs come sorted,
    so it costs one pass).

    Shapes: rows, cols (E,) int64 in [0, n), weights (E,) float32 -> crow (n + 1,) int64,
    col (E',) int64, values (E',) float32, E' = E - (#self loops) + n.
    """
    e = rows.shape[0]
    diag = np.ones(n, np.float32)
    for m in range(e):
        if rows[m] == cols[m]:
            diag[rows[m]] += weights[m]
    deg = diag.copy()
    crow = np.zeros(n + 1, np.int64)
    m = 0
    while m < e:  # a run of one row's edges (its whole row, the graph sorted) summed in a register
        r = rows[m]
        total, count = deg[r], crow[r + 1]
        while m < e and rows[m] == r:
            if cols[m] != r:
                total += weights[m]
                count += 1
            m += 1
        deg[r], crow[r + 1] = total, count
    for i in range(n):
        crow[i + 1] += crow[i] + 1  # + the diagonal entry
    inv_sqrt = np.empty(n, np.float32)
    one, tiny = np.float32(1.0), np.float32(1e-12)
    for i in range(n):
        inv_sqrt[i] = one / np.sqrt(max(deg[i], tiny))
    fill = crow[:-1].copy()
    col = np.empty(crow[n], np.int64)
    value = np.empty(crow[n], np.float32)
    m = 0
    while m < e:
        r = rows[m]
        at, scale = fill[r], inv_sqrt[r]
        while m < e and rows[m] == r:
            c = cols[m]
            if c != r:
                col[at] = c
                value[at] = scale * weights[m] * inv_sqrt[c]
                at += 1
            m += 1
        fill[r] = at
    for i in range(n):
        col[fill[i]] = i
        value[fill[i]] = diag[i] * inv_sqrt[i] * inv_sqrt[i]
    sort_buckets(crow, col, value)  # each row by column, stable
    return crow, col, value


# ---------------------------------------------------------------------------
# Configuration
# ---------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class GCNConfig(JsonConfig):
    """Architecture of :class:`GCN`; serialisable with :meth:`to_dict` / :meth:`from_dict`.

    Attributes:
        in_dim: input feature dimension F (132 for SIFT with every feature part).
        widths: output width of each graph layer; their number is the depth L.
            The authors used 12 layers growing 32 → 1024; the default keeps 12 layers
            but caps the width at 128 so 4 views × 500 keypoints run in < 30 ms on 2 CPU cores.
        out_dim: embedding dimension d of the output.
        groups: group-norm groups (every normalised width must be divisible by it).
        norm: "graph" (the authors': statistics over the nodes of each graph and the
            channels of a group), "node" (per-node group norm) or "none".
        norm_layers: how many of the first layers are followed by group norm; None = L-1
            (the paper: after layers 1 … 11 of 12).
        skip_layers: 1-based layers whose output also receives a linear projection of
            the input features and of the previous skip layer's output (the paper: 7, 12).
        self_skip: per-layer linear self-skip ``+ H U + c`` (the authors' layer).
        eps: group-norm epsilon.
    """

    in_dim: int = 132
    widths: Tuple[int, ...] = (64, 64, 96, 96, 128, 128, 128, 128, 128, 128, 128, 128)
    out_dim: int = 128
    groups: int = 8
    norm: str = "graph"
    norm_layers: Optional[int] = None
    skip_layers: Tuple[int, ...] = (7, 12)
    self_skip: bool = True
    eps: float = 1e-5
    # Optional edge-scoring head (0 = none, the paper's model: scores are EEᵀ). With
    # edge_features = F_e > 0 an MLP([e_a·e_b, |e_a − e_b|, edge features]) -> logit scores
    # the candidate edges of :func:`gcn_match_ros.edges.candidates.candidate_edges` (k = edge_k).
    edge_features: int = 0
    edge_hidden: int = 64
    edge_k: int = 4

    def __post_init__(self) -> None:
        object.__setattr__(self, "widths", tuple(int(w) for w in self.widths))
        object.__setattr__(self, "skip_layers", tuple(sorted(int(s) for s in self.skip_layers)))
        L = len(self.widths)
        if self.in_dim < 1 or self.out_dim < 1:
            raise ValueError(f"GCNConfig: in_dim and out_dim must be >= 1, got {self.in_dim}, {self.out_dim}")
        if L < 1 or any(w < 1 for w in self.widths):
            raise ValueError(f"GCNConfig.widths must be a non-empty list of positive ints, got {self.widths}")
        if self.norm not in ("graph", "node", "none"):
            raise ValueError(f"GCNConfig.norm must be 'graph', 'node' or 'none', got {self.norm!r}")
        if any(not 1 <= s <= L for s in self.skip_layers) or len(set(self.skip_layers)) != len(self.skip_layers):
            raise ValueError(f"GCNConfig.skip_layers must be distinct layers in 1..{L}, got {self.skip_layers}")
        if self.norm_layers is not None and not 0 <= self.norm_layers <= L:
            raise ValueError(f"GCNConfig.norm_layers must be in 0..{L}, got {self.norm_layers}")
        if self.norm != "none":
            bad = [w for w in self.widths[:self.n_norm_layers] if w % self.groups]
            if self.groups < 1 or bad:
                raise ValueError(f"GCNConfig: widths {bad} are not divisible by groups={self.groups}")

    @property
    def n_norm_layers(self) -> int:
        """Number of leading layers followed by group norm."""
        if self.norm == "none":
            return 0
        return len(self.widths) - 1 if self.norm_layers is None else self.norm_layers



# ---------------------------------------------------------------------------
# Modules
# ---------------------------------------------------------------------------
class GraphSkipConv(nn.Module):
    r"""Graph convolution with a linear self-skip (the authors' layer).

    .. math:: H' = \mathrm{relu}(\hat A H W + b) + H U + c

    W and U are applied in one fused matmul ``H [W | U] + [0 | c]``; b is added
    by the sparse ``addmm`` after propagation. Without self-skip: relu(Â H W + b).

    Shapes:
        h (N, in_dim), adj (N, N) sparse -> (N, out_dim).
    """

    def __init__(self, in_dim: int, out_dim: int, self_skip: bool = True) -> None:
        super().__init__()
        self.out_dim = out_dim
        self.self_skip = self_skip
        k = 2 if self_skip else 1
        self.weight = nn.Parameter(torch.empty(k * out_dim, in_dim))
        self.bias = nn.Parameter(torch.zeros(k * out_dim))
        nn.init.kaiming_uniform_(self.weight, a=5 ** 0.5)  # nn.Linear's default

    def forward(self, h: Tensor, adj: Tensor) -> Tensor:
        d = self.out_dim
        if not self.self_skip:
            return torch.relu(torch.addmm(self.bias, adj, h @ self.weight.t()))
        zero_c = torch.cat([torch.zeros_like(self.bias[:d]), self.bias[d:]])
        y = torch.addmm(zero_c, h, self.weight.t())
        conv = torch.addmm(self.bias[:d], adj, y[:, :d])
        if torch.is_grad_enabled():
            return torch.relu(conv) + y[:, d:]
        return torch.relu_(conv).add_(y[:, d:])


class GraphGroupNorm(nn.Module):
    """Group norm of node features, per graph or per node.

    mode "graph": for every graph of the batch and every channel group, mean and
    variance over all nodes of that graph and the channels of the group (the authors'
    GraphGroupNorm); batch-size independent, so one block-diagonal forward of several
    graphs equals separate forwards. mode "node": ``F.group_norm`` per node.
    A learned per-channel affine (gamma, beta) follows.

    Shapes:
        h (N, C), batch (N,) int64 graph of each node or None (one graph) -> (N, C).
    """

    def __init__(self, channels: int, groups: int, mode: str = "graph", eps: float = 1e-5) -> None:
        super().__init__()
        if channels % groups:
            raise ValueError(f"GraphGroupNorm: channels={channels} not divisible by groups={groups}")
        self.groups, self.mode, self.eps = groups, mode, eps
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))

    def forward(self, h: Tensor, batch: Optional[Tensor] = None, num_graphs: int = 1) -> Tensor:
        if self.mode == "node":
            return F.group_norm(h, self.groups, self.weight, self.bias, self.eps)
        n, c = h.shape
        g = self.groups
        # Column sums are much faster on CPU than a reduction over a (N, G, C/G) view;
        # var = E[x²] - E[x]² per (graph, group), then one fused multiply-add.
        if batch is None or num_graphs == 1:
            count = float(max(n, 1) * (c // g))
            mean = h.sum(dim=0).view(g, -1).sum(dim=1) / count                 # (G,)
            sq = (h * h).sum(dim=0).view(g, -1).sum(dim=1) / count
            inv = torch.rsqrt((sq - mean * mean).clamp(min=0.0) + self.eps)
            scale = self.weight * inv.repeat_interleave(c // g)                 # (C,)
            shift = self.bias - mean.repeat_interleave(c // g) * scale
            return torch.addcmul(shift, h, scale)
        count = (torch.bincount(batch, minlength=num_graphs).clamp(min=1) * (c // g)).to(h.dtype)[:, None]
        zeros = h.new_zeros(num_graphs, c)
        mean = zeros.index_add(0, batch, h).view(num_graphs, g, -1).sum(dim=2) / count      # (B, G)
        sq = zeros.index_add(0, batch, h * h).view(num_graphs, g, -1).sum(dim=2) / count
        inv = torch.rsqrt((sq - mean * mean).clamp(min=0.0) + self.eps)
        scale = self.weight * inv.repeat_interleave(c // g, dim=1)              # (B, C)
        shift = self.bias - mean.repeat_interleave(c // g, dim=1) * scale
        return torch.addcmul(shift[batch], h, scale[batch])


class GCN(nn.Module):
    """Graph embedding network; see the module docstring and :class:`GCNConfig`.

    Call ``model(x, edge_index, edge_weight, node_ptr=None)``:

    Args:
        x: (N, in_dim) float node features (:func:`gcn_match_ros.node_features.node_features`).
        edge_index: (2, E) int64 directed edges of A (both directions of each
            undirected edge, as in :class:`graph.CorrespondenceGraph`), no self loops needed.
        edge_weight: (E,) float edge weights.
        node_ptr: (B+1,) int64 node offsets of the B graphs of a block-diagonal batch
            (:func:`collate`); None = a single graph.

    Returns:
        E: (N, out_dim) embeddings with unit rows (zero rows impossible up to eps).
    """

    def __init__(self, config: GCNConfig = GCNConfig()) -> None:
        super().__init__()
        self.config = config
        dims = (config.in_dim,) + config.widths
        self.layers = nn.ModuleList(GraphSkipConv(dims[i], dims[i + 1], config.self_skip)
                                    for i in range(len(config.widths)))
        self.norms = nn.ModuleList(GraphGroupNorm(config.widths[i], config.groups, config.norm, config.eps)
                                   for i in range(config.n_norm_layers))
        skips = config.skip_layers
        # input -> every skip layer; previous skip layer -> next skip layer
        self.input_skips = nn.ModuleList(nn.Linear(config.in_dim, config.widths[s - 1]) for s in skips)
        self.hop_skips = nn.ModuleList(nn.Linear(config.widths[a - 1], config.widths[b - 1])
                                       for a, b in zip(skips[:-1], skips[1:]))
        self.out = nn.Linear(config.widths[-1], config.out_dim)
        if config.edge_features > 0:
            h = config.edge_hidden
            self.edge_head = nn.Sequential(nn.Linear(1 + config.out_dim + config.edge_features, h), nn.ReLU(),
                                           nn.Linear(h, h), nn.ReLU(), nn.Linear(h, 1))

    def score_edges(self, E: Tensor, rows: Tensor, cols: Tensor, edge_x: Tensor) -> Tensor:
        """Logits of candidate edges (rows[m], cols[m]) from the embeddings and edge features.

        Without gradients (inference) the edges go through the head :data:`EDGE_CHUNK` at a time
        with in-place ReLUs: the hidden activations then stay in the CPU's cache (20 667 edges
        of a 4 x 500 window: 6.2 -> 3.1-4.0 ms on 2 cores, bitwise the same logits).

        Shapes: E (N, out_dim), rows/cols (M,) int64, edge_x (M, edge_features) -> (M,)."""
        if torch.is_grad_enabled():
            return self._edge_logits(E, rows, cols, edge_x)
        out = torch.empty(rows.shape[0], dtype=E.dtype, device=E.device)
        for start in range(0, rows.shape[0], EDGE_CHUNK):
            stop = start + EDGE_CHUNK
            out[start:stop] = self._edge_logits(E, rows[start:stop], cols[start:stop], edge_x[start:stop], True)
        return out

    def _edge_logits(self, E: Tensor, rows: Tensor, cols: Tensor, edge_x: Tensor, in_place: bool = False) -> Tensor:
        ea, eb = E.index_select(0, rows), E.index_select(0, cols)  # E[rows]: the same rows, ~5x slower
        h = torch.cat([(ea * eb).sum(1, keepdim=True), (ea - eb).abs(), edge_x.to(E.dtype)], dim=1)
        for layer in self.edge_head:
            h = h.relu_() if in_place and isinstance(layer, nn.ReLU) else layer(h)
        return h.squeeze(1)

    def forward(self, x: Tensor, edge_index: Tensor, edge_weight: Tensor,
                node_ptr: Optional[Tensor] = None) -> Tensor:
        cfg = self.config
        _check_2d(x, "x", cols=cfg.in_dim)
        n = x.shape[0]
        _check_edges(edge_index, edge_weight, n)
        batch, num_graphs = None, 1
        if node_ptr is not None:
            _check_ptr(node_ptr, n)
            num_graphs = node_ptr.shape[0] - 1
            if num_graphs > 1:
                batch = torch.repeat_interleave(torch.arange(num_graphs, device=x.device),
                                                torch.diff(node_ptr.long()))
        adj = normalized_adjacency(edge_index, edge_weight.to(x.dtype), n)
        h = x
        skip_rank = {s: k for k, s in enumerate(cfg.skip_layers)}
        last_skip: Optional[Tensor] = None
        for i, layer in enumerate(self.layers):
            h = layer(h, adj)
            k = skip_rank.get(i + 1)
            if k is not None:
                h = h + self.input_skips[k](x)
                if last_skip is not None:
                    h = h + self.hop_skips[k - 1](last_skip)
            if i < len(self.norms):
                h = self.norms[i](h, batch, num_graphs)
            if k is not None:
                last_skip = h
        return F.normalize(self.out(h), p=2.0, dim=1, eps=1e-12)

    @classmethod
    def from_config(cls, config: Union[GCNConfig, Dict[str, Any]]) -> "GCN":
        """Build from a :class:`GCNConfig` or its dict."""
        return cls(config if isinstance(config, GCNConfig) else GCNConfig.from_dict(config))


# ---------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------
def graph_tensors(graph: CorrespondenceGraph) -> Tuple[Tensor, Tensor]:
    """The graph's edges as tensors.

    Shapes: graph with E stored edges -> edge_index (2, E) int64, edge_weight (E,) float32.
    """
    edge_index = torch.from_numpy(np.stack([graph.rows, graph.cols]).astype(np.int64, copy=False))
    return edge_index, torch.from_numpy(np.ascontiguousarray(graph.weights, dtype=np.float32))


def _as_tensor(a, dtype=None) -> Tensor:
    t = a if isinstance(a, Tensor) else torch.from_numpy(np.ascontiguousarray(a))
    return t if dtype is None else t.to(dtype)


def collate(items: Sequence[tuple]) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Concatenate graphs into one block-diagonal graph for a single forward pass.

    Each item is ``(x, graph)`` with a :class:`graph.CorrespondenceGraph`, or
    ``(x, edge_index, edge_weight)``; x may be a numpy array or a tensor.

    Returns:
        ``(x, edge_index, edge_weight, node_ptr)``: node indices of graph b are
        shifted by ``node_ptr[b]``; graph b's rows of the output are
        ``node_ptr[b]:node_ptr[b+1]``.

    Shapes:
        items: B graphs with n_b nodes and E_b edges ->
        x (Σn_b, F), edge_index (2, ΣE_b) int64, edge_weight (ΣE_b,) float32, node_ptr (B+1,) int64.
    """
    if len(items) == 0:
        raise ValueError("collate: needs at least one graph")
    xs, idx, ws, sizes = [], [], [], []
    offset = 0
    for b, item in enumerate(items):
        if len(item) == 2:
            x, graph = item
            ei, ew = graph_tensors(graph)
        elif len(item) == 3:
            x, ei, ew = item
            ei, ew = _as_tensor(ei, torch.int64), _as_tensor(ew, torch.float32)
        else:
            raise ValueError(f"collate: item {b} must be (x, graph) or (x, edge_index, edge_weight)")
        x = _as_tensor(x, torch.float32)
        _check_2d(x, f"items[{b}].x")
        if xs and x.shape[1] != xs[0].shape[1]:
            raise ValueError(f"items[{b}].x: expected shape (N, {xs[0].shape[1]}), got {_fmt(tuple(x.shape))}")
        _check_edges(ei, ew, x.shape[0])
        xs.append(x)
        idx.append(ei + offset)
        ws.append(ew)
        sizes.append(x.shape[0])
        offset += x.shape[0]
    ptr = torch.zeros(len(items) + 1, dtype=torch.int64)
    ptr[1:] = torch.cumsum(torch.tensor(sizes, dtype=torch.int64), 0)
    return torch.cat(xs), torch.cat(idx, dim=1), torch.cat(ws), ptr


def embed_problem(model: GCN, problem: Problem, graph_config: GraphConfig = GraphConfig(),
                  feature_config: FeatureConfig = FeatureConfig(),
                  graph: Optional[CorrespondenceGraph] = None) -> Tuple[np.ndarray, CorrespondenceGraph]:
    """Embed the keypoints of one problem (inference mode, model in eval mode).

    Builds the graph with ``graph_config`` unless ``graph`` is given, the features
    with ``feature_config`` (use the checkpoint's: ``meta["graph_config"]``,
    ``meta["feature_config"]``), and runs one forward pass on the model's device.

    Shapes: problem with N keypoints -> E (N, out_dim) float32 numpy, unit rows; the graph.
    """
    if graph is None:
        graph = build_graph(problem, graph_config)
    device = next(model.parameters()).device
    x = torch.from_numpy(node_features(problem, feature_config)).to(device)
    ei, ew = (t.to(device) for t in graph_tensors(graph))
    was_training = model.training
    model.eval()
    try:
        with torch.inference_mode():
            E = model(x, ei, ew)
    finally:
        model.train(was_training)
    return E.cpu().numpy(), graph
