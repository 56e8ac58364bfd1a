"""The mapper with ``device: cuda`` against the same mapper on the CPU (skipped without a CUDA device).

Run where a GPU is lent (``scripts/device_check.sh``). The frames are rendered from the renderer benchmark's
surfel room, and nothing here imports open3d, ROS or rosbags, so the test runs on a GPU box that has torch alone.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from roigsf_ros.core.frame import Frame
from roigsf_ros.mapping.mapper import Mapper, MapperConfig
from roigsf_ros.perf.render import room_camera, room_scene
from roigsf_ros.render.rasterize import render_map

pytestmark = pytest.mark.skipif(
    not torch.cuda.is_available(),
    reason="no CUDA device: the mapper's CUDA path is checked where a GPU is lent (scripts/device_check.sh)",
)

WIDTH, HEIGHT = 80, 60


def room_frame(index: int, yaw_deg: float) -> Frame:
    """Colour and expected depth of the benchmark room (20k surfels) from its centre, looking at ``yaw_deg``."""
    T_wc, intr = room_camera(WIDTH, HEIGHT, yaw_deg)
    with torch.no_grad():
        out = render_map(room_scene(20_000), T_wc, intr)
    rgb = (out.color.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    depth = torch.where(out.alpha > 0.5, out.expected_depth(), 0.0).numpy().astype(np.float32)
    return Frame(index=index, rgb=rgb, depth_m=depth, T_wc=T_wc)


def held_out_quality(mapper: Mapper, frame: Frame) -> tuple[float, float]:
    """PSNR (dB) and depth L1 (m, where the frame has depth) of the map at ``frame``'s pose."""
    out = mapper.render(frame.T_wc)
    rgb = out.color.detach().clamp(0, 1).cpu().numpy()
    mse = float(np.mean((rgb - frame.rgb / 255.0) ** 2))
    depth = out.expected_depth().detach().cpu().numpy()
    valid = frame.depth_m > 0
    return -10.0 * math.log10(mse), float(np.abs(depth - frame.depth_m)[valid].mean())


def test_cuda_mapper_matches_the_cpu_mapper() -> None:
    """Five keyframes mapped on CUDA (torch renderer, torch Adam) and on the CPU (numba): maps of the same size and
    the same held-out quality, with the map and ``h_train`` on the device they were asked for."""
    intr = room_camera(WIDTH, HEIGHT)[1]
    train = [room_frame(i, yaw) for i, yaw in enumerate((-40.0, -10.0, 20.0, 50.0, 80.0))]
    held_out = room_frame(9, 35.0)
    results = {}
    for device in ("cpu", "cuda"):
        mapper = Mapper(intr, MapperConfig(iters_per_keyframe=20, seed=3, device=device))
        for f in train:
            assert mapper.add_keyframe(f)
        assert all(p.device.type == device for p in mapper.map.parameters())
        h_train = mapper.h_train
        assert all(h.device.type == device and bool(torch.isfinite(h).all()) for h in h_train.values())
        assert float(h_train["means"].sum()) > 0
        stats = mapper.stats
        assert stats.steps == 5 * 20 and stats.steps_skipped_nonfinite == 0
        results[device] = (*held_out_quality(mapper, held_out), mapper.n_surfels)
    (psnr_cpu, l1_cpu, n_cpu), (psnr_cuda, l1_cuda, n_cuda) = results["cpu"], results["cuda"]
    assert psnr_cpu > 20.0 and l1_cpu < 0.05, results  # the CPU mapper learns the room: the comparison means something
    assert abs(psnr_cuda - psnr_cpu) < 0.5, results
    assert abs(l1_cuda - l1_cpu) < 0.01, results
    assert abs(n_cuda - n_cpu) <= 0.02 * n_cpu, results
