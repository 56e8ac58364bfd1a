"""The simple keyframe rules: every frame, every n-th frame, and GauS-SLAM's unmapped-pixel rule."""

from __future__ import annotations

from typing import Any

import numpy as np

from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame
from roigsf_ros.policies.base import KeyframeMap, KeyframePolicy, register_policy


@register_policy("all")
class AllFrames(KeyframePolicy):
    """Every frame is a keyframe."""

    reads_map = False

    def observe(self, frame: Frame, keyframe_map: KeyframeMap) -> list[Frame]:
        """Always the frame itself."""
        return [frame]


@register_policy("every-n")
class EveryN(KeyframePolicy):
    """Every ``n``-th frame seen (the 0th, n-th, 2n-th, ...), counted in arrival order.

    The parameter's public name is ``every_n`` (the node parameter, ``roigsf map --every-n``, a spec
    ``every-n:every_n=10``); ``n`` (positional here, and in older specs and results) is an accepted alias.
    """

    reads_map = False

    def __init__(self, n: int | None = None, *, every_n: int | None = None) -> None:
        if n is not None and every_n is not None and n != every_n:
            raise InputError("every_n", f"given twice, as every_n={every_n} and as its alias n={n}")
        name, value = ("every_n", every_n) if every_n is not None else ("n", 5 if n is None else n)
        if int(value) < 1:
            raise InputError(name, f"must be at least 1, got {value}")
        self.n = int(value)
        """Every how many frames: the value of ``every_n`` (or its alias ``n``)."""
        self._seen = 0

    def observe(self, frame: Frame, keyframe_map: KeyframeMap) -> list[Frame]:
        """The frame itself for every ``n``-th observed frame, starting with the first."""
        pick = self._seen % self.n == 0
        self._seen += 1
        return [frame] if pick else []

    def reset(self) -> None:
        """Restart the count."""
        self._seen = 0

    def params(self) -> dict[str, Any]:
        """``{"every_n": n}``."""
        return {"every_n": self.n}


@register_policy("gaus-slam")
class GausSlam(KeyframePolicy):
    """GauS-SLAM's rule: a keyframe when more than ``tau_k`` of its pixels render with alpha < ``alpha_threshold``.

    The fraction counts pixels with valid input depth only (a pixel that never returns depth,
    such as a window, can never be mapped); an empty map makes any frame a keyframe.
    """

    def __init__(self, tau_k: float = 0.01, alpha_threshold: float = 0.5) -> None:
        if not 0.0 <= float(tau_k) < 1.0:
            raise InputError("tau_k", f"must be in [0, 1), got {tau_k}")
        if not 0.0 < float(alpha_threshold) <= 1.0:
            raise InputError("alpha_threshold", f"must be in (0, 1], got {alpha_threshold}")
        self.tau_k = float(tau_k)
        self.alpha_threshold = float(alpha_threshold)
        self.last_unmapped_fraction = 1.0

    def unmapped_fraction(self, frame: Frame, keyframe_map: KeyframeMap) -> float:
        """Fraction of the frame's valid-depth pixels that render with alpha below the threshold."""
        if keyframe_map.n_surfels == 0:
            return 1.0
        valid = keyframe_map.valid_depth_mask(frame.depth_m)
        if not valid.any():
            return 0.0
        alpha = keyframe_map.render_alpha(frame.T_wc)
        return float(np.mean(alpha[valid] < self.alpha_threshold))

    def observe(self, frame: Frame, keyframe_map: KeyframeMap) -> list[Frame]:
        """The frame itself when its unmapped fraction exceeds ``tau_k`` (always for an empty map)."""
        self.last_unmapped_fraction = self.unmapped_fraction(frame, keyframe_map)
        return [frame] if keyframe_map.n_surfels == 0 or self.last_unmapped_fraction > self.tau_k else []

    def params(self) -> dict[str, Any]:
        """``tau_k`` and ``alpha_threshold``."""
        return {"tau_k": self.tau_k, "alpha_threshold": self.alpha_threshold}


__all__ = ["AllFrames", "EveryN", "GausSlam"]
