"""The rasteriser of :mod:`monose3.robot.rasterize` compiled for the CPU (numba): the same
pixels, depths and barycentrics, bit for bit, at a fraction of the time.

On the CPU the PyTorch rasteriser spends its time in hundreds of small tensor operations per
render rather than in arithmetic. These loops do the same float32 arithmetic in the same order
(each sum and product as the tensor code writes it, every constant a float32, no fused
multiply-adds), so every coverage test and depth key comes out equal; the z-buffer's minimum
does not depend on the order in which triangles are drawn. The tests compare the two on
renders of many poses. Compiled on first use and cached beside this file.
"""

from __future__ import annotations

import numba
import numpy as np

_F = np.float32
_ID_BITS = 40
_MAX_DEPTH_KEY = (1 << 22) - 1


@numba.njit(cache=True, nogil=True)
def _project(x, y, z, fx, fy, cx, cy):
    """``geometry.camera.project`` of one point: x / max(z, 1e-6) * f + c, in float32."""
    zc = max(z, _F(1e-6))
    return x / zc * fx + cx, y / zc * fy + cy


@numba.njit(cache=True, nogil=True)
def _corners(verts, faces, K, b, f):
    """Face ``f`` of batch row ``b`` on screen: its corners' pixels and depths, and its doubled
    signed area (``rasterize._signed_area``)."""
    fx, fy, cx, cy = K[b, 0, 0], K[b, 1, 1], K[b, 0, 2], K[b, 1, 2]
    i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
    z0, z1, z2 = verts[b, i0, 2], verts[b, i1, 2], verts[b, i2, 2]
    u0, v0 = _project(verts[b, i0, 0], verts[b, i0, 1], z0, fx, fy, cx, cy)
    u1, v1 = _project(verts[b, i1, 0], verts[b, i1, 1], z1, fx, fy, cx, cy)
    u2, v2 = _project(verts[b, i2, 0], verts[b, i2, 1], z2, fx, fy, cx, cy)
    area = (u1 - u0) * (v2 - v0) - (u2 - u0) * (v1 - v0)
    return u0, v0, z0, u1, v1, z1, u2, v2, z2, area


@numba.njit(cache=True, nogil=True)
def _draw(verts, faces, K, cullable, width, height, near, inside_eps, depth_unit, zbuf, covered):
    """Every triangle of every batch row: its box, the edge test of each pixel centre in it, and
    either the z-buffer's key (quantised depth, triangle id) folded in by minimum (``zbuf``)
    or the pixel marked (``covered``: silhouettes, no depth). The setup is
    ``rasterize._candidates``', the pixel test ``_scatter_chunk``'s and ``_cover_chunk``'s."""
    n_faces = faces.shape[0]
    zero, one = _F(0.0), _F(1.0)
    for b in range(verts.shape[0]):
        for f in range(n_faces):
            u0, v0, z0, u1, v1, z1, u2, v2, z2, area = _corners(verts, faces, K, b, f)
            if not (z0 > near and z1 > near and z2 > near):
                continue
            lo_u = max(np.ceil(min(min(u0, u1), u2)), zero)
            lo_v = max(np.ceil(min(min(v0, v1), v2)), zero)
            hi_u = min(np.floor(max(max(u0, u1), u2)), _F(width - 1))
            hi_v = min(np.floor(max(max(v0, v1), v2)), _F(height - 1))
            drawn = hi_u >= lo_u and hi_v >= lo_v and abs(area) > _F(1e-6) and (area < zero or not cullable[f])
            if not drawn:  # (written so that NaNs are dropped, as the tensor code's comparisons drop them)
                continue
            # barycentrics at the box's corner and their slopes per pixel (_barycentrics_at, _barycentric_slopes)
            r0u, r0v, r1u, r1v, r2u, r2v = u0 - lo_u, v0 - lo_v, u1 - lo_u, v1 - lo_v, u2 - lo_u, v2 - lo_v
            a0 = (r1u * r2v - r1v * r2u) / area
            a1 = (r2u * r0v - r2v * r0u) / area
            a2 = (r0u * r1v - r0v * r1u) / area
            sx0, sx1, sx2 = (v1 - v2) / area, (v2 - v0) / area, (v0 - v1) / area
            sy0, sy1, sy2 = (u2 - u1) / area, (u0 - u2) / area, (u1 - u0) / area
            iz0, iz1, iz2 = one / z0, one / z1, one / z2
            box_w, box_h = int(hi_u - lo_u) + 1, int(hi_v - lo_v) + 1
            corner = (b * height + int(lo_v)) * width + int(lo_u)
            tid = b * n_faces + f
            for dy in range(box_h):
                ty = _F(dy)
                for dx in range(box_w):
                    tx = _F(dx)
                    w0 = (a0 + sx0 * tx) + sy0 * ty
                    w1 = (a1 + sx1 * tx) + sy1 * ty
                    w2 = (a2 + sx2 * tx) + sy2 * ty
                    if not (w0 >= inside_eps and w1 >= inside_eps and w2 >= inside_eps):
                        continue
                    pixel = corner + dy * width + dx
                    if covered.shape[0]:
                        covered[pixel] = True
                        continue
                    total = (w0 + w1) + w2
                    inverse = ((w0 / total) * iz0 + (w1 / total) * iz1) + (w2 / total) * iz2
                    level = min(max(np.int64(one / inverse / depth_unit), 0), _MAX_DEPTH_KEY)
                    key = (level << _ID_BITS) | tid
                    if key < zbuf[pixel]:
                        zbuf[pixel] = key


@numba.njit(cache=True, nogil=True)
def _resolve(zbuf, verts, faces, K, width, height, empty, face, depth, bary):
    """``rasterize._resolve``: per covered pixel, the winning face, its depth and (where
    ``bary`` has rows) its perspective-correct barycentrics."""
    n_faces = faces.shape[0]
    mask = (1 << _ID_BITS) - 1
    zero = _F(0.0)
    for pixel in range(zbuf.shape[0]):
        if zbuf[pixel] == empty:
            continue
        tri = zbuf[pixel] & mask
        b, f = tri // n_faces, tri % n_faces
        face[pixel] = f
        u0, v0, z0, u1, v1, z1, u2, v2, z2, area = _corners(verts, faces, K, b, f)
        px, py = _F(pixel % width), _F((pixel // width) % height)
        r0u, r0v, r1u, r1v, r2u, r2v = u0 - px, v0 - py, u1 - px, v1 - py, u2 - px, v2 - py
        p0 = max((r1u * r2v - r1v * r2u) / area, zero) / z0
        p1 = max((r2u * r0v - r2v * r0u) / area, zero) / z1
        p2 = max((r0u * r1v - r0v * r1u) / area, zero) / z2
        norm = (p0 + p1) + p2
        depth[pixel] = _F(1.0) / norm
        if bary.shape[0]:
            bary[pixel, 0], bary[pixel, 1], bary[pixel, 2] = p0 / norm, p1 / norm, p2 / norm


def zbuffer(verts: np.ndarray, faces: np.ndarray, K: np.ndarray, cullable: np.ndarray, size: tuple[int, int],
            near: float, inside_eps: float, depth_unit: float, empty: int) -> np.ndarray:  # fmt: skip
    """The z-buffer ``[B * H * W]`` (int64 keys, ``empty`` where nothing is drawn) of camera-frame
    ``verts`` ``[B, V, 3]`` (float32) with ``K`` ``[B, 3, 3]`` (float32)."""
    width, height = size
    zbuf = np.full(len(verts) * width * height, empty, np.int64)
    _draw(verts, faces, K, cullable, width, height, _F(near), _F(inside_eps), _F(depth_unit), zbuf,
          np.zeros(0, np.bool_))  # fmt: skip
    return zbuf


def coverage(verts: np.ndarray, faces: np.ndarray, K: np.ndarray, cullable: np.ndarray, size: tuple[int, int],
             near: float, inside_eps: float) -> np.ndarray:  # fmt: skip
    """The silhouettes ``[B * H * W]`` (bool) of ``verts``, as :func:`zbuffer` draws them."""
    width, height = size
    covered = np.zeros(len(verts) * width * height, np.bool_)
    _draw(verts, faces, K, cullable, width, height, _F(near), _F(inside_eps), _F(1.0), np.zeros(0, np.int64),
          covered)  # fmt: skip
    return covered


def resolve(zbuf: np.ndarray, verts: np.ndarray, faces: np.ndarray, K: np.ndarray, size: tuple[int, int],
            empty: int, barycentrics: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:  # fmt: skip
    """(face ``[B * H * W]`` (-1 where empty), depth (0 there), barycentrics ``[B * H * W, 3]`` or
    None) of a :func:`zbuffer` (``empty`` where nothing was drawn)."""
    width, height = size
    face = np.full(zbuf.shape, -1, np.int64)
    depth = np.zeros(zbuf.shape, np.float32)
    bary = np.zeros((len(zbuf) if barycentrics else 0, 3), np.float32)
    _resolve(zbuf, verts, faces, K, width, height, empty, face, depth, bary)
    return face, depth, bary if barycentrics else None
