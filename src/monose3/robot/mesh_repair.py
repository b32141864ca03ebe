"""Closing the holes of a robot's link meshes, so that the renderer may skip their back faces.

Several visual meshes (the Panda's links 3 to 6 and hand) are open: parts meet without sharing
vertices, and some shells leave openings that another part covers. Back-face culling is exact
only on closed meshes: through an opening the renderer would show nothing where the inside of
the far wall belongs. A cap over each opening (its boundary loop triangulated, wound against
the mesh so that the link becomes closed) makes culling exact again: a ray from outside that
leaves the link through a back face has entered it through a front face or a cap. Culling halves
the triangles a render tests, and on the CPU the pose fit spends most of its time rendering.

A cap is kept only if no view shows it outside the link's own silhouette (:func:`caps_hidden`): an
opening that is really seen through (a gap in the hand) must stay open, and its link is drawn
from both sides as before. ``tools/build_robot_assets.py`` caps the shipped meshes once.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from monose3.geometry.rotations import quat_xyzw_to_matrix
from monose3.robot.meshes import RobotMesh, surplus_edges, welded_vertex_ids
from monose3.robot.rasterize import rasterize_coverage

CHECK_VIEWS = 64  # directions a link is rendered from to see whether its caps show
CHECK_SIZE = 240  # pixels across the square image the link fills
# Share of a link's silhouette pixels its caps may add (where a cap meets the outline): the
# shipped caps add at most 1e-4 of them, the hand's would add 1e-3 to 1e-2.
CAP_TOLERANCE = 1e-4


def boundary_loops(faces: np.ndarray) -> list[list[int]]:
    """The closed loops ``[[i0, i1, ...], ...]`` of vertex ids (welded) along which the mesh
    ``faces`` ``[F, 3]`` is open, each in the direction of its faces' edges. Every edge's surplus
    use in one direction (:func:`monose3.robot.meshes.surplus_edges`) enters once, so loops always
    close; a loop that passes a vertex twice is cut there into simple loops."""
    out = surplus_edges(faces)
    loops = []
    while out:
        start = next(iter(out))
        loop, vertex = [start], start
        while (vertex := _take_edge(out, vertex)) != start:
            loop.append(vertex)
        loops.extend(_simple_loops(loop))
    return loops


def _take_edge(out: dict[int, list[int]], vertex: int) -> int:
    nxt = out[vertex].pop()
    if not out[vertex]:
        del out[vertex]
    return nxt


def _simple_loops(loop: list[int]) -> list[list[int]]:
    """``loop`` cut at each vertex it passes twice into loops that pass each vertex once."""
    done, stack, position = [], [], {}
    for vertex in loop:
        if vertex in position:
            k = position[vertex]
            done.append(stack[k:])
            for v in stack[k + 1 :]:
                del position[v]
            stack = stack[: k + 1]
        else:
            position[vertex] = len(stack)
            stack.append(vertex)
    return [part for part in [*done, stack] if len(part) >= 3]


def min_area_triangulation(points: np.ndarray) -> np.ndarray:
    """Triangles ``[n - 2, 3]`` (indices ``i < m < j`` into ``points`` ``[n, 3]``, a closed polygon in
    space) of least total area, by dynamic programming over the polygon's diagonals (Liepa's
    hole filling, 2003): on a flat polygon this is any triangulation inside it, on a bent one the
    smallest surface the loop spans, so the cap stays where the missing surface was."""
    n = len(points)
    cost = np.zeros((n, n))
    split = np.zeros((n, n), int)
    for gap in range(2, n):
        for i in range(n - gap):
            j = i + gap
            m = np.arange(i + 1, j)
            area = 0.5 * np.linalg.norm(np.cross(points[m] - points[i], points[j] - points[i]), axis=-1)
            total = cost[i, m] + cost[m, j] + area
            k = int(np.argmin(total))
            cost[i, j], split[i, j] = total[k], m[k]
    triangles, todo = [], [(0, n - 1)]
    while todo:
        i, j = todo.pop()
        if j - i >= 2:
            m = split[i, j]
            triangles.append((i, m, j))
            todo += [(i, m), (m, j)]
    return np.array(triangles, np.int64).reshape(-1, 3)


def hole_caps(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Cap triangles ``[C, 3]`` (indices into ``vertices``) closing every hole of the mesh
    ``faces`` ``[F, 3]`` (one link's): each boundary loop triangulated by
    :func:`min_area_triangulation` and wound against the loop, so each boundary edge is then used
    once each way. Vertices are matched by position (:func:`welded_vertex_ids`)."""
    used = np.unique(faces)
    welded = welded_vertex_ids(vertices[used])
    first = used[np.unique(welded, return_index=True)[1]]  # one vertex index per position
    ids = np.full(len(vertices), -1)
    ids[used] = welded
    caps = []
    for loop in boundary_loops(ids[faces]):
        corners = first[np.array(loop)]
        caps.append(corners[min_area_triangulation(vertices[corners])[:, ::-1]])
    return np.concatenate(caps) if caps else np.zeros((0, 3), np.int64)


def caps_hidden(vertices: np.ndarray, faces: np.ndarray, caps: np.ndarray, views: int = CHECK_VIEWS) -> bool:
    """Whether the ``caps`` stay inside the silhouette of the mesh ``faces`` from ``views``
    directions (random, fixed seed; all faces drawn from both sides): they may add at most
    :data:`CAP_TOLERANCE` of its pixels (where a cap meets the outline)."""
    rng = np.random.default_rng(0)
    rot = torch.as_tensor(quat_xyzw_to_matrix(rng.normal(size=(views, 4))))  # uniform rotations
    used = vertices[np.unique(faces)]
    centre = (used.max(0) + used.min(0)) / 2
    radius = np.linalg.norm(used - centre, axis=1).max()
    distance = 4 * radius  # the link then spans at most 0.26 focal lengths from the image's centre
    focal = 0.9 * (CHECK_SIZE / 2) / 0.26
    K = torch.tensor([[focal, 0, CHECK_SIZE / 2], [0, focal, CHECK_SIZE / 2], [0, 0, 1]]).expand(views, 3, 3)
    verts = torch.as_tensor(vertices - centre) @ rot.transpose(1, 2) + torch.tensor([0.0, 0.0, distance])
    size = (CHECK_SIZE, CHECK_SIZE)
    mesh = rasterize_coverage(verts, torch.as_tensor(faces), K, size)
    capped = rasterize_coverage(verts, torch.as_tensor(np.concatenate([faces, caps])), K, size)
    return int((capped & ~mesh).sum()) <= CAP_TOLERANCE * int(mesh.sum())


def capped_mesh(mesh: RobotMesh) -> tuple[RobotMesh, dict[str, str]]:
    """``mesh`` with the holes of each link closed (its ``caps``) where the caps stay hidden
    (:func:`hole_caps`, :func:`caps_hidden`), and per open link what was done."""
    face_link = mesh.face_link
    caps, report = [], {}
    for link, name in enumerate(mesh.links):
        faces = mesh.faces[face_link == link]
        link_caps = hole_caps(mesh.vertices, faces) if len(faces) else np.zeros((0, 3), np.int64)
        if not len(link_caps):
            continue
        if caps_hidden(mesh.vertices, faces, link_caps):
            caps.append(link_caps)
            report[name] = f"closed with {len(link_caps)} cap triangles"
        else:
            report[name] = f"left open: {len(link_caps)} cap triangles would show"
    all_caps = np.concatenate(caps) if caps else np.zeros((0, 3), np.int64)
    return dataclasses.replace(mesh, caps=all_caps), report
