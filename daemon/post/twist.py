"""Twist distribution along a limb (the chapter's 5.59), exact in world orientation.

Captured data puts the forearm's pronation/supination where anatomy has it (between
elbow and wrist); vertex-weighted rigs deform better when the long-axis rotation is
spread over shoulder, elbow and wrist. For a chain of joints ``j_0 .. j_{n-1}``
(shoulder, elbow, wrist: the rotations ``parent_from_upperarm``,
``upperarm_from_lowerarm``, ``lowerarm_from_hand``), each rotation is split as

    q_k = swing_k ⊗ T(τ_k),      T(a) = rotation by a about the bone's long axis
                                  (+Y, the child frame's; applied first)

The twist pooled from the lower joints, ``τ = Σ_{k>=1} τ_k``, is shared by the
fractions ``f_k`` (Σ f_k = 1): joint ``k >= 1`` ends with twist ``f_k τ``, joint 0
with its own twist plus ``f_0 τ``. It is moved one joint up at a time, from the
wrist towards the shoulder, by an excess ``e_k``:

    e_{n-1} = τ_{n-1} - f_{n-1} τ,     e_k = τ_k + e_{k+1} - f_k τ
    q_{k-1} <- q_{k-1} ⊗ T(e_k),       q_k <- T(-e_k) ⊗ q_k

``q_{k-1} q_k`` is unchanged by each move, so every bone from ``j_k`` down keeps its
world orientation (the hand exactly, up to rounding); the twist of ``q_{k-1}`` grows
by exactly ``e_k`` (``swing ⊗ T(a) ⊗ T(e) = swing ⊗ T(a + e)``) and that of ``q_k``
shrinks by it (``T(-e) swing T(a) = [T(-e) swing T(e)] T(a - e)``, a swing again):
the swing stays in place in the world, only its axis is re-expressed in the
re-twisted parent. The upper and lower arm bones themselves turn about their own long
axes, which is the point: their envelopes take a share of the twist.

Unlike 5.59 on Euler channels (``ry`` of a ZXY/XZY joint), the twist here is the
swing-twist one, which is independent of the rig's rotation order.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np

from retargetd.daemon.compiled import kernel
from retargetd.daemon.post._kernels import qmul, twist_about
from retargetd.daemon.post.pose import PoseBuffer
from retargetd.daemon.rotations import twist_angle
from retargetd.protocols.frames import F64Array, IntArray

#: The chapter's default: "distribute the total longitudinal rotations of the arm
#: among the wrist, elbow, and shoulder joints" equally.
DEFAULT_FRACTIONS = (1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0)
#: Bone long axis in the bone's own frame (RIGS.md "Bone axes": +Y origin -> aim).
LONG_AXIS = (0.0, 1.0, 0.0)

#: Arm chains (shoulder, elbow, wrist bones) of the shipped rigs (plug-in-gait and
#: cmu41 share the first names, menache has its own) and the synthetic performer, by
#: bone name.
ARM_CHAINS: dict[str, tuple[tuple[str, str, str], ...]] = {
    "rig": (("lupperarm", "llowerarm", "lhand"), ("rupperarm", "rlowerarm", "rhand")),
    # menache's hand hangs on the ulna (the radius is its own bone, a sibling).
    "menache": (("lupperarm", "lulna", "lhand"), ("rupperarm", "rulna", "rhand")),
    "performer": (
        ("l_upper_arm", "l_forearm", "l_hand"),
        ("r_upper_arm", "r_forearm", "r_hand"),
    ),
}


@kernel
def _distribute(
    q: F64Array,
    chains: IntArray,
    fractions: F64Array,
    axis: F64Array,
    rest_tw: F64Array,
    tw: F64Array,
) -> None:  # pragma: no cover - compiled
    ux, uy, uz = axis[0], axis[1], axis[2]
    n = chains.shape[1]
    for c in range(chains.shape[0]):
        total = 0.0
        for k in range(n):
            b = chains[c, k]
            tw[k] = twist_about(q[b, 0], q[b, 1], q[b, 2], q[b, 3], ux, uy, uz)
            if k > 0:
                rel = tw[k] - rest_tw[c, k]
                total += math.atan2(math.sin(rel), math.cos(rel))
        excess = 0.0
        for k in range(n - 1, 0, -1):
            excess = tw[k] + excess - rest_tw[c, k] - fractions[k] * total
            s, co = math.sin(0.5 * excess), math.cos(0.5 * excess)
            b, p = chains[c, k], chains[c, k - 1]
            # Parent: q_p ⊗ T(e).
            r = qmul(q[p, 0], q[p, 1], q[p, 2], q[p, 3], co, s * ux, s * uy, s * uz)
            q[p, 0], q[p, 1], q[p, 2], q[p, 3] = r
            # Child: T(-e) ⊗ q_b.
            r = qmul(co, -s * ux, -s * uy, -s * uz, q[b, 0], q[b, 1], q[b, 2], q[b, 3])
            q[b, 0], q[b, 1], q[b, 2], q[b, 3] = r


class TwistDistribution:
    """Share the long-axis twist of limb chains over their joints (module docstring).

    Args:
        bone_parents: (B,) parent index per bone, -1 for a root.
        chains: each a sequence of n >= 2 bone indices, each the child of the one
            before (shoulder -> elbow -> wrist), all chains the same length.
        fractions: (n,) share of the pooled twist per joint, each in [0, 1], summing
            to 1; default a third each.
        axis: (3,) the bones' long axis in their own frame (normalized here).
        rest_parent_from_bone_quat: (B, 4) float64 (w, x, y, z): the rest pose's
            rotations, when the rest pose itself holds twist (a solve's calibration:
            pass ``Calibration.rest_parent_from_bone_quat`` and apply the stage to
            ``rest ⊗ solve.parent_from_bone_quat``). Twist is then counted from the
            rest twist: joint ``k >= 1`` ends with its rest twist plus ``f_k τ``, and
            the rest pose passes unchanged. Default: identity rest.

    Raises:
        ValueError: naming a bad chain, fraction or axis.
    """

    def __init__(
        self,
        bone_parents: Sequence[int],
        chains: Sequence[Sequence[int]],
        fractions: Sequence[float] = DEFAULT_FRACTIONS,
        axis: Sequence[float] = LONG_AXIS,
        rest_parent_from_bone_quat: F64Array | None = None,
    ) -> None:
        parents = np.asarray(bone_parents, dtype=np.int64)
        chain_arr = np.asarray(chains, dtype=np.int64)
        if chain_arr.ndim != 2 or chain_arr.shape[1] < 2 or chain_arr.shape[0] < 1:
            raise ValueError(
                f"chains must be equal-length sequences of >= 2 bones; got {chains!r}"
            )
        if chain_arr.min() < 0 or chain_arr.max() >= len(parents):
            raise ValueError(
                f"chains index bones 0..{len(parents) - 1}; got {chains!r}"
            )
        for chain in chain_arr:
            for parent, child in itertools.pairwise(chain):
                if parents[child] != parent:
                    raise ValueError(
                        f"bone {child} is not the child of bone {parent} in chain "
                        f"{chain.tolist()}"
                    )
        if len(np.unique(chain_arr)) != chain_arr.size:
            raise ValueError(f"a bone appears twice in chains {chains!r}")
        frac = np.asarray(fractions, dtype=np.float64)
        if (
            frac.shape != (chain_arr.shape[1],)
            or not np.all((frac >= 0.0) & (frac <= 1.0))
            or abs(frac.sum() - 1.0) > 1e-9
        ):
            raise ValueError(
                f"fractions must be {chain_arr.shape[1]} values in [0, 1] summing to "
                f"1; got {fractions!r}"
            )
        ax = np.asarray(axis, dtype=np.float64)
        norm = float(np.linalg.norm(ax)) if ax.shape == (3,) else 0.0
        if not norm > 0.0:
            raise ValueError(f"axis must be a non-zero 3-vector; got {axis!r}")
        self.n_bones = len(parents)
        self.chains = chain_arr
        self.fractions = frac
        self.axis = ax / norm
        self._tw = np.zeros(chain_arr.shape[1])
        self._rest_tw = np.zeros(chain_arr.shape)
        if rest_parent_from_bone_quat is not None:
            rest = np.asarray(rest_parent_from_bone_quat, dtype=np.float64)
            if rest.shape != (len(parents), 4):
                raise ValueError(
                    f"rest_parent_from_bone_quat must be ({len(parents)}, 4); got "
                    f"{rest.shape}"
                )
            self._rest_tw[:] = twist_angle(rest[chain_arr], self.axis)

    def apply_quat(self, parent_from_bone_quat: F64Array, out: F64Array) -> F64Array:
        """Distribute the twist of one pose's rotations.

        Args:
            parent_from_bone_quat: (B, 4) float64 (w, x, y, z), unit.
            out: (B, 4) float64 destination (may be the input itself).

        Returns:
            ``out``: the rotations with the chains' twist redistributed.
        """
        if out is not parent_from_bone_quat:
            np.copyto(out, parent_from_bone_quat)
        _distribute(
            out, self.chains, self.fractions, self.axis, self._rest_tw, self._tw
        )
        return out

    def apply(self, pose: PoseBuffer, out: PoseBuffer) -> PoseBuffer:
        """Distribute the twist of one pose.

        Args:
            pose: the solved pose (B bones).
            out: the destination (may be ``pose``).

        Returns:
            ``out``.
        """
        if out is not pose:
            out.copy_from(pose)
        _distribute(
            out.parent_from_bone_quat,
            self.chains,
            self.fractions,
            self.axis,
            self._rest_tw,
            self._tw,
        )
        return out


def arm_chains(bone_names: Sequence[str]) -> list[list[int]]:
    """The arm chains (shoulder, elbow, wrist) present in ``bone_names``.

    Args:
        bone_names: (B,) bone names of a rig or the synthetic performer.

    Returns:
        Bone-index chains from :data:`ARM_CHAINS` whose three bones all exist.
    """
    index = {n: i for i, n in enumerate(bone_names)}
    return [
        [index[n] for n in chain]
        for chains in ARM_CHAINS.values()
        for chain in chains
        if all(n in index for n in chain)
    ]
