"""2DGS renderer speed: forward, forward+backward and exact geometric Fisher in a synthetic room.

The scene: surfels sampled by area on the floor, ceiling and walls of a 5 x 4 x 2.7 m room and on
three boxes, oriented with the surfaces (small jitter), seen from a camera in the middle of the
room (90 deg horizontal field of view). Timings are medians over ``--repeats`` after one warm-up,
float32 on the CPU with 2 threads (torch and numba), the numba backend unless ``--backend torch``;
JSON also records process CPU time. ``--device cuda`` times the torch backend on the GPU instead (each
timed call ends with ``torch.cuda.synchronize()``, so the times are the GPU's work, not its launch).
"fwd" builds the autograd graph as training does; "fwd+bwd" adds the backward pass of a loss over
colour, depth and alpha; "Fisher" is the exact geometric Fisher (means, quats, log_scales) of colour + depth
for one view, measured in the same run as the forward+backward it is compared with. Environment (set
before Python starts; results do not change): ``MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000`` make runs
faster and steadier on this kind of VM; on a machine shared with other busy processes, torch's OpenMP workers
spin between operations and steal the cores (2 torch threads measured 5-10x slower there) unless
``OMP_WAIT_POLICY=PASSIVE`` is set (or ``--torch-threads 1``). The numba workers are pinned one per CPU when
they use every CPU (:func:`~roigsf_ros.render.numba_setup.pin_workers`; not with ``ROIGSF_PIN_THREADS=0``), so
the timings do not depend on where the scheduler puts them; the JSON's ``pinned_workers`` says how many were.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.perf import MAX_THREADS, check_options, check_out_file, environment, threads_text, write_results
from roigsf_ros.render.fisher import GEOMETRIC_PARAMS, fisher_diag
from roigsf_ros.render.numba_setup import (
    PIN_ENV,
    numba_available,
    pin_workers,
    pinned_workers,
    set_numba_threads,
)
from roigsf_ros.render.rasterize import render_map
from roigsf_ros.render.surfels import SH_C0, SurfelMap, check_device, frame_from_normals, rotmat_to_quat

ROOM = (5.0, 4.0, 2.7)  # x, y extent (centred on 0) and height (z up, floor at 0), metres
BOXES = (((1.2, 0.8, 0.0), (0.8, 0.6, 0.9)), ((-1.5, -1.0, 0.0), (0.6, 1.0, 0.5)), ((0.5, -1.4, 0.0), (1.0, 0.5, 1.2)))
CASES = ((160, 120, 5_000), (160, 120, 20_000), (160, 120, 50_000), (320, 240, 20_000))
FISHER_CASE = (160, 120, 20_000)
TARGET_FWD_MS = 10.0
"""Target of the forward at 160x120 with 20k surfels (issue 12), milliseconds."""
TARGET_FWD_BWD_MS = 25.0
"""Target of the forward+backward at 160x120 with 20k surfels (issue 12), milliseconds."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``roigsf perf render``."""
    parser.add_argument("--out", type=Path, metavar="FILE.json", help="also write the results as JSON here")
    parser.add_argument("--repeats", type=int, default=7, metavar="N", help="timed repeats; medians (default 7)")
    parser.add_argument("--threads", type=int, default=2, metavar="T", help="numba kernel threads (default 2)")
    parser.add_argument(
        "--torch-threads", type=int, default=None, metavar="T", help="torch intra-op threads (default: --threads)"
    )
    parser.add_argument(
        "--backend", choices=("auto", "numba", "torch"), default="auto", help="renderer backend (default auto)"
    )
    parser.add_argument(
        "--device",
        default="cpu",
        metavar="DEV",
        help="torch device of the surfels: cpu (default) or cuda[:N] (the torch backend)",
    )


def _rects() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Room and box faces as (corner, edge u, edge v); normals u x v point into the free space."""
    sx, sy, sz = ROOM
    x0, y0 = -sx / 2, -sy / 2
    e = np.eye(3)
    faces = [
        (np.array([x0, y0, 0.0]), sx * e[0], sy * e[1]),  # floor, normal +z
        (np.array([x0, y0, sz]), sy * e[1], sx * e[0]),  # ceiling, normal -z
        (np.array([x0, y0, 0.0]), sy * e[1], sz * e[2]),  # wall x = x0, normal +x
        (np.array([-x0, y0, 0.0]), sz * e[2], sy * e[1]),  # wall x = -x0, normal -x
        (np.array([x0, y0, 0.0]), sz * e[2], sx * e[0]),  # wall y = y0, normal +y
        (np.array([x0, -y0, 0.0]), sx * e[0], sz * e[2]),  # wall y = -y0, normal -y
    ]
    for (cx, cy, cz), (bx, by, bz) in BOXES:
        o = np.array([cx - bx / 2, cy - by / 2, cz])
        faces += [
            (o + bz * e[2], bx * e[0], by * e[1]),  # top, +z
            (o, by * e[1], bz * e[2]),  # -x side: u x v = +x, flip below
            (o + bx * e[0], by * e[1], bz * e[2]),  # +x side
            (o, bx * e[0], bz * e[2]),  # -y side: u x v = -y
            (o + by * e[1], bx * e[0], bz * e[2]),  # +y side: flip below
        ]
    out = []
    for k, (c, u, v) in enumerate(faces):
        if k >= 6 and (k - 6) % 5 in (1, 4):  # outward normals for box sides
            u, v = v, u
        out.append((c, u, v))
    return out


def room_scene(n: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> SurfelMap:
    """``n`` surfels on the room's surfaces (uniform by area), isotropic scale 0.8 x mean spacing."""
    rng = np.random.default_rng(seed)
    rects = _rects()
    areas = np.array([np.linalg.norm(np.cross(u, v)) for _, u, v in rects])
    face = rng.choice(len(rects), size=n, p=areas / areas.sum())
    st = rng.random((n, 2))
    corner = np.stack([rects[f][0] for f in face])
    eu = np.stack([rects[f][1] for f in face])
    ev = np.stack([rects[f][2] for f in face])
    means = corner + st[:, :1] * eu + st[:, 1:] * ev
    normals = np.cross(eu, ev)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals += rng.normal(scale=0.05, size=normals.shape)
    rot = frame_from_normals(torch.from_numpy(normals), torch.tensor([0.3, 0.5, 0.8], dtype=torch.float64))
    spacing = math.sqrt(areas.sum() / n)
    log_s = np.log(0.8 * spacing * rng.uniform(0.8, 1.25, size=(n, 2)))
    opac = rng.uniform(0.5, 0.95, size=n)
    col = 0.25 + 0.5 * rng.random((n, 3))
    m = SurfelMap(
        means=torch.from_numpy(means),
        quats=rotmat_to_quat(rot),
        log_scales=torch.from_numpy(log_s),
        opacity_logits=torch.from_numpy(np.log(opac / (1 - opac))),
        sh_dc=torch.from_numpy((col - 0.5) / SH_C0),
    )
    return m.to(dtype=dtype)


def room_camera(width: int, height: int, yaw_deg: float = 20.0) -> tuple[np.ndarray, Intrinsics]:
    """Camera-to-world pose in the middle of the room at 1.4 m, looking horizontally; 90 deg HFOV."""
    yaw = math.radians(yaw_deg)
    fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    right = np.cross(down, fwd)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, fwd], axis=1)  # OpenCV: x right, y down, z forward
    T[:3, 3] = [0.2, 0.1, 1.4]
    f = width / 2.0
    return T, Intrinsics(width, height, f, f, (width - 1) / 2, (height - 1) / 2)


def _time(fn: Callable[[], Any], repeats: int, device: torch.device) -> tuple[float, float]:
    """Median wall-clock and median process CPU milliseconds of ``fn`` after one warm-up call (on a GPU, up to
    the end of the work it queued).
    """
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    fn()
    sync()
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        sync()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall) * 1e3, statistics.median(cpu) * 1e3


def bench_case(
    width: int, height: int, n: int, repeats: int, fisher: bool, backend: str, device: torch.device | None = None
) -> dict[str, Any]:
    """Median milliseconds of forward (with and without graph), forward+backward, and optionally Fisher."""
    device = device or torch.device("cpu")
    m = room_scene(n).to(device=device).requires_grad_()
    T_wc, intr = room_camera(width, height)

    def forward() -> Any:
        return render_map(m, T_wc, intr, backend=backend)

    def forward_backward() -> None:
        out = render_map(m, T_wc, intr, backend=backend)
        loss = out.color.sum() + out.depth.sum() + out.alpha.sum()
        loss.backward()
        for p in m.parameters():
            p.grad = None

    def forward_nograd() -> None:
        with torch.no_grad():
            render_map(m, T_wc, intr, backend=backend)

    with torch.no_grad():
        out = render_map(m, T_wc, intr, backend=backend)
    row: dict[str, Any] = {
        "width": width,
        "height": height,
        "surfels": n,
        "visible_surfels": int(out.visible.sum()),
        "mean_contributors_per_pixel": float(out.n_contrib.float().mean()),
        "max_contributors_per_pixel": int(out.n_contrib.max()),
        "min_alpha": float(out.alpha.min()),
    }
    timed = {"forward": forward, "forward_nograd": forward_nograd, "forward_backward": forward_backward}
    if fisher:
        md = m.detach()
        timed["fisher_geometric"] = lambda: fisher_diag(
            md, T_wc, intr, outputs=("color", "depth"), params=GEOMETRIC_PARAMS, backend=backend
        )
    for name, fn in timed.items():
        row[f"{name}_ms"], row[f"{name}_cpu_ms"] = _time(fn, repeats, device)
    if fisher:
        row["fisher_over_forward_backward"] = row["fisher_geometric_ms"] / row["forward_backward_ms"]
    return row


def run(args: argparse.Namespace) -> int:
    """Run every case, print a table, optionally write JSON."""
    check_options(args, {"repeats": 1, "threads": 1, "torch_threads": 1}, most=dict.fromkeys(
        ("threads", "torch_threads"), MAX_THREADS))  # fmt: skip
    check_out_file(args.out, "render")
    torch.set_num_threads(args.torch_threads or args.threads)
    device = check_device(args.device, "--device")
    backend = args.backend
    numba_threads = None
    if device.type != "cpu":
        if backend == "numba":
            raise InputError("--backend", f"numba runs on the CPU only, not on --device {args.device}")
        backend = "torch"
    elif backend != "torch" and numba_available():
        numba_threads = set_numba_threads(args.threads)
        pin_workers()  # one worker per CPU where they use every CPU: no scheduler modes in the timings
        backend = "numba"
    elif backend == "numba":
        raise InputError("--backend", "numba is not installed")
    else:
        backend = "torch"
    load_before = os.getloadavg()[0]
    rows = [bench_case(w, h, n, args.repeats, (w, h, n) == FISHER_CASE, backend, device) for w, h, n in CASES]
    result = {
        "benchmark": "render",
        "backend": backend,
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "environment": environment(load_before),
        "numba_threads": numba_threads,  # fewer than asked where numba has fewer (its most: the CPUs)
        "env": {
            k: os.environ.get(k) for k in ("MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_", "OMP_WAIT_POLICY", PIN_ENV)
        },
        "pinned_workers": len(pinned_workers()),
        "repeats": args.repeats,
        "targets_ms": {"forward_160x120_20k": TARGET_FWD_MS, "forward_backward_160x120_20k": TARGET_FWD_BWD_MS},
        "cases": rows,
    }
    head = f"{'size':>9} {'surfels':>8} {'visible':>8} {'contrib/px':>10} {'fwd':>8} {'fwd no-grad':>11} {'fwd+bwd':>8}"
    print(head + f" {'Fisher':>8} {'ratio':>6}")
    for r in rows:
        fisher = (
            f" {r['fisher_geometric_ms']:8.1f} {r['fisher_over_forward_backward']:6.2f}"
            if "fisher_geometric_ms" in r
            else ""
        )
        print(
            f"{r['width']:>4}x{r['height']:<4} {r['surfels']:8d} {r['visible_surfels']:8d} "
            f"{r['mean_contributors_per_pixel']:10.1f} {r['forward_ms']:8.1f} {r['forward_nograd_ms']:11.1f} "
            f"{r['forward_backward_ms']:8.1f}{fisher}"
        )
    threads = threads_text(args.threads, numba_threads, result["threads"])
    print(
        f"(backend {backend} on {result['device_name'] or 'the CPU'}, {threads}; wall-clock milliseconds, medians; "
        "targets at "
        f"160x120 with 20k surfels: fwd <= "
        f"{TARGET_FWD_MS:g}, fwd+bwd <= {TARGET_FWD_BWD_MS:g}, Fisher <= fwd+bwd; 1-min load average "
        f"{result['environment']['load_average_1min'][0]:.1f} -> "
        f"{result['environment']['load_average_1min'][1]:.1f}: other processes inflate these times)"
    )
    write_results(args.out, result)
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m roigsf_ros.perf.render``: this benchmark alone, for a machine with torch but without the CLI's
    other dependencies (ROS, open3d, rosbags), such as a lent GPU box (``scripts/device_check.sh``).
    """
    parser = argparse.ArgumentParser(prog="python -m roigsf_ros.perf.render", description=__doc__)
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run(args)
    except InputError as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
