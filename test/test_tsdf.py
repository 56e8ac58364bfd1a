"""TSDF fusion: geometry of the extracted mesh, surface voxels and normals, bookkeeping, office0."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from roigsf_ros.core.camera import Intrinsics, load_cam_params
from roigsf_ros.core.errors import InputError
from roigsf_ros.data.replica import load_traj
from roigsf_ros.evaluation.metrics import mesh_metrics, raycast_depth, raycasting_scene
from roigsf_ros.mapping import tsdf
from roigsf_ros.mapping.tsdf import TSDFVolume, canonical_mesh, tsdf_mesh_from_depths

INTR = Intrinsics(160, 120, 120.0, 120.0, 79.5, 59.5)


def look_at(eye: np.ndarray, target: np.ndarray, up: tuple = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose at ``eye`` whose optical axis (+z, OpenCV) points at ``target``."""
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, eye
    return T


def ring_poses(radius: float = 2.0, n: int = 8) -> np.ndarray:
    """Cameras around the origin, alternately above and below it, all looking at it."""
    poses = []
    for k in range(n):
        a = 2 * np.pi * k / n + 0.3
        poses.append(look_at(np.array([radius * np.cos(a), radius * np.sin(a), 1.0 if k % 2 else -1.0]), np.zeros(3)))
    return np.stack(poses)


@pytest.fixture(scope="module")
def sphere_volume() -> tuple[TSDFVolume, o3d.geometry.TriangleMesh, np.ndarray]:
    sphere = o3d.geometry.TriangleMesh.create_sphere(0.5, resolution=60)
    scene = raycasting_scene(sphere)
    poses = ring_poses()
    volume = TSDFVolume(voxel_size_m=0.02, block_count=8)  # the hash map has to grow
    for T in poses:
        assert volume.integrate(raycast_depth(scene, T, INTR), T, INTR)
    return volume, sphere, poses


def test_sphere_mesh_lies_on_the_surface_and_covers_it(sphere_volume: tuple) -> None:
    volume, sphere, poses = sphere_volume
    mesh = volume.extract_mesh()
    verts = np.asarray(mesh.vertices)
    assert len(mesh.triangles) > 10_000
    radial_error = np.abs(np.linalg.norm(verts, axis=1) - 0.5)
    assert np.median(radial_error) < 0.25 * volume.voxel_size_m
    assert np.quantile(radial_error, 0.98) < 0.5 * volume.voxel_size_m
    assert radial_error.max() < volume.voxel_size_m
    m = mesh_metrics(mesh, sphere, n_samples=30_000, observed_poses=poses, intr=INTR)
    assert m["precision@1cm"] > 0.98 and m["recall@1cm"] > 0.98
    assert m["accuracy_cm"] < 0.5 and m["completion_cm"] < 0.5
    assert not mesh.has_vertex_colors()  # no colour was fused


def test_extracted_mesh_is_in_canonical_order_whatever_order_open3d_emits(sphere_volume: tuple) -> None:
    """The mesh metrics sample a mesh by triangle order: the same geometry in any order must give the same mesh."""
    volume, sphere, _ = sphere_volume
    mesh = volume.extract_mesh()
    verts, tris = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    assert np.all(np.diff(verts[:, 0]) >= 0)  # vertices sorted (x first)
    assert np.all(tris[:, 0] == tris.min(axis=1))  # each triangle starts at its smallest index
    assert np.all(np.diff(tris[:, 0]) >= 0)  # triangles sorted
    rng = np.random.default_rng(0)
    v_perm, t_perm = rng.permutation(len(verts)), rng.permutation(len(tris))
    inv = np.empty_like(v_perm)
    inv[v_perm] = np.arange(len(v_perm))
    shuffled = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts[v_perm]),
                                         o3d.utility.Vector3iVector(np.roll(inv[tris[t_perm]], 1, axis=1)))  # fmt: skip
    shuffled.vertex_normals = o3d.utility.Vector3dVector(np.asarray(mesh.vertex_normals)[v_perm])
    again = canonical_mesh(shuffled)
    np.testing.assert_array_equal(np.asarray(again.vertices), verts)
    np.testing.assert_array_equal(np.asarray(again.triangles), tris)  # the same triangles, orientation kept
    np.testing.assert_array_equal(np.asarray(again.vertex_normals), np.asarray(mesh.vertex_normals))
    a = mesh_metrics(mesh, sphere, n_samples=5_000)
    assert mesh_metrics(again, sphere, n_samples=5_000) == a
    assert mesh_metrics(shuffled, sphere, n_samples=5_000)["precision@1cm"] != a["precision@1cm"]  # order mattered


def test_surface_voxels_normals_point_outward(sphere_volume: tuple) -> None:
    volume, _, _ = sphere_volume
    centres, tsdf, weight, normals = volume.surface_voxels()
    assert len(centres) > 1000
    assert centres.shape == normals.shape == (len(tsdf), 3) and weight.shape == tsdf.shape
    assert np.all(np.abs(tsdf) <= volume.voxel_size_m / volume.sdf_trunc_m + 1e-4)
    assert np.all(weight >= 1)
    # The centres sit on the voxel lattice and within one voxel of the sphere, consistent with their TSDF.
    np.testing.assert_allclose(centres / volume.voxel_size_m, np.round(centres / volume.voxel_size_m), atol=1e-6)
    radius = np.linalg.norm(centres, axis=1)
    assert np.abs(radius - 0.5).max() < 1.5 * volume.voxel_size_m
    assert np.median(np.abs(radius - 0.5 - tsdf * volume.sdf_trunc_m)) < 0.25 * volume.voxel_size_m
    # Unit normals along the outward radius: toward free space and the cameras.
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    cos = np.sum(normals * centres / radius[:, None], axis=1)
    assert cos.mean() > 0.95 and np.quantile(cos, 0.05) > 0.8
    # A stricter band and a weight floor select subsets.
    assert len(volume.surface_voxels(max_abs_tsdf=0.1).tsdf) < len(tsdf)
    assert len(volume.surface_voxels(min_weight=3).tsdf) < len(tsdf)


def test_numba_neighbour_lookup_equals_the_vectorised_reference(sphere_volume: tuple) -> None:
    """Issue 12: the 6-neighbour lookup behind surface normals (every scoring TSDF update) as one numba pass."""
    vol = sphere_volume[0]
    res = vol.block_resolution
    _, keys = vol._active_blocks()
    rng = np.random.default_rng(0)
    b_idx = rng.integers(0, len(keys), 5000)
    local = rng.integers(0, res, (5000, 3))
    local[:64] = [[0, 0, 0], [res - 1, res - 1, res - 1]] * 32  # block corners: neighbours in other blocks
    fast = vol._neighbour_flat_indices(keys, b_idx, local)
    # The reference: every voxel's 6 offsets at once, block steps by floor division (the code before issue 12).
    shifts = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), -1).reshape(27, 3)
    found_buf, found = vol.vbg.hashmap().find(o3d.core.Tensor((keys[:, None, :] + shifts[None]).reshape(-1, 3)
                                                              .astype(np.int32)))  # fmt: skip
    table = np.where(found.numpy().reshape(-1), found_buf.numpy().reshape(-1).astype(np.int64), -1).reshape(-1, 27)
    offsets = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    moved = local[:, None, :] + offsets[None]
    step = np.floor_divide(moved, res)
    moved -= step * res
    nb = table[b_idx[:, None], (step[..., 0] + 1) * 9 + (step[..., 1] + 1) * 3 + (step[..., 2] + 1)]
    ref = np.where(nb >= 0, nb * res**3 + moved[..., 0] + res * moved[..., 1] + res * res * moved[..., 2], -1)
    np.testing.assert_array_equal(fast, ref)
    assert (ref == -1).any() and (ref >= 0).mean() > 0.5


def test_plane_from_tilted_views_normals_face_the_cameras() -> None:
    """A wall z = 2 m seen from three positions: voxels on it, normals -z, toward every camera."""
    plane = o3d.geometry.TriangleMesh.create_box(4.0, 4.0, 0.01).translate((-2.0, -2.0, 2.0))
    scene = raycasting_scene(plane)
    poses = [look_at(np.array([x, 0.3, 0.0]), np.array([0.0, 0.0, 2.0]), up=(0, -1, 0)) for x in (-0.5, 0.0, 0.6)]
    frames = [(raycast_depth(scene, T, INTR), T, None) for T in poses]
    volume = TSDFVolume(voxel_size_m=0.02)
    for depth, T, _ in frames:
        volume.integrate(depth, T, INTR)
    sv = volume.surface_voxels()
    assert np.abs(sv.centres_m[:, 2] - 2.0).max() <= 0.02 + 1e-6
    assert np.mean(sv.normals[:, 2]) < -0.99
    for T in poses:
        assert np.all(np.sum(sv.normals * (T[:3, 3] - sv.centres_m), axis=1) > 0)
    verts = np.asarray(volume.extract_mesh().vertices)
    assert np.abs(verts[:, 2] - 2.0).max() < 0.5 * volume.voxel_size_m
    # Surface voxels come in grid order: a second volume fed the same frames gives identical arrays.
    again = TSDFVolume(voxel_size_m=0.02, block_count=3)
    for depth, T, _ in frames:
        again.integrate(depth, T, INTR)
    for a, b in zip(sv, again.surface_voxels(), strict=True):
        np.testing.assert_array_equal(a, b)
    # The one-call helper builds the same mesh (up to vertex order, which follows the hash map's).
    other = np.asarray(tsdf_mesh_from_depths(frames, INTR, voxel_size_m=0.02).vertices)
    assert other.shape == verts.shape
    assert cKDTree(verts).query(other)[0].max() < 1e-5 and cKDTree(other).query(verts)[0].max() < 1e-5


def test_skipped_frames_and_rejected_inputs() -> None:
    volume = TSDFVolume(voxel_size_m=0.05, depth_max_m=3.0)
    T = np.eye(4)
    zeros = np.zeros((INTR.height, INTR.width), np.float32)
    assert not volume.integrate(zeros, T, INTR)
    assert not volume.integrate(np.full_like(zeros, np.nan), T, INTR)
    assert not volume.integrate(np.full_like(zeros, 5.0), T, INTR)  # all beyond depth_max_m
    assert (volume.n_skipped, volume.n_integrated) == (3, 0)
    assert len(volume.extract_mesh().triangles) == 0
    assert len(volume.surface_voxels().tsdf) == 0
    bad = T.copy()
    bad[0, 3] = np.nan
    with pytest.raises(InputError):
        volume.integrate(np.ones_like(zeros), bad, INTR)
    with pytest.raises(InputError):
        volume.integrate(np.ones((10, 10), np.float32), T, INTR)
    with pytest.raises(InputError):
        volume.integrate(np.ones_like(zeros), T, INTR, rgb=np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(InputError):
        TSDFVolume(voxel_size_m=0.02, sdf_trunc_m=0.01)
    # A partly invalid frame is fused, its invalid pixels ignored.
    depth = np.ones_like(zeros)
    depth[:, :40] = np.nan
    assert volume.integrate(depth, T, INTR)
    assert (volume.n_skipped, volume.n_integrated) == (3, 1)


def test_colour_is_fused_and_mesh_saved(tmp_path: Path) -> None:
    volume = TSDFVolume(voxel_size_m=0.04)
    depth = np.full((INTR.height, INTR.width), 1.5, np.float32)
    rgb = np.zeros((INTR.height, INTR.width, 3), np.uint8)
    rgb[..., 0] = 200
    assert volume.integrate(depth, np.eye(4), INTR, rgb)
    path = tmp_path / "mesh.ply"
    saved = volume.save_mesh(path)
    assert saved.has_vertex_colors()
    np.testing.assert_allclose(np.asarray(saved.vertex_colors).mean(0), [200 / 255, 0, 0], atol=1e-3)
    loaded = o3d.io.read_triangle_mesh(str(path))
    assert len(loaded.triangles) == len(saved.triangles) > 0
    assert [p.name for p in tmp_path.iterdir()] == ["mesh.ply"]
    # min_weight counts frames: one frame is not enough for min_weight 2.
    assert len(volume.extract_mesh(min_weight=2).triangles) == 0


def test_office0_raycast_fusion_recall(office0: Path) -> None:
    """Ten office0 views ray-cast at 160x90 and fused at 2 cm cover what they saw (recall@5cm)."""
    gt = o3d.io.read_triangle_mesh(str(office0 / "office0_mesh.ply"))
    intr = load_cam_params(office0 / "cam_params.json").resized(160, 90)
    poses = load_traj(office0 / "office0" / "traj.txt")[0:1000:100]
    scene = raycasting_scene(gt)
    frames = [(raycast_depth(scene, T, intr), T, None) for T in poses]
    mesh = tsdf_mesh_from_depths(frames, intr, voxel_size_m=0.02)
    m = mesh_metrics(mesh, gt, n_samples=100_000, observed_poses=poses, intr=intr)
    assert m["recall@5cm"] > 0.97 and m["precision@5cm"] > 0.97
    assert m["recall@1cm"] > 0.85 and m["precision@1cm"] > 0.85
    assert 0.05 < m["gt_observed_fraction"] < 0.95


def test_reserve_ahead_grows_the_block_map_before_it_is_full_and_changes_no_value() -> None:
    """The block hash map doubles once more than half of it is used (the rehash out of a time-critical fusion)."""
    intr = Intrinsics(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)
    depth = np.full((24, 32), 1.5, np.float32)
    a, b = TSDFVolume(0.05, block_count=8), TSDFVolume(0.05, block_count=8)
    assert not a.reserve_ahead()  # empty: nothing to do
    a.integrate(depth, np.eye(4), intr)
    b.integrate(depth, np.eye(4), intr)
    hm = a.vbg.hashmap()
    cap = hm.capacity()
    assert hm.size() > cap // 2 and a.reserve_ahead() and hm.capacity() == 2 * cap
    assert not a.reserve_ahead(max_fill=1.0)
    va, vb = a.surface_voxels(), b.surface_voxels()
    np.testing.assert_array_equal(va.centres_m, vb.centres_m)


def test_a_volume_without_colour_holds_the_same_geometry_in_a_smaller_block_map() -> None:
    """The scoring TSDF stores no colour: its surface voxels, normals and frontier equal a coloured volume's,
    its blocks take 8 bytes a voxel instead of 20 (a 2.5x cheaper allocation when open3d grows the map with the
    GIL held), and colour given to it is refused by name."""
    intr = Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5)
    rng = np.random.default_rng(5)
    a, b = TSDFVolume(0.05), TSDFVolume(0.05, with_color=False)
    for T in ring_poses(n=6):
        depth = np.full((48, 64), 2.0, np.float32) + rng.uniform(-0.05, 0.05, (48, 64)).astype(np.float32)
        a.integrate(depth, T, intr, rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
        b.integrate(depth, T, intr)
    va, vb = a.surface_voxels(), b.surface_voxels()
    assert len(va.centres_m) > 100
    for name in va._fields:
        np.testing.assert_array_equal(getattr(va, name), getattr(vb, name))
    np.testing.assert_array_equal(a.frontier_mask(va), b.frontier_mask(vb))
    for vol, per_voxel in ((a, 20), (b, 8)):  # bytes a voxel over the whole capacity
        hm = vol.vbg.hashmap()
        total = sum(v.numpy().nbytes for v in hm.value_tensors())
        assert total == per_voxel * hm.capacity() * vol.block_resolution**3
    assert not b.has_color
    with pytest.raises(InputError, match="rgb"):
        b.integrate(np.full((48, 64), 2.0, np.float32), np.eye(4), intr, np.zeros((48, 64, 3), np.uint8))


def test_mesh_colours_are_clamped_to_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """Marching cubes interpolates fused colour to just past 1 (1.0000001 on the demo's map): the mesh clamps it, as
    open3d's PLY writer did with a "Write Ply clamped color value" warning in every run."""
    volume = TSDFVolume(voxel_size_m=0.04)
    depth = np.full((INTR.height, INTR.width), 1.5, np.float32)
    assert volume.integrate(depth, np.eye(4), INTR, np.full((INTR.height, INTR.width, 3), 255, np.uint8))
    canonical = tsdf.canonical_mesh

    def past_one(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
        out = canonical(mesh)
        out.vertex_colors = o3d.utility.Vector3dVector(np.asarray(out.vertex_colors) * (1 + 1e-7))
        return out

    monkeypatch.setattr(tsdf, "canonical_mesh", past_one)
    colours = np.asarray(volume.extract_mesh().vertex_colors)
    assert len(colours) > 0 and colours.max() == 1.0
