"""The base of every config: a frozen dataclass, validated on construction, with one to/from-dict.

Each field of a method config is a ROS parameter of the same name (:mod:`roigsf_ros.nodes.node_params`)
and a key of ``config/*.yaml``; ``from_dict`` takes such a mapping, ``to_dict`` gives the JSON-friendly one.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any, Self

from roigsf_ros.core.errors import InputError


@dataclass(frozen=True)
class Config:
    """Base class: subclasses are ``@dataclass(frozen=True)`` and check their fields in :meth:`validate`."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> Self:
        """Self when every field is in range, else InputError naming the field (run on construction)."""
        return self

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


__all__ = ["Config"]
