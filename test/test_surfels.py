"""SurfelMap: activations, container operations, 2DGS PLY layout and round trip, RGB-D seeding."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.render.rasterize import render_map
from roigsf_ros.render.surfels import SH_C0, SurfelMap, quat_to_rotmat, rotmat_to_quat, surfels_from_rgbd

# The vertex properties hbb1/2d-gaussian-splatting writes (construct_list_of_attributes, SH degree 1).
FIELDS_2DGS_DEG1 = [
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    "f_rest_0", "f_rest_1", "f_rest_2", "f_rest_3", "f_rest_4", "f_rest_5", "f_rest_6", "f_rest_7", "f_rest_8",
    "opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3",
]  # fmt: skip


def random_map(n: int = 50, seed: int = 0, sh_rest: bool = True) -> SurfelMap:
    g = torch.Generator().manual_seed(seed)
    return SurfelMap(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 2, generator=g) - 3,
        opacity_logits=torch.randn(n, generator=g),
        sh_dc=torch.randn(n, 3, generator=g),
        sh_rest=torch.randn(n, 3, 3, generator=g) if sh_rest else None,
    )


def read_header(path) -> tuple[list[str], int]:
    raw = path.read_bytes()
    head = raw[: raw.index(b"end_header\n") + len(b"end_header\n")]
    return head.decode("ascii").splitlines(), len(head)


def test_rotations_orthonormal_and_normal_is_tu_cross_tv() -> None:
    m = random_map(200)
    R = m.rotations()
    eye = torch.eye(3).expand(200, 3, 3)
    assert torch.allclose(R.transpose(1, 2) @ R, eye, atol=1e-5)
    assert torch.allclose(torch.linalg.det(R), torch.ones(200), atol=1e-5)
    assert torch.allclose(torch.linalg.cross(R[..., 0], R[..., 1], dim=-1), R[..., 2], atol=1e-5)
    assert torch.allclose(m.normals(), R[..., 2])
    # w, x, y, z convention: a rotation by 90 deg about z maps x to y.
    q = torch.tensor([[math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]])
    x_axis, y_axis = torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0])
    assert torch.allclose(quat_to_rotmat(q)[0] @ x_axis, y_axis, atol=1e-6)


def test_rotmat_to_quat_round_trip() -> None:
    q = torch.randn(500, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    R = quat_to_rotmat(q)
    q2 = rotmat_to_quat(R)
    assert torch.all(q2[:, 0] >= 0)
    assert torch.allclose(quat_to_rotmat(q2), R, atol=1e-12)


def test_activations_and_colors() -> None:
    m = random_map(10)
    assert torch.allclose(m.scales(), m.log_scales.exp())
    assert torch.allclose(m.opacities(), torch.sigmoid(m.opacity_logits))
    assert torch.allclose(m.colors(), (0.5 + SH_C0 * m.sh_dc).clamp_min(0))
    d = torch.tensor([[0.0, 0.0, 2.0]]).expand(10, 3)  # looking along +z: only the z term (coefficient 2)
    expected = (0.5 + SH_C0 * m.sh_dc + 0.4886025119029199 * m.sh_rest[:, 1]).clamp_min(0)
    assert torch.allclose(m.colors(d), expected, atol=1e-6)


def test_container_operations() -> None:
    a, b = random_map(5, 1), random_map(7, 2, sh_rest=False)
    c = a.append(b)
    assert len(c) == 12 and c.sh_rest is not None and torch.all(c.sh_rest[5:] == 0)
    keep = torch.zeros(12, dtype=torch.bool)
    keep[[0, 6]] = True
    s = c.select(keep)
    assert torch.equal(s.means, c.means[[0, 6]])
    assert len(c.prune(keep)) == 10
    e = SurfelMap.empty(sh_degree=1)
    assert len(e) == 0 and len(SurfelMap.cat([e, a])) == 5
    d = c.clone().requires_grad_()
    assert all(p.requires_grad and p.is_leaf for p in d.parameters())
    assert list(d.named_parameters()) == ["means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"]
    assert not any(p.requires_grad for p in d.detach().parameters())
    assert d.to(dtype=torch.float64).dtype == torch.float64
    with pytest.raises(InputError, match="quats"):
        SurfelMap(torch.zeros(3, 3), torch.zeros(2, 4), torch.zeros(3, 2), torch.zeros(3), torch.zeros(3, 3))


@pytest.mark.parametrize("with_rest", [True, False])
def test_ply_round_trip_exact(tmp_path, with_rest: bool) -> None:
    m = random_map(40, 5, sh_rest=with_rest)
    path = tmp_path / "point_cloud.ply"
    m.save_ply(path)
    back = SurfelMap.load_ply(path)
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        a, b = getattr(m, name), getattr(back, name)
        assert (a is None) == (b is None)
        if a is not None:
            assert torch.equal(a, b), name
    assert not list(tmp_path.glob(".*tmp*"))  # atomic write left no temporary file


def test_ply_header_is_the_2dgs_layout(tmp_path) -> None:
    m = random_map(3, 6)
    path = tmp_path / "a.ply"
    m.save_ply(path)
    lines, size = read_header(path)
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 3"]
    assert lines[3:-1] == [f"property float {f}" for f in FIELDS_2DGS_DEG1]
    assert lines[-1] == "end_header"
    rec = np.frombuffer(path.read_bytes()[size:], dtype=np.dtype([(f, "<f4") for f in FIELDS_2DGS_DEG1]))
    # f_rest is channel-major (2DGS: features_rest.transpose(1, 2).flatten): f_rest_{3 * channel + coeff}.
    assert rec["f_rest_5"][1] == m.sh_rest[1, 2, 1].item()
    assert rec["f_rest_1"][2] == m.sh_rest[2, 1, 0].item()
    assert rec["rot_0"][0] == m.quats[0, 0].item() and rec["scale_1"][0] == m.log_scales[0, 1].item()
    assert np.all(rec["nx"] == 0) and rec["opacity"][2] == m.opacity_logits[2].item()
    m0 = random_map(2, 6, sh_rest=False)
    m0.save_ply(tmp_path / "b.ply")
    assert not any("f_rest" in line for line in read_header(tmp_path / "b.ply")[0])


def test_ply_degree3_truncated_to_degree1(tmp_path) -> None:
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", *[f"f_rest_{i}" for i in range(45)]]
    names += ["opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3"]
    vals = np.arange(2 * len(names), dtype="<f4").reshape(2, -1)
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 2\n"
    header += "".join(f"property float {n}\n" for n in names) + "end_header\n"
    path = tmp_path / "deg3.ply"
    path.write_bytes(header.encode() + vals.tobytes())
    m = SurfelMap.load_ply(path)
    rest = vals[:, 6:51].reshape(2, 3, 15)[:, :, :3].transpose(0, 2, 1)
    assert np.array_equal(m.sh_rest.numpy(), rest)


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (b"not a ply at all", "not a PLY"),
        (b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n", "binary_little_endian"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n", "missing"),
    ],
)
def test_bad_ply_names_the_file(tmp_path, content: bytes, problem: str) -> None:
    path = tmp_path / "broken.ply"
    path.write_bytes(content)
    with pytest.raises(InputError, match=problem) as err:
        SurfelMap.load_ply(path)
    assert str(path) in str(err.value)
    with pytest.raises(InputError, match="not found"):
        SurfelMap.load_ply(tmp_path / "missing.ply")


def test_truncated_and_nan_ply_rejected(tmp_path) -> None:
    m = random_map(4, 7)
    path = tmp_path / "t.ply"
    m.save_ply(path)
    path.write_bytes(path.read_bytes()[:-4])
    with pytest.raises(InputError, match="truncated"):
        SurfelMap.load_ply(path)
    m.means[1, 0] = float("nan")
    m.save_ply(path)
    with pytest.raises(InputError, match="non-finite"):
        SurfelMap.load_ply(path)


def test_ply_with_bytes_after_the_vertices_is_refused_naming_the_file(tmp_path) -> None:
    """A body longer than the header's vertex count x row size is damaged, not silently read in part."""
    path = tmp_path / "map.ply"
    random_map(4, 8).save_ply(path)
    good = path.read_bytes()
    path.write_bytes(good + b"garbage!")
    with pytest.raises(InputError, match=r"8 bytes after the 4 vertices of \d+ bytes") as err:
        SurfelMap.load_ply(path)
    assert str(path) in str(err.value)
    path.write_bytes(good)
    assert len(SurfelMap.load_ply(path)) == 4


# ------------------------------------------------------------------------------------ RGB-D
def plane_scene(width: int = 64, height: int = 48):
    """Depth of the plane n . X = d (camera frame) seen by a pinhole camera, and a camera pose."""
    intr = Intrinsics(width, height, 50.0, 52.0, (width - 1) / 2, (height - 1) / 2)
    n_cam = np.array([0.3, -0.2, -1.0])
    n_cam /= np.linalg.norm(n_cam)
    d = -2.0  # plane points X with n . X = d (n faces the camera)
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([(xs - intr.cx) / intr.fx, (ys - intr.cy) / intr.fy, np.ones_like(xs)], -1)
    depth = d / (rays @ n_cam)
    c, s = math.cos(0.4), math.sin(0.4)
    T_wc = np.array([[c, 0, s, 1.0], [0, 1, 0, -0.5], [-s, 0, c, 2.0], [0, 0, 0, 1]])
    return intr, depth, T_wc, n_cam, d


@pytest.mark.parametrize("stride", [1, 3])
def test_rgbd_on_a_plane(stride: int) -> None:
    intr, depth, T_wc, n_cam, d = plane_scene()
    rgb = np.random.default_rng(0).random((intr.height, intr.width, 3))
    m = surfels_from_rgbd(rgb, depth, T_wc, intr, stride=stride, opacity=0.8, dtype=torch.float64)
    assert len(m) == len(range(stride // 2, intr.height, stride)) * len(range(stride // 2, intr.width, stride))
    R, t = T_wc[:3, :3], T_wc[:3, 3]
    n_w = R @ n_cam
    pts = m.means.numpy()
    assert np.abs(pts @ n_w - (d + n_w @ t)).max() < 1e-9  # centres on the plane (world frame)
    assert np.abs(m.normals().numpy() - n_w).max() < 1e-6  # normals = plane normal, facing the camera
    sl = (slice(stride // 2, None, stride),) * 2
    expected_s = depth[sl].reshape(-1) * stride / math.sqrt(intr.fx * intr.fy)
    assert np.allclose(m.scales().numpy(), expected_s[:, None])
    assert np.allclose(m.opacities().numpy(), 0.8)
    assert np.allclose(m.colors().numpy(), rgb[sl].reshape(-1, 3))


@pytest.mark.parametrize("max_stretch", [1.0, 1.5, 4.0])
def test_rgbd_stretch_follows_the_incidence(max_stretch: float) -> None:
    """The first axis lies along the tilt and is 1 / cos(incidence) longer, clamped at ``max_stretch``."""
    intr, depth, T_wc, n_cam, _ = plane_scene()
    rgb = np.full((intr.height, intr.width, 3), 0.5)
    m = surfels_from_rgbd(rgb, depth, T_wc, intr, max_stretch=max_stretch, dtype=torch.float64)
    ys, xs = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
    rays = np.stack([(xs - intr.cx) / intr.fx, (ys - intr.cy) / intr.fy, np.ones_like(xs)], -1).reshape(-1, 3)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    cos = np.abs(rays @ n_cam)
    footprint = depth.reshape(-1) / math.sqrt(intr.fx * intr.fy)
    scales = m.scales().numpy()
    assert np.allclose(scales[:, 1], footprint)
    assert np.allclose(scales[:, 0], footprint / np.maximum(cos, 1.0 / max_stretch))
    if max_stretch > 1.0:  # the stretched axis, in the camera frame, is the ray's part in the plane
        R = T_wc[:3, :3]
        tu_cam = (R.T @ quat_to_rotmat(m.quats).numpy()[:, :, 0].T).T
        tilt = rays - (rays @ n_cam)[:, None] * n_cam
        tilt /= np.linalg.norm(tilt, axis=-1, keepdims=True)
        assert np.abs(np.abs((tu_cam * tilt).sum(-1)) - 1.0).max() < 1e-9
    with pytest.raises(InputError, match="max_stretch"):
        surfels_from_rgbd(rgb, depth, T_wc, intr, max_stretch=0.5)


def test_rgbd_stretch_closes_the_gaps_of_a_grazing_surface() -> None:
    """Isotropic surfels seeded from a floor seen at ~80 deg leave holes in a frontal view; stretched ones do not."""
    intr = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
    T_grazing = np.eye(4)  # camera 0.3 m above the floor y = 0.3 (camera frame, y down), looking along z
    ray_y = (np.arange(48, dtype=np.float64)[:, None].repeat(64, 1) - intr.cy) / intr.fy
    depth = np.where(ray_y > 0.05, 0.3 / np.maximum(ray_y, 1e-9), 0.0)  # rows that hit the floor within 6 m
    depth[depth > 6.0] = 0.0
    rgb = np.full((48, 64, 3), 0.5)
    # A camera 1 m above the floor looking straight down at x = 0, z = 1.5 (in the frame of the first camera), where
    # the first one sees the floor at 78-80 deg.
    T_top = np.array([[1.0, 0, 0, 0.0], [0, 0, 1, -0.7], [0, -1, 0, 1.5], [0, 0, 0, 1]])
    alpha = {}
    for stretch in (1.0, 4.0):
        m = surfels_from_rgbd(rgb, depth, T_grazing, intr, opacity=0.9, scale_factor=0.7, max_stretch=stretch)
        out = render_map(m, T_top, intr, with_distortion=False)
        alpha[stretch] = out.alpha.numpy()[16:32, 16:48]  # floor 1.3-1.7 m from the first camera
    assert (alpha[1.0] < 0.5).mean() > 0.2  # gaps between the isotropic surfels
    assert (alpha[4.0] < 0.5).mean() < 0.01


def test_rgbd_skips_invalid_depth_and_mask() -> None:
    intr, depth, T_wc, _, _ = plane_scene()
    depth = depth.copy()
    depth[0, :10] = np.nan
    depth[1, :5] = 0.0
    depth[2, :3] = np.inf
    depth[3, :2] = 50.0
    mask = np.ones(depth.shape, bool)
    mask[10, :7] = False
    rgb = np.full((intr.height, intr.width, 3), 0.5)
    m = surfels_from_rgbd(rgb, depth, T_wc, intr, mask=mask, max_depth=10.0)
    assert len(m) == depth.size - 10 - 5 - 3 - 2 - 7
    assert all(torch.isfinite(p).all() for p in m.parameters())
    assert surfels_from_rgbd(rgb, np.zeros_like(depth), T_wc, intr).means.shape == (0, 3)


def test_rgbd_validates_inputs() -> None:
    intr, depth, T_wc, _, _ = plane_scene()
    rgb = np.zeros((intr.height, intr.width, 3))
    with pytest.raises(InputError, match="depth"):
        surfels_from_rgbd(rgb, depth[:-1], T_wc, intr)
    with pytest.raises(InputError, match="rgb"):
        surfels_from_rgbd(rgb[..., :2], depth, T_wc, intr)
    bad = T_wc.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError, match="T_wc"):
        surfels_from_rgbd(rgb, depth, bad, intr)
    with pytest.raises(InputError, match="stride"):
        surfels_from_rgbd(rgb, depth, T_wc, intr, stride=0)
