"""``roigsf demo``: the main job: active mapping of the shipped bag over ROS 2, with a report.

One process: the bag player node and the three nodes of ``active_mapping`` (mapper, NBV planner, keyframe
selector: :class:`~roigsf_ros.nodes.active_mapping.ActiveMapping`, sharing one map) on one executor. The
frames still travel as ROS messages on the camera topics, but player and subscribers share one DDS
participant, so they match at once: with the player in a process of its own the first frames were lost
to discovery on a loaded machine (4 of 150 with a 1 s start delay). The player's timing does not matter
to the result (the nodes go by the messages' stamps), and the report reads the final map directly.

At the end of the stream the selector decides the frames it still holds (``~/finish``; only with its
``lookahead``), the mapper finishes its queue, the map gets ``--final-iters`` refinement
steps over all keyframes, and the run folder receives (atomically) ``metrics.json``, ``mesh.ply``,
``map.ply`` + ``keyframes.json``, ``strip.png`` (input vs rendered colour and depth of non-keyframes),
``plot.png`` (trajectory with keyframes, next to the strip) and ``replay.json`` (player and node
counters). Ctrl-C stops the player and the nodes cleanly and writes nothing.

The report reads the bag with the camera settings the mapper runs with (its camera parameters after the params
files and ``--set``), and the player plays only the topics the camera nodes read. A robot's bag (RealSense names,
pose on TF, compressed images) needs ``--realsense [NS]``: it sets those names and pose_source tf on the mapper and
the keyframe selector (and the planner's camera_info_topic), with the transports read from the bag's topic types,
over the params files. ``roigsf map``'s camera options (``--tf-child-frame``, ``--depth-transport``, ...) set one
name on both camera nodes, over ``--realsense``'s; a ``--set NODE.NAME=VALUE`` still wins. Settings with which the
mapper or the selector would read no frame of the bag are refused before anything starts, naming the parameter.

``--rate 0`` plays as fast as the nodes can take the bag without losing anything
(:class:`~roigsf_ros.nodes.lockstep.Lockstep`): each frame
waits until the nodes received the one before and have room for it. Played blindly as fast as possible, the nodes'
queues overflowed (47 of the shipped bag's 150 frames received), windows went to the fallback, and a bag's whole /tf
came before its images were decoded.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from roigsf_ros.cli import (
    add_camera_options,
    camera_options,
    camera_topics,
    check_writable,
    chosen_gt_mesh,
    metric_notes,
    realsense_hint,
)
from roigsf_ros.core.config import check_field_value
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import check_replaceable
from roigsf_ros.core.ros_domain import check_domain_id, domain_id_from_env
from roigsf_ros.data.bags import (
    SAMPLE_BAG,
    SAMPLE_GT_MESH,
    BagFrame,
    BagReader,
    bag_info,
    bag_topic_types,
    resized_frame,
    sample_path,
)
from roigsf_ros.data.replica import scene_gt_mesh
from roigsf_ros.nodes.lockstep import KEYFRAMES_NOT_MAPPED

if TYPE_CHECKING:
    import open3d as o3d

    from roigsf_ros.experiments.offline import EvalConfig
    from roigsf_ros.mapping.mapper import Mapper
    from roigsf_ros.nodes.active_mapping import ActiveMapping
    from roigsf_ros.nodes.bag_camera import BagCamera
    from roigsf_ros.nodes.bag_player import BagPlayer

DEFAULT_RATE = 1.0
"""Playback rate of the demo: real time, a window of 8 frames every 0.8 s. A planner call (ROI, Fisher of 8
candidates, the chosen view's uncertainty) takes 0.3-0.7 s at 160x120 on 2 cores beside the mapper; a window
that comes while the previous one is still being answered waits for that answer, and only a second one behind
it is decided by the fallback policy (counted; docs/measured-figures.md, "Issue 12 in the SLAM loop").
``--rate 0.25`` gives the mapper four times the optimisation per frame."""
DEFAULT_FINAL_ITERS = 150
"""Refinement steps over all keyframes after the stream (the mapper's ``final_iters`` for offline runs)."""
DEFAULT_POLICY = "roi-gsurfisher"

SUMMARY_ROWS = (
    ("frames", "n_frames", "{:d}"),
    ("keyframes", "n_keyframes", "{:d}"),
    ("surfels", "map_size", "{:d}"),
    ("PSNR non-keyframes (dB)", "psnr", "{:.2f}"),
    ("SSIM non-keyframes", "ssim", "{:.3f}"),
    ("depth L1 (cm)", "depth_l1_cm", "{:.2f}"),
    ("precision @5cm", "precision@5cm", "{:.3f}"),
    ("recall @5cm", "recall@5cm", "{:.3f}"),
    ("planner answers/calls", "planner", "{}"),
    ("fallbacks", "fallbacks", "{:d}"),
    ("keyframes not mapped", "keyframes_not_mapped", "{:d}"),
    ("slowest planner call (s)", "planner_max_scoring_s", "{:.2f}"),
    ("slowest window answer (s)", "selector_max_answer_s", "{:.2f}"),
    ("slowest novelty (s)", "selector_max_novelty_s", "{:.2f}"),
    ("longest frame gap (s)", "selector_max_frame_gap_s", "{:.2f}"),
    ("kernel warm-up (s)", "warm_up_s", "{:.1f}"),
    ("dropped frames", "dropped_frames", "{:d}"),
    ("frames TF never posed", "bag_frames_without_tf", "{:d}"),
    ("frames refused", "bag_frames_refused", "{:d}"),
    ("wall time (s)", "wall_s", "{:.1f}"),
)
"""The demo's table: label, metrics key, format."""


# ------------------------------------------------------------------------------------ evaluation
def evaluate_map(
    mapper: Mapper,
    frames: Sequence[BagFrame],
    gt_mesh: Path | None,
    eval_config: EvalConfig | None = None,
) -> tuple[dict[str, Any], list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], o3d.geometry.TriangleMesh]:
    """Image metrics on the frames that are not keyframes, mesh metrics against ``gt_mesh``, strip rows, mesh.

    ``frames`` are the recorded frames (the bag); a frame is a keyframe when its stamp is one of the
    mapper's keyframe ids (the mapper node names keyframes by stamp). Recall is against the GT culled
    to what the bag's poses observe, as in :func:`roigsf_ros.experiments.offline.run_offline`.
    """
    from roigsf_ros import evaluation
    from roigsf_ros.core.frame import spread_indices
    from roigsf_ros.experiments.offline import EvalConfig, run_mesh_metrics

    ev = eval_config or EvalConfig()
    cfg = mapper.config
    keyframe_ids = {int(i) for i in mapper.keyframe_ids}
    others = [f for f in frames if f.stamp_ns not in keyframe_ids][:: ev.eval_every]
    images = evaluation.render_metrics(
        mapper.render_rgb_depth, others, mapper.valid_depth_mask, strip=spread_indices(len(others), ev.strip_frames)
    )
    rows = images.strip_rows
    mesh = mapper.mesh()
    metrics: dict[str, Any] = {
        "n_frames": len(frames),
        "n_keyframes": len(keyframe_ids),
        "keyframe_ids": sorted(keyframe_ids),
        "keyframes_in_bag": sum(f.stamp_ns in keyframe_ids for f in frames),
        "map_size": mapper.n_surfels,
        **{k: v for k, v in images.means().items() if k != "depth_l1_m"},
        "eval_on": "non-keyframes",
        "eval_depth": cfg.eval_depth,
        "mesh_vertices": len(mesh.vertices),
        "mesh_triangles": len(mesh.triangles),
    }
    if gt_mesh is not None:
        poses = np.stack([f.T_wc for f in frames])
        metrics |= run_mesh_metrics(mesh, gt_mesh, poses, frames[0].intrinsics, ev, cfg)
    return metrics, rows, mesh


def save_plot(
    path: Path,
    poses: np.ndarray,
    is_keyframe: np.ndarray,
    strip_rgb: np.ndarray | None,
    gt_points: np.ndarray | None = None,
    title: str = "",
) -> None:
    """Write a PNG: the trajectory seen from above with its keyframes (numbered, with view directions), and the strip.

    ``poses`` [N, 4, 4] camera-to-world in stream order, ``is_keyframe`` [N] bool, ``strip_rgb`` the
    comparison strip [H, W, 3] uint8 (input vs render), ``gt_points`` [M, 3] for a faint floor plan.
    The view plane is the two world axes along which the camera moved most.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from roigsf_ros.core.fileio import atomic_path

    xyz = poses[:, :3, 3]
    a, b = np.sort(np.argsort(xyz.std(axis=0))[-2:])
    names = "xyz"
    fig, axes = plt.subplots(
        1,
        2 if strip_rgb is not None else 1,
        figsize=(14, 6),
        gridspec_kw={"width_ratios": [1, 1.3]} if strip_rgb is not None else None,
    )
    ax = axes[0] if strip_rgb is not None else axes
    if gt_points is not None and len(gt_points):
        c = 3 - a - b  # the axis looked along: keep a band at the cameras' height, a floor plan
        gt_points = gt_points[np.abs(gt_points[:, c] - np.median(xyz[:, c])) < 0.4]
        ax.scatter(gt_points[:, a], gt_points[:, b], s=0.2, c="0.8", rasterized=True, label="ground truth")
    ax.plot(xyz[:, a], xyz[:, b], "-", color="tab:blue", lw=1, label=f"trajectory ({len(xyz)} frames)")
    ax.plot(xyz[0, a], xyz[0, b], "o", color="tab:blue", ms=5)
    kf = np.flatnonzero(is_keyframe)
    scale = 0.25 * max(np.ptp(xyz[:, a]), np.ptp(xyz[:, b]), 1e-3)
    view = poses[kf, :3, 2]  # optical axis
    ax.quiver(xyz[kf, a], xyz[kf, b], view[:, a], view[:, b], color="tab:red", angles="xy", scale_units="xy",
              scale=1.0 / scale, width=0.004)  # fmt: skip
    ax.scatter(xyz[kf, a], xyz[kf, b], c="tab:red", s=25, zorder=3, label=f"keyframes ({len(kf)})")
    for n, i in enumerate(kf):
        ax.annotate(str(n), (xyz[i, a], xyz[i, b]), textcoords="offset points", xytext=(3, 3), fontsize=7)
    ax.set_xlabel(f"{names[a]} (m)")
    ax.set_ylabel(f"{names[b]} (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("trajectory and keyframes (from above)")
    if strip_rgb is not None:
        axes[1].imshow(strip_rgb)
        axes[1].set_axis_off()
        axes[1].set_title("non-keyframes: input | render | depth input | depth render")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def format_table(metrics: dict[str, Any]) -> str:
    """The demo's short table (rows of :data:`SUMMARY_ROWS` that have a value)."""
    lines = []
    for label, key, fmt in SUMMARY_ROWS:
        value = metrics.get(key)
        if value is not None:
            lines.append(f"  {label:<26} {fmt.format(value)}")
    lines += [f"  {note}" for note in metric_notes(metrics)]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------ the run
def _ros_value(text: str) -> Any:
    """A ``--set`` value as YAML would read it (1 -> int, 1.0 -> float, true -> bool, [a, b] -> list)."""
    import yaml

    return yaml.safe_load(text)


def parse_sets(items: Sequence[str]) -> dict[str, dict[str, Any]]:
    """``NODE.NAME=VALUE`` strings as ``{node: {name: value}}`` (NODE: mapper, nbv_planner, keyframe_selector).

    A value that does not fit the type of the method's setting of that name (the mapper's :class:`MapperConfig`, the
    planner's :class:`NBVConfig`: the node parameters of the same names) is refused now, not once the nodes started.
    """
    from roigsf_ros.mapping.mapper import MapperConfig
    from roigsf_ros.nbv.config import NBVConfig
    from roigsf_ros.nodes.active_mapping import NODE_NAMES

    configs: dict[str, type] = {"mapper": MapperConfig, "nbv_planner": NBVConfig}
    out: dict[str, dict[str, Any]] = {}
    for item in items:
        key, sep, value = item.partition("=")
        node, dot, name = key.partition(".")
        if not sep or not dot or not name:
            raise InputError("--set", f"'{item}' is not NODE.NAME=VALUE")
        if node not in NODE_NAMES:
            raise InputError("--set", f"'{item}': unknown node '{node}' (one of {', '.join(NODE_NAMES)})")
        out.setdefault(node, {})[name] = _ros_value(value)
        if node in configs:
            check_field_value(configs[node], name, out[node][name], f"--set {item}")
    return out


def _window_period_s(system: ActiveMapping, frames: Sequence[BagFrame], rate: float) -> float | None:
    """Seconds between two of the selector's triggers at playback ``rate`` (its ``trigger_every``, else its
    ``window``, frames at the bag's median frame interval); None as fast as possible or with under two frames.
    """
    if rate <= 0 or len(frames) < 2:
        return None
    every = int(system.selector.get_parameter("trigger_every").value) or int(system.selector.window)
    return every * float(np.median(np.diff([f.stamp_ns for f in frames]))) * 1e-9 / rate


def fallback_hint(metrics: dict[str, Any]) -> str | None:
    """A line saying why windows went to the selector's fallback, from what the run measured: the longest wait for
    the planner's answer to a window of the stream (and the two largest parts of the planner's slowest request)
    longer than the time between windows, or frames that reached the selector more than that apart (held up, then a
    burst: windows came faster than any planner answers them); None without fallbacks or without either sign.
    """
    period = metrics.get("window_period_s")
    if not metrics.get("fallbacks") or period is None:
        return None
    slowest, gap = metrics.get("selector_max_answer_s"), metrics.get("selector_max_frame_gap_s")
    why = []
    if gap is not None and gap > period:
        novelty = metrics.get("selector_max_novelty_s")
        held = f"; its novelty took up to {novelty:.2f} s" if novelty else ""
        why.append(f"frames reached the selector up to {gap:.2f} s apart, then in a burst{held}")
    if slowest is not None and slowest > period:
        phases = {k: v for k, v in (metrics.get("planner_slowest_phases_s") or {}).items() if k != "scoring"}
        parts = ", ".join(f"{k} {v:.2f} s" for k, v in sorted(phases.items(), key=lambda kv: -kv[1])[:2])
        why.append(f"the planner's longest answer took {slowest:.2f} s (its slowest request: {parts})")
    if not why:
        return None
    return (
        f"  note: {metrics['fallbacks']} window(s) went to the fallback: {'; '.join(why)}; a window came every "
        f"{period:.2f} s at rate x{metrics['rate']:g}, and a lower --rate gives them the time"
    )


def mapping_hint(metrics: dict[str, Any]) -> str | None:
    """A line saying how many of the keyframes the selector named the mapper did not map, and why; None if all."""
    lost = metrics.get("keyframes_not_mapped") or 0
    if not lost:
        return None
    why = {"keyframes_dropped_overflow": "its keyframe queue was full", "keyframes_missing": "their frame was gone",
           "keyframes_no_depth": "their depth had no valid pixel",
           "keyframes_failed": "inserting them failed"}  # fmt: skip
    parts = ", ".join(f"{n} {why[k]}" for k, n in (metrics.get("keyframe_losses") or {}).items() if n)
    line = f"  note: the mapper did not map {lost} of the {metrics['keyframes_published']} keyframes named ({parts})"
    if metrics.get("policy") == "gaus-slam":  # its rule reads the map, which lags the keyframes it named
        line += (
            "; gaus-slam names nearly every frame it judges on a map without the keyframes it named just before "
            "(keyframe_selector.map_wait_s 0, or waits that expired: map_waits_expired in replay.json)"
        )
    else:
        line += f"; the mapper inserts keyframes more slowly than they came at rate x{metrics['rate']:g}"
    return line


class _Progress:
    """One status line: frames received, keyframes, surfels, planner answers/calls, fallbacks, queue."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.total = total
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self._last_print = 0.0
        self._last_text = ""

    @staticmethod
    def line(status: dict[str, Any], total: int) -> str:
        m, s = status["mapper"], status["selector"]
        planner = f"planner {s['planner_answers']}/{s['planner_calls']}" if s["policy"] != "gaus-slam" else "no planner"
        return (
            f"frames {s['frames']:>4}/{total}  keyframes {m['keyframes']:>3} (queued {m['pending_keyframes']})  "
            f"surfels {m['surfels'] / 1000:6.1f}k  {planner}, fallbacks {s['fallbacks']}"
        )

    def update(self, status: dict[str, Any], final: bool = False) -> None:
        if not self.enabled:
            return
        text = self.line(status, self.total)
        if self.tty:
            print(f"\r{text}", end="\n" if final else "", file=sys.stderr, flush=True)
        elif (final and text != self._last_text) or time.monotonic() - self._last_print >= 10.0:
            print(text, file=sys.stderr, flush=True)
            self._last_print, self._last_text = time.monotonic(), text


def with_camera_options(sets: dict[str, dict[str, Any]], args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """``sets`` (the ``--set`` values) over the camera options typed (``--tf-child-frame`` and the rest, as ``roigsf
    map`` has them): each on both camera nodes (``--camera-info-topic`` also on the planner), under a ``--set`` of the
    same parameter. A value the options refuse is named by its option, before anything starts.
    """
    from roigsf_ros.nodes.bag_camera import CAMERA_NODES, CAMERA_PARAMETERS

    camera_topics(args)  # checks the typed values, naming the option
    typed = {CAMERA_PARAMETERS[field]: value for field, value in camera_options(args).items()}
    out = {node: dict(values) for node, values in sets.items()}
    for node in CAMERA_NODES:
        out[node] = typed | out.get(node, {})
    if "camera_info_topic" in typed:
        out.setdefault("nbv_planner", {}).setdefault("camera_info_topic", typed["camera_info_topic"])
    return {node: values for node, values in out.items() if values}


def demo_camera(
    bag: Path,
    params: dict[str, dict[str, Any]] | None = None,
    params_files: Sequence[Path] = (),
    realsense: str | None = None,
    domain_id: int | None = None,
) -> BagCamera:
    """The bag's camera as the demo's nodes will read it (:func:`~roigsf_ros.nodes.bag_camera.bag_camera`); when the
    mapper would read no frame, the error suggests ``--realsense`` if the bag has RealSense names.
    """
    from roigsf_ros.nodes.bag_camera import NoFrameError, bag_camera

    try:
        return bag_camera(bag, params, params_files, realsense, domain_id)
    except NoFrameError as exc:
        hint = realsense_hint(bag, bag_topic_types(bag), realsense)
        raise InputError(exc.where, f"{exc.problem}{hint}") from None


DEMO_MARKS, DEMO_OUTPUT = ("metrics.json",), "a demo's output"
"""What a demo's ``--out`` may replace (it always replaces its own earlier run): an empty folder or one with these."""


def run_demo(
    bag: Path,
    out: Path,
    policy: str | None = None,
    rate: float = DEFAULT_RATE,
    final_iters: int = DEFAULT_FINAL_ITERS,
    gt_mesh: Path | None = None,
    domain_id: int | None = None,
    params: dict[str, dict[str, Any]] | None = None,
    params_files: Sequence[Path] = (),
    progress: bool = True,
    drain_timeout_s: float = 120.0,
    realsense: str | None = None,
    camera: BagCamera | None = None,
    no_gt_mesh_reason: str = "no ground-truth mesh given",
) -> dict[str, Any]:
    """Replay ``bag`` into the nodes (one process), refine the map, evaluate it, write ``out``; the metrics.

    ``gt_mesh``: the mesh the map's mesh metrics are taken against (None: none, and ``no_gt_mesh_reason`` says why in
    metrics.json; the demo's: :func:`default_gt_mesh`). ``camera``: the bag's camera as :func:`demo_camera` resolved
    it (its ``params`` then replace ``params`` and ``realsense``); None resolves it here. Raises KeyboardInterrupt
    after a clean stop on Ctrl-C (nothing written).
    """
    from rclpy.parameter import Parameter

    from roigsf_ros import evaluation
    from roigsf_ros.core.fileio import atomic_dir, write_json
    from roigsf_ros.nodes.active_mapping import ActiveMapping
    from roigsf_ros.nodes.bag_player import BagPlayer
    from roigsf_ros.nodes.lockstep import Lockstep, selector_took, system_busy
    from roigsf_ros.nodes.node_params import context_with_params_files
    from roigsf_ros.nodes.shared_map import save_snapshot

    t0 = time.perf_counter()
    if gt_mesh is not None and not gt_mesh.is_file():
        raise InputError(gt_mesh, "ground-truth mesh not found")
    if camera is None:
        camera = demo_camera(bag, params, params_files, realsense, domain_id)
    # the recorded frames, read as the mapper reads them: what the map is evaluated against
    # (frames whose messages do not convert are refused by the nodes too, and counted, not fatal)
    with BagReader(bag, camera.topics, skip_refused=True) as reader:
        frames, skipped, no_tf = list(reader.frames()), reader.skipped_frames, reader.no_tf
        no_tf_reason = reader.last_tf_error if no_tf else ""
        refused, refusal = reader.refused, reader.refusal_reasons
        reparented, reparent_note = reader.tf_reparented, reader.tf_reparent_note
        child_note = reader.child_frame_note
    if not frames:
        why = f" ({refused} refused: {refusal})" if refused else ""
        raise InputError(bag, f"no complete frame on {', '.join(camera.topics.types())}{why}")
    node_params = {k: dict(v) for k, v in camera.params.items()}
    if policy is not None:  # given: over the params files (a node's override beats a file), under a --set of it
        node_params.setdefault("keyframe_selector", {}).setdefault("policy", policy)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if domain_id is None:
        domain_id = domain_id_from_env() or 0
    context = context_with_params_files(params_files, domain_id)
    system: ActiveMapping | None = None
    player: BagPlayer | None = None
    lockstep: Lockstep | None = None
    try:
        system = ActiveMapping(context=context, params=node_params)
        if rate <= 0:
            lockstep = Lockstep(system, camera.topics.resolved().color)
        player = BagPlayer(
            context=context,
            pace=lockstep,
            parameter_overrides=[
                Parameter("bag", value=str(bag)),
                Parameter("topics", value=list(camera.play)),  # a robot's other topics (and types) are not needed
                Parameter("rate", value=float(rate)),
                Parameter("start_delay_s", value=0.5),
                Parameter("progress_period_s", value=0.0),
            ],
        )
        if lockstep is not None:
            lockstep.player = player
        system.executor.add_node(player)
        system.start()
        bar = _Progress(len(frames), progress)
        t_stream = time.perf_counter()
        while not player.wait(0.25):
            bar.update(system.status())
        if player.error is not None:
            raise RuntimeError(f"bag player failed: {player.error}")
        # The stream is over: once the selector has seen the last frames (or 5 s passed), it decides what it still
        # holds (only with its lookahead); then the mapper inserts every keyframe it named (its idle optimisation
        # is not waited for: the refinement below does that work).
        deadline = time.monotonic() + drain_timeout_s
        seen_by = time.monotonic() + min(5.0, drain_timeout_s)
        while not selector_took(system, len(frames)) and time.monotonic() < seen_by:
            time.sleep(0.05)
        system.selector.finish()
        settled_since, last = time.monotonic(), None
        while time.monotonic() < deadline:
            st = system.status()
            bar.update(st)
            sel, mp = st["selector"], st["mapper"]
            key = (sel["frames"], sel["keyframes_published"], mp["keyframe_msgs"])
            if key != last:
                settled_since, last = time.monotonic(), key
            busy = system_busy(st)
            # Done when nothing moved for a while: 1 s once every frame is in, 5 s if some never came.
            quiet_s = 1.0 if sel["frames"] >= len(frames) else 5.0
            if not busy and time.monotonic() - settled_since > quiet_s:
                break
            time.sleep(0.1)
        t_stream = time.perf_counter() - t_stream
        status = system.status()
        bar.update(status, final=True)
        player_summary = player.summary()
    finally:  # also on Ctrl-C: stop playback, the executor and every node thread, then the context
        # Order matters: a node destroyed while the executor thread still spins fails in that thread
        # (InvalidHandle: "cannot use Destroyable because destruction was requested", a traceback at the
        # end of the demo). Stop the playback thread, then the executor (ActiveMapping.shutdown joins it
        # and destroys its own nodes), and only then destroy the player.
        if player is not None:
            player.stop()
        if system is not None:
            system.shutdown()
        if player is not None:
            player.destroy_node()
        context.try_shutdown()

    mapper = system.shared.mapper
    if mapper is None or not mapper.keyframes:
        raise RuntimeError(f"no keyframe was mapped (is the bag's camera stream complete?); node status: {status}")
    t_refine = time.perf_counter()
    if final_iters > 0:
        tty = progress and sys.stderr.isatty()
        step = max(1, final_iters // 20)
        for done in range(0, final_iters, step):
            mapper.optimise(min(step, final_iters - done), newest=None)
            if tty:
                print(
                    f"\rrefining the map: {min(done + step, final_iters)}/{final_iters} steps", end="", file=sys.stderr
                )
        mapper.prune()
        if progress:
            end = f"refined the map: {final_iters} steps over {len(mapper.keyframes)} keyframes"
            print(f"\r{end}" if tty else end, file=sys.stderr)
    t_refine = time.perf_counter() - t_refine

    frames = [resized_frame(f, mapper.intr) for f in frames]  # as the mapper took them (input_width/input_height)
    metrics, rows, mesh = evaluate_map(mapper, frames, gt_mesh)
    sel = status["selector"]
    metrics |= {
        "policy": sel["policy"],  # the selector's: --policy, a --set or a params file, else its default
        "policy_params": sel["policy_params"],  # a policy deciding alone: the parameters it ran with
        "bag": str(bag),
        "gt_mesh": None if gt_mesh is None else str(gt_mesh),  # what the mesh metrics were taken against
        "no_gt_mesh_reason": no_gt_mesh_reason if gt_mesh is None else None,
        "rate": rate,
        "lockstep_stalls": None if lockstep is None else lockstep.stalls,  # frames played before the nodes were ready
        "lockstep_wait_s": None if lockstep is None else lockstep.waited_s,
        "frames_received": sel["frames"],
        "dropped_frames": len(frames) - sel["frames"],  # recorded but not received complete and valid
        "bag_incomplete_stamps": skipped,
        "bag_frames_without_tf": no_tf,  # complete in the bag, but TF never gives their pose: not in n_frames
        "bag_frames_without_tf_reason": no_tf_reason,
        "bag_frames_refused": refused,  # complete and posed, but their messages do not convert: not in n_frames
        "bag_frames_refused_reason": refusal,
        "tf_reparented": reparented,  # a TF frame changed parent: the poses through it moved (metric_notes says it)
        "tf_reparent_note": reparent_note or None,
        "tf_child_frame_note": child_note or None,  # the poses are another frame's than the images' (metric_notes)
        "camera_topics": reader.topics.record(),  # how the bag was read, resolved against it
        "planner": f"{sel['planner_answers']}/{sel['planner_calls']}",
        "planner_calls": sel["planner_calls"],
        "planner_answers": sel["planner_answers"],
        "planner_failures": sel["planner_failures"],
        "planner_not_ready": sel["planner_not_ready"],  # asked again: the map had no keyframe yet
        "planner_timeouts": sel["planner_timeouts"],
        "fallbacks": sel["fallbacks"],
        "warm_up_s": status["nbv_planner"]["warm_up_s"],
        "planner_max_scoring_s": status["nbv_planner"]["max_scoring_s"] if sel["planner_calls"] else None,
        "planner_slowest_phases_s": status["nbv_planner"]["slowest_phases_s"],
        "window_period_s": _window_period_s(system, frames, rate),
        "selector_max_answer_s": sel["max_answer_s"] if sel["planner_answers"] else None,
        "selector_max_novelty_s": sel["max_novelty_s"] if sel["max_novelty_s"] > 0 else None,
        "selector_max_frame_gap_s": sel["max_frame_gap_s"],
        "keyframes_published": sel["keyframes_published"],
        "keyframes_not_mapped": sum(status["mapper"][k] for k in KEYFRAMES_NOT_MAPPED),
        "keyframe_losses": {k: status["mapper"][k] for k in KEYFRAMES_NOT_MAPPED},
        "stream_s": t_stream,
        "final_iters": final_iters,
        "refine_s": t_refine,
        "mapper_config": mapper.config.to_dict(),
    }
    poses = np.stack([f.T_wc for f in frames])
    is_kf = np.array([f.stamp_ns in set(mapper.keyframe_ids) for f in frames])
    gt_points = None
    if gt_mesh is not None:
        gt_points = evaluation.sample_surface(evaluation.as_legacy_mesh(gt_mesh, "gt_mesh"), 20_000, 0)
    import open3d as o3d

    reads = [p for p in (bag, gt_mesh, *params_files) if p is not None]
    with atomic_dir(out, overwrite=True, marks=DEMO_MARKS, what=DEMO_OUTPUT, inputs=reads) as tmp:
        snap = system.shared.snapshot(with_h_train=system.shared.h_train_to_save())
        save_snapshot(snap, tmp)  # map.ply + keyframes.json (+ h_train.npz)
        if not o3d.io.write_triangle_mesh(str(tmp / "mesh.ply"), mesh):
            raise OSError(f"{out / 'mesh.ply'}: open3d could not write the mesh")
        strip = evaluation.save_comparison_strip(tmp / "strip.png", rows) if rows else None
        title = f"{bag.name}: policy {sel['policy']}"  # the one that ran: --policy, a --set or a params file
        save_plot(tmp / "plot.png", poses, is_kf, strip, gt_points, title=title)
        write_json(tmp / "replay.json", evaluation.to_json_safe({"player": player_summary, "status": status}))
        metrics["wall_s"] = time.perf_counter() - t0
        write_json(tmp / "metrics.json", evaluation.to_json_safe(metrics))
    return metrics


def default_gt_mesh(bag: Path, option: str | None) -> tuple[Path | None, str]:
    """The mesh the demo's mesh metrics are taken against, and why there is none: ``--gt-mesh`` (``option``), else the
    bag's own (a bag folder's, or a ``.mcap``'s folder's), by the rule of ``roigsf map`` (:func:`chosen_gt_mesh`).
    """
    return chosen_gt_mesh(option, scene_gt_mesh(bag))


def _pace(rate: float) -> str:
    """How the bag is played, in words: ``at rate x2``, or ``in lockstep`` (``--rate`` <= 0)."""
    return f"at rate x{rate:g}" if rate > 0 else "in lockstep (each frame once the nodes took the one before)"


def _check_numbers(args: argparse.Namespace) -> None:
    """Refuse the demo's numeric options that make no sense, naming the option, before anything is read or started
    (a negative ``--rate`` is meaningful: <= 0 plays in lockstep).
    """
    if not math.isfinite(args.rate):
        raise InputError("--rate", f"must be a finite number (<= 0: as fast as the nodes take it), got {args.rate}")
    if args.final_iters < 0:
        raise InputError("--final-iters", f"must be >= 0, got {args.final_iters}")
    if args.domain_id is not None:
        check_domain_id(args.domain_id)


def _run(args: argparse.Namespace) -> int:
    _check_numbers(args)
    domain_id = args.domain_id if args.domain_id is not None else domain_id_from_env()
    bag = Path(args.bag) if args.bag is not None else sample_path(SAMPLE_BAG)
    gt_mesh, no_mesh = default_gt_mesh(bag, args.gt_mesh)
    if gt_mesh is not None and not gt_mesh.is_file():  # now, not after the replay
        raise InputError(gt_mesh, "ground-truth mesh not found (--gt-mesh)")
    mesh_note = f"mesh metrics against {gt_mesh}" if gt_mesh is not None else f"no mesh metrics ({no_mesh})"
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    check_writable(out)  # the run folder is written at the end: fail now, not after the replay
    params_files = [Path(f) for f in args.params_file]
    check_replaceable(out, DEMO_MARKS, DEMO_OUTPUT, (bag, gt_mesh, *params_files))
    from roigsf_ros.nodes.node_params import params_file_sections  # rclpy: imported once a demo runs

    for f in params_files:  # now, naming the file, not as rclpy's parse error after the bag was read
        params_file_sections(f, strict=True)
    sets = with_camera_options(parse_sets(args.set), args)
    policy = sets.get("keyframe_selector", {}).get("policy", args.policy)  # a --set wins over --policy
    if policy is not None:  # now, not once the nodes started and warmed up
        from roigsf_ros.nodes.keyframe_selector import PLANNER_POLICIES, alone_policies
        from roigsf_ros.policies.base import unknown_policy

        names = (*PLANNER_POLICIES, *alone_policies())
        if policy not in names:
            given = "--policy" if policy == args.policy else "--set keyframe_selector.policy"
            raise unknown_policy(str(policy), names, given)
    # the nodes' camera settings, read from the bag as they will read it: fails now, naming the topic or parameter
    camera = demo_camera(bag, sets, params_files, args.realsense, domain_id)
    info = bag_info(bag, camera.topics)
    given = f" (policy {args.policy})" if args.policy is not None else ""
    size = f"{info['width']}x{info['height']}" if info["width"] is not None else "an undecoded size"
    unposed = (
        f" (and {info['frames_without_tf']} more that TF does not pose: {info['no_tf_reason']})"
        if info.get("frames_without_tf")
        else ""
    )
    print(
        f"bag {bag}: {info['frame_count']} frames{unposed} of {size}, depth {info['depth_encoding']}, pose from "
        f"{info['pose_source']}, {info['duration_s']:.1f} s; playing {_pace(args.rate)} into active_mapping"
        f"{given}, then {args.final_iters} refinement steps; {mesh_note}"
    )
    metrics = run_demo(
        bag,
        out,
        policy=args.policy,
        rate=args.rate,
        final_iters=args.final_iters,
        gt_mesh=gt_mesh,
        domain_id=domain_id,
        params_files=params_files,
        progress=not args.no_progress,  # the demo prints a plain status line every 10 s when stderr is no terminal
        camera=camera,
        no_gt_mesh_reason=no_mesh,
    )
    print(f"\nactive-mapping demo on {bag} (policy {metrics['policy']}) -> {out}")
    print(format_table(metrics))
    print(f"  {mesh_note}")
    for hint in (fallback_hint(metrics), mapping_hint(metrics)):
        if hint:
            print(hint)
    saved_h = ", h_train.npz" if (out / "h_train.npz").is_file() else ""
    print(f"  results in {out}/: metrics.json, mesh.ply, map.ply, keyframes.json{saved_h}, plot.png, strip.png, "
          "replay.json")  # fmt: skip
    missed = info["frame_count"] - metrics["frames_received"]
    if missed:  # the map and its figures are of the frames that came: say so, and fail
        back = info.get("frames_stamped_back") or 0
        why = (f"; the bag's stamps go back at {back} frame(s), first at {info['first_stamped_back']}, and the nodes "
               "drop a frame stamped before one they delivered unless the next frame stays back too" if back
               else "")  # fmt: skip
        print(
            f"roigsf demo: error: {missed} of the bag's {info['frame_count']} frames did not reach the nodes complete "
            f"and valid ({_pace(args.rate)}; replay.json has the player's and the nodes' counts{why}): the "
            "results are of the rest",
            file=sys.stderr,
        )
        return 1
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``demo`` subcommand."""
    p = sub.add_parser(
        "demo",
        help="the main job: active mapping of the shipped bag over ROS 2 (player + active_mapping), with a report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--bag",
        default=None,
        metavar="BAG",
        help=f"bag to replay (default: the shipped sample, {SAMPLE_BAG} of the checkout, else of the installed "
        "package's share folder)",
    )
    p.add_argument(
        "--out", default="runs/demo", metavar="RUN", help="run folder, replaced when done (default runs/demo)"
    )
    p.add_argument(
        "--policy",
        default=None,
        metavar="P",
        help=f"keyframe selector policy, over the params files' (default: theirs, else {DEFAULT_POLICY}; also "
        "roi-fisher, close-front, fisherrf, random, gaus-slam, every-n, all, novelty, or a policy added to the "
        "library; an added policy's own parameters: --set keyframe_selector.policy_params=KEY=VALUE:...)",
    )
    p.add_argument(
        "--rate",
        type=float,
        default=DEFAULT_RATE,
        metavar="X",
        help=f"playback rate factor; 1.0 real time, <= 0 as fast as the nodes take the frames, in lockstep with them "
        f"(nothing lost; default {DEFAULT_RATE})",
    )
    p.add_argument(
        "--final-iters",
        type=int,
        default=DEFAULT_FINAL_ITERS,
        metavar="N",
        help=f"refinement steps over all keyframes after the stream (default {DEFAULT_FINAL_ITERS})",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NODE.NAME=VALUE",
        help="a node parameter, e.g. mapper.iters_per_keyframe=20 or keyframe_selector.window=6 (repeatable)",
    )
    p.add_argument(
        "--params-file",
        action="append",
        default=[],
        metavar="YAML",
        help="ROS params file for the nodes, over their defaults (config/*.yaml; repeatable, later files win), e.g. "
        "config/recommended/planner.yaml",
    )
    add_camera_options(
        p,
        realsense_help="a robot's bag: RealSense names under NS (default /camera) on the mapper and the keyframe "
        "selector (NS/color/image_raw, NS/aligned_depth_to_color/image_raw, NS/color/camera_info; also the "
        "planner's camera_info_topic), pose from TF, transports from the bag's topic types; over the params files, "
        "under the options below (set on both camera nodes) and under --set NODE.NAME=VALUE",
        transport_default="the nodes' (their params files', else raw; with --realsense auto: from the bag)",
    )
    p.add_argument(
        "--domain-id",
        type=int,
        default=None,
        metavar="N",
        help="ROS domain id (default: ROS_DOMAIN_ID or 0); discovery stays on localhost",
    )
    p.add_argument(
        "--gt-mesh",
        default=None,
        metavar="PLY",
        help="ground-truth mesh for the mesh metrics (default: the bag's own, as roigsf map finds it: mesh.ply in the "
        f"bag folder, else NAME_mesh.ply beside the folder NAME, as {SAMPLE_GT_MESH} beside the shipped sample; "
        "without either, no mesh metrics; '' for none)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress display")
    p.set_defaults(func=_run)
