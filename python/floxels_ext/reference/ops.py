"""Pure-PyTorch references for every ``torch.ops.floxels`` op.

These define the semantics that the C++/CUDA kernels must reproduce; the tests compare
the two on random inputs (and by float64 gradcheck). They favour clarity over speed,
and use autograd for every gradient.

Grid convention (shared by all ops): a grid is a lattice of *samples*; sample
``(iz, iy, ix)`` sits at ``origin + (ix, iy, iz) * spacing`` and dense grids are stored
``(C, Z, Y, X)`` (x fastest). Interpolation is trilinear between samples; a query
outside the lattice is clamped to its border, exactly like
``grid_sample(padding_mode="border", align_corners=True)``: the value is that of the
nearest border point and the gradient with respect to the clamped coordinate is zero.

Non-finite input (docs/ops.md): a point with a NaN or +-inf coordinate gives a NaN
gather row (a constant: zero gradient), is ignored by scatters and occupancy, makes
``dt_loss`` NaN (zero gradient row); a non-finite flow makes ``cluster_consistency_loss``
non-finite; ``dbscan`` and ``problem_setup`` refuse such points. Huge finite coordinates
clamp like any outside point (clamped in floating point before any conversion to an index).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

__all__ = [
    "fixed_segment_sum",
    "trilinear_gather",
    "trilinear_scatter",
    "points_to_occupancy",
    "edt",
    "dt_loss",
    "dt_residual",
    "dt_sample",
    "dt_evidence",
    "cluster_mean",
    "cluster_consistency_loss",
    "corner_gather",
    "corner_scatter",
    "dbscan",
    "problem_setup",
]


def _continuous_index(points: torch.Tensor, origin: Sequence[float], spacing: float) -> torch.Tensor:
    o = torch.as_tensor(list(origin), dtype=points.dtype, device=points.device)
    return (points - o) / spacing  # (N, 3) in (x, y, z) sample units


def _finite_rows(points: torch.Tensor) -> torch.Tensor:
    """(N,) bool: rows whose three coordinates are finite."""
    return torch.isfinite(points).all(dim=1)


def _corners(points, origin, spacing, shape_zyx):
    """Lower corner index (N, 3 xyz, long), fractional offset (N, 3, differentiable), upper index.

    Non-finite rows are placed at the origin (in-range indices; callers mask them)."""
    points = torch.where(_finite_rows(points)[:, None], points, torch.zeros_like(points))
    u = _continuous_index(points, origin, spacing)
    size = torch.tensor([shape_zyx[2], shape_zyx[1], shape_zyx[0]], device=points.device)
    hi = (size - 1).to(points.dtype)
    # clamp like grid_sample's border mode: zero gradient outside [0, size-1]
    inside = (u > 0) & (u < hi)
    uc = torch.where(inside, u, u.detach().clamp(min=torch.zeros_like(hi), max=hi))
    i0 = torch.minimum(uc.detach().floor().long(), (size - 2).clamp(min=0))
    i1 = torch.minimum(i0 + 1, size - 1)
    frac = uc - i0.to(points.dtype)
    return i0, frac, i1


def trilinear_gather(grid: torch.Tensor, points: torch.Tensor, origin: Sequence[float], spacing: float) -> torch.Tensor:
    """Sample ``grid`` (C, Z, Y, X) at ``points`` (N, 3); returns (N, C). A non-finite point
    gives a NaN row (zero gradient)."""
    C, Z, Y, X = grid.shape
    i0, t, i1 = _corners(points, origin, spacing, (Z, Y, X))
    out = points.new_zeros(points.shape[0], C) if points.shape[0] else grid.new_zeros(0, C)
    for cz in (0, 1):
        iz = i1[:, 2] if cz else i0[:, 2]
        wz = t[:, 2] if cz else 1 - t[:, 2]
        for cy in (0, 1):
            iy = i1[:, 1] if cy else i0[:, 1]
            wy = t[:, 1] if cy else 1 - t[:, 1]
            for cx in (0, 1):
                ix = i1[:, 0] if cx else i0[:, 0]
                wx = t[:, 0] if cx else 1 - t[:, 0]
                out = out + (wz * wy * wx)[:, None] * grid[:, iz, iy, ix].T
    return torch.where(_finite_rows(points)[:, None], out, torch.full_like(out, math.nan))


def trilinear_scatter(values: torch.Tensor, points: torch.Tensor, origin: Sequence[float], spacing: float,
                      grid_shape: Sequence[int]) -> torch.Tensor:
    """Adjoint of :func:`trilinear_gather`: splat ``values`` (N, C) onto a zero (C, Z, Y, X) grid.

    ``<trilinear_scatter(v, p), G> == <v, trilinear_gather(G, p)>`` for every grid G (with
    finite points); a non-finite point is ignored.
    """
    Z, Y, X = grid_shape
    C = values.shape[1]
    values = torch.where(_finite_rows(points)[:, None], values, torch.zeros_like(values))
    i0, t, i1 = _corners(points, origin, spacing, (Z, Y, X))
    flat = values.new_zeros(C, Z * Y * X)
    for cz in (0, 1):
        iz = i1[:, 2] if cz else i0[:, 2]
        wz = t[:, 2] if cz else 1 - t[:, 2]
        for cy in (0, 1):
            iy = i1[:, 1] if cy else i0[:, 1]
            wy = t[:, 1] if cy else 1 - t[:, 1]
            for cx in (0, 1):
                ix = i1[:, 0] if cx else i0[:, 0]
                wx = t[:, 0] if cx else 1 - t[:, 0]
                lin = (iz * Y + iy) * X + ix
                flat = flat.index_add(1, lin, (values * (wz * wy * wx)[:, None]).T)
    return flat.view(C, Z, Y, X)


def points_to_occupancy(points: torch.Tensor, origin: Sequence[float], spacing: float,
                        grid_shape: Sequence[int]) -> torch.Tensor:
    """Bool (Z, Y, X) grid marking the sample nearest to each point.

    Snapping: index = floor((p - origin) / spacing + 0.5) per axis (round half up);
    points whose index falls outside the grid, or with a NaN/inf coordinate, are ignored.
    """
    Z, Y, X = grid_shape
    # always in float64: float32 would snap points near half-sample boundaries differently
    u = torch.floor(_continuous_index(points.double(), origin, spacing) + 0.5)
    lim = torch.tensor([X, Y, Z], device=points.device, dtype=torch.float64)
    ok = ((u >= 0) & (u < lim)).all(dim=1)  # in float: NaN fails, huge values never reach .long()
    idx = u[ok].long()
    occ = torch.zeros(Z * Y * X, dtype=torch.bool, device=points.device)
    occ[(idx[:, 2] * Y + idx[:, 1]) * X + idx[:, 0]] = True
    return occ.view(Z, Y, X)


def _min_plus_1d(f: torch.Tensor, dim: int, chunk: int = 1 << 22) -> torch.Tensor:
    """g[i] = min_j f[j] + (i - j)^2 along ``dim`` (exact, int64, O(n^2) per line)."""
    f = f.movedim(dim, -1)
    n = f.shape[-1]
    lead = f.shape[:-1]
    f2 = f.reshape(-1, n)
    ar = torch.arange(n, device=f.device)
    sq = (ar[:, None] - ar[None, :]) ** 2  # (i, j)
    out = torch.empty_like(f2)
    rows = max(1, chunk // (n * n))
    for s in range(0, f2.shape[0], rows):
        blk = f2[s : s + rows]
        out[s : s + rows] = (blk[:, None, :] + sq[None]).min(dim=-1).values
    return out.view(*lead, n).movedim(-1, dim)


def edt(occupancy: torch.Tensor, spacing: float = 1.0) -> torch.Tensor:
    """Exact Euclidean distance (times ``spacing``) from every sample to the nearest True sample.

    Separable exact algorithm on integer squared distances (min-plus convolution with
    (i-j)^2 along each axis), so it matches ``scipy.ndimage.distance_transform_edt(~occ)``
    exactly. Returns float32; +inf everywhere if nothing is occupied. Quadratic per line:
    meant for small test grids.
    """
    if occupancy.dim() != 3:
        raise ValueError(f"occupancy must be (Z, Y, X), got {tuple(occupancy.shape)}")
    big = 1 << 40  # "infinite" squared distance; stays exact in int64 after 3 additions
    f = torch.where(occupancy, 0, big).to(torch.int64)
    for d in (2, 1, 0):
        f = _min_plus_1d(f, d).clamp(max=big)
    out = torch.sqrt(f.double()) * spacing
    out[f >= big] = float("inf")
    return out.float()


def dt_loss(points: torch.Tensor, flow: torch.Tensor, dts: Sequence[torch.Tensor], origins: Sequence[float],
            spacing: float, time_offsets: Sequence[float], weights: Sequence[float], truncation: float) -> torch.Tensor:
    """sum_k w_k * mean_i DT_k(p_i + t_k f_i), DT values >= truncation (or NaN) counting as 0
    (no gradient). A row whose point or flow has a NaN/inf coordinate makes the loss NaN and
    gets a zero gradient row; a finite query that overflows to +-inf clamps to the border."""
    K = len(dts)
    assert len(origins) == 3 * K and len(time_offsets) == K and len(weights) == K
    total = flow.new_zeros(())
    n = points.shape[0]
    if n == 0:
        return total
    ok = (_finite_rows(points) & _finite_rows(flow))[:, None]
    p = torch.where(ok, points, torch.zeros_like(points))
    f = torch.where(ok, flow, torch.zeros_like(flow))
    big = torch.finfo(flow.dtype).max
    for k in range(K):
        q = (p + time_offsets[k] * f).clamp(-big, big)  # overflow clamps like the kernels
        v = trilinear_gather(dts[k][None].to(flow.dtype), q, origins[3 * k : 3 * k + 3], spacing)[:, 0]
        v = torch.where(v < truncation, v, torch.zeros_like(v))
        v = torch.where(ok[:, 0], v, torch.full_like(v, math.nan))
        total = total + weights[k] * v.sum() / n
    return total


def _dt_queries(points, motion, time_offset):
    """Queries ``p + t m`` with non-finite rows at 0 (masked by the callers) and finite overflow
    clamped like the kernels; and the (N,) mask of finite rows."""
    ok = (_finite_rows(points) & _finite_rows(motion))[:, None]
    p = torch.where(ok, points, torch.zeros_like(points))
    m = torch.where(ok, motion, torch.zeros_like(motion))
    big = torch.finfo(points.dtype).max
    return (p + time_offset * m).clamp(-big, big), ok[:, 0]


def _counts(points: torch.Tensor, observed: torch.Tensor | None, k: int) -> torch.Tensor:
    """(N,) bool: scan k counts for each point (bit k of ``observed``; None: every point)."""
    if observed is None:
        return torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
    return ((observed.long() >> k) & 1) == 1


def dt_residual(points: torch.Tensor, motion: torch.Tensor, dts: Sequence[torch.Tensor], origins: Sequence[float],
                spacing: float, time_offsets: Sequence[float], weights: Sequence[float], cap: float,
                squared: bool, observed: torch.Tensor | None = None) -> torch.Tensor:
    """(N,): sum_k w_k * c(min(DT_k(p + t_k m), cap)), c = x or x^2, over the scans whose bit is
    set in ``observed`` (all without it); NaN for a non-finite point or motion row."""
    total = points.new_zeros(points.shape[0])
    for k, d in enumerate(dts):
        q, _ = _dt_queries(points, motion, time_offsets[k])
        v = trilinear_gather(d[None].to(points.dtype), q, origins[3 * k : 3 * k + 3], spacing)[:, 0].clamp_max(cap)
        total = total + torch.where(_counts(points, observed, k), weights[k] * (v * v if squared else v), 0.0)
    # a non-finite row is NaN whatever its bits (like the kernels)
    return torch.where(_finite_rows(points) & _finite_rows(motion), total, math.nan)


def dt_sample(points: torch.Tensor, motion: torch.Tensor, dts: Sequence[torch.Tensor], origins: Sequence[float],
              spacing: float, time_offsets: Sequence[float]) -> torch.Tensor:
    """(K, N, 4): DT_k at p + t_k m and its gradient with respect to the query (autograd through
    :func:`trilinear_gather`: 0 along a clamped axis); NaN value and zero gradient for a
    non-finite row."""
    out = []
    for k, d in enumerate(dts):
        q, ok = _dt_queries(points, motion, time_offsets[k])
        with torch.enable_grad():
            q = q.detach().requires_grad_(True)
            v = trilinear_gather(d[None].to(points.dtype), q, origins[3 * k : 3 * k + 3], spacing)[:, 0]
            (g,) = torch.autograd.grad(v.sum(), q, allow_unused=True)
        g = torch.zeros_like(q) if g is None else g
        v = torch.where(ok, v.detach(), torch.full_like(v, math.nan))
        out.append(torch.cat([v[:, None], torch.where(ok[:, None], g, torch.zeros_like(g))], 1))
    return torch.stack(out) if out else points.new_zeros(0, points.shape[0], 4)


def dt_evidence(points: torch.Tensor, flow: torch.Tensor, labels: torch.Tensor | None, cells: torch.Tensor,
                dts: Sequence[torch.Tensor], origins: Sequence[float], spacing: float, time_offsets: Sequence[float],
                weights: Sequence[float], cap: float, margin: float, ratio: float,
                observed: torch.Tensor | None = None):
    """Motion evidence per group = run of consecutive rows with equal labels (for label < 0 or
    no labels: equal cells). rf / rz: the group's mean :func:`dt_residual` with ``flow`` / zero
    flow (float64 sums); per row (rz - rf, rz - rf > max(ratio * rz, margin), rf, rz). A group
    with a non-finite residual: NaN, False."""
    n = points.shape[0]
    rf = dt_residual(points, flow, dts, origins, spacing, time_offsets, weights, cap, False, observed)
    rz = dt_residual(points, torch.zeros_like(flow), dts, origins, spacing, time_offsets, weights, cap, False, observed)
    lab = labels.long() if labels is not None else torch.full((n,), -1, dtype=torch.long, device=points.device)
    same = (lab[1:] == lab[:-1]) & ((lab[1:] >= 0) | (cells[1:].long() == cells[:-1].long()))
    gid = torch.cumsum(torch.cat([torch.ones(min(n, 1), dtype=torch.long, device=points.device),
                                  (~same).long()]), 0) - 1
    sums = torch.zeros(n, 2, dtype=torch.float64, device=points.device).index_add_(
        0, gid, torch.stack([rf, rz], 1).double())
    count = torch.bincount(gid, minlength=n).double()
    m = sums[gid] / count[gid, None]
    mf, mz = m[:, 0].to(points.dtype), m[:, 1].to(points.dtype)
    gain = mz - mf
    explained = gain > torch.clamp(mz * ratio, min=margin)
    return gain, explained, mf, mz


def cluster_mean(values: torch.Tensor, labels: torch.Tensor, num_clusters: int) -> torch.Tensor:
    """Mean of ``values`` (N, C) per cluster label in [0, num_clusters); label -1 is ignored."""
    keep = labels >= 0
    lab = labels[keep]
    sums = values.new_zeros(num_clusters, values.shape[1]).index_add(0, lab, values[keep])
    cnt = torch.bincount(lab, minlength=num_clusters).to(values.dtype).clamp(min=1)
    return sums / cnt[:, None]


def cluster_consistency_loss(flow: torch.Tensor, labels: torch.Tensor, num_clusters: int) -> torch.Tensor:
    """(1/N) sum_i ||f_i - mean flow of cluster(i)||; noise points (label -1) contribute 0.

    The norm's gradient at 0 is taken as 0 (every point of a cluster having the same flow,
    e.g. at the zero initialisation, gives zero gradient rather than NaN). A non-finite flow
    in a cluster makes the loss NaN (or inf); that cluster's gradient rows are then 0 or NaN.
    """
    n = flow.shape[0]
    if n == 0:
        return flow.new_zeros(())
    means = cluster_mean(flow, labels, num_clusters)
    keep = labels >= 0
    d = flow[keep] - means[labels[keep]]
    sq = (d * d).sum(dim=1)
    nz = sq > 0
    # sq is 0 or NaN where not positive: NaN (a non-finite flow) propagates, like the kernels
    norms = torch.where(nz, torch.sqrt(torch.where(nz, sq, torch.ones_like(sq))), sq.detach())
    return norms.sum() / n


def corner_gather(params: torch.Tensor, corner_idx: torch.Tensor, corner_w: torch.Tensor) -> torch.Tensor:
    """(N, C) = sum_j corner_w[:, j] * params[corner_idx[:, j]] (compact trilinear gather)."""
    return (params[corner_idx.long()] * corner_w[..., None]).sum(dim=1)


def corner_scatter(values: torch.Tensor, corner_idx: torch.Tensor, corner_w: torch.Tensor,
                   num_params: int) -> torch.Tensor:
    """Adjoint of :func:`corner_gather`: (num_params, C) sums of corner_w-weighted values."""
    contrib = (values[:, None, :] * corner_w[..., None]).reshape(-1, values.shape[1])
    return values.new_zeros(num_params, values.shape[1]).index_add(0, corner_idx.long().reshape(-1), contrib)


def dbscan(points: torch.Tensor, eps: float, min_samples: int) -> torch.Tensor:
    """DBSCAN labels (N,) int64, -1 = noise, with scikit-learn's semantics (O(N^2) memory:
    small inputs only).

    Distances as sklearn's KDTree: float64 coordinates, ``(dx*dx + dy*dy) + dz*dz <= eps*eps``;
    neighbourhoods include the point itself; core iff ``|neighbourhood| >= min_samples``.
    Clusters are the connected components of core points, numbered by their smallest core
    index (sklearn's dbscan_inner visits points in index order); a border point takes the
    smallest cluster id among its core neighbours (the cluster that reaches it first).
    Non-finite points raise ``ValueError`` (the op raises ``RuntimeError``).
    """
    p = points.detach().to("cpu", torch.float64)
    if not bool(torch.isfinite(p).all()):
        raise ValueError("dbscan points must be finite (found NaN/inf)")
    n = p.shape[0]
    labels = torch.full((n,), -1, dtype=torch.int64)
    if n == 0:
        return labels
    d = p[:, None, :] - p[None, :, :]
    r = (d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]) + d[..., 2] * d[..., 2]
    adj = r <= float(eps) * float(eps)
    core = adj.sum(1) >= min_samples
    # Components of the core-core graph by min-label propagation (converges to the smallest
    # core index of each component).
    cc = torch.where(core, torch.arange(n), torch.full((n,), n))
    core_adj = adj & core[:, None] & core[None, :]
    while True:
        new = torch.where(core_adj, cc[None, :], n).amin(1).minimum(cc)
        if torch.equal(new, cc):
            break
        cc = new
    firsts = torch.unique(cc[core])  # sorted smallest core index per component
    cid = torch.full((n + 1,), n, dtype=torch.int64)
    cid[firsts] = torch.arange(firsts.numel())
    core_label = torch.where(core, cid[cc], torch.full((n,), n))
    best = torch.where(adj & core[None, :], core_label[None, :], n).amin(1)
    labels = torch.where(core, core_label, torch.where(best < n, best, -1))
    return labels.to(points.device)


def cell_key(points: torch.Tensor, origin: Sequence[float], spacing: float, grid_shape: Sequence[int]) -> torch.Tensor:
    """(N,) int64 lattice index (z * Y + y) * X + x of each point's cell: the clamped floor of
    ``(p - origin) / spacing`` (the sort key of :func:`problem_setup`), clamped in floating point
    (NaN to 0) before the conversion to an integer."""
    Z, Y, X = (int(s) for s in grid_shape)
    o = torch.tensor([float(v) for v in origin], dtype=points.dtype, device=points.device)
    hi = torch.tensor([X - 1, Y - 1, Z - 1], dtype=points.dtype, device=points.device)
    ic = torch.fmin(torch.fmax(((points - o) / spacing).floor(), hi.new_zeros(())), hi).long()
    return (ic[:, 2] * Y + ic[:, 1]) * X + ic[:, 0]


def problem_setup(points: torch.Tensor, labels: torch.Tensor | None, origin: Sequence[float], spacing: float,
                  grid_shape: Sequence[int], tile: int):
    """The optimiser's per-target tables (``floxels::problem_setup``), step by step:

    * ``order``: points sorted stably by (label, flow-grid cell), the cell being the
      clamped floor of ``(p - origin) / spacing``, numbered (z * Y + y) * X + x;
    * each sorted point's 8 trilinear corners (x fastest, then y, then z) and weights,
      clamped like :func:`trilinear_gather`, renumbered densely over the touched
      vertices in lattice order (``vertices`` holds each row's lattice index);
    * segments: runs of sorted points with equal corner rows and labels, also cut every
      ``tile`` points (``seg_ptr``: first point of each, then N); per vertex, its
      ``segment * 8 + corner`` entries in segment order (``vtx_ptr``, ``vtx_entry``).

    Returns (order, sorted points, sorted labels (empty if None), corner_idx, corner_w,
    vertices, seg_ptr, vtx_ptr, vtx_entry, number of clusters). Non-finite points raise
    ``ValueError`` (the op raises ``RuntimeError``).
    """
    if not bool(torch.isfinite(points).all()):
        raise ValueError("problem_setup: points must be finite (found NaN/inf coordinates)")
    # the corners and the segment tables as the Python path that the op replaced built them
    from floxels_ext.ops.corners import compact_corners
    from floxels_ext.ops.solver import _segments

    n = points.shape[0]
    key = cell_key(points, origin, spacing, grid_shape)
    if labels is not None:
        key = (labels.long() + 1) * math.prod(int(s) for s in grid_shape) + key
    order = torch.sort(key, stable=True).indices
    ps = points[order]
    lab = labels.long()[order] if labels is not None else None
    cc = compact_corners(ps, origin, spacing, grid_shape)
    seg_ptr, vtx_ptr, vtx_entry = _segments(cc.corner_idx, lab, [0, n], cc.num_params, tile)
    ncl = int(lab.max()) + 1 if lab is not None and n else 0
    return (order, ps, lab if lab is not None else order.new_empty(0), cc.corner_idx, cc.corner_w, cc.vertices,
            seg_ptr, vtx_ptr, vtx_entry, max(ncl, 0))


def nearest_neighbor(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Index into ``y`` of the nearest row of each row of ``x``: squared distances from the
    coordinate differences, NaN as +inf, first index among ties (the op's rule)."""
    d = (x[:, None, :] - y[None, :, :]).square().sum(dim=2)
    d = torch.where(torch.isnan(d), torch.full_like(d, float("inf")), d)
    return d.argmin(dim=1)


def fixed_segment_sum(values: torch.Tensor, index: torch.Tensor, rows: int, limit: float, void_row: bool = False,
                      count: bool = False) -> torch.Tensor:
    """(rows, C [+1]) float64 sums of ``values`` (M, C) by ``index`` (M,): each finite term
    clamped to +-limit and rounded (ties to even) to a multiple of 2^-24, the integers summed;
    a non-finite term makes its row's column NaN (``void_row``: the whole row's value columns);
    ``count`` appends the row's number of terms; terms of an index outside [0, rows) are ignored
    (the op's rule, csrc/kernels/segment_sum.h)."""
    scale = float(2 ** 24)
    idx = index.to(torch.int64)
    keep = (idx >= 0) & (idx < rows)
    v, idx = values.to(torch.float64)[keep], idx[keep]
    C = v.shape[1]
    bad = ~torch.isfinite(v)
    fixed = torch.round(v.nan_to_num(0.0, 0.0, 0.0).clamp(-limit, limit) * scale).to(torch.int64)
    acc = torch.zeros(rows, C, dtype=torch.int64, device=v.device).index_add_(0, idx, fixed)
    flags = torch.zeros(rows, C, dtype=torch.int64, device=v.device).index_add_(0, idx, bad.to(torch.int64))
    flagged = flags > 0
    if void_row:
        flagged = flagged.any(dim=1, keepdim=True).expand(rows, C)
    out = torch.where(flagged, float("nan"), acc.to(torch.float64) / scale)
    if count:
        n = torch.zeros(rows, dtype=torch.int64, device=v.device).index_add_(0, idx, torch.ones_like(idx))
        out = torch.cat([out, n.to(torch.float64)[:, None]], 1)
    return out
