"""Compare two bags message by message: per topic, how many messages differ; for pose topics, how far.

    python scripts/compare_bags.py bags/synth_room /tmp/regen/bag

What ``bash scripts/make_sample_bag.sh --check`` runs against a fresh regeneration of the sample bag.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader


def read_topics(bag: Path) -> tuple[dict[str, list[bytes]], dict[str, str]]:
    """Every message's raw bytes per topic, in bag order, and each topic's message type."""
    raws: dict[str, list[bytes]] = {}
    types: dict[str, str] = {}
    with AnyReader([bag]) as reader:
        for conn, _, raw in reader.messages():
            raws.setdefault(conn.topic, []).append(bytes(raw))
            types[conn.topic] = conn.msgtype
    return raws, types


def pose_values(bag: Path, topic: str) -> np.ndarray:
    """[N, 7] position (m) and quaternion (x, y, z, w) of each PoseStamped on ``topic``."""
    rows = []
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _, raw in reader.messages(connections=conns):
            p = reader.deserialize(raw, conn.msgtype).pose
            rows.append([p.position.x, p.position.y, p.position.z, *(getattr(p.orientation, k) for k in "xyzw")])
    return np.array(rows, dtype=np.float64).reshape(-1, 7)


def main(argv: list[str] | None = None) -> int:
    """Print one line per topic; exit 1 when the topics or message counts differ, a message of another type differs,
    or a pose differs by more than ``--pose-tol``; else 0.

    Poses are compared by value: their quaternions' last bits move on another CPU (the README's regeneration check,
    38 of 150 off by up to 2.2e-16). It used to exit 0 on any content difference, so a check could not fail.
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a", type=Path)
    parser.add_argument("b", type=Path)
    parser.add_argument(
        "--pose-tol", type=float, default=1e-9, help="largest position (m) or quaternion difference of one pose"
    )
    args = parser.parse_args(argv)
    (raw_a, types), (raw_b, _) = read_topics(args.a), read_topics(args.b)
    if sorted(raw_a) != sorted(raw_b) or any(len(raw_a[t]) != len(raw_b[t]) for t in raw_a):
        print(f"topics or message counts differ: {args.a} {sorted(raw_a)} vs {args.b} {sorted(raw_b)}")
        return 1
    differ = []
    for topic in sorted(raw_a):
        n_diff = sum(x != y for x, y in zip(raw_a[topic], raw_b[topic], strict=True))
        line = f"{topic}: {len(raw_a[topic])} messages, {n_diff} differ"
        if n_diff and types[topic] == "geometry_msgs/msg/PoseStamped":
            d = np.abs(pose_values(args.a, topic) - pose_values(args.b, topic))
            line += f" (position up to {d[:, :3].max():.3g} m, quaternion up to {d[:, 3:].max():.3g})"
            if d.max() > args.pose_tol:
                differ.append(topic)
        elif n_diff:
            differ.append(topic)
        print(line)
    if differ:
        print(f"the bags differ on {', '.join(differ)}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
