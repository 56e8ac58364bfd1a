"""Offline runs: map a whole frame sequence with a keyframe policy, evaluate it, write the run folder."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from tqdm import tqdm

from roigsf_ros import evaluation
from roigsf_ros.core.camera import Intrinsics, check_pose, depth_points_w
from roigsf_ros.core.config import Config
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import atomic_dir, check_run_output, write_json
from roigsf_ros.core.frame import Frame, spread_indices
from roigsf_ros.data.sources import FrameSequence, check_frame_source
from roigsf_ros.mapping.mapper import Mapper, MapperConfig
from roigsf_ros.nbv.novelty import ObservedSurface
from roigsf_ros.policies.base import KeyframePolicy, checked_keyframes

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------- offline run
def _test_scene_metrics(mapper: Mapper, test_source: FrameSequence, progress: bool) -> dict[str, Any]:
    """PSNR, SSIM, depth L1 and the hole split (see :func:`evaluation.render_metrics`) of the final map at every
    frame of ``test_source`` (a bad pose: skipped, counted), and which holes are on surface that no keyframe's depth
    observed (``test_scene_holes_unseen_share``: of the hole pixels with depth, those farther than the novelty's 5 cm
    from every keyframe's depth, so a matter of which frames were keyframes; the rest the map saw and does not
    render).
    """
    skipped = 0

    def frames() -> Iterator[Frame]:
        nonlocal skipped
        for frame in tqdm(test_source, desc="test scene", unit="frame", disable=not progress, dynamic_ncols=True):
            try:
                check_pose(frame.T_wc, f"test frame {frame.index} pose")
            except InputError as exc:
                skipped += 1
                log.warning("%s: %s; not evaluated", getattr(test_source, "path", "test_source"), exc)
                continue
            yield frame

    seen = ObservedSurface()  # what the keyframes' depth observed, as the novelty counts it (5 cm)
    for kf in mapper.keyframes:
        seen.add(kf.depth_m.cpu().numpy(), kf.T_wc, mapper.intr, kf.valid.cpu().numpy())
    current: list[Frame] = []
    holes = [0, 0]  # hole pixels with depth, of which on surface no keyframe's depth reaches

    def evaluated() -> Iterator[Frame]:  # render_metrics calls covered() once per frame, after drawing it from here
        for frame in frames():
            current[:] = [frame]
            yield frame

    def covered(T_wc: np.ndarray) -> np.ndarray:
        mask = mapper.covered_mask(T_wc)
        frame = current[0]
        hole = ~mask & mapper.valid_depth_mask(frame.depth_m)
        if hole.any():
            points = depth_points_w(frame.depth_m, frame.T_wc, mapper.intr, hole)
            holes[0] += len(points)
            holes[1] += seen.unreached_points(points)
        return mask

    res = evaluation.render_metrics(mapper.render_rgb_depth, evaluated(), mapper.valid_depth_mask, covered=covered)
    means = res.means()
    return {
        "test_scene": str(getattr(test_source, "path", "given")),
        "test_scene_frames": means["n_eval_frames"],
        "test_scene_psnr": means["psnr"],
        "test_scene_ssim": means["ssim"],
        "test_scene_depth_l1_cm": means["depth_l1_cm"],
        "test_scene_psnr_covered": means.get("psnr_covered"),
        "test_scene_uncovered_pixel_fraction": means.get("uncovered_pixel_fraction"),
        "test_scene_uncovered_error_share": means.get("uncovered_error_share"),
        "test_scene_holes_unseen_share": holes[1] / holes[0] if holes[0] else 0.0,
        "test_scene_frames_skipped_bad_pose": skipped,
    }


@dataclass(frozen=True)
class EvalConfig(Config):
    """What an offline run evaluates and how (not part of the mapper's state)."""

    eval_every: int = 1
    """Evaluate every this-many-th non-keyframe (1 = all of them)."""
    strip_frames: int = 4
    """Rows of the comparison strip (evaluated frames spread over the sequence)."""
    mesh_samples: int = 200_000
    """Points sampled on each mesh for the mesh metrics."""
    mesh_taus_m: tuple[float, ...] = (0.01, 0.05)
    """Distance thresholds of precision / recall / F-score."""
    cull_gt_to_observed: bool = True
    """Cull the GT mesh to what the sequence's cameras observe before recall/completion."""
    seed: int = 0
    """Seed of the mesh sampling."""

    def validate(self) -> EvalConfig:
        """Self, or InputError naming the first field out of range."""
        for name, lo in (("eval_every", 1), ("strip_frames", 0), ("mesh_samples", 1)):
            if int(getattr(self, name)) < lo:
                raise InputError(name, f"must be at least {lo}, got {getattr(self, name)}")
        if not self.mesh_taus_m or not all(t > 0 for t in self.mesh_taus_m):
            raise InputError("mesh_taus_m", f"must be positive metres, got {self.mesh_taus_m}")
        return self


def _cameras(other: FrameSequence, source: FrameSequence) -> str:
    """`` (its W x H fx .. against W x H fx ..)``: how two sequences' cameras differ, for an error."""

    def camera(seq: FrameSequence) -> str:
        k = seq.intrinsics
        return f"{k.width}x{k.height} px, fx {k.fx:g}, fy {k.fy:g}, cx {k.cx:g}, cy {k.cy:g}"

    return f" ({camera(other)}, against {camera(source)})"


def run_mesh_metrics(
    mesh: o3d.geometry.TriangleMesh,
    gt_mesh: Path,
    poses: np.ndarray | None,
    intr: Intrinsics,
    ev: EvalConfig,
    cfg: MapperConfig,
) -> dict[str, Any]:
    """A run's mesh against ``gt_mesh`` as ``ev`` asks: precision/recall/F at ``ev.mesh_taus_m``, the GT culled to what
    the run's ``poses`` [N, 4, 4] (camera-to-world, ``intr``; None: none) observe up to the mapper's ``max_depth_m``
    when ``ev.cull_gt_to_observed``; the keys ``gt_mesh`` and ``gt_culling`` say against what.
    """
    cull = ev.cull_gt_to_observed and poses is not None and len(poses) > 0
    metrics = evaluation.mesh_metrics(
        mesh,
        gt_mesh,
        taus_m=ev.mesh_taus_m,
        n_samples=ev.mesh_samples,
        seed=ev.seed,
        observed_poses=poses if cull else None,
        intr=intr if cull else None,
        cull_max_depth_m=cfg.max_depth_m,
    )
    metrics["gt_mesh"] = str(gt_mesh)
    metrics["gt_culling"] = (
        "GT samples culled to those seen (in image, in range, unoccluded) from the poses of all "
        "frames of the run before recall/completion; precision/accuracy use the whole GT mesh"
        if cull
        else "none: recall/completion against the whole GT mesh"
    )
    return metrics


def run_offline(
    source: FrameSequence,
    policy: KeyframePolicy,
    config: MapperConfig | None,
    out_dir: str | Path,
    gt_mesh: str | Path | None = None,
    eval_config: EvalConfig | None = None,
    progress: bool = True,
    overwrite: bool = False,
    eval_source: FrameSequence | None = None,
    test_source: FrameSequence | None = None,
    no_gt_mesh_reason: str = "no ground-truth mesh given",
    command: str | None = None,
) -> dict[str, Any]:
    """Map a whole frame sequence (e.g. :func:`roigsf_ros.data.sources.open_frames`) offline into ``out_dir``.

    Files (written atomically): ``metrics.json``, ``mesh.ply``, ``map.ply``, ``keyframes.json`` and
    ``strip.png`` (input vs rendered colour and depth of a few evaluated frames). Image metrics are
    over non-keyframes; mesh metrics need ``gt_mesh`` (without: ``gt_mesh`` null and ``no_gt_mesh_reason``, as in
    ``roigsf demo``'s metrics.json). Frames with a non-rigid pose are skipped and
    counted, and so are those the source skips (a bag's frames without a pose on TF, incomplete stamps, frames
    whose messages do not convert: ``frames_skipped_no_tf`` and ``frames_skipped_refused`` with the reason,
    ``frames_skipped_incomplete``; frames repeating an earlier frame's stamp: ``frames_skipped_repeated_stamp``), and
    frames stamped before the frame mapped before them are counted (``frames_stamped_back``). ``eval_source``: the image
    metrics compare with its frames, at its poses, instead of the mapped ones (the same frames in the same
    order and size: e.g. the noise-free render of a simulated sensor's sequence, so that sensor noise is not
    counted as map error). ``test_source``: frames the policy never sees (e.g. poses between the mapped ones,
    ``roigsf scene render --offset``), the same set for every policy, also evaluated (``test_scene_*`` metrics;
    the non-keyframes differ from one policy to the next). ``command``: the command line that ran it, kept in
    metrics.json beside the source's path and image size (what was mapped). Returns the metrics dict.
    """
    if not isinstance(config, MapperConfig | None):  # a dict gave a bare AttributeError deep in the Mapper
        raise InputError("config", f"must be a MapperConfig (MapperConfig(**values)), got a {type(config).__name__}")
    if not callable(getattr(policy, "observe", None)):  # a policy's name gave a bare AttributeError
        raise InputError("policy", f"must be a keyframe policy (make_policy(name, ...)), got {policy!r}")
    check_frame_source(source, "source")
    if eval_source is not None:
        if len(eval_source) != len(source):
            raise InputError("eval_source", f"has {len(eval_source)} frames, the mapped sequence {len(source)}")
        if eval_source.intrinsics != source.intrinsics:
            why = f"its camera differs from the mapped sequence's{_cameras(eval_source, source)}"
            raise InputError("eval_source", why)
    if test_source is not None and test_source.intrinsics != source.intrinsics:
        raise InputError(getattr(test_source, "path", "test_source"), "its camera differs from the mapped sequence's"
                         f"{_cameras(test_source, source)}")  # fmt: skip
    ev = eval_config or EvalConfig()
    evaluation.check_eval_size(source.intrinsics)
    gt_path = Path(gt_mesh) if gt_mesh is not None else None
    if gt_path is not None:
        evaluation.check_gt_mesh(gt_path)
    out_final = Path(out_dir)
    reads = (getattr(source, "path", None), gt_path)
    keep = check_run_output(out_final, overwrite, "a map's output", reads, ("metrics.json",))
    cfg = config or MapperConfig()
    mapper = Mapper(source.intrinsics, cfg)
    policy.reset()
    t0 = time.perf_counter()
    frame_ids: list[int | None] = []  # None for a frame skipped for its pose
    poses: list[np.ndarray] = []
    bad_pose = 0
    bar = tqdm(total=len(source), desc="mapping", unit="frame", disable=not progress, dynamic_ncols=True)
    named: set[int] = set()  # the frames the policy named so far
    for frame in source:
        try:
            T = check_pose(frame.T_wc, f"frame {frame.index} pose")
        except InputError as exc:
            bad_pose += 1
            log.warning("%s; frame skipped", exc)
            frame_ids.append(None)
            poses.append(np.full((4, 4), np.nan))
            bar.update(1)
            continue
        poses.append(T)
        frame_ids.append(int(frame.index))
        # The policy names the frames to insert now: this one, or an earlier one (the NBV window
        # policies); the mapper's keyframe ids below are the truth (it skips a frame without depth).
        try:
            chosen = policy.observe(frame, mapper)
        except Exception as exc:  # a policy's own bug: its traceback, and which policy and frame
            exc.add_note(f"in keyframe policy {policy.name!r}: observe() of frame {frame.index}")
            raise
        for keyframe in checked_keyframes(policy, chosen, named):
            mapper.add_keyframe(keyframe)
        bar.update(1)
        bar.set_postfix(keyframes=len(mapper.keyframes), surfels=mapper.n_surfels, refresh=False)
    # Frames the source could not give (a bag: incomplete stamps, no pose on TF, messages that do not convert),
    # counted by it after the pass.
    skipped_no_tf = int(getattr(source, "skipped_no_tf", 0))
    skipped_incomplete = int(getattr(source, "skipped_incomplete", 0))
    skipped_refused = int(getattr(source, "skipped_refused", 0))
    skipped_repeated = int(getattr(source, "skipped_repeated", 0))
    given_back = int(getattr(source, "given_back", 0))
    no_tf_reason = str(getattr(source, "no_tf_reason", "")) if skipped_no_tf else ""
    refused_reason = str(getattr(source, "refused_reason", "")) if skipped_refused else ""
    reparented = int(getattr(source, "tf_reparented", 0))
    reparent_note = str(getattr(source, "tf_reparent_note", "")) if reparented else ""
    if reparented:  # every pose through that frame may be wrong, and nothing else would show it
        log.warning("%s: TF %s (%d change(s) of parent)", getattr(source, "path", "source"), reparent_note, reparented)
    child_note = str(getattr(source, "tf_child_frame_note", ""))
    if child_note:  # the poses are another frame's than the images': every figure is wrong
        log.warning("%s: %s", getattr(source, "path", "source"), child_note)
    skipped = skipped_no_tf + skipped_incomplete + skipped_refused + skipped_repeated
    if skipped:
        log.warning(
            "%s: %d frames skipped without a pose on TF%s, %d incomplete, %d refused%s, %d repeating an earlier "
            "frame's stamp",
            getattr(source, "path", "source"), skipped_no_tf, f" ({no_tf_reason})" if no_tf_reason else "",
            skipped_incomplete, skipped_refused, f" ({refused_reason})" if refused_reason else "", skipped_repeated,
        )  # fmt: skip
        bar.set_postfix(skipped=skipped, refresh=False)
        bar.update(skipped)
    if given_back:
        log.warning(
            "%s: the stamps go back at %d frame(s) (first: %s): they were mapped in the bag's order, and frame ids "
            "follow the stamps", getattr(source, "path", "source"), given_back, getattr(source, "first_given_back", ""),
        )  # fmt: skip
    bar.close()
    for keyframe in checked_keyframes(policy, policy.finish(mapper), named, "finish"):  # what it still holds at the end
        mapper.add_keyframe(keyframe)
    if cfg.final_iters and mapper.keyframes:
        mapper.refine(cfg.final_iters)
    t_map = time.perf_counter() - t0
    if not mapper.keyframes:  # no map to render, mesh or save: say why instead of failing in the mesh writer
        no_depth = mapper.stats.frames_skipped_no_depth
        why = f"{no_depth} keyframe(s) had no valid depth" if no_depth else f"policy {policy.name} chose none"
        raise InputError(getattr(source, "path", "source"), f"no keyframe could be mapped from {len(frame_ids)} "
                         f"frame(s): {why}")  # fmt: skip
    inserted = set(mapper.keyframe_ids)
    is_keyframe = [fid is not None and fid in inserted for fid in frame_ids]

    # Image metrics on non-keyframes, against the final map.
    candidates = [i for i, k in enumerate(is_keyframe) if not k and np.isfinite(poses[i]).all()]
    chosen_list = candidates[:: ev.eval_every]
    chosen = set(chosen_list)
    quiet = not progress or not chosen
    bar = tqdm(total=len(chosen), desc="evaluating", unit="frame", disable=quiet, dynamic_ncols=True)

    def held_out() -> Iterator[Frame]:
        for i, frame in enumerate(source if eval_source is None else eval_source):
            if i in chosen:
                bar.update(1)
                if eval_source is None:
                    yield frame  # pose already checked above
                    continue
                if frame.index != frame_ids[i]:
                    raise InputError("eval_source", f"frame {i} is number {frame.index}, the mapped one {frame_ids[i]}")
                yield Frame(frame.index, frame.rgb, frame.depth_m, check_pose(frame.T_wc, f"eval frame {frame.index}"))

    images = evaluation.render_metrics(
        mapper.render_rgb_depth, held_out(), mapper.valid_depth_mask,
        strip=spread_indices(len(chosen_list), ev.strip_frames),
    )  # fmt: skip
    bar.close()
    strip_rows = images.strip_rows
    if not strip_rows and mapper.keyframes:  # every frame was a keyframe: show keyframes instead
        for j in spread_indices(len(mapper.keyframes), ev.strip_frames):
            kf = mapper.keyframes[j]
            rgb, depth = mapper.render_rgb_depth(kf.T_wc)
            strip_rows.append((kf.rgb_u8.cpu().numpy(), rgb, kf.depth_m.cpu().numpy(), depth))

    test_metrics = _test_scene_metrics(mapper, test_source, progress) if test_source is not None else {}
    mesh = mapper.mesh()
    metrics: dict[str, Any] = {
        "source": str(getattr(source, "path", "in memory")),
        "image_size": [source.intrinsics.width, source.intrinsics.height],
        "command": command,
        "camera_topics": topics.record() if (topics := getattr(source, "camera_topics", None)) is not None else None,
        "intrinsics": asdict(source.intrinsics),  # as read (a --cam file over the folder's own shows here)
        "policy": policy.name,
        "policy_params": policy.params(),
        "n_frames": len(is_keyframe),
        "n_keyframes": len(mapper.keyframes),
        "keyframe_ids": mapper.keyframe_ids,
        "map_size": mapper.n_surfels,
        **images.means(),
        "eval_every": ev.eval_every,
        "eval_on": "non-keyframes",
        "eval_against": "the mapped frames" if eval_source is None else str(getattr(eval_source, "path", "other")),
        "eval_depth": cfg.eval_depth,
        "eval_frames_without_gt_depth": images.frames_without_gt_depth,
        **test_metrics,
        "frames_skipped_bad_pose": bad_pose,
        "frames_skipped_no_tf": skipped_no_tf,
        "frames_skipped_no_tf_reason": no_tf_reason or None,
        "tf_reparented": reparented,
        "tf_reparent_note": reparent_note or None,
        "tf_child_frame_note": child_note or None,
        "frames_skipped_refused": skipped_refused,
        "frames_skipped_refused_reason": refused_reason or None,
        "frames_skipped_incomplete": skipped_incomplete,
        "frames_skipped_repeated_stamp": skipped_repeated,
        "frames_stamped_back": given_back,
        "mesh_vertices": len(mesh.vertices),
        "mesh_triangles": len(mesh.triangles),
    }
    metrics |= {f"mapper_{k}": v for k, v in asdict(mapper.stats).items()}
    if gt_path is not None:
        valid = [p for p in poses if np.isfinite(p).all()]
        metrics |= run_mesh_metrics(mesh, gt_path, np.stack(valid) if valid else None, source.intrinsics, ev, cfg)
    else:
        metrics |= {"gt_mesh": None, "no_gt_mesh_reason": no_gt_mesh_reason}
    metrics["wall_s"] = time.perf_counter() - t0
    metrics["mapping_wall_s"] = t_map
    metrics["config"] = cfg.to_dict()
    metrics["eval_config"] = ev.to_dict()

    with atomic_dir(out_final, overwrite, **keep) as tmp:
        mapper.save(tmp)
        if not o3d.io.write_triangle_mesh(str(tmp / "mesh.ply"), mesh):
            raise OSError(f"{out_final / 'mesh.ply'}: open3d could not write the mesh")
        if strip_rows:
            evaluation.save_comparison_strip(tmp / "strip.png", strip_rows)
        metrics["wall_s"] = time.perf_counter() - t0
        write_json(tmp / "metrics.json", evaluation.to_json_safe(metrics))
    return metrics


__all__ = ["EvalConfig", "run_mesh_metrics", "run_offline"]
