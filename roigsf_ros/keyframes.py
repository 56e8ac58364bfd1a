"""Keyframe policies: which incoming frames the mapper trains on.

A policy sees every frame in order through ``observe(frame, mapper) -> bool`` and answers whether
the frame is a keyframe. Policies are made by name with :func:`make_policy`; later modules add
NBV policies to the same registry with :func:`register_policy`.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from roigsf_ros.errors import InputError
from roigsf_ros.replica import Frame

if TYPE_CHECKING:
    from roigsf_ros.mapping import Mapper


class KeyframePolicy:
    """Base class: decides frame by frame whether a frame becomes a keyframe."""

    name = "base"

    def observe(self, frame: Frame, mapper: Mapper) -> bool:
        """True when ``frame`` should be inserted as a keyframe into ``mapper``."""
        raise NotImplementedError

    def reset(self) -> None:
        """Forget any state, to start a new sequence."""

    def params(self) -> dict[str, Any]:
        """The policy's parameters, for metrics.json and logs."""
        return {}


_REGISTRY: dict[str, Callable[..., KeyframePolicy]] = {}


def register_policy(name: str) -> Callable[[type[KeyframePolicy]], type[KeyframePolicy]]:
    """Class decorator adding a policy to the registry under ``name``."""

    def deco(cls: type[KeyframePolicy]) -> type[KeyframePolicy]:
        if name in _REGISTRY:
            raise ValueError(f"keyframe policy {name!r} registered twice")
        cls.name = name
        _REGISTRY[name] = cls
        return cls

    return deco


def _register_nbv_policies() -> None:
    """Import the NBV window policies (they register themselves; a top-level import would be a cycle)."""
    import roigsf_ros.nbv_policies  # noqa: F401


def policy_names() -> list[str]:
    """Names of every registered policy."""
    _register_nbv_policies()
    return sorted(_REGISTRY)


def make_policy(name: str, **params: Any) -> KeyframePolicy:
    """A policy by registered name; ``None``-valued params are dropped, unknown ones are an InputError."""
    _register_nbv_policies()
    if name not in _REGISTRY:
        raise InputError("--policy", f"unknown keyframe policy {name!r}; choose one of {', '.join(policy_names())}")
    factory = _REGISTRY[name]
    given = {k: v for k, v in params.items() if v is not None}
    accepted = set(inspect.signature(factory).parameters)
    extra = sorted(set(given) - accepted)
    if extra:
        raise InputError("--policy", f"policy {name!r} takes no parameter(s) {', '.join(extra)}")
    return factory(**given)


@register_policy("all")
class AllFrames(KeyframePolicy):
    """Every frame is a keyframe."""

    def observe(self, frame: Frame, mapper: Mapper) -> bool:
        """Always True."""
        return True


@register_policy("every-n")
class EveryN(KeyframePolicy):
    """Every ``n``-th frame seen (the 0th, n-th, 2n-th, ...), counted in arrival order."""

    def __init__(self, n: int = 5) -> None:
        if int(n) < 1:
            raise InputError("--every-n", f"must be at least 1, got {n}")
        self.n = int(n)
        self._seen = 0

    def observe(self, frame: Frame, mapper: Mapper) -> bool:
        """True for every ``n``-th observed frame, starting with the first."""
        pick = self._seen % self.n == 0
        self._seen += 1
        return pick

    def reset(self) -> None:
        """Restart the count."""
        self._seen = 0

    def params(self) -> dict[str, Any]:
        """``{"n": n}``."""
        return {"n": self.n}


@register_policy("gaus-slam")
class GausSlam(KeyframePolicy):
    """GauS-SLAM's rule: a keyframe when more than ``tau_k`` of its pixels render with alpha < ``alpha_threshold``.

    The fraction counts pixels with valid input depth only (a pixel that never returns depth,
    such as a window, can never be mapped); an empty map makes any frame a keyframe.
    """

    def __init__(self, tau_k: float = 0.01, alpha_threshold: float = 0.5) -> None:
        if not 0.0 <= float(tau_k) < 1.0:
            raise InputError("--tau-k", f"must be in [0, 1), got {tau_k}")
        if not 0.0 < float(alpha_threshold) <= 1.0:
            raise InputError("alpha_threshold", f"must be in (0, 1], got {alpha_threshold}")
        self.tau_k = float(tau_k)
        self.alpha_threshold = float(alpha_threshold)
        self.last_unmapped_fraction = 1.0

    def unmapped_fraction(self, frame: Frame, mapper: Mapper) -> float:
        """Fraction of the frame's valid-depth pixels that render with alpha below the threshold."""
        if mapper.n_surfels == 0:
            return 1.0
        valid = mapper.valid_depth_mask(frame.depth_m)
        if not valid.any():
            return 0.0
        alpha = mapper.render_alpha(frame.T_wc)
        return float(np.mean(alpha[valid] < self.alpha_threshold))

    def observe(self, frame: Frame, mapper: Mapper) -> bool:
        """True when the unmapped fraction exceeds ``tau_k`` (always for an empty map)."""
        self.last_unmapped_fraction = self.unmapped_fraction(frame, mapper)
        return mapper.n_surfels == 0 or self.last_unmapped_fraction > self.tau_k

    def params(self) -> dict[str, Any]:
        """``tau_k`` and ``alpha_threshold``."""
        return {"tau_k": self.tau_k, "alpha_threshold": self.alpha_threshold}
