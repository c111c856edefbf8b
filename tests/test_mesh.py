"""Tests of carvi_torch.mesh: marching cubes meshes, components, transforms, export.

References: analytic volumes of boxes and balls, a brute-force flood fill for
connected components, trimesh's own loaders for round trips.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np
import pytest
import torch
import trimesh

from carvi_torch.mesh import (empty_mesh, largest_component, occupancy_to_mesh, read_mesh_arrays, transform_mesh,
                              write_mesh)


def grid_T(sx=1.0, sy=1.0, sz=1.0, origin=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """The carving layout: (d, h, w) -> (x, y, z) = (origin + sx w, sy h, sz d); det < 0."""
    T = torch.zeros(4, 4)
    T[0, 2], T[1, 1], T[2, 0] = sx, sy, sz
    T[:3, 3] = torch.tensor(origin)
    T[3, 3] = 1
    return T


def ball(n: int, r: float) -> torch.Tensor:
    c = (n - 1) / 2
    d, h, w = torch.meshgrid(*(torch.arange(n, dtype=torch.float64),) * 3, indexing="ij")
    return (d - c) ** 2 + (h - c) ** 2 + (w - c) ** 2 <= r * r


# --------------------------------------------------------------------------- occupancy_to_mesh


@pytest.mark.parametrize("T", [grid_T(0.5, 2.0, 1.5, (3.0, -1.0, 7.0)), torch.eye(4)], ids=["carve-layout", "identity"])
def test_box_mesh_is_closed_outward_and_has_the_voxel_volume(T):
    occ = torch.zeros(12, 10, 14, dtype=torch.bool)
    occ[2:9, 3:8, 1:13] = True  # 7 x 5 x 12 voxels
    mesh = occupancy_to_mesh(occ, T)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward faces whatever the handedness of T
    voxel_volume = 7 * 5 * 12 * abs(float(torch.linalg.det(T[:3, :3])))
    # the 0.5 level surface passes half-way between voxel centres: exact up to chamfered edges
    assert mesh.volume == pytest.approx(voxel_volume, rel=0.06)
    assert mesh.volume < voxel_volume
    # vertices are in the camera frame: the bounds are the voxel cells' bounds
    corners = torch.tensor([[1.5, 2.5, 0.5, 1.0], [8.5, 7.5, 12.5, 1.0]]) @ T.T
    lo, hi = corners[:, :3].min(0).values.numpy(), corners[:, :3].max(0).values.numpy()
    tol = 2e-3 * float(T[:3, :3].abs().max())  # the level sits 0.001 voxel below 0.5
    assert np.allclose(mesh.bounds[0], lo, atol=tol) and np.allclose(mesh.bounds[1], hi, atol=tol)


def test_ball_mesh_volume_close_to_voxel_and_analytic_volume():
    occ = ball(30, 11.0)
    mesh = occupancy_to_mesh(occ, grid_T())
    assert mesh.is_watertight and mesh.volume > 0
    assert mesh.volume == pytest.approx(float(occ.sum()), rel=0.03)
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * 11.0 ** 3, rel=0.05)


def test_random_occupancy_meshes_are_watertight():
    gen = torch.Generator().manual_seed(0)
    for density in (0.2, 0.35, 0.5, 0.65, 0.8) * 4:  # ambiguous cases everywhere
        occ = torch.rand(9, 8, 10, generator=gen) < density
        mesh = occupancy_to_mesh(occ, grid_T(1.0, 0.7, 1.3))
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0


def test_occupancy_touching_the_border_is_closed():
    occ = torch.ones(4, 5, 6, dtype=torch.bool)
    mesh = occupancy_to_mesh(occ.numpy(), np.eye(4))
    assert mesh.is_watertight and mesh.volume == pytest.approx(4 * 5 * 6, rel=0.1)


def test_empty_occupancy_gives_empty_mesh_and_bad_input_raises():
    mesh = occupancy_to_mesh(torch.zeros(5, 5, 5, dtype=torch.bool), torch.eye(4))
    assert len(mesh.vertices) == 0 and len(mesh.faces) == 0
    assert len(empty_mesh().faces) == 0
    with pytest.raises(ValueError, match="occupancy"):
        occupancy_to_mesh(torch.zeros(5, 5, dtype=torch.bool), torch.eye(4))
    with pytest.raises(ValueError, match="voxel_to_camera"):
        occupancy_to_mesh(torch.ones(3, 3, 3, dtype=torch.bool), torch.eye(3))


def test_largest_component_option_drops_small_parts():
    occ = torch.zeros(10, 10, 10, dtype=torch.bool)
    occ[1:5, 1:5, 1:5] = True
    occ[7:9, 7:9, 7:9] = True
    full = occupancy_to_mesh(occ, torch.eye(4))
    big = occupancy_to_mesh(occ, torch.eye(4), largest_component=True)
    assert len(full.split(only_watertight=False)) == 2 and len(big.split(only_watertight=False)) == 1
    assert big.volume == pytest.approx(full.volume - occupancy_to_mesh(occ & (torch.arange(10) >= 6).view(-1, 1, 1),
                                                                        torch.eye(4)).volume)


# --------------------------------------------------------------------------- largest_component


def flood_fill_largest(occ: np.ndarray, conn: int) -> np.ndarray:
    """Brute force: BFS over neighbours whose offset has at most ``conn`` non-zero coordinates."""
    offsets = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)
               if 0 < abs(a) + abs(b) + abs(c) <= conn]
    seen = np.zeros_like(occ, dtype=bool)
    best = []
    for start in zip(*np.nonzero(occ)):
        if seen[start]:
            continue
        comp, queue = [], deque([start])
        seen[start] = True
        while queue:
            v = queue.popleft()
            comp.append(v)
            for o in offsets:
                u = tuple(np.add(v, o))
                if all(0 <= u[i] < occ.shape[i] for i in range(3)) and occ[u] and not seen[u]:
                    seen[u] = True
                    queue.append(u)
        if len(comp) > len(best):
            best = comp
    out = np.zeros_like(occ, dtype=bool)
    for v in best:
        out[v] = True
    return out


@pytest.mark.parametrize("conn", [1, 2, 3])
def test_largest_component_matches_flood_fill_batched(conn):
    rng = np.random.default_rng(conn)
    occ = rng.random((4, 7, 6, 8)) < 0.3
    occ[2] = False  # an empty item
    got = largest_component(occ, connectivity=conn)
    assert got.shape == occ.shape and got.dtype == bool
    for b in range(4):
        expect = flood_fill_largest(occ[b], conn)
        assert got[b].sum() == expect.sum()  # same size (ties may pick another component)
        assert np.array_equal(largest_component(occ[b], connectivity=conn), got[b])
        if b != 2:
            assert np.array_equal(got[b], expect) or got[b].sum() == expect.sum()
    assert not got[2].any()


def test_largest_component_tensor_in_tensor_out_and_ties():
    occ = torch.zeros(1, 1, 7, dtype=torch.bool)
    occ[0, 0, [0, 1, 3, 4, 6]] = True
    out = largest_component(occ, connectivity=1)
    assert isinstance(out, torch.Tensor) and out.dtype == torch.bool
    assert out[0, 0].tolist() == [True, True, False, False, False, False, False]  # first of the tied pair
    with pytest.raises(ValueError, match="connectivity"):
        largest_component(occ, connectivity=4)
    with pytest.raises(ValueError, match="occupancy"):
        largest_component(torch.zeros(3, 3, dtype=torch.bool))


# --------------------------------------------------------------------------- transform and write


def test_transform_mesh_maps_vertices_and_keeps_faces_outward():
    mesh = occupancy_to_mesh(ball(12, 4.0), torch.eye(4))
    A = torch.tensor([[2.0, 0, 0, 1], [0, 2, 0, -3], [0, 0, 2, 5], [0, 0, 0, 1]])
    moved = transform_mesh(mesh, A)
    assert np.allclose(moved.vertices, mesh.vertices * 2 + [1, -3, 5])
    assert moved.volume == pytest.approx(mesh.volume * 8)
    mirror = np.diag([-1.0, 1, 1, 1])  # image x flip: a reflection
    flipped = transform_mesh(mesh, mirror)
    assert flipped.volume == pytest.approx(mesh.volume) and flipped.volume > 0
    assert len(transform_mesh(empty_mesh(), A).vertices) == 0
    with pytest.raises(ValueError, match="A"):
        transform_mesh(mesh, np.ones((4, 4)))


@pytest.mark.parametrize("name", ["m.ply", "m.obj", "m.glb", "m"])
def test_write_mesh_round_trip(tmp_path, name):
    mesh = occupancy_to_mesh(ball(10, 3.5), grid_T(0.5, 1.0, 2.0))
    path = write_mesh(mesh, tmp_path / "sub" / name)
    assert path.exists() and path.suffix in (".ply", ".obj", ".glb")
    back = trimesh.load(path, force="mesh", process=False)
    assert len(back.faces) == len(mesh.faces)
    assert back.volume == pytest.approx(mesh.volume, rel=1e-5)
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary left behind


def test_write_mesh_bad_extension_and_empty_mesh(tmp_path):
    with pytest.raises(ValueError, match="extension"):
        write_mesh(empty_mesh(), tmp_path / "m.xyz")
    path = write_mesh(empty_mesh(), tmp_path / "e.ply")
    assert path.stat().st_size > 0


@pytest.mark.parametrize("fmt", ["ply", "obj", "stl", "off", "glb"])
def test_read_mesh_arrays_gives_the_written_triangles(tmp_path, fmt):
    """Every format the writer writes reads back as the written triangles (their centroids and the enclosed volume,
    within the formats' float32), as float64 ``(V, 3)`` and int64 ``(F, 3)``; PLY, read by the parser alone, gives
    ``trimesh.load(process=False)``'s arrays exactly."""
    mesh = occupancy_to_mesh(ball(8, 2.5), grid_T(0.5, 1.0, 2.0))
    path = write_mesh(mesh, tmp_path / f"m.{fmt}")
    v, f = read_mesh_arrays(path)
    assert v.dtype == np.float64 and f.dtype == np.int64 and v.shape[1] == 3 and f.shape == mesh.faces.shape

    def centroids(vertices, faces):
        c = np.asarray(vertices, dtype=np.float64)[faces].mean(axis=1)
        return c[np.lexsort(np.round(c, 3).T[::-1])]
    np.testing.assert_allclose(centroids(v, f), centroids(mesh.vertices, mesh.faces), atol=1e-4)
    assert trimesh.Trimesh(v, f, process=False).volume == pytest.approx(mesh.volume, rel=1e-5)
    if fmt == "ply":
        ref = trimesh.load(path, force="mesh", process=False)
        np.testing.assert_array_equal(v, np.asarray(ref.vertices, dtype=np.float64))
        np.testing.assert_array_equal(f, np.asarray(ref.faces))


def test_read_mesh_arrays_splits_a_ply_of_quads_as_trimesh_does(tmp_path):
    """A PLY of quadrilaterals (another tool's file) is not read as triangles by reshaping: trimesh splits it."""
    path = tmp_path / "quad.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
                    "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    v, f = read_mesh_arrays(path)
    assert f.shape == (2, 3) and sorted(set(f.ravel().tolist())) == [0, 1, 2, 3]
    np.testing.assert_array_equal(f, trimesh.load(path, force="mesh", process=False).faces)


@pytest.mark.parametrize("vertices, faces, why", [
    (np.eye(3), np.zeros((0, 3), int), "has no faces"),
    (np.array([[0.0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), np.array([[0, 1, 2]]), "not \\(V, 3\\) finite"),
    (np.eye(3), np.array([[0, 1, 7]]), "face index 7 is outside its 3 vertices"),
    (np.eye(3), np.array([[0, -1, 2]]), "face index -1 is outside"),
])
def test_read_mesh_arrays_refuses_unusable_meshes(tmp_path, vertices, faces, why):
    path = tmp_path / "bad.ply"
    path.write_bytes(trimesh.exchange.ply.export_ply(trimesh.Trimesh(vertices, faces, process=False)))
    with pytest.raises(ValueError, match=why):
        read_mesh_arrays(path)


def test_read_mesh_arrays_lets_the_parsers_errors_through(tmp_path):
    """A file cut inside its header, and one that does not exist: the parser's or the file system's error."""
    path = write_mesh(occupancy_to_mesh(ball(8, 2.5), grid_T(0.5, 1.0, 2.0)), tmp_path / "m.ply")
    path.write_bytes(path.read_bytes()[:40])
    with pytest.raises((ValueError, IndexError, KeyError)):
        read_mesh_arrays(path)
    with pytest.raises(FileNotFoundError):
        read_mesh_arrays(tmp_path / "none.ply")


def test_read_mesh_arrays_used_only_ignores_unused_vertices(tmp_path):
    """A model whose unused vertex is NaN: refused by default (the export stores every vertex), read with
    ``used_only`` (evaluate's metric reads only the vertices its faces name); a NaN vertex a face names is refused
    either way."""
    path = tmp_path / "m.off"
    path.write_text("OFF\n4 1 0\n0 0 0\n1 0 0\n0 1 0\nnan nan nan\n3 0 1 2\n")
    with pytest.raises(ValueError, match="finite"):
        read_mesh_arrays(path)
    v, f = read_mesh_arrays(path, used_only=True)
    assert v.shape == (4, 3) and f.tolist() == [[0, 1, 2]]
    from carvi_torch.evaluation.scoring import read_mesh

    assert read_mesh(path).faces.tolist() == [[0, 1, 2]]  # a ground-truth model as evaluate reads it
    path.write_text("OFF\n4 1 0\n0 0 0\n1 0 0\n0 1 0\nnan nan nan\n3 0 1 3\n")
    with pytest.raises(ValueError, match="among those its faces name"):
        read_mesh_arrays(path, used_only=True)
