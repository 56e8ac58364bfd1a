#!/usr/bin/env python3
r"""A bench with the carved unseen term carved from the keyframes' captured depth (issue 10, thirty-ninth session).

``unseen_source=carved`` carves its grid from the map's median depth rendered at each keyframe, and where the map
renders nothing there it carves free space up to ``far_m``: a hole in the map over surface the keyframe did see then
carves the space behind that surface as observed. A robot has the keyframes' own depth images. This runs ``roigsf
bench`` with the arguments given after ``--`` and, for the run's duration, replaces
:func:`roigsf_ros.nbv.unseen.carved_space` by a carve from the depth of the scene's frame at each keyframe pose
(matched exactly; a valid depth carves up to it, a pixel without one carves free space up to ``far_m``, as the map's
empty pixels do). Only policies with ``unseen_source=carved`` are affected: run the variant alone in its bench, beside
a bench of the plain variant. The scene must be a Replica-layout folder at the bench's image size (no ``--width``).
Writes ``--out`` (JSON: the calls and how far the closest frame's pose was from each keyframe pose, 0 when matched).

    .venv/bin/python scripts/carve_from_captured.py --out runs/s39/captured_shelf.json -- --scene runs/shelf_dome_120 \
        --setting pool --seeds 3 --overwrite --set densify_stride=2 --pool-set n_views=20 --pool-set pool_stride=2 \
        --pool-set initial_iters=60 --pool-set iters_per_view=20 --pool-set mesh_samples=50000 \
        --uncertainty-views 6 --uncertainty-maps 3 --policies roi-gsurfisher:unseen_weight=1:unseen_source=carved \
        --out runs/s39/bench_pool_shelf_Vc
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from roigsf_ros.cli import main as roigsf_main
from roigsf_ros.cli import wrapped_command_args
from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import write_json
from roigsf_ros.data.replica import ReplicaSequence
from roigsf_ros.mapping.observed_space import ObservedSpace
from roigsf_ros.nbv import unseen as unseen_module

POSE_MATCH_TOL = 1e-6
"""Largest distance (metres of the centre plus the rotation matrices' absolute differences) between a keyframe pose
and the frame it is matched to: the pool's keyframes are the scene's frames, so the match is exact."""


def captured_carver(scene: Path, log: dict[str, Any]) -> Callable[..., ObservedSpace]:
    """A stand-in for ``carved_space`` that carves from the captured depth of ``scene``'s frames at the keyframe poses;
    it counts its calls and the largest pose mismatch in ``log``.
    """
    seq = ReplicaSequence(scene)
    depths: dict[int, np.ndarray] = {}

    def depth_at(T_wc: np.ndarray) -> np.ndarray:
        err = np.linalg.norm(seq.poses[:, :3, 3] - T_wc[:3, 3], axis=1)
        err += np.abs(seq.poses[:, :3, :3] - T_wc[:3, :3]).sum(axis=(1, 2))
        k = int(np.argmin(err))
        log["max_pose_error"] = max(log["max_pose_error"], float(err[k]))
        if err[k] > POSE_MATCH_TOL:
            raise InputError(
                str(scene), f"no frame has the keyframe pose at {T_wc[:3, 3]} (closest off by {err[k]:.3g})"
            )
        if k not in depths:
            depths[k] = seq.frame(k).depth_m.astype(np.float64)
        return depths[k]

    def carve(
        _surfel_map: object,
        poses: Sequence[np.ndarray] | np.ndarray,
        intr: Intrinsics,
        lo_m: np.ndarray,
        hi_m: np.ndarray,
        cfg: Any,
        _should_stop: object = None,
    ) -> ObservedSpace:
        pose_arr = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        depth = np.zeros((len(pose_arr), intr.height, intr.width))
        for i, T in enumerate(pose_arr):
            d = depth_at(T)
            if d.shape != depth.shape[1:]:
                raise InputError(
                    str(scene), f"frames are {d.shape[::-1]}, the scoring is at {intr.width}x{intr.height}"
                )
            depth[i] = np.where(d > 0, d, np.inf)  # no return: free up to far_m, as where the map renders nothing
        log["calls"] += 1
        return ObservedSpace.carve(lo_m, hi_m, cfg.unseen_voxel_m, pose_arr, depth, intr, cfg.far_m)

    return carve


def main(argv: list[str] | None = None) -> int:
    """Run the bench with the captured carve in place, then restore the scorer's and write the call log as JSON."""
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     usage="%(prog)s --out JSON -- --scene DIR <roigsf bench arguments>")  # fmt: skip
    parser.add_argument("--out", required=True, type=Path, help="JSON file of the call log")
    args, bench_args = wrapped_command_args(parser, argv)
    if "--scene" not in bench_args[:-1]:
        parser.error("the bench's arguments must give --scene DIR: its captured depth is what this carves")
    scene = Path(bench_args[bench_args.index("--scene") + 1])
    log: dict[str, Any] = {"calls": 0, "max_pose_error": 0.0}
    try:
        carve = captured_carver(scene, log)
    except InputError as exc:
        print(f"carve_from_captured.py: error: {exc}", file=sys.stderr)
        return 2
    original = unseen_module.carved_space
    unseen_module.carved_space = carve  # type: ignore[assignment]
    try:
        rc = roigsf_main(["bench", *bench_args])
    finally:
        unseen_module.carved_space = original
    if rc:
        return int(rc)  # the bench failed (it said why): no log that looks complete
    write_json(args.out, {"bench_args": bench_args, **log})
    print(f"captured carve: {log['calls']} calls, largest pose mismatch {log['max_pose_error']:.2g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
