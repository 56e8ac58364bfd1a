"""The ROS domain id a command or node runs on: ``--domain-id`` or ``ROS_DOMAIN_ID``, checked before any ROS context
exists (rcl stops with a traceback on a non-number; Fast DDS refuses a large one only after leaving files in /dev/shm).
Plain Python, so the command line can check it without importing rclpy.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

from roigsf_ros.core.errors import InputError

MAX_DOMAIN_ID = 232
"""The largest ROS 2 domain id (on Linux; 0..101 are the portable ones): the largest whose DDS ports fit in 16 bits with
Fast DDS's defaults (port base 7400 + domain gain 250 x id + offsets: 7400 + 250 x 232 = 65400 leaves room for the
participants' ports below 65536, 233 gives 65650). Past it Fast DDS fails with "port number is too high" after the
nodes' shared-memory files are made, and leaves them in /dev/shm.
"""


def check_domain_id(value: int, where: str = "--domain-id") -> int:
    """``value`` if it is a ROS domain id in 0..:data:`MAX_DOMAIN_ID`, else an InputError naming ``where`` (the
    option or variable it came from): the one check of every ``roigsf`` command with ``--domain-id``, made before
    any ROS context exists, since Fast DDS refuses a larger one only after leaving files in /dev/shm.
    """
    if not 0 <= value <= MAX_DOMAIN_ID:
        raise InputError(where, f"must be a ROS domain id in 0..{MAX_DOMAIN_ID}, got {value}")
    return value


def domain_id_from_env(environ: Mapping[str, str] | None = None) -> int | None:
    """``ROS_DOMAIN_ID`` checked as :func:`check_domain_id` does (errors name the variable); None when it is unset."""
    env = os.environ if environ is None else environ
    text = env.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return None
    try:
        value = int(text)
    except ValueError:
        raise InputError("ROS_DOMAIN_ID", f"not an integer: {env['ROS_DOMAIN_ID']!r}") from None
    return check_domain_id(value, "ROS_DOMAIN_ID")


__all__ = ["MAX_DOMAIN_ID", "check_domain_id", "domain_id_from_env"]
