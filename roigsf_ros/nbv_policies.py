"""Stream NBV keyframe policies: pick the next keyframe from a window of recent frames by its pose.

The "stream" setting of the NBV experiments: frames arrive in trajectory order, as in SLAM. The
policy keeps the most recent ``window`` frames as candidates; every ``trigger_every`` frames
(default: ``window``) it scores the candidates' *poses* (never their images) against the current
map and TSDF and turns the best one into a keyframe. A frame's image is used only once it has been
chosen, when it is inserted into the mapper. The first frame is always a keyframe (empty map).

Registered names (see :func:`roigsf_ros.keyframes.make_policy`): ``"random"`` (a seeded uniform
pick from the window, the baseline) and one policy per :data:`roigsf_ros.nbv.MODES`:
``"roi-gsurfisher"``, ``"roi-fisher"``, ``"close-front"``, ``"fisherrf"``.

Important contract difference from the per-frame policies: the winner of a window is generally a
*past* frame, which ``observe`` can no longer answer True for. So at a trigger ``observe`` calls
``mapper.add_keyframe(winner)`` itself and returns False; only the very first frame is answered
True (the caller inserts it, as for any policy). Callers must therefore read which frames became
keyframes from ``mapper.keyframe_ids`` (or this policy's :attr:`StreamNBVPolicy.inserted_ids`,
the frames it inserted itself), not from ``observe``'s return value.

The TSDF the ROI and close-front scores need is fused, as in the paper, from the map's *rendered*
depth (and colour) at each keyframe pose, incrementally: a keyframe is fused the first time the
policy sees it in ``mapper.keyframes`` (right after its insertion).
"""

from __future__ import annotations

from collections import deque
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from roigsf_ros.camera import check_pose
from roigsf_ros.errors import InputError
from roigsf_ros.keyframes import KeyframePolicy, register_policy
from roigsf_ros.nbv import NBVConfig, NBVResult, NBVScorer
from roigsf_ros.replica import Frame
from roigsf_ros.tsdf import TSDFVolume

if TYPE_CHECKING:
    from roigsf_ros.mapping import Mapper


class StreamNBVPolicy(KeyframePolicy):
    """Windowed stream selection: at each trigger the best-scoring window frame becomes a keyframe.

    Parameters (all optional):

    - ``window`` (8): candidates kept, the most recent frames that are not keyframes yet.
    - ``trigger_every`` (``window``): frames between two selections (counted after the first frame).
    - ``seed`` (0): seed of the ``"random"`` pick (unused by the scored modes).
    - ``voxel_size_m`` / ``sdf_trunc_m`` (None): the scoring TSDF; None takes the mapper's
      ``mesh_voxel_size_m`` / ``mesh_sdf_trunc_m``.
    - ``min_alpha`` (None): rendered depth is fused where the map's alpha reaches this (None: the
      mapper's ``mesh_min_alpha``); the depth kind is the mapper's ``mesh_depth``.
    - ``epsilon``, ``delta``, ``fisher_downsample``, ``sigma_p``, ``phi``, ``near_m``, ``far_m``:
      passed to :class:`roigsf_ros.nbv.NBVConfig` (None: its default). The mode is the policy name.

    ``h_train``: the ROI modes use the mapper's running ``h_train`` when it covers the scorer's
    parameters with the same outputs and ``sigma_p`` is 1 (its Fisher is unweighted); otherwise the
    scorer recomputes it from the keyframe poses, as it always does for ``"fisherrf"``. W_f (close
    front) is computed exactly from the keyframe poses on the current TSDF surface.

    After a trigger, :attr:`last_result` is the scorer's :class:`NBVResult` (None for random),
    :attr:`last_candidate_ids` the window's frame ids in the scored order, and
    :attr:`inserted_ids` lists every frame the policy inserted itself.
    """

    mode: str | None = None
    """NBV score mode (None: random pick)."""

    def __init__(
        self,
        window: int = 8,
        trigger_every: int | None = None,
        seed: int = 0,
        voxel_size_m: float | None = None,
        sdf_trunc_m: float | None = None,
        min_alpha: float | None = None,
        epsilon: float | None = None,
        delta: float | None = None,
        fisher_downsample: int | None = None,
        sigma_p: float | None = None,
        phi: float | None = None,
        near_m: float | None = None,
        far_m: float | None = None,
    ) -> None:
        if int(window) != window or int(window) < 1:
            raise InputError("window", f"must be a positive integer, got {window!r}")
        trigger_every = int(window) if trigger_every is None else trigger_every
        if int(trigger_every) != trigger_every or int(trigger_every) < 1:
            raise InputError("trigger_every", f"must be a positive integer, got {trigger_every!r}")
        if min_alpha is not None and not 0.0 <= float(min_alpha) <= 1.0:
            raise InputError("min_alpha", f"must be in [0, 1], got {min_alpha}")
        self.window = int(window)
        self.trigger_every = int(trigger_every)
        self.seed = int(seed)
        self.voxel_size_m = voxel_size_m
        self.sdf_trunc_m = sdf_trunc_m
        self.min_alpha = min_alpha
        nbv = {"epsilon": epsilon, "delta": delta, "fisher_downsample": fisher_downsample, "sigma_p": sigma_p,
               "phi": phi, "near_m": near_m, "far_m": far_m}  # fmt: skip
        self._nbv_overrides = {k: v for k, v in nbv.items() if v is not None}
        self.config = NBVConfig(mode=self.mode or "roi-gsurfisher", **self._nbv_overrides)
        self.scorer = NBVScorer(self.config)
        self.reset()

    # ------------------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the window, the TSDF, the counters and re-seed the random pick."""
        self._buffer: deque[Frame] = deque(maxlen=self.window)
        self._seen = 0
        self._since_trigger = 0
        self._n_fused = 0
        self._rng = np.random.default_rng(self.seed)
        self.tsdf: TSDFVolume | None = None
        """The scoring TSDF (rendered depth of the keyframes); None until the first keyframe is fused."""
        self.inserted_ids: list[int] = []
        """Frame ids this policy inserted itself with ``mapper.add_keyframe`` (not the first frame)."""
        self.triggers = 0
        """Selections made so far."""
        self.last_result: NBVResult | None = None
        self.last_candidate_ids: list[int] = []

    def params(self) -> dict[str, Any]:
        """Window, trigger, seed, TSDF settings and the NBV overrides, for metrics.json."""
        out: dict[str, Any] = {"window": self.window, "trigger_every": self.trigger_every, "seed": self.seed}
        out |= {"voxel_size_m": self.voxel_size_m, "sdf_trunc_m": self.sdf_trunc_m, "min_alpha": self.min_alpha}
        return out | dict(self._nbv_overrides)

    @property
    def pending_ids(self) -> list[int]:
        """Frame ids currently in the candidate window."""
        return [f.index for f in self._buffer]

    # ------------------------------------------------------------------------------ TSDF
    @property
    def needs_tsdf(self) -> bool:
        """Whether the mode scores against the TSDF (ROI and close-front modes)."""
        return self.mode is not None and self.mode != "fisherrf"

    def sync_tsdf(self, mapper: Mapper) -> int:
        """Fuse the rendered depth at every keyframe pose not fused yet; returns how many were fused."""
        if not self.needs_tsdf:
            self._n_fused = len(mapper.keyframes)
            return 0
        cfg = mapper.config
        if self.tsdf is None and len(mapper.keyframes) > self._n_fused:
            voxel = self.voxel_size_m if self.voxel_size_m is not None else cfg.mesh_voxel_size_m
            trunc = self.sdf_trunc_m if self.sdf_trunc_m is not None else max(cfg.mesh_sdf_trunc_m, voxel)
            self.tsdf = TSDFVolume(voxel_size_m=voxel, sdf_trunc_m=trunc, depth_max_m=cfg.max_depth_m)
        min_alpha = cfg.mesh_min_alpha if self.min_alpha is None else float(self.min_alpha)
        n = 0
        while self._n_fused < len(mapper.keyframes):
            T = mapper.keyframes[self._n_fused].T_wc
            depth, rgb = mapper.rendered_rgbd(T, min_alpha=min_alpha)
            self.tsdf.integrate(depth, T, mapper.intr, rgb)
            self._n_fused += 1
            n += 1
        return n

    # ------------------------------------------------------------------------------ scoring
    def _h_train(self, mapper: Mapper) -> dict[str, torch.Tensor] | None:
        """The mapper's running h_train when it matches what the scorer needs, else None (recompute)."""
        cfg, mcfg = self.config, mapper.config
        if self.mode == "fisherrf" or not mcfg.track_h_train or cfg.sigma_p != 1.0:
            return None
        if tuple(mcfg.fisher_outputs) != tuple(cfg.fisher_outputs):
            return None
        h = mapper.h_train
        needed = [p for p in cfg.fisher_params if p != "sh_rest" or mapper.map.sh_rest is not None]
        return h if all(p in h for p in needed) else None

    def choose(self, candidates: list[Frame], mapper: Mapper) -> int:
        """Index into ``candidates`` of the frame to insert (scores poses only)."""
        if self.mode is None:
            self.last_result = None
            return int(self._rng.integers(len(candidates)))
        self.sync_tsdf(mapper)
        result = self.scorer.score(
            mapper.map,
            self._h_train(mapper),
            self.tsdf if self.needs_tsdf else None,
            mapper.keyframe_poses,
            [f.T_wc for f in candidates],
            mapper.intr,
            mode=self.mode,
        )
        self.last_result = result
        return result.best_index

    # ------------------------------------------------------------------------------ stream
    def observe(self, frame: Frame, mapper: Mapper) -> bool:
        """True only for the first frame; at a trigger inserts the window's best frame itself (returns False).

        Frames with a non-rigid pose are ignored (never candidates).
        """
        try:
            check_pose(frame.T_wc, f"frame {frame.index} pose")
        except InputError:
            return False
        first = self._seen == 0
        self._seen += 1
        if first:
            return True  # the caller inserts it; it is fused at the next call
        self.sync_tsdf(mapper)
        self._buffer.append(frame)
        self._since_trigger += 1
        if self._since_trigger < self.trigger_every:
            return False
        self._since_trigger = 0
        candidates = list(self._buffer)
        self.last_candidate_ids = [f.index for f in candidates]
        pick = self.choose(candidates, mapper)
        winner = candidates[pick]
        self._buffer.remove(winner)
        self.triggers += 1
        if mapper.add_keyframe(winner):
            self.inserted_ids.append(int(winner.index))
            self.sync_tsdf(mapper)
        return False


def _make(name: str, mode: str | None) -> type[StreamNBVPolicy]:
    cls = type(
        "StreamPolicy_" + name.replace("-", "_"),
        (StreamNBVPolicy,),
        {
            "mode": mode,
            "__doc__": f"Stream policy {name!r}: " + ("seeded random pick." if mode is None else f"NBV mode {mode!r}."),
        },
    )
    return register_policy(name)(cls)  # type: ignore[return-value]


RandomStream = _make("random", None)
ROIGSurFisherStream = _make("roi-gsurfisher", "roi-gsurfisher")
ROIFisherStream = _make("roi-fisher", "roi-fisher")
CloseFrontStream = _make("close-front", "close-front")
FisherRFStream = _make("fisherrf", "fisherrf")

STREAM_POLICIES = ("random", "roi-gsurfisher", "roi-fisher", "close-front", "fisherrf")
"""Names this module registers."""

__all__ = [
    "STREAM_POLICIES",
    "CloseFrontStream",
    "FisherRFStream",
    "ROIFisherStream",
    "ROIGSurFisherStream",
    "RandomStream",
    "StreamNBVPolicy",
]
