"""Tests of carvi_torch.marching: the batched torch marching cubes against scikit-image.

Reference: :func:`carvi_torch.mesh.occupancy_to_mesh` (scikit-image's Lewiner marching cubes, one
grid at a time) and a plain loop over cubes. Two meshes are the same when their vertex sets agree
within a tolerance and, after matching vertices, their oriented triangle sets are equal.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from carvi_torch.marching import case_table, marching_cubes, marching_cubes_naive, occupancy_to_meshes
from carvi_torch.mesh import occupancy_to_mesh
from conftest import requires_cuda

#: Vertices agree within this many voxels: scikit-image returns float32 vertices (about 4e-6 at index 60).
VOXEL_TOL = 1e-5


def _oriented_triangles(faces: np.ndarray) -> np.ndarray:
    """Triangles, each rotated to start at its smallest vertex index (a rotation keeps the winding), sorted."""
    start = faces.argmin(axis=1)[:, None]
    rotated = np.take_along_axis(faces, (start + np.arange(3)) % 3, axis=1)
    return rotated[np.lexsort(rotated.T[::-1])]


def assert_same_mesh(v1: np.ndarray, f1: np.ndarray, v2: np.ndarray, f2: np.ndarray, tol: float) -> None:
    """Same vertices within ``tol`` (each matched to its nearest, one to one) and the same oriented triangles."""
    assert v1.shape == v2.shape and f1.shape == f2.shape
    if len(v1) == 0:
        return
    dist, match = cKDTree(v1).query(v2)  # v2[i] is v1[match[i]]
    assert dist.max() <= tol
    assert len(np.unique(match)) == len(v1)
    assert np.array_equal(_oriented_triangles(f1), _oriented_triangles(match[f2]))


def random_affine(generator: torch.Generator, batch: int) -> torch.Tensor:
    """Affine maps with random signs of the determinant (both handednesses occur)."""
    T = torch.zeros(batch, 4, 4, dtype=torch.float64)
    T[:, :3] = torch.randn(batch, 3, 4, generator=generator, dtype=torch.float64)
    T[:, 3, 3] = 1.0
    return T


@pytest.mark.parametrize("shape,density", [((5, 7, 6), 0.3), ((5, 7, 6), 0.6), ((17, 13, 19), 0.5),
                                           ((24, 24, 24), 0.15), ((24, 24, 24), 0.85)])
def test_random_grids_match_scikit_image(shape, density, generator):
    occ = torch.rand((3,) + shape, generator=generator) < density
    occ[2] = False  # a grid without surface in the batch
    T = random_affine(generator, 3)
    meshes = occupancy_to_meshes(occ, T)
    for i in range(3):
        ref = occupancy_to_mesh(occ[i], T[i])
        tol = VOXEL_TOL * float(T[i, :3, :3].abs().sum(1).max())
        assert_same_mesh(np.asarray(ref.vertices), np.asarray(ref.faces), *meshes[i], tol)
    assert meshes[2][0].shape == (0, 3) and meshes[2][1].shape == (0, 3)


def test_types_cast_on_the_device_are_the_host_casts(generator):
    """``vertex_dtype``/``face_dtype`` (a PLY file's float32 and int32): the float64 / int64 meshes cast, value for
    value, with the types asked for."""
    occ = torch.rand(4, 9, 8, 10, generator=generator) < 0.4
    T = random_affine(generator, 4)
    wide = occupancy_to_meshes(occ, T)
    narrow = occupancy_to_meshes(occ, T, vertex_dtype=torch.float32, face_dtype=torch.int32)
    for (v, f), (v32, f32) in zip(wide, narrow):
        assert v.dtype == np.float64 and f.dtype == np.int64 and v32.dtype == np.float32 and f32.dtype == np.int32
        assert len(v) > 0 and np.array_equal(v.astype(np.float32), v32) and np.array_equal(f, f32)


def test_every_cube_pattern_matches_scikit_image():
    """All 256 corner patterns, each alone in its own grid (and in one batch)."""
    occ = torch.zeros(256, 2, 2, 2, dtype=torch.bool)
    for p in range(256):
        for k in range(8):
            occ[p].view(-1)[k] = bool(p >> k & 1)
    meshes = occupancy_to_meshes(occ, torch.eye(4, dtype=torch.float64).expand(256, 4, 4))
    for p in range(1, 256):
        ref = occupancy_to_mesh(occ[p], torch.eye(4))
        assert_same_mesh(np.asarray(ref.vertices), np.asarray(ref.faces), *meshes[p], VOXEL_TOL)
    assert case_table().shape == (256, 5, 3)


def test_batched_op_matches_the_naive_loop(generator):
    occ = torch.rand(2, 9, 8, 7, generator=generator) < 0.5
    mc = marching_cubes(occ)
    for (v, f), grid in zip(mc.split(), occ):
        vn, fn = marching_cubes_naive(grid.numpy())
        # both name a vertex by its edge: the same float64 arithmetic, so equal to the last bit
        assert_same_mesh(vn, fn, v.numpy(), f.numpy(), 1e-12)


def test_meshes_are_closed_and_outward_whatever_the_handedness(generator):
    occ = torch.zeros(2, 12, 12, 12, dtype=torch.bool)
    occ[:, 2:10, 3:9, 4:11] = True
    occ[:, 5:7, 5:7, :] = False  # a tunnel: genus 1
    T = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    T[1, 0, 0] = -2.0  # a reflection
    for v, f in occupancy_to_meshes(occ, T):
        m = trimesh.Trimesh(v, f, process=False)
        assert m.is_watertight and m.is_winding_consistent and m.volume > 0
        assert m.euler_number == 0  # a torus


def test_real_cad_shells_match_scikit_image(shared_data):
    """Thin, open voxel shells of real CAD models (PASCAL3D+): the hardest topology for the ambiguous cases."""
    grids = []
    for name in ("aeroplane01", "chair01", "bicycle01"):
        z = np.load(shared_data / "pascal3d_cad" / f"{name}.npz")
        mesh = trimesh.Trimesh(z["vertices"], z["faces"], process=False)
        vox = mesh.voxelized(pitch=float(mesh.extents.max()) / 40).matrix
        grid = np.zeros((44, 44, 44), bool)
        grid[:vox.shape[0], :vox.shape[1], :vox.shape[2]] = vox[:44, :44, :44]
        grids.append(grid)
    occ = torch.from_numpy(np.stack(grids))
    T = torch.eye(4, dtype=torch.float64).expand(len(grids), 4, 4)
    for grid, (v, f) in zip(occ, occupancy_to_meshes(occ, T)):
        ref = occupancy_to_mesh(grid, torch.eye(4))
        assert len(ref.faces) > 1000
        assert_same_mesh(np.asarray(ref.vertices), np.asarray(ref.faces), v, f, VOXEL_TOL)


@requires_cuda
def test_cuda_matches_the_cpu(generator):
    occ = torch.rand(5, 30, 31, 32, generator=generator) < 0.5
    T = random_affine(generator, 5)
    cpu = occupancy_to_meshes(occ, T)
    gpu = occupancy_to_meshes(occ.cuda(), T.cuda())
    for (v1, f1), (v2, f2) in zip(cpu, gpu):
        assert np.array_equal(f1, f2)
        assert np.allclose(v1, v2, rtol=0, atol=1e-9)
