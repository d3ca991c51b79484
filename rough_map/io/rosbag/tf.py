"""The tf tree of a bag: ``tf2_msgs/TFMessage`` transforms and their composition.

A sensor's mounting on the vehicle is published on ``/tf_static``; :func:`static_transform`
walks the tree of frames from one frame to another.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rough_map._files import PathLike
from rough_map.io.rosbag.messages import (
    TF_MESSAGE,
    TF_STATIC_TOPIC,
    frame_name,
    rotations,
    stamp_ns,
    valid_quaternion,
)
from rough_map.io.rosbag.reader import open_bag, topic_messages

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Transform:
    """One transform of a ``tf2_msgs/TFMessage``: pose of ``child`` in ``parent``.

    ``p_parent = R(quaternion) @ p_child + translation``.

    Attributes
    ----------
    t : float
        Stamp, s since the Unix epoch.
    parent, child : str
        Frame ids (leading "/" removed).
    translation : tuple of float
        m.
    quaternion : tuple of float
        x, y, z, w.
    """

    t: float
    parent: str
    child: str
    translation: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous transform child -> parent (m)."""
        transform = np.eye(4)
        transform[:3, :3] = rotations(np.asarray([self.quaternion])).as_matrix()[0]
        transform[:3, 3] = self.translation
        return transform


def tf_transforms(msg: Any) -> list[Transform]:
    """The transforms of a ``tf2_msgs/TFMessage``.

    Transforms with a zero or non-finite quaternion, or a non-finite translation, are left
    out with a warning.
    """
    out = []
    skipped = 0
    for tf in msg.transforms:
        tr, q = tf.transform.translation, tf.transform.rotation
        translation = (float(tr.x), float(tr.y), float(tr.z))
        quaternion = (float(q.x), float(q.y), float(q.z), float(q.w))
        if not valid_quaternion(np.array(quaternion)) or not np.isfinite(translation).all():
            skipped += 1
            continue
        out.append(
            Transform(
                t=stamp_ns(tf.header) * 1e-9,
                parent=frame_name(tf.header.frame_id),
                child=frame_name(tf.child_frame_id),
                translation=translation,
                quaternion=quaternion,
            )
        )
    if skipped:
        log.warning("%d transforms with a non-finite or zero pose skipped", skipped)
    return out


def read_transforms(bag: PathLike, topic: str = TF_STATIC_TOPIC) -> list[Transform]:
    """All transforms published on a ``tf2_msgs/TFMessage`` topic, in bag order.

    Raises
    ------
    FileFormatError
        Unknown topic, wrong message type, or an unreadable bag.
    """
    with open_bag(bag) as reader:
        return [
            tf
            for _, msg in topic_messages(reader, Path(bag), topic, TF_MESSAGE)
            for tf in tf_transforms(msg)
        ]


def static_transform(transforms: list[Transform], source: str, target: str) -> np.ndarray | None:
    """Compose transforms into the 4x4 transform ``source`` -> ``target`` frame (m).

    The transforms form a tree (tf); the path between the two frames may go up and down it.

    Returns
    -------
    ndarray, shape (4, 4), or None
        ``p_target = T @ p_source``; identity if the frames are equal; None if not connected.
    """
    source, target = frame_name(source), frame_name(target)
    if source == target:
        return np.eye(4)
    edges: dict[str, list[tuple[str, np.ndarray]]] = {}
    for tf in transforms:  # later transforms of the same pair win, like in tf
        m = tf.matrix()
        edges.setdefault(tf.child, []).append((tf.parent, m))
        edges.setdefault(tf.parent, []).append((tf.child, np.linalg.inv(m)))
    # Breadth-first from the source; each node keeps source -> node.
    found = {source: np.eye(4)}
    queue = deque([source])
    while queue:
        node = queue.popleft()
        for neighbour, node_to_neighbour in reversed(edges.get(node, [])):
            if neighbour not in found:
                found[neighbour] = node_to_neighbour @ found[node]
                if neighbour == target:
                    return found[neighbour]
                queue.append(neighbour)
    return None


def static_transforms(reader: AnyReader, path: Path) -> list[Transform]:
    """The transforms on ``/tf_static`` of an open bag; none if it has no such topic."""
    topics = {c.topic: c.msgtype for c in reader.connections}
    if topics.get(TF_STATIC_TOPIC) != TF_MESSAGE:
        return []
    return [
        tf
        for _, msg in topic_messages(reader, path, TF_STATIC_TOPIC, TF_MESSAGE)
        for tf in tf_transforms(msg)
    ]
