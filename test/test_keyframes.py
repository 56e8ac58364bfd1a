"""Keyframe policies: registry, every-n ids, and GauS-SLAM's unmapped-pixel rule on a ray-cast room."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame
from roigsf_ros.mapping.mapper import Mapper, MapperConfig
from roigsf_ros.policies.base import KeyframePolicy, make_policy, policy_names, register_policy
from roigsf_ros.policies.rules import GausSlam

INTR = Intrinsics(width=48, height=36, fx=40.0, fy=40.0, cx=23.5, cy=17.5)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def room_frame(index: int, T_wc: np.ndarray) -> Frame:
    """Ray-cast a 4 x 3 x 2.5 m box room with a smooth procedural texture at ``T_wc``."""
    box = o3d.geometry.TriangleMesh.create_box(4.0, 3.0, 2.5).translate((-2.0, -1.5, 0.0))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(box))
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float64)  # pixel centres at integers
    d_cam = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)], -1)
    d_w = d_cam @ T_wc[:3, :3].T  # camera z = 1, so the hit distance t is the z-depth
    rays = np.concatenate([np.broadcast_to(T_wc[:3, 3], d_w.shape), d_w], -1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    hit = np.isfinite(t)
    pts = T_wc[:3, 3] + d_w * np.where(hit, t, 0)[..., None]
    rgb = 0.5 + 0.35 * np.sin(np.stack([3 * pts[..., 0] + pts[..., 2], 4 * pts[..., 1], 5 * pts[..., 2]], -1))
    depth = np.where(hit, t, 0.0).astype(np.float32)
    return Frame(index=index, rgb=(rgb * 255).astype(np.uint8), depth_m=depth, T_wc=T_wc)


def test_registry_and_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    from roigsf_ros.policies import base

    monkeypatch.setattr(base, "_REGISTRY", dict(base._REGISTRY))  # test-odd below: registered for this test only
    assert {"all", "every-n", "gaus-slam"} <= set(policy_names())
    assert isinstance(make_policy("gaus-slam"), GausSlam)
    assert make_policy("gaus-slam", tau_k=0.2, n=None).tau_k == 0.2  # None-valued params are dropped
    with pytest.raises(InputError, match="unknown keyframe policy"):
        make_policy("nope")
    with pytest.raises(InputError, match="takes no parameter"):
        make_policy("gaus-slam", n=3)
    with pytest.raises(InputError, match=r"^n: must be at least 1"):  # the field, no CLI flag: callers rename it
        make_policy("every-n", n=0)
    with pytest.raises(InputError, match=r"^tau_k: must be in \[0, 1\)"):
        make_policy("gaus-slam", tau_k=1.5)

    @register_policy("test-odd")
    class Odd(KeyframePolicy):
        def observe(self, frame: Frame, mapper: Mapper) -> list[Frame]:
            return [frame] if frame.index % 2 == 1 else []

    assert "test-odd" in policy_names() and make_policy("test-odd").name == "test-odd"
    with pytest.raises(ValueError, match="twice"):
        register_policy("test-odd")(Odd)


def test_every_n_and_all_pick_the_right_ids() -> None:
    frames = [Frame(index=10 * i + 3, rgb=np.zeros((1, 1, 3), np.uint8), depth_m=np.zeros((1, 1)), T_wc=np.eye(4))
              for i in range(11)]  # fmt: skip
    pol = make_policy("every-n", n=4)
    picked = [f.index for f in frames if pol.observe(f, None)]
    assert picked == [3, 43, 83]  # arrival order 0, 4, 8 whatever the frame numbers
    pol.reset()
    assert [f.index for f in frames[:5] if pol.observe(f, None)] == [3, 43]
    assert all(make_policy("all").observe(f, None) for f in frames)


def test_gaus_slam_rule() -> None:
    mapper = Mapper(INTR, MapperConfig(iters_per_keyframe=15, track_h_train=False))
    pol = make_policy("gaus-slam")  # tau_k = 0.01, alpha threshold 0.5
    first = room_frame(0, look_at((0.0, 0.0, 1.2), (2.0, 0.2, 1.0)))  # looking at the +x wall
    assert pol.observe(first, mapper)  # empty map: always a keyframe
    assert mapper.add_keyframe(first)

    # The same view is fully explained by the map: not a keyframe.
    again = room_frame(1, first.T_wc.copy())
    assert not pol.observe(again, mapper)
    assert pol.last_unmapped_fraction <= 0.01

    # Looking the other way (the -x wall, never seen): a keyframe, nearly every pixel unmapped.
    back = room_frame(2, look_at((0.0, 0.0, 1.2), (-2.0, -0.2, 1.0)))
    assert pol.observe(back, mapper)
    assert pol.last_unmapped_fraction > 0.9

    # A small turn reveals a sliver of new wall: more than 1 % unmapped, so a keyframe.
    turn = room_frame(3, look_at((0.0, 0.0, 1.2), (2.0, 1.2, 1.0)))
    assert pol.observe(turn, mapper)
    assert 0.01 < pol.last_unmapped_fraction < 0.9
    # ... but not with a tolerant tau_k above that fraction.
    assert not make_policy("gaus-slam", tau_k=min(0.99, pol.last_unmapped_fraction + 0.05)).observe(turn, mapper)

    # A camera that sees nothing (no valid depth) has nothing unmapped: not a keyframe.
    blind = Frame(index=4, rgb=first.rgb, depth_m=np.zeros_like(first.depth_m), T_wc=first.T_wc)
    assert not pol.observe(blind, mapper)
