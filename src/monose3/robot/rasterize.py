"""Batched triangle rasterisation in PyTorch, on whatever device the inputs are on (on the CPU, compiled).

For every triangle the pixel centres of its bounding box (of a larger box, of each row the
span between where the row enters and leaves the triangle) are enumerated, tested with edge
functions, and the nearest surface per pixel is kept with a ``scatter_reduce('amin')`` z-buffer
over (quantised depth, triangle id) keys. OpenCV pixel-centre convention: pixel (u, v) is
covered when the point (u, v) of the image plane, as projected by K, lies inside the
triangle. Where only the silhouette is wanted, :func:`rasterize_coverage` marks the covered
pixels and skips the depth.

On the CPU the same arithmetic runs compiled (``rasterize_cpu.py``, numba: the same pixels,
depths and barycentrics, bit for bit, 4-10x faster); the tensor code below runs on a GPU, and on
the CPU where numba is missing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from monose3.geometry.camera import project

try:
    from monose3.robot import rasterize_cpu
except ImportError:  # no numba (a Python it does not support yet): the tensor code on the CPU too
    rasterize_cpu = None

NEAR = 0.01  # metres: triangles with a vertex closer than this are not drawn
DEPTH_UNIT = 1e-5  # metres per z-buffer step (40 m range in 22 bits)
_ID_BITS = 40
_EMPTY = torch.iinfo(torch.int64).max
# Candidate pixels handled at once: bounds the memory of one pass (about 60 bytes each).
CHUNK = 4_000_000
_INSIDE_EPS = 1e-5  # a pixel on an edge belongs to both triangles: no cracks between them
# Barycentric change per pixel below which an edge is taken as running along the row (its
# crossing column would carry rounding of more than a pixel).
_FLAT_SLOPE = 1e-4
SMALL_BOX = 9  # pixels: boxes this small are tested whole


@dataclass
class Fragments:
    """The nearest triangle at each pixel: ``face`` ``[B, H, W]`` (-1 where empty), its
    perspective-correct barycentric coordinates ``bary`` ``[B, H, W, 3]`` (None where not
    asked for) and ``depth`` (z, 0 where empty)."""

    face: torch.Tensor
    bary: torch.Tensor | None
    depth: torch.Tensor

    @property
    def mask(self) -> torch.Tensor:
        return self.face >= 0


_EDGES = ((1, 2), (2, 0), (0, 1))  # barycentric i is the edge function of the opposite edge


def _signed_area(uv: torch.Tensor) -> torch.Tensor:
    """Doubled signed screen area ``[...]`` of triangles ``[..., 3, 2]`` (negative: clockwise, y down)."""
    d1, d2 = uv[..., 1, :] - uv[..., 0, :], uv[..., 2, :] - uv[..., 0, :]
    return d1[..., 0] * d2[..., 1] - d2[..., 0] * d1[..., 1]


def _barycentrics_at(uv: torch.Tensor, point: torch.Tensor, area: torch.Tensor) -> torch.Tensor:
    """Screen barycentrics ``[..., 3]`` of ``point`` ``[..., 2]``, from coordinates relative to
    the point (float32 keeps its precision on thin triangles that way)."""
    rel = uv - point[..., None, :]
    w = [rel[..., a, 0] * rel[..., b, 1] - rel[..., a, 1] * rel[..., b, 0] for a, b in _EDGES]
    return torch.stack(w, -1) / area[..., None]


def _barycentric_slopes(uv: torch.Tensor, area: torch.Tensor) -> torch.Tensor:
    """d(barycentric)/dx and /dy ``[..., 2, 3]``: barycentrics are affine in the pixel."""
    dx = [uv[..., a, 1] - uv[..., b, 1] for a, b in _EDGES]
    dy = [uv[..., b, 0] - uv[..., a, 0] for a, b in _EDGES]
    return torch.stack([torch.stack(dx, -1), torch.stack(dy, -1)], -2) / area[..., None, None]


@dataclass
class _Candidates:
    """The triangles to draw and, per triangle, what testing its candidate pixels needs:
    ``table`` rows (screen barycentrics at its box's corner, their x and y slopes, 1/z of its
    corners, its box's width), ``ids`` (the box corner's flat pixel index, the triangle's id)
    and ``counts`` (pixels in its box)."""

    table: torch.Tensor
    ids: torch.Tensor
    counts: torch.Tensor


def _candidates(verts: torch.Tensor, faces: torch.Tensor, K: torch.Tensor, size: tuple[int, int],
                cullable: torch.Tensor | None) -> _Candidates:  # fmt: skip
    """The triangles that can cover a pixel: in front of the camera, with a pixel centre in
    their box, not degenerate, and facing it where ``cullable``."""
    width, height = size
    uv = project(verts, K)
    # Per corner (rows of faces.T), so that min/max over the 3 corners are elementwise.
    corners = faces.T.reshape(-1)
    batch_f = (verts.shape[0], 3, faces.shape[0])
    u, v, z = (x.index_select(1, corners).view(batch_f) for x in (uv[..., 0], uv[..., 1], verts[..., 2]))  # [B, 3, F]
    lo_u = _fold3(torch.minimum, u, 1).ceil().clamp_min(0)
    lo_v = _fold3(torch.minimum, v, 1).ceil().clamp_min(0)
    hi_u = _fold3(torch.maximum, u, 1).floor().clamp_max(width - 1)
    hi_v = _fold3(torch.maximum, v, 1).floor().clamp_max(height - 1)
    # The doubled signed area (as _signed_area gives it), so that faces turned away are dropped
    # before anything is gathered for them.
    area = (u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (u[:, 2] - u[:, 0]) * (v[:, 1] - v[:, 0])
    keep = (z > NEAR).all(1) & (hi_u >= lo_u) & (hi_v >= lo_v) & (area.abs() > 1e-6)
    if cullable is not None:
        # Clockwise on screen (y down) is facing away for outward-wound closed meshes.
        keep &= (area < 0) | ~cullable
    kept = keep.view(-1).nonzero(as_tuple=True)[0]
    b_idx, f_idx = kept // faces.shape[0], kept % faces.shape[0]
    u, v, z = (_gather_corners(x, b_idx, f_idx) for x in (u, v, z))  # [T, 3] each
    uv_kept = torch.stack([u, v], -1)  # [T, 3, 2]
    area, lo_u, lo_v, hi_u, hi_v = (x.view(-1).index_select(0, kept) for x in (area, lo_u, lo_v, hi_u, hi_v))
    lo, hi = torch.stack([lo_u, lo_v], -1), torch.stack([hi_u, hi_v], -1)
    box_w = hi[:, 0] - lo[:, 0] + 1
    counts = (box_w * (hi[:, 1] - lo[:, 1] + 1)).long()
    # One row per triangle, gathered once per candidate pixel.
    slopes = _barycentric_slopes(uv_kept, area)
    at_corner = _barycentrics_at(uv_kept, lo, area)
    table = torch.cat([at_corner, slopes[:, 0], slopes[:, 1], 1.0 / z, box_w[:, None]], 1)
    corner_pixel = (b_idx * height + lo[:, 1].long()) * width + lo[:, 0].long()
    return _Candidates(table, torch.stack([corner_pixel, b_idx * faces.shape[0] + f_idx], 1), counts)


def _gather_corners(values: torch.Tensor, b_idx: torch.Tensor, f_idx: torch.Tensor) -> torch.Tensor:
    """``values[b_idx, :, f_idx]`` (``[B, 3, F]`` -> ``[T, 3]``) by ``index_select``, many times
    faster on the CPU than advanced indexing."""
    at = b_idx * values[0].numel() + f_idx
    flat = values.reshape(-1)
    return torch.stack([flat.index_select(0, at + c * values.shape[2]) for c in range(3)], -1)


def _in_chunks(candidates: _Candidates, fold) -> None:
    """``fold(counts, table, ids)`` over runs of triangles of about :data:`CHUNK` candidate pixels."""
    counts = candidates.counts
    ends = counts.cumsum(0)
    start = 0
    while start < len(counts):
        stop = int(torch.searchsorted(ends, ends[start] - counts[start] + CHUNK, right=True))
        stop = max(stop, start + 1)
        fold(counts[start:stop], candidates.table[start:stop], candidates.ids[start:stop])
        start = stop


def rasterize(
    verts: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,
    size: tuple[int, int],
    cullable: torch.Tensor | None = None,
    barycentrics: bool = True,
) -> Fragments:
    """Rasterise camera-frame vertices ``[B, V, 3]`` (OpenCV axes) of triangles ``faces``
    ``[F, 3]`` with intrinsics ``[B, 3, 3]`` into ``size`` = (W, H) images. Back faces are
    skipped where ``cullable`` ``[F]`` (faces of closed, outward-wound meshes); the rest are
    drawn from both sides. Without ``barycentrics`` (only shading reads them) ``bary`` is None."""
    width, height = size
    batch, verts, K = verts.shape[0], verts.float(), K.float()
    if _compiled(verts):
        return _rasterize_compiled(verts, faces, K, size, cullable, barycentrics)
    zbuf = torch.full((batch * height * width,), _EMPTY, dtype=torch.int64, device=verts.device)
    fold = lambda counts, table, ids: _scatter_chunk(zbuf, counts, table, ids, width)  # noqa: E731
    _in_chunks(_candidates(verts, faces, K, size, cullable), fold)
    return _resolve(zbuf, verts, faces, K, batch, size, barycentrics)


def rasterize_coverage(
    verts: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,
    size: tuple[int, int],
    cullable: torch.Tensor | None = None,
) -> torch.Tensor:
    """The silhouettes ``[B, H, W]`` (bool) that :func:`rasterize` gives as its ``mask``, without
    its depth test: every pixel some triangle covers (for callers that compare silhouettes only)."""
    width, height = size
    batch, verts = verts.shape[0], verts.float()
    if _compiled(verts):
        v, f, k, cull = _as_arrays(verts, faces, K, cullable)
        covered = rasterize_cpu.coverage(v, f, k, cull, size, NEAR, -_INSIDE_EPS)
        return torch.from_numpy(covered).view(batch, height, width)
    covered = torch.zeros(batch * height * width, dtype=torch.bool, device=verts.device)
    fold = lambda counts, table, ids: _cover_chunk(covered, counts, table, ids, width)  # noqa: E731
    _in_chunks(_candidates(verts, faces, K.float(), size, cullable), fold)
    return covered.view(batch, height, width)


def _compiled(verts: torch.Tensor) -> bool:
    """Whether ``verts`` are drawn by the compiled rasteriser: on the CPU, where numba is there."""
    return rasterize_cpu is not None and verts.device.type == "cpu"


def _as_arrays(verts, faces, K, cullable) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The compiled rasteriser's inputs: float32 vertices and K, int64 faces, a cullable flag per face."""
    cull = np.zeros(len(faces), np.bool_) if cullable is None else cullable.numpy()
    as_array = lambda x, dtype: np.ascontiguousarray(x.detach().numpy(), dtype)  # noqa: E731
    return as_array(verts, np.float32), as_array(faces, np.int64), as_array(K, np.float32), cull


def _rasterize_compiled(verts, faces, K, size, cullable, barycentrics: bool) -> Fragments:
    """:func:`rasterize` by ``rasterize_cpu``."""
    width, height = size
    v, f, k, cull = _as_arrays(verts, faces, K, cullable)
    zbuf = rasterize_cpu.zbuffer(v, f, k, cull, size, NEAR, -_INSIDE_EPS, DEPTH_UNIT, _EMPTY)
    face, depth, bary = rasterize_cpu.resolve(zbuf, v, f, k, size, _EMPTY, barycentrics)
    shape = (len(v), height, width)
    bary = None if bary is None else torch.from_numpy(bary).view(*shape, 3)
    return Fragments(face=torch.from_numpy(face).view(shape), bary=bary, depth=torch.from_numpy(depth).view(shape))


def _candidate_pixels(counts: torch.Tensor, table: torch.Tensor, width: int):
    """Each candidate pixel of the triangles: its triangle's index in ``table``, its column and
    row in the triangle's box, and its screen barycentrics. Small boxes are tested whole; in a
    larger one, per row only the pixels between where the row enters and leaves the triangle
    (:func:`_row_spans`): a box holds six times as many pixels as its triangle covers in the
    fit's renders at 320x240, where finding the spans costs more than it saves in a small box.
    Only the barycentrics' columns of ``table`` are gathered per candidate: most are not covered."""
    small = counts <= SMALL_BOX
    boxed = torch.where(small, counts, 0)
    tri_small = torch.repeat_interleave(torch.arange(len(counts), device=counts.device), boxed)
    offset = torch.arange(len(tri_small), device=counts.device) - (boxed.cumsum(0) - boxed).index_select(0, tri_small)
    box_w = table[:, 12].long().index_select(0, tri_small)
    dy_small = offset // box_w
    tri_large, dy_large, dx_large = _spanned_pixels(counts, table, ~small)
    tri = torch.cat([tri_small, tri_large])
    dy = torch.cat([dy_small, dy_large])
    dx = torch.cat([offset - dy_small * box_w, dx_large])
    row = table[:, :9].contiguous().index_select(0, tri)
    w = row[:, 0:3] + row[:, 3:6] * dx[:, None] + row[:, 6:9] * dy[:, None]  # screen barycentrics
    return tri, dx, dy, w


def _spanned_pixels(counts: torch.Tensor, table: torch.Tensor, chosen: torch.Tensor):
    """(triangle, row, column in its box) ``[N]`` each of the pixels of the ``chosen`` triangles'
    row spans (:func:`_row_spans`)."""
    device = counts.device
    rows = torch.where(chosen, counts // table[:, 12].long(), 0)
    tri = torch.repeat_interleave(torch.arange(len(rows), device=device), rows)  # one per box row
    dy = torch.arange(len(tri), device=device) - (rows.cumsum(0) - rows).index_select(0, tri)
    start, span = _row_spans(table.index_select(0, tri), dy)
    pair = torch.repeat_interleave(torch.arange(len(span), device=device), span)
    # index_select throughout: several times faster on the CPU than indexing with a tensor
    first = (span.cumsum(0) - span).index_select(0, pair)
    dx = start.index_select(0, pair) + torch.arange(len(pair), device=device) - first
    return tri.index_select(0, pair), dy.index_select(0, pair), dx


def _row_spans(rows: torch.Tensor, dy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(first column, number of columns) ``[R]`` of the pixels of each box row (``rows``, the
    triangles' ``table`` rows; ``dy``, the row in the box) that can be inside the triangle: each
    barycentric is affine along the row, so each edge bounds the row's columns on one side. A pixel
    of margin each side covers rounding; the edge test of :func:`_covers` decides."""
    at_row = rows[:, 0:3] + rows[:, 6:9] * dy[:, None]
    slope = rows[:, 3:6]
    crossing = (-_INSIDE_EPS - at_row) / slope  # column where each barycentric reaches the edge
    flat = slope.abs() < _FLAT_SLOPE  # an edge nearly along the row: bounds nothing here
    lower = _fold3(torch.maximum, torch.where((slope > 0) & ~flat, crossing, -torch.inf))
    upper = _fold3(torch.minimum, torch.where((slope < 0) & ~flat, crossing, torch.inf))
    last = rows[:, 12] - 1
    start = (lower.ceil() - 1).clamp(0, None).minimum(last + 1)
    stop = (upper.floor() + 1).minimum(last)
    return start.long(), (stop - start + 1).clamp_min(0).long()


def _scatter_chunk(
    zbuf: torch.Tensor, counts: torch.Tensor, table: torch.Tensor, ids: torch.Tensor, width: int
) -> None:
    """Test the candidate pixels of some triangles and fold the covered ones into ``zbuf``."""
    tri, dx, dy, w = _candidate_pixels(counts, table, width)
    inside = _covers(w).nonzero(as_tuple=True)[0]  # the depth of the covered ones only
    tri, w, dx, dy = (x.index_select(0, inside) for x in (tri, w, dx, dy))
    tid, inverse_z = ids.index_select(0, tri), table[:, 9:12].index_select(0, tri)
    w = w / _fold3(torch.add, w)[:, None]
    depth = 1.0 / _fold3(torch.add, w * inverse_z)  # perspective-correct z
    key = (depth / DEPTH_UNIT).long().clamp(0, (1 << 22) - 1) << _ID_BITS | tid[:, 1]
    zbuf.scatter_reduce_(0, _pixels(tid[:, 0], dx, dy, width), key, reduce="amin")


def _cover_chunk(
    covered: torch.Tensor, counts: torch.Tensor, table: torch.Tensor, ids: torch.Tensor, width: int
) -> None:
    """Test the candidate pixels of some triangles and mark the covered ones in ``covered``."""
    tri, dx, dy, w = _candidate_pixels(counts, table, width)
    inside = _covers(w).nonzero(as_tuple=True)[0]
    tri, dx, dy = (x.index_select(0, inside) for x in (tri, dx, dy))
    covered[_pixels(ids[:, 0].index_select(0, tri), dx, dy, width)] = True


def _pixels(corner: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, width: int) -> torch.Tensor:
    """Flat pixel indices of the pixels ``dx``, ``dy`` into boxes whose top-left pixel is ``corner``."""
    return corner + dy * width + dx


def _fold3(op, x: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """``op`` (``torch.add``, ``torch.maximum``, ...) over the three entries of ``x`` along ``dim``,
    left to right: the same sums as torch's reductions, several times faster on the CPU over so few."""
    a, b, c = x.unbind(dim)
    return op(op(a, b), c)


def _covers(barycentrics: torch.Tensor) -> torch.Tensor:
    """Whether a triangle covers the pixel of each of its screen ``barycentrics`` ``[N, 3]``
    (a pixel on an edge belongs to both triangles: no cracks between them)."""
    return _fold3(torch.logical_and, barycentrics >= -_INSIDE_EPS)


def gather_vertices(values: torch.Tensor, batch_index: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """``values[batch_index[:, None], corners]`` (``[B, V, C]`` -> ``[N, 3, C]``) with one
    ``index_select``, many times faster on the CPU than advanced indexing."""
    b, v, c = values.shape
    flat = (batch_index[:, None] * v + corners).reshape(-1)
    return values.reshape(b * v, c).index_select(0, flat).view(-1, 3, c)


def _resolve(zbuf, verts, faces, K, batch, size, barycentrics: bool) -> Fragments:
    """Winning triangle per pixel, its depth and (with ``barycentrics``) its perspective-correct barycentrics."""
    width, height = size
    covered = zbuf != _EMPTY
    tri_id = torch.where(covered, zbuf & ((1 << _ID_BITS) - 1), torch.zeros_like(zbuf))
    face = torch.where(covered, tri_id % faces.shape[0], torch.full_like(zbuf, -1)).view(batch, height, width)
    bary = torch.zeros(batch * height * width, 3, device=verts.device) if barycentrics else None
    depth = torch.zeros(batch * height * width, device=verts.device)
    pix = covered.nonzero(as_tuple=True)[0]
    if len(pix):
        ids = tri_id.index_select(0, pix)
        b, f = ids // faces.shape[0], ids % faces.shape[0]
        tri = gather_vertices(verts, b, faces.index_select(0, f))  # [N, 3, 3]
        uv = project(tri, K.index_select(0, b))
        pixel = torch.stack([pix % width, (pix // width) % height], -1).float()
        w = _barycentrics_at(uv, pixel, _signed_area(uv)).clamp_min(0)
        persp = w / tri[..., 2]
        norm = _fold3(torch.add, persp)[:, None]
        if bary is not None:
            bary.index_copy_(0, pix, persp / norm)
        depth.index_copy_(0, pix, 1.0 / norm[:, 0])
    bary = None if bary is None else bary.view(batch, height, width, 3)
    return Fragments(face=face, bary=bary, depth=depth.view(batch, height, width))
