"""Stream NBV keyframe policies: pick the next keyframe from a window of recent frames by its pose.

The "stream" setting of the NBV experiments: frames arrive in trajectory order, as in SLAM. The
policy keeps the most recent ``window`` frames as candidates; every ``trigger_every`` frames
(default: ``window``) it scores the candidates' *poses* (never their images) against the current
map and TSDF and turns the best one into a keyframe. A frame's image is used only once it has been
chosen, when it is inserted into the mapper. The first frame is always a keyframe (empty map).

Registered names (see :func:`roigsf_ros.policies.base.make_policy`): ``"random"`` (a seeded uniform
pick from the window, the baseline), one policy per :data:`roigsf_ros.nbv.scorer.MODES`:
``"roi-gsurfisher"``, ``"roi-fisher"``, ``"close-front"``, ``"fisherrf"``, and ``"novelty"`` (beyond the paper:
the window frame whose *captured* depth shows the most surface no keyframe's depth has shown,
:mod:`roigsf_ros.nbv.novelty`; the scored modes can add the same term with ``novelty_weight``). Novelty reads a
candidate's depth, which a stream frame has (the camera took it) and a pool candidate has not.

At a trigger ``observe`` returns the window's winner, generally a *past* frame: the caller inserts
it (the policy never changes the map). With ``lookahead`` (beyond the paper) a trigger decides the frames before the
newest ``lookahead``, so a window is decided later and :meth:`StreamNBVPolicy.finish` decides what is still held at
the end of the sequence. The window and trigger rule live in :class:`CandidateWindow`,
which the keyframe selector node also runs when the planner node chooses for it.

The TSDF the ROI and close-front scores need is fused, as in the paper, from the map's *rendered*
depth (and colour) at each keyframe pose, incrementally (:class:`roigsf_ros.nbv.state.ScoringState`,
the same state the planner node keeps): a keyframe is fused the first time the policy sees its pose in
``keyframe_map.keyframe_poses`` (right after its insertion).
"""

from __future__ import annotations

import inspect
from collections import deque
from collections.abc import Mapping
from dataclasses import fields
from types import MappingProxyType
from typing import Any

import numpy as np
import torch

from roigsf_ros.core.camera import check_pose
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame
from roigsf_ros.mapping.tsdf import TSDFVolume
from roigsf_ros.nbv.config import NBVConfig
from roigsf_ros.nbv.novelty import (
    NOVELTY_RADIUS_M,
    NOVELTY_VOXEL_M,
    ObservedSurface,
    check_novelty_settings,
    fuse_novelty,
)
from roigsf_ros.nbv.scorer import NBVResult
from roigsf_ros.nbv.state import ScoringState, running_h_train_fits
from roigsf_ros.policies.base import KeyframeMap, KeyframePolicy, register_policy, unknown_parameters


class CandidateWindow:
    """The stream window and trigger: the last ``window`` frames not chosen yet, a selection every ``trigger_every``.

    :meth:`push` answers which frames to decide among now: the very first frame alone (an empty map makes
    it a keyframe), then the whole window every ``trigger_every`` frames. The caller picks one and
    :meth:`remove` s it, so a frame is chosen at most once.
    """

    def __init__(self, window: int = 8, trigger_every: int | None = None) -> None:
        if int(window) != window or int(window) < 1:
            raise InputError("window", f"must be a positive integer, got {window!r}")
        trigger_every = int(window) if trigger_every is None else trigger_every
        if int(trigger_every) != trigger_every or int(trigger_every) < 1:
            raise InputError("trigger_every", f"must be a positive integer, got {trigger_every!r}")
        self.window = int(window)
        self.trigger_every = int(trigger_every)
        self.reset()

    def reset(self) -> None:
        """Forget the window and the counts."""
        self._buffer: deque[Frame] = deque(maxlen=self.window)
        self._seen = 0
        self._since_trigger = 0

    @property
    def pending_ids(self) -> list[int]:
        """Frame ids currently in the window."""
        return [f.index for f in self._buffer]

    def push(self, frame: Frame) -> tuple[list[Frame], bool]:
        """Add ``frame``; returns (frames to decide among now, whether this is the first frame). [] = nothing due."""
        self._seen += 1
        if self._seen == 1:
            return [frame], True
        self._buffer.append(frame)
        self._since_trigger += 1
        if self._since_trigger < self.trigger_every:
            return [], False
        self._since_trigger = 0
        return list(self._buffer), False

    def held(self) -> list[Frame]:
        """The frames in the window now, oldest first (what a selection would decide among)."""
        return list(self._buffer)

    def remove(self, frame: Frame) -> None:
        """Drop ``frame`` (by identity: frames hold arrays) from the window if it is still there."""
        for i, f in enumerate(self._buffer):
            if f is frame:
                del self._buffer[i]
                return


def split_lookahead(frames: list[Frame], lookahead: int) -> tuple[list[Frame], list[Frame]]:
    """(candidates, ahead): the held ``frames`` (oldest first) but the newest ``lookahead``, and those newest."""
    n = len(frames) - max(int(lookahead), 0)
    return frames[: max(n, 0)], frames[max(n, 0) :]


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
    - ``trigger`` ("window"): "window" inserts the best candidate at every trigger (the paper's setting, one
      keyframe per window); "adaptive" (beyond the paper) inserts it only when its raw gain is at least
      ``adaptive_ratio`` (1.0) x the median of the last ``adaptive_history`` (8) triggers' best gains, or
      after ``adaptive_max_gap`` (4) triggers without a keyframe; a skipped window's frames stay candidates.
      Use it with ``trigger_every`` < ``window`` so that the keyframe rate adapts around 1 / (2 trigger_every).
      "budget" (beyond the paper) keeps the paper's keyframe count but not its spacing: each frame earns
      1 / ``budget_every`` (None: ``window``) of a keyframe, at most ``budget_burst`` (3) are banked, and a trigger
      holding a whole one inserts its best when the gain reaches ``adaptive_ratio`` x the median of the recent
      triggers' gains, or when the next trigger would overflow the bank; so a sequence of F frames yields at most
      1 + (F - 1) // ``budget_every`` keyframes, placed where the gain is high. The gain is the novelty N when it
      is scored (below), else the unseen fraction U when ``unseen_weight`` > 0 (new space is what a keyframe should
      bring), else F (Eq. 10) / I_vis.
    - ``novelty_weight`` (0; beyond the paper): adds ``novelty_weight x z(N)`` to the scored modes' fused score, N
      the candidate's observed novelty (:meth:`roigsf_ros.nbv.novelty.ObservedSurface.new_area_m2`: the area of its
      back-projected depth farther than ``novelty_radius_m`` (0.05) from all the depth of the frames this policy
      returned, voxelised at ``novelty_voxel_m`` (0.025)). The ``"novelty"`` policy ranks by N alone.
    - ``lookahead`` (0; beyond the paper, needs the novelty): a trigger decides among the window's frames except the
      newest ``lookahead``, which only judge them: a candidate's N becomes its own new area plus the most one of
      those newer frames would still add after it (:meth:`ObservedSurface.lookahead_new_voxels`), so surface a
      later frame also shows is left to the next pick. The window holds ``window + lookahead`` frames; with
      ``lookahead = trigger_every`` each window is decided one trigger late, and :meth:`finish` decides the
      frames still held when the sequence ends.
    - ``novelty_measure`` ("area"; beyond the paper): what N counts. "area" is the candidate's own new surface
      (above); "pixels" counts the pixels of all the frames the window holds (candidates and those ahead) whose
      surface no keyframe observed and the candidate (with the best frame ahead, under ``lookahead``) brings within
      ``novelty_radius_m`` (:meth:`ObservedSurface.held_pixels_covered`): surface the trajectory looks at often or
      from near weighs more, as it does in the PSNR of the frames between keyframes.
    - ``epsilon``, ``delta``, ``fisher_downsample``, ``sigma_p``, ``phi``, ``near_m``, ``far_m`` and any
      other :class:`roigsf_ros.nbv.config.NBVConfig` field by name (e.g. ``unseen_weight``): passed to the
      scorer's config (None: its default). The mode is the policy name; unknown names raise InputError.

    ``h_train``: the ROI modes use the map's running ``h_train`` when it covers the scorer's
    parameters with the same outputs and ``sigma_p`` is 1 (its Fisher is unweighted); otherwise the
    scorer recomputes it from the keyframe poses, as it always does for ``"fisherrf"``. W_f (close
    front) is computed exactly from the keyframe poses on the current TSDF surface.

    After a trigger, :attr:`last_result` is the scorer's :class:`NBVResult` (None for random),
    :attr:`last_candidate_ids` the window's frame ids in the scored order (:attr:`last_ahead_ids` those that only
    judged them), and
    :attr:`inserted_ids` lists every frame the policy chose at a trigger (not the first frame).
    """

    mode: str | None = None
    """NBV score mode (None: random pick, or the novelty alone when :attr:`novelty_only`)."""
    novelty_only: bool = False
    """Rank by the observed novelty alone (policy ``"novelty"``)."""

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
        trigger: str = "window",
        adaptive_ratio: float = 1.0,
        adaptive_history: int = 8,
        adaptive_max_gap: int = 4,
        budget_every: float | None = None,
        budget_burst: float = 3.0,
        novelty_weight: float = 0.0,
        novelty_voxel_m: float = NOVELTY_VOXEL_M,
        novelty_radius_m: float = NOVELTY_RADIUS_M,
        novelty_measure: str = "area",
        lookahead: int = 0,
        **nbv_options: Any,
    ) -> None:
        if not (isinstance(lookahead, int | float) and int(lookahead) == lookahead and lookahead >= 0):
            raise InputError("lookahead", f"must be an integer >= 0, got {lookahead!r}")
        self.lookahead = int(lookahead)
        CandidateWindow(window, trigger_every)  # checks both as given
        every = int(window) if trigger_every is None else trigger_every
        self.candidates = CandidateWindow(int(window) + self.lookahead, every)
        if not (isinstance(novelty_weight, int | float) and np.isfinite(novelty_weight) and novelty_weight >= 0):
            raise InputError("novelty_weight", f"must be a finite number >= 0, got {novelty_weight!r}")
        if novelty_weight > 0 and self.mode is None:
            alone = " (it ranks by the novelty alone)" if self.novelty_only else " (policy novelty ranks by it alone)"
            raise InputError("novelty_weight", f"policy {self.name!r} has no fused score to add it to{alone}")
        self.novelty_weight = float(novelty_weight)
        if self.lookahead and not self.uses_novelty:
            raise InputError("lookahead", "judges the observed novelty: use policy novelty or novelty_weight > 0")
        if self.lookahead and trigger != "window":
            raise InputError("lookahead", f"decides one keyframe per trigger: needs trigger 'window', not {trigger!r}")
        check_novelty_settings(novelty_voxel_m, novelty_radius_m, novelty_measure)  # now, not at the first frame
        if novelty_measure != "area" and not self.uses_novelty:
            raise InputError("novelty_measure", "counts the observed novelty: use policy novelty or novelty_weight > 0")
        self.novelty_measure = novelty_measure
        self.novelty_voxel_m = float(novelty_voxel_m)
        self.novelty_radius_m = float(novelty_radius_m)
        for name, v in (("voxel_size_m", voxel_size_m), ("sdf_trunc_m", sdf_trunc_m)):
            if v is not None and not (np.isfinite(v) and v > 0):
                raise InputError(name, f"must be a finite number > 0 (m), got {v!r}")
        if min_alpha is not None and not 0.0 <= float(min_alpha) <= 1.0:
            raise InputError("min_alpha", f"must be in [0, 1], got {min_alpha}")
        if trigger not in TRIGGERS:
            raise InputError("trigger", f"must be one of {', '.join(TRIGGERS)}, got {trigger!r}")
        if trigger != "window" and self.mode is None and not self.novelty_only:
            raise InputError("trigger", f"{trigger!r} needs a scored mode (random has no gain)")
        if not (np.isfinite(adaptive_ratio) and adaptive_ratio >= 0):
            raise InputError("adaptive_ratio", f"must be a finite number >= 0, got {adaptive_ratio!r}")
        for name, v in (("adaptive_history", adaptive_history), ("adaptive_max_gap", adaptive_max_gap)):
            if int(v) != v or int(v) < 1:
                raise InputError(name, f"must be a positive integer, got {v!r}")
        budget_every = float(int(window) if budget_every is None else budget_every)
        every = self.candidates.trigger_every
        if trigger == "budget" and not (np.isfinite(budget_every) and budget_every >= every):
            raise InputError("budget_every", f"must be >= trigger_every ({every}), got {budget_every!r}")
        if trigger == "budget" and not (np.isfinite(budget_burst) and budget_burst >= 1 + every / budget_every):
            raise InputError("budget_burst", f"must be >= 1 + trigger_every / budget_every "
                             f"({1 + every / budget_every:g}), got {budget_burst!r}")  # fmt: skip
        self.budget_every = budget_every
        self.budget_burst = float(budget_burst)
        self.trigger = trigger
        self.adaptive_ratio = float(adaptive_ratio)
        self.adaptive_history = int(adaptive_history)
        self.adaptive_max_gap = int(adaptive_max_gap)
        self.window = int(window)
        self.trigger_every = self.candidates.trigger_every
        self.seed = int(seed)
        self.voxel_size_m = voxel_size_m
        self.sdf_trunc_m = sdf_trunc_m
        self.min_alpha = min_alpha
        nbv = {"epsilon": epsilon, "delta": delta, "fisher_downsample": fisher_downsample, "sigma_p": sigma_p,
               "phi": phi, "near_m": near_m, "far_m": far_m}  # fmt: skip
        unknown = sorted(set(nbv_options) - {f.name for f in fields(NBVConfig)} | ({"mode"} & set(nbv_options)))
        if unknown:
            own = inspect.signature(StreamNBVPolicy.__init__).parameters  # the names a typo is matched against
            takes = {k for k, p in own.items() if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and k != "self"}
            raise unknown_parameters(self.name, unknown, takes | {f.name for f in fields(NBVConfig)} - {"mode"})
        nbv |= nbv_options
        self._nbv_overrides = {k: v for k, v in nbv.items() if v is not None}
        self.config = NBVConfig(mode=self.mode or "roi-gsurfisher", **self._nbv_overrides)
        self.reset()

    # ------------------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the window, the TSDF, the counters and re-seed the random pick."""
        self.candidates.reset()
        self._rng = np.random.default_rng(self.seed)
        self.state: ScoringState | None = None
        """The scoring state (TSDF, its products); made at the first selection, from the map's settings."""
        self.inserted_ids: list[int] = []
        """Frame ids this policy chose at its triggers (not the first frame)."""
        self.triggers = 0
        """Selections made so far."""
        self.last_result: NBVResult | None = None
        self.last_candidate_ids: list[int] = []
        self.last_ahead_ids: list[int] = []
        """Frame ids that judged the last selection's candidates without being candidates (``lookahead``)."""
        self.gains: deque[float] = deque(maxlen=self.adaptive_history)
        """Raw gains of the recent triggers' best candidates (``trigger="adaptive"`` or ``"budget"``)."""
        self.skipped_triggers = 0
        """Triggers that inserted no keyframe (``trigger="adaptive"`` or ``"budget"``; with "budget" also those
        that were not scored because less than a whole keyframe was banked)."""
        self._gap = 0
        self.tokens = 0.0
        """Keyframes banked (``trigger="budget"``): + 1 / ``budget_every`` per frame after the first."""
        self.observed = (
            ObservedSurface(self.novelty_voxel_m, self.novelty_radius_m, self.novelty_measure)
            if self.uses_novelty
            else None
        )
        """What the depth of the frames this policy returned observed (when novelty is scored)."""
        self.last_novelty: np.ndarray | None = None
        """[M] observed novelty (m^2, or pixels) of the last trigger's candidates, when novelty is scored."""

    def params(self) -> dict[str, Any]:
        """Window, trigger, seed, TSDF settings and the NBV overrides, for metrics.json."""
        out: dict[str, Any] = {"window": self.window, "trigger_every": self.trigger_every, "seed": self.seed}
        if self.trigger == "adaptive":
            out |= {"trigger": self.trigger, "adaptive_ratio": self.adaptive_ratio,
                    "adaptive_history": self.adaptive_history, "adaptive_max_gap": self.adaptive_max_gap}  # fmt: skip
        elif self.trigger == "budget":
            out |= {"trigger": self.trigger, "adaptive_ratio": self.adaptive_ratio,
                    "adaptive_history": self.adaptive_history, "budget_every": self.budget_every,
                    "budget_burst": self.budget_burst}  # fmt: skip
        if self.uses_novelty:
            out |= {"novelty_voxel_m": self.novelty_voxel_m, "novelty_radius_m": self.novelty_radius_m}
            out |= {"novelty_measure": self.novelty_measure} if self.novelty_measure != "area" else {}
            out |= {"novelty_weight": self.novelty_weight} if not self.novelty_only else {}
            out |= {"lookahead": self.lookahead} if self.lookahead else {}
        if self.mode is None:
            return out
        out |= {"voxel_size_m": self.voxel_size_m, "sdf_trunc_m": self.sdf_trunc_m, "min_alpha": self.min_alpha}
        return out | dict(self._nbv_overrides)

    @property
    def uses_novelty(self) -> bool:
        """Whether candidates' observed novelty is scored (policy ``"novelty"`` or ``novelty_weight`` > 0)."""
        return self.novelty_only or self.novelty_weight > 0

    @property
    def pending_ids(self) -> list[int]:
        """Frame ids currently in the candidate window."""
        return self.candidates.pending_ids

    @property
    def tsdf(self) -> TSDFVolume | None:
        """The scoring TSDF (rendered depth of the keyframes); None until the first keyframe is fused."""
        return self.state.tsdf if self.state is not None else None

    # ------------------------------------------------------------------------------ TSDF
    @property
    def needs_tsdf(self) -> bool:
        """Whether the mode scores against the TSDF (ROI and close-front modes)."""
        return self.mode is not None and self.mode != "fisherrf"

    def _state(self, keyframe_map: KeyframeMap) -> ScoringState:
        """The scoring state, made on first use with the TSDF settings (None: the map's mesh settings)."""
        if self.state is None:
            self.state = ScoringState.for_map(keyframe_map.config, self.config, self.voxel_size_m, self.sdf_trunc_m)
        return self.state

    def _render(self, keyframe_map: KeyframeMap):
        min_alpha = keyframe_map.config.mesh_min_alpha if self.min_alpha is None else float(self.min_alpha)
        return lambda T: keyframe_map.rendered_rgbd(T, min_alpha=min_alpha)

    def sync_tsdf(self, keyframe_map: KeyframeMap) -> int:
        """Fuse the rendered depth at every keyframe pose not fused yet; returns how many were fused."""
        if not self.needs_tsdf:
            return 0
        return self._state(keyframe_map).sync(
            self._render(keyframe_map), keyframe_map.keyframe_poses, keyframe_map.intr
        )

    # ------------------------------------------------------------------------------ scoring
    def _h_train(self, keyframe_map: KeyframeMap) -> dict[str, torch.Tensor] | None:
        """The map's running h_train when it matches what the scorer needs, else None (recompute)."""
        mcfg = keyframe_map.config
        if not mcfg.track_h_train or self.mode is None or not keyframe_map.h_train_complete:
            return None  # a map loaded without its h_train.npz lacks the loaded keyframes': recomputed from the poses
        h = keyframe_map.h_train
        fits = running_h_train_fits(h, tuple(mcfg.fisher_outputs), self.config, self.mode)
        needed = [p for p in self.config.fisher_params if p != "sh_rest" or keyframe_map.map.sh_rest is not None]
        return h if fits and all(p in h for p in needed) else None

    def novelty(
        self, candidates: list[Frame], keyframe_map: KeyframeMap, ahead: list[Frame] | None = None
    ) -> np.ndarray:
        """[M] observed novelty (``novelty_measure``: m^2 or pixels) of each candidate's valid depth against the frames
        returned so far (with the frames ``ahead``: its lookahead novelty, ``lookahead`` in the class docstring).
        """
        if self.observed is None:
            raise InputError("novelty_weight", "novelty is not scored by this policy")
        return self.observed.frames_novelty(candidates, keyframe_map.intr, keyframe_map.config, ahead)

    def _returned(self, frame: Frame, keyframe_map: KeyframeMap) -> None:
        """Note a frame this policy returns (the caller inserts it): its depth is observed from now on."""
        if self.observed is not None:
            self.observed.add_frame(frame, keyframe_map.intr, keyframe_map.config)

    def choose(self, candidates: list[Frame], keyframe_map: KeyframeMap, ahead: list[Frame] | None = None) -> int:
        """Index into ``candidates`` of the frame to insert (scores poses, and with novelty the frames' depth; the
        frames ``ahead`` only judge the novelty).
        """
        self.last_novelty = self.novelty(candidates, keyframe_map, ahead) if self.uses_novelty else None
        if self.mode is None:
            self.last_result = None
            if self.novelty_only:
                return int(np.argmax(self.last_novelty))  # ties: the oldest
            return int(self._rng.integers(len(candidates)))
        mcfg = keyframe_map.config
        result = self._state(keyframe_map).score(
            keyframe_map.map,
            self._h_train(keyframe_map),
            tuple(mcfg.fisher_outputs),
            keyframe_map.keyframe_poses,
            [f.T_wc for f in candidates],
            keyframe_map.intr,
            self._render(keyframe_map),
            mode=self.mode,
        )
        self.last_result = result
        if self.last_novelty is None:
            return result.best_index
        return int(np.argmax(fuse_novelty(result.fused, self.last_novelty, self.novelty_weight)))

    # ------------------------------------------------------------------------------ stream
    def observe(self, frame: Frame, keyframe_map: KeyframeMap) -> list[Frame]:
        """The first frame; at a trigger the window's best frame (a past one, generally); else nothing.

        Frames with a non-rigid pose are ignored (never candidates).
        """
        try:
            check_pose(frame.T_wc, f"frame {frame.index} pose")
        except InputError:
            return []
        self.sync_tsdf(keyframe_map)
        candidates, first = self.candidates.push(frame)
        if not first:
            self.tokens = min(self.tokens + 1.0 / self.budget_every, self.budget_burst)
        if first:
            self._returned(frame, keyframe_map)
        if first or not candidates:
            return candidates
        if self.trigger == "budget" and self.tokens < 1.0 - 1e-9:
            self.skipped_triggers += 1  # nothing banked: not even scored; the window's frames stay candidates
            return []
        return self._decide(candidates, keyframe_map)

    def finish(self, keyframe_map: KeyframeMap) -> list[Frame]:
        """With ``lookahead``: the best of the frames still held (nothing is ahead of them now), once; else nothing."""
        held = self.candidates.held()
        if not self.lookahead or not held:
            return []
        self.sync_tsdf(keyframe_map)
        chosen = self._decide(held, keyframe_map, lookahead=0)
        for f in held:
            self.candidates.remove(f)  # decided: a second call returns nothing
        return chosen

    def _decide(self, frames: list[Frame], keyframe_map: KeyframeMap, lookahead: int | None = None) -> list[Frame]:
        """Choose among ``frames`` (all but the newest ``lookahead``, which only judge them) and return the pick."""
        candidates, ahead = split_lookahead(frames, self.lookahead if lookahead is None else lookahead)
        if not candidates:
            return []  # the first trigger of a late decision: every frame held is still ahead
        self.last_candidate_ids = [f.index for f in candidates]
        self.last_ahead_ids = [f.index for f in ahead]
        pick = self.choose(candidates, keyframe_map, ahead)
        winner = candidates[pick]
        self.triggers += 1
        if self.trigger != "window" and not self._accept(pick):
            self.skipped_triggers += 1  # the window's frames stay candidates
            return []
        if self.trigger == "budget":
            self.tokens -= 1.0
        self.candidates.remove(winner)
        self.inserted_ids.append(int(winner.index))
        self._returned(winner, keyframe_map)
        return [winner]

    def gain(self, pick: int) -> float:
        """Raw (not z-scored, so comparable across windows) expected gain of candidate ``pick`` of the last
        trigger: its observed novelty N (m^2) when novelty is scored; else F of Eq. 10 for the Fisher modes, I_vis of
        Eq. 14 for close-front; for ``trigger="budget"`` with the unseen term on, its unseen fraction U.
        """
        if self.last_novelty is not None:
            return float(self.last_novelty[pick])
        r = self.last_result
        if r is None:
            return 0.0
        if self.trigger == "budget" and getattr(r, "unseen", None) is not None:
            return float(r.unseen[pick])
        return float(r.close_front[pick] if self.mode == "close-front" else r.fisher[pick])

    def _accept(self, pick: int) -> bool:
        """Adaptive and budget triggers (beyond the paper): insert the window's best only when its raw gain reaches
        ``adaptive_ratio`` x the median of the last ``adaptive_history`` triggers' best gains, or when forced:
        ``adaptive_max_gap`` triggers in a row inserted nothing ("adaptive"), or the bank would overflow by the
        next trigger ("budget"). The first two triggers always insert.
        """
        g = self.gain(pick)
        ok = len(self.gains) < 2 or g >= self.adaptive_ratio * float(np.median(self.gains))
        if self.trigger == "budget":
            ok = ok or self.tokens + self.trigger_every / self.budget_every > self.budget_burst + 1e-9
        else:
            ok = ok or self._gap + 1 >= self.adaptive_max_gap
        self.gains.append(g)
        self._gap = 0 if ok else self._gap + 1
        return ok


TRIGGERS = ("window", "adaptive", "budget")
"""Stream triggers: ``window`` (the paper's setting: one keyframe per trigger), ``adaptive`` or ``budget`` (see
:meth:`StreamNBVPolicy._accept`)."""


def _make(name: str, mode: str | None, novelty_only: bool = False) -> type[StreamNBVPolicy]:
    what = f"NBV mode {mode!r}." if mode is not None else "seeded random pick."
    what = "observed novelty alone." if novelty_only else what
    cls = type(
        "StreamPolicy_" + name.replace("-", "_"),
        (StreamNBVPolicy,),
        {
            "mode": mode,
            "novelty_only": novelty_only,
            "reads_map": mode is not None,
            "__doc__": f"Stream policy {name!r}: {what}",
        },
    )
    return register_policy(name)(cls)  # type: ignore[return-value]


RandomStream = _make("random", None)
ROIGSurFisherStream = _make("roi-gsurfisher", "roi-gsurfisher")
ROIFisherStream = _make("roi-fisher", "roi-fisher")
CloseFrontStream = _make("close-front", "close-front")
FisherRFStream = _make("fisherrf", "fisherrf")
NoveltyStream = _make("novelty", None, novelty_only=True)

STREAM_POLICIES = ("random", "roi-gsurfisher", "roi-fisher", "close-front", "fisherrf", "novelty")
"""Names this module registers."""

RECOMMENDED_STREAM_POLICY = "roi-gsurfisher"
"""The policy of the variant the README recommends for choosing keyframes in a stream (the stream variant); its
parameters are :data:`RECOMMENDED_STREAM` and its mapper's :data:`RECOMMENDED_STREAM_MAPPER`."""
RECOMMENDED_STREAM: Mapping[str, int | float] = MappingProxyType(
    {"window": 13, "unseen_weight": 1.0, "novelty_weight": 4.0, "lookahead": 13}
)
"""The stream variant's parameters (``roi-gsurfisher:window=13:unseen_weight=1:novelty_weight=4:lookahead=13``):
``make_policy(RECOMMENDED_STREAM_POLICY, **RECOMMENDED_STREAM)``. Not the default, which stays the paper's one
keyframe per window of 8. As node parameters (``config/recommended/stream.yaml``) ``unseen_weight`` belongs to the
planner, which scores for the selector, and the rest to the selector. Read-only."""
RECOMMENDED_STREAM_MAPPER: Mapping[str, float] = MappingProxyType({"init_max_stretch": 4.0})
"""The :class:`~roigsf_ros.mapping.mapper.MapperConfig` fields the stream variant was measured with (its keyframes
are far apart, and stretched new surfels close the gaps between them at grazing angles). Read-only."""

__all__ = [
    "RECOMMENDED_STREAM",
    "RECOMMENDED_STREAM_MAPPER",
    "RECOMMENDED_STREAM_POLICY",
    "STREAM_POLICIES",
    "TRIGGERS",
    "CandidateWindow",
    "CloseFrontStream",
    "FisherRFStream",
    "NoveltyStream",
    "ROIFisherStream",
    "ROIGSurFisherStream",
    "RandomStream",
    "StreamNBVPolicy",
    "split_lookahead",
]
