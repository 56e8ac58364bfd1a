"""Compile (or load from numba's disk cache) every CPU kernel mapping and NBV scoring use, on a tiny scene.

The numba kernels (rasteriser forward/backward, Fisher, ROI visibility) compile on their first call,
30-60 s on 2 cores with a cold cache: on a fresh machine the planner's first requests then took that
long and the keyframe selector decided most of the demo's first windows with its fallback.
:func:`warm_up_kernels` makes those first calls on a 32x24 textured wall (one keyframe, a few optimiser
steps, a scoring TSDF, two candidates scored in each Fisher mode and one alone, the uncertainty image), with the same
argument types as the real calls, so the real work starts compiled. With a warm cache it takes about a
second (the cached machine code is loaded). ``python -m roigsf_ros.nbv.warmup`` runs it (set-up does).
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.frame import Frame
from roigsf_ros.mapping.mapper import Mapper, MapperConfig
from roigsf_ros.nbv.config import NBVConfig
from roigsf_ros.nbv.scorer import NBVScorer
from roigsf_ros.nbv.state import ScoringState

WARMUP_INTRINSICS = Intrinsics(width=32, height=24, fx=24.0, fy=24.0, cx=15.5, cy=11.5)
"""The warm-up camera: small enough that, compiled, the whole pass takes well under a second."""

_ONCE = threading.Lock()
_DONE: list[dict[str, float]] = []


def _wall_frame(index: int, x_m: float) -> Frame:
    """A seeded random texture on a wall 1.5 m in front of a camera at (x_m, 0, 0) looking along +z."""
    rng = np.random.default_rng(index)
    h, w = WARMUP_INTRINSICS.height, WARMUP_INTRINSICS.width
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    T = np.eye(4)
    T[0, 3] = x_m
    return Frame(index=index, rgb=rgb, depth_m=np.full((h, w), 1.5, np.float32), T_wc=T)


def warm_up_kernels(nbv: NBVConfig | None = None) -> dict[str, float]:
    """Run mapping and NBV scoring once on a tiny scene so every numba kernel is compiled; seconds per phase.

    ``nbv``: the scoring settings to warm up with (default ``NBVConfig()``); both Fisher modes
    (ROI-weighted and FisherRF's) are scored whatever its mode.
    """
    nbv = nbv or NBVConfig()
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    mapper = Mapper(WARMUP_INTRINSICS, MapperConfig(iters_per_keyframe=2))
    frames = [_wall_frame(1, 0.0), _wall_frame(2, 0.1)]
    for frame in frames:
        mapper.add_keyframe(frame)  # densify, forward + backward, prune
    h_train = mapper.h_train  # the keyframes' Fisher (the geometric kernels)
    times["mapping_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    poses = np.stack([f.T_wc for f in frames])
    state = ScoringState(nbv, 0.02, 0.08, 10.0, cache_h_train=True)
    candidates = [_wall_frame(3, 0.05).T_wc, _wall_frame(4, -0.05).T_wc]
    outputs = tuple(mapper.config.fisher_outputs)
    for mode in ("roi-gsurfisher", "fisherrf"):
        state.score(mapper.map, h_train, outputs, poses, candidates, WARMUP_INTRINSICS, mapper.rendered_rgbd, mode)
    # A lone candidate: with fewer candidates than threads the ROI splits one camera's voxels (its own kernel).
    state.score(
        mapper.map, h_train, outputs, poses, candidates[:1], WARMUP_INTRINSICS, mapper.rendered_rgbd, "roi-gsurfisher"
    )
    NBVScorer(nbv).uncertainty(mapper.map, h_train, candidates[0], WARMUP_INTRINSICS, None)
    times["scoring_s"] = time.perf_counter() - t0
    times["total_s"] = times["mapping_s"] + times["scoring_s"]
    return times


def warm_up_once(nbv: NBVConfig | None = None) -> dict[str, float] | None:
    """:func:`warm_up_kernels` the first time a process calls it (its timings); None afterwards (already warm)."""
    with _ONCE:
        if _DONE:
            return None
        times = warm_up_kernels(nbv)
        _DONE.append(times)
        return times


def main() -> int:
    """``python -m roigsf_ros.nbv.warmup``: warm the kernels up and print how long it took."""
    times = warm_up_kernels()
    print(
        f"numba kernels ready in {times['total_s']:.1f} s (mapping {times['mapping_s']:.1f} s, "
        f"scoring {times['scoring_s']:.1f} s)"
    )
    return 0


__all__ = ["WARMUP_INTRINSICS", "warm_up_kernels", "warm_up_once"]


if __name__ == "__main__":
    sys.exit(main())
