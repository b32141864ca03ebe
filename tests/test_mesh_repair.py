"""Closing open link meshes so that back faces can be skipped: boundary loops, the least-area
caps, the check that caps stay hidden, and the shipped meshes closed where it is safe."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from monose3.robot import RobotModel
from monose3.robot.mesh_repair import boundary_loops, capped_mesh, caps_hidden, hole_caps, min_area_triangulation
from monose3.robot.meshes import RobotMesh, surplus_edges
from monose3.robot.rasterize import rasterize

# A unit cube's six sides, each a quad counter-clockwise seen from outside.
CUBE_CORNERS = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
CUBE_QUADS = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]


def _triangles(quads) -> np.ndarray:
    return np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


def _tube(segments: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """An open-ended tube (radius 0.5, length 1, along z), outward-wound."""
    angle = 2 * np.pi * np.arange(segments) / segments
    ring = np.stack([0.5 * np.cos(angle), 0.5 * np.sin(angle)], -1)
    verts = np.concatenate([np.c_[ring, np.zeros(segments)], np.c_[ring, np.ones(segments)]])
    quads = [(i, (i + 1) % segments, segments + (i + 1) % segments, segments + i) for i in range(segments)]
    return verts, _triangles(quads)


def _mesh(verts: np.ndarray, faces: np.ndarray) -> RobotMesh:
    return RobotMesh(("link",), verts, np.zeros(len(verts), int), faces, np.full((len(faces), 3), 0.5))


def test_a_closed_cube_has_no_boundary_and_an_open_one_a_loop():
    faces = _triangles(CUBE_QUADS)
    assert not surplus_edges(faces)
    loops = boundary_loops(faces[2:])  # the x = 0 side removed
    assert len(loops) == 1 and sorted(loops[0]) == [0, 1, 2, 3]


def test_the_least_area_triangulation_stays_inside_a_flat_polygon():
    # An L: any triangle across its notch would add area outside it.
    polygon = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0], [1, 2, 0], [0, 2, 0]], float)
    triangles = min_area_triangulation(polygon)
    assert len(triangles) == len(polygon) - 2
    corners = polygon[triangles]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=-1)
    assert area.sum() == pytest.approx(3.0)


def test_caps_close_a_cube_with_a_missing_side_and_keep_its_winding():
    open_cube = _triangles(CUBE_QUADS)[2:]
    caps = hole_caps(CUBE_CORNERS, open_cube)
    assert len(caps) == 2
    assert not surplus_edges(np.concatenate([open_cube, caps]))
    assert caps_hidden(CUBE_CORNERS, open_cube, caps)
    capped, report = capped_mesh(_mesh(CUBE_CORNERS, open_cube))
    assert capped.closed_faces().all() and "closed" in report["link"]


def test_an_opening_seen_through_stays_open():
    verts, faces = _tube()
    caps = hole_caps(verts, faces)
    assert len(caps) == 2 * (16 - 2)  # one disc per end
    assert not caps_hidden(verts, faces, caps)  # seen along its axis, a tube is a ring
    capped, report = capped_mesh(_mesh(verts, faces))
    assert not len(capped.caps) and not capped.closed_faces().any()
    assert "left open" in report["link"]


def test_culling_a_capped_cube_draws_what_the_open_cube_shows():
    open_cube = _triangles(CUBE_QUADS)[2:]
    caps = hole_caps(CUBE_CORNERS, open_cube)
    verts = torch.as_tensor(CUBE_CORNERS + [0.5, -0.5, 3.0])[None]  # its open side (x = 0) faces the camera
    K = torch.tensor([[[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]]])

    def culled(faces: np.ndarray) -> torch.Tensor:
        return rasterize(verts, torch.as_tensor(faces), K, (160, 120), torch.ones(len(faces), dtype=torch.bool)).mask

    both_sides = rasterize(verts, torch.as_tensor(open_cube), K, (160, 120)).mask
    assert (both_sides & ~culled(open_cube)).sum() > 100  # through the opening: the inside's back faces
    assert torch.equal(culled(np.concatenate([open_cube, caps])), both_sides)


@pytest.mark.parametrize("robot", ["panda", "kuka"])
def test_the_shipped_meshes_are_closed_but_where_a_cap_would_show(robot):
    mesh = RobotModel(robot).mesh
    closed = mesh.closed_faces()
    open_links = {mesh.links[i] for i in np.unique(mesh.drawn_face_link[~closed])}
    assert open_links == ({"panda_hand"} if robot == "panda" else set())
