"""Where the package's own files (params files, the sample bag) are: in the checkout, else where the install put them.

setup.py installs ``config/`` and ``bags/`` into ``share/roigsf_ros/``; a command run from the checkout reads the
checkout's copies (what its tests and scripts edit), one run from anywhere else the installed ones.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

PACKAGE = "roigsf_ros"

CHECKOUT_ROOT = Path(__file__).resolve().parents[2]
"""The repository root when this module runs from the source tree (it then holds ``package.xml``); installed, it is
``site-packages``, which holds no ``package.xml``."""


def share_folders() -> list[Path]:
    """The package's share folders, most specific first: the one the ament index names (needs AMENT_PREFIX_PATH), then
    the one under the interpreter's prefix (``pip install`` puts setup.py's data files there: a command run straight
    from its venv without a sourced workspace). Only those that exist.
    """
    folders: list[Path] = []
    try:
        from ament_index_python.packages import get_package_share_directory

        folders.append(Path(get_package_share_directory(PACKAGE)))
    except (ImportError, LookupError, OSError, ValueError):  # no ament index, or the package not in it
        pass
    folders.append(Path(sys.prefix) / "share" / PACKAGE)
    unique: list[Path] = []
    for folder in folders:
        if folder.is_dir() and folder not in unique:
            unique.append(folder)
    return unique


def _candidates(relative: str) -> list[Path]:
    """The checkout's ``relative`` (when this runs from one), then each share folder's."""
    places = [CHECKOUT_ROOT / relative] if (CHECKOUT_ROOT / "package.xml").is_file() else []
    return places + [folder / relative for folder in share_folders()]


def package_path(relative: str, complete: Callable[[Path], bool] = Path.exists) -> Path | None:
    """``relative`` (e.g. ``"config"``, ``"bags/synth_room"``) in the checkout, else in the first share folder
    (:func:`share_folders`), the first where ``complete(path)`` holds; None when none has it.
    """
    return next((path for path in _candidates(relative) if complete(path)), None)


def package_path_places(relative: str) -> str:
    """Where :func:`package_path` looks for ``relative``, for an error message."""
    places = _candidates(relative) or [Path(sys.prefix) / "share" / PACKAGE / relative]
    return ", ".join(str(p) for p in places)


__all__ = ["CHECKOUT_ROOT", "PACKAGE", "package_path", "package_path_places", "share_folders"]
