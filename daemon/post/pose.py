"""The per-frame pose the post stages read and write.

A :class:`PoseBuffer` is allocated once per stream (STYLE §5) and reused every frame;
stages copy into their ``out`` buffer and never resize it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from retargetd.protocols.frames import F64Array


@dataclass(slots=True, eq=False)
class PoseBuffer:
    """One solved pose.

    Attributes:
        t_s: the pose's time, seconds (the source's clock; only differences matter).
        parent_from_bone_quat: (B, 4) float64 (w, x, y, z); for the root bone it is
            ``world_from_root``.
        root_pos: (3,) float64, metres, world: the root bone's origin.
    """

    t_s: float
    parent_from_bone_quat: F64Array
    root_pos: F64Array

    @classmethod
    def new(cls, n_bones: int) -> PoseBuffer:
        """A pose of ``n_bones`` identity rotations at the origin, ``t_s = 0``.

        Args:
            n_bones: number of bones B (>= 1).

        Returns:
            The new buffer.

        Raises:
            ValueError: ``n_bones`` < 1.
        """
        if n_bones < 1:
            raise ValueError(f"n_bones must be >= 1; got {n_bones}")
        quat = np.zeros((n_bones, 4))
        quat[:, 0] = 1.0
        return cls(0.0, quat, np.zeros(3))

    @property
    def n_bones(self) -> int:
        """Number of bones B."""
        return int(self.parent_from_bone_quat.shape[0])

    def copy_from(self, other: PoseBuffer) -> PoseBuffer:
        """Copy ``other`` into this buffer (same bone count), in place.

        Args:
            other: the source pose.

        Returns:
            ``self``.
        """
        self.t_s = other.t_s
        np.copyto(self.parent_from_bone_quat, other.parent_from_bone_quat)
        np.copyto(self.root_pos, other.root_pos)
        return self
