"""Keyframe policies: the contract, the map they may read, and the registry of policies by name.

A policy sees every frame in order through ``observe(frame, keyframe_map) -> list[Frame]`` and answers
with the frames to insert now, in order (none, the frame itself, or an earlier frame it held back: the
stream NBV policies choose from a window of past frames). When the sequence ends the caller inserts what
``finish(keyframe_map)`` returns (a policy that decides late still holds frames). The caller inserts them; a policy
never changes the map. Policies are made by name with :func:`make_policy`; :mod:`roigsf_ros.policies`
imports every module that registers one (:mod:`~roigsf_ros.policies.rules`,
:mod:`~roigsf_ros.policies.stream`), so the registry is complete once the package is imported.
"""

from __future__ import annotations

import difflib
import functools
import inspect
import logging
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Protocol

import numpy as np
from torch import Tensor

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.config import check_annotation
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame
from roigsf_ros.mapping.mapper import MapperConfig
from roigsf_ros.render.surfels import SurfelMap

_log = logging.getLogger(__name__)


class KeyframeMap(Protocol):
    """What a keyframe policy may read of the map (:class:`roigsf_ros.mapping.mapper.Mapper` is one)."""

    intr: Intrinsics
    config: MapperConfig
    map: SurfelMap
    loaded_keyframe_ids: list[int]
    """Frame ids of the keyframes a resumed map read from disk (poses only, no images; empty for a map built here)."""

    @property
    def n_surfels(self) -> int:
        """Number of surfels in the map."""
        ...

    @property
    def h_train_complete(self) -> bool:
        """Whether the running training Fisher covers every keyframe (else it is recomputed from the poses)."""
        ...

    @property
    def keyframe_poses(self) -> np.ndarray:
        """[K, 4, 4] camera-to-world poses of the keyframes, in insertion order."""
        ...

    @property
    def h_train(self) -> dict[str, Tensor]:
        """The running training Fisher (empty when not tracked)."""
        ...

    def valid_depth_mask(self, depth_m: np.ndarray) -> np.ndarray:
        """[H, W] bool: input depth the mapper would use."""
        ...

    def render_alpha(self, T_wc: np.ndarray) -> np.ndarray:
        """[H, W] accumulated alpha of the map at ``T_wc``."""
        ...

    def rendered_rgbd(
        self, T_wc: np.ndarray, depth_mode: str | None = None, min_alpha: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The map's own depth_m [H, W] and rgb [H, W, 3] uint8 at ``T_wc``, as TSDF fusion takes them."""
        ...


def _checked_init(init: Callable[..., None]) -> Callable[..., None]:
    """``init`` (a policy's ``__init__``) checking first that each argument given has its parameter's type, for
    numbers (:func:`~roigsf_ros.core.config.check_annotation`): a word or a bool for a number is an InputError naming
    the parameter, whether the policy is built by :func:`make_policy` or directly.
    """
    sig: inspect.Signature | None = None

    @functools.wraps(init)
    def checked(self: KeyframePolicy, *args: Any, **kwargs: Any) -> None:
        nonlocal sig
        if sig is None:  # resolved on the first call: the annotations are strings until every module is in
            try:
                sig = inspect.signature(init, eval_str=True)
            except NameError:  # a name imported for type checking only: its annotations stay strings, unchecked
                sig = inspect.signature(init)
        try:
            given = sig.bind(self, *args, **kwargs).arguments
        except TypeError:  # a missing or unknown argument: the constructor's own error says which
            given = {}
        for key, value in given.items():
            if sig.parameters[key].kind not in (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD):
                check_annotation(key, value, sig.parameters[key].annotation)  # self: no annotation, not checked
        init(self, *args, **kwargs)

    return checked


class KeyframePolicy:
    """Base class: decides frame by frame whether a frame becomes a keyframe. Each subclass's ``__init__`` checks its
    numeric arguments' types against its annotations before it runs (:func:`_checked_init`).
    """

    name = "base"
    reads_map = True
    """Whether :meth:`observe` reads the keyframe map (renders or scores on it); the keyframe selector subscribes to
    the mapper's map only for a policy that does. True unless a policy says otherwise: one added to the library may."""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """Wrap the subclass's own ``__init__`` (if it defines one) in the argument type check."""
        super().__init_subclass__(**kwargs)
        if "__init__" in cls.__dict__:
            cls.__init__ = _checked_init(cls.__dict__["__init__"])  # type: ignore[method-assign]

    def observe(self, frame: Frame, keyframe_map: KeyframeMap) -> list[Frame]:
        """The frames to insert as keyframes now (in order), after seeing ``frame``; the caller inserts them."""
        raise NotImplementedError

    def finish(self, keyframe_map: KeyframeMap) -> list[Frame]:
        """The frames to insert when the sequence ends (a policy deciding late still holds some); default none."""
        return []

    def reset(self) -> None:
        """Forget any state, to start a new sequence."""

    @property
    def pending_ids(self) -> list[int]:
        """Ids of the frames in the policy's candidate window (the last frames not chosen, those that lost a selection
        too until newer ones push them out); [] for a policy that decides each frame as it comes.
        """
        return []

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


def policy_names() -> list[str]:
    """Names of every registered policy."""
    return sorted(_REGISTRY)


def policy_parameters(name: str) -> list[str]:
    """The parameter names policy ``name``'s constructor takes (an InputError for an unknown name)."""
    if name not in _REGISTRY:
        raise unknown_policy(name)
    variadic = (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)
    return [k for k, p in inspect.signature(_REGISTRY[name]).parameters.items() if p.kind not in variadic]


def unknown_parameters(policy: str, unknown: Iterable[str], known: Iterable[str]) -> InputError:
    """The InputError of parameters ``policy`` does not take, each followed by the closest names it does take
    (``windw (did you mean 'window'?)``; difflib, as the nodes' hints for an undeclared parameter).
    """
    known = sorted(known)
    parts = []
    for name in unknown:
        close = difflib.get_close_matches(name, known, n=3, cutoff=0.75)
        parts.append(name + (f" (did you mean {' or '.join(map(repr, close))}?)" if close else ""))
    return InputError(f"policy {policy!r}", f"takes no parameter(s) {', '.join(parts)}")


def parse_value(text: str) -> bool | int | float | str | tuple[str, ...]:
    """A parameter value from text: true/false, an int, a float, ``a+b+c`` a list of names (for list-valued
    options such as ``fisher_params``; ``,`` and ``:`` already separate policies and parameters), else the string.
    """
    t = text.strip()
    if t.lower() in ("true", "false"):
        return t.lower() == "true"
    for kind in (int, float) if "_" not in t else ():  # Python reads 2_5 as 25: a typo, kept as text (refused)
        try:
            return kind(t)
        except ValueError:
            pass
    if "+" in t:
        return tuple(p.strip() for p in t.split("+"))
    return t


def parse_params(pairs: Iterable[str], where: str, expected: str) -> dict[str, Any]:
    """``KEY=VALUE`` texts (a policy spec's ``name:key=value:...`` after the name) as a dict, values by
    :func:`parse_value`: the one reader of ``roigsf bench --policies``, ``roigsf map --policy`` and the keyframe
    selector's ``policy_params``; a pair without ``=`` or key is an InputError at ``where`` saying ``expected``; a key
    given twice takes the later value, with a warning (the spec's label still reads both).
    """
    params: dict[str, Any] = {}
    for pair in (p.strip() for p in pairs if p.strip()):
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise InputError(where, f"{expected}, got {pair!r}")
        key, parsed = key.strip(), parse_value(value)
        if key in params:  # `$F2:unseen_weight=2` (F2 has unseen_weight=1): documented commands rely on it
            _log.warning("%s: %s given twice (%s, then %s): the later is used", where, key, params[key], parsed)
        params[key] = parsed
    return params


def unknown_policy(name: str, choices: Sequence[str] | None = None, where: str | None = None) -> InputError:
    """The InputError of a policy name not among ``choices`` (default: every registered one, sorted), with the closest
    names: ``policy 'evry-n': unknown keyframe policy (did you mean 'every-n'?); choose one of ...``, or, ``where``
    given (a node parameter, a command-line option), ``WHERE: unknown policy 'evry-n' (did you mean ...``.
    """
    names = sorted(policy_names()) if choices is None else list(choices)
    close = difflib.get_close_matches(name, names, n=2, cutoff=0.75)
    hint = f" (did you mean {' or '.join(map(repr, close))}?)" if close else ""
    if where is None:
        return InputError(f"policy {name!r}", f"unknown keyframe policy{hint}; choose one of {', '.join(names)}")
    return InputError(where, f"unknown policy {name!r}{hint}; choose one of {', '.join(names)}")


def checked_keyframes(policy: KeyframePolicy, chosen: object, named: set[int], call: str = "observe") -> list[Frame]:
    """What ``policy.observe`` (or ``finish``: ``call``) returned, as the frames to insert: a list or tuple of Frames,
    none named twice (within it, or already in ``named``, the frame ids named so far, to which they are added).

    Anything else is an InputError naming the policy: a bad return type once failed deep in the caller, and a frame
    named twice was inserted twice (the same keyframe id in the map and its Fisher counted twice).
    """
    where = f"keyframe policy {policy.name!r}"
    if not isinstance(chosen, list | tuple):
        raise InputError(where, f"{call}() returned {type(chosen).__name__}, not a list of the frames to insert")
    ids = []
    for f in chosen:
        if not isinstance(f, Frame):
            raise InputError(where, f"{call}() returned a {type(f).__name__} among its frames, not a Frame")
        if f.index in ids:
            raise InputError(where, f"{call}() named frame {f.index} twice in one answer")
        if f.index in named:
            raise InputError(where, f"{call}() named frame {f.index} again: it is a keyframe already")
        ids.append(f.index)
    named.update(ids)
    return list(chosen)


def make_policy(name: str, **params: Any) -> KeyframePolicy:
    """A policy by registered name; ``None``-valued params are dropped; an unknown one is an InputError naming the
    policy (``policy 'x': ...``, no command-line flag: callers are the CLI, a node parameter, a pool config), and a
    value not of its parameter's type (a word for a number, say) one naming the parameter (the constructor's check,
    :func:`_checked_init`).
    """
    if name not in _REGISTRY:
        raise unknown_policy(name)
    factory = _REGISTRY[name]
    given = {k: v for k, v in params.items() if v is not None}
    sig = inspect.signature(factory).parameters  # names only: the constructor checks the types
    extra = sorted(set(given) - set(sig))
    if extra and not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in sig.values()):
        raise unknown_parameters(
            name, extra, (k for k, p in sig.items() if p.kind is not inspect.Parameter.VAR_POSITIONAL)
        )
    return factory(**given)


__all__ = [
    "KeyframeMap",
    "KeyframePolicy",
    "checked_keyframes",
    "make_policy",
    "parse_params",
    "parse_value",
    "policy_names",
    "policy_parameters",
    "register_policy",
    "unknown_parameters",
    "unknown_policy",
]
