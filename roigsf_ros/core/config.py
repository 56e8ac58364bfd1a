"""The base of every config: a frozen dataclass, validated on construction, with one to/from-dict.

Each field of a method config is a ROS parameter of the same name (:mod:`roigsf_ros.nodes.node_params`)
and a key of ``config/*.yaml``; ``from_dict`` takes such a mapping, ``to_dict`` gives the JSON-friendly one.
"""

from __future__ import annotations

import difflib
import functools
import numbers
import types
from collections.abc import Mapping
from dataclasses import MISSING, asdict, dataclass, fields, is_dataclass
from typing import Any, Self, Union, get_args, get_origin, get_type_hints

import numpy as np

from roigsf_ros.core.errors import InputError

_WORDS = {int: "a whole number", float: "a number"}


def _kinds(annotation: Any) -> tuple[Any, ...]:
    """The types a (possibly union) ``annotation`` names."""
    return get_args(annotation) if get_origin(annotation) in (Union, types.UnionType) else (annotation,)


def fits_annotation(value: Any, annotation: Any) -> bool:
    """Whether ``value`` has the type ``annotation`` names, for numbers, which a command line can give as words:
    ``int`` takes a whole number, ``float`` any number (neither takes a bool: ``true`` is no window size), ``X | None``
    also None. Other annotations (``str``, ``bool``, ``Any``, a tuple of names) are not checked here: each config or
    policy checks those itself, where its error can list the choices.
    """
    kinds = _kinds(annotation)
    if value is None:
        return type(None) in kinds or not all(k in _WORDS or k is type(None) for k in kinds)
    checked = [k for k in kinds if k in _WORDS]
    if len(checked) < len([k for k in kinds if k is not type(None)]):
        return True
    number = isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_)
    return any((k is float and number) or (k is int and number and float(value).is_integer()) for k in checked)


def annotation_words(annotation: Any) -> str:
    """What a field of ``annotation`` takes, in words (``a whole number``), for an error naming the field."""
    words = [_WORDS[k] for k in _kinds(annotation) if k in _WORDS]
    if type(None) in _kinds(annotation):
        words.append("none")
    return " or ".join(words)


def check_annotation(name: str, value: Any, annotation: Any) -> None:
    """InputError naming ``name`` unless ``value`` fits ``annotation`` (:func:`fits_annotation`): the one type check
    of config fields and policy arguments.
    """
    if not fits_annotation(value, annotation):
        raise InputError(name, f"must be {annotation_words(annotation)}, got {value!r}")


def check_field_value(cls: type, name: str, value: Any, where: str) -> bool:
    """Whether config class ``cls`` has a field ``name``; if it has, an InputError naming ``where`` unless ``value``
    fits the field's type (:func:`fits_annotation`): a command line's check before any work (``roigsf demo --set
    mapper.iters_per_keyframe=abc`` was refused only once the nodes had started).
    """
    hints = _field_types(cls)
    if name not in hints or name.startswith("_"):
        return False
    check_annotation(where, value, hints[name])
    return True


@functools.cache
def _field_types(cls: type) -> dict[str, Any]:
    """A config class's field annotations, resolved once per class."""
    return get_type_hints(cls)


class UnknownFieldError(InputError, TypeError):
    """A config built with a keyword that is none of its fields (a TypeError too, as Python's own for a bad keyword)."""


class _ConfigType(type):
    """The config classes' metaclass: a keyword that is no field is named with the closest fields (the dataclass's
    own TypeError, ``unexpected keyword argument 'unseen_wieght'``, named none).
    """

    def __call__(cls, *args: Any, **kwargs: Any) -> Any:
        if kwargs and is_dataclass(cls):
            names = [f.name for f in fields(cls) if f.init]
            unknown = [k for k in kwargs if k not in names]
            if unknown:
                close = {k: difflib.get_close_matches(k, names, n=1) for k in unknown}
                hints = ", ".join(f"{k} (did you mean {c[0]}?)" if c else k for k, c in close.items())
                listed = "" if all(close.values()) else f"; its fields: {', '.join(names)}"
                raise UnknownFieldError(cls.__name__, f"no field {hints}{listed}")
        return super().__call__(*args, **kwargs)


@dataclass(frozen=True)
class Config(metaclass=_ConfigType):
    """Base class: subclasses are ``@dataclass(frozen=True)`` and check their fields' ranges in :meth:`validate`; the
    base checks every field's type against its annotation first (:func:`fits_annotation`), so a word where a number
    belongs is an InputError naming the field, not a TypeError inside a comparison.
    """

    def __post_init__(self) -> None:
        hints = _field_types(type(self))
        for f in fields(self):
            check_annotation(f.name, getattr(self, f.name), hints[f.name])
        self.validate()

    def validate(self) -> Self:
        """Self when every field is in range, else InputError naming the field (run on construction)."""
        return self

    @classmethod
    def given(cls, value: Any, where: str = "config") -> Self:
        """``value`` as this config (None: the defaults), else an InputError naming ``where``: a mapping of fields
        (``RECOMMENDED_UNSEEN`` itself) used to fail deep in the work on a missing attribute.
        """
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        hint = f": give {cls.__name__}(**it)" if isinstance(value, Mapping) else ""
        raise InputError(where, f"expected a {cls.__name__}, got {type(value).__name__}{hint}")

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> Self:
        """A config from a {name: value} mapping (ROS parameters, JSON); lists become tuples, unknown names raise."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise InputError(cls.__name__, f"unknown parameter(s) {', '.join(unknown)}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})

    def to_dict(self) -> dict[str, Any]:
        """Every field as a JSON-friendly dict (tuples become lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    def changed(self) -> dict[str, Any]:
        """The fields whose values differ from their declared defaults, in field order, JSON-friendly as
        :meth:`to_dict` (a field without a default is left out): what a node's start-up line names, so its log says
        which settings beyond the defaults it runs with.
        """
        here, out = self.to_dict(), {}
        for f in fields(self):
            if f.default is not MISSING:
                default = f.default
            elif f.default_factory is not MISSING:
                default = f.default_factory()
            else:
                continue
            default = asdict(default) if is_dataclass(default) else default  # a nested config, as to_dict has it
            if here[f.name] != (list(default) if isinstance(default, tuple) else default):
                out[f.name] = here[f.name]
        return out


__all__ = [
    "Config",
    "UnknownFieldError",
    "annotation_words",
    "check_annotation",
    "check_field_value",
    "fits_annotation",
]
