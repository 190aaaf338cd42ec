"""A Hermite spine (the chapter's 5.60-5.61): a smooth curve through the solved spine
points, with K joints placed along it for targets with more spine bones.

Between consecutive points ``P_i`` and ``P_{i+1}`` each coordinate is the cubic
(5.60) ``p(u) = a u³ + b u² + c u + d``, ``u`` in [0, 1], with tangent (5.61)
``p'(u) = 3a u² + 2b u + c``. Solving ``p(0) = P_i``, ``p(1) = P_{i+1}``,
``p'(0) = T_i``, ``p'(1) = T_{i+1}`` gives

    a = 2 P_i - 2 P_{i+1} + T_i + T_{i+1}     b = -3 P_i + 3 P_{i+1} - 2 T_i - T_{i+1}
    c = T_i                                   d = P_i

The tangent at a join is shared by the two segments meeting there ("make sure that
the tangent vectors at the ends of the curves are matching"), so the curve is C1.
Tangents are finite differences of the points: central ``(P_{i+1} - P_{i-1}) / 2``
inside, the second-order one-sided ``±(3 P_e - 4 P_{e±1} + P_{e±2}) / 2`` at the
ends (``P_1 - P_0`` for two points). Both are exact for a quadratic, so a smooth bend
is followed to third order (error bound in the tests).

Joints are placed at equal arc length from the first point to the last (uniform
separation, as the shifting pivot also assumes), the arc length tabulated on
:data:`SAMPLES_PER_SEGMENT` chords per segment; the first and last joints are the end
points exactly.

:func:`hermite_chain` drives a target's spine from the curve (``retargetd retarget
--spread hermite``): K target joints at equal arc length along the curve through the
P solved spine points, each chain joint's world rotation turned (by the shortest
arc) so its bone points along the chord to the next placed joint.
"""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.compiled import kernel
from retargetd.protocols.frames import F64Array

#: Chords per segment for the arc-length table. The chord underestimates the arc by
#: about (κ h)² / 24 relative; for a spine bent to a 0.2 m radius over 0.15 m
#: segments that is 3e-6 of the length at 64 chords.
SAMPLES_PER_SEGMENT = 64


@kernel
def _fit(points: F64Array, coeffs: F64Array) -> None:  # pragma: no cover - compiled
    n = points.shape[0]
    for i in range(n - 1):
        for d in range(3):
            p0, p1 = points[i, d], points[i + 1, d]
            if n == 2:
                t0 = t1 = p1 - p0
            else:
                if i == 0:
                    t0 = 0.5 * (-3.0 * p0 + 4.0 * p1 - points[2, d])
                else:
                    t0 = 0.5 * (p1 - points[i - 1, d])
                if i == n - 2:
                    t1 = 0.5 * (3.0 * p1 - 4.0 * p0 + points[n - 3, d])
                else:
                    t1 = 0.5 * (points[i + 2, d] - p0)
            coeffs[i, 0, d] = 2.0 * p0 - 2.0 * p1 + t0 + t1
            coeffs[i, 1, d] = -3.0 * p0 + 3.0 * p1 - 2.0 * t0 - t1
            coeffs[i, 2, d] = t0
            coeffs[i, 3, d] = p0


@kernel
def _place(
    points: F64Array,
    coeffs: F64Array,
    cum: F64Array,
    out: F64Array,
    tangents: F64Array,
) -> None:  # pragma: no cover - compiled
    n_seg = coeffs.shape[0]
    s = (cum.shape[0] - 1) // n_seg
    # Arc-length table: cum[j] at u = (j mod s) / s of segment j // s.
    cum[0] = 0.0
    px, py, pz = coeffs[0, 3, 0], coeffs[0, 3, 1], coeffs[0, 3, 2]
    for j in range(1, cum.shape[0]):
        seg = min((j - 1) // s, n_seg - 1)
        u = (j - seg * s) / s
        x = ((coeffs[seg, 0, 0] * u + coeffs[seg, 1, 0]) * u + coeffs[seg, 2, 0]) * u
        y = ((coeffs[seg, 0, 1] * u + coeffs[seg, 1, 1]) * u + coeffs[seg, 2, 1]) * u
        z = ((coeffs[seg, 0, 2] * u + coeffs[seg, 1, 2]) * u + coeffs[seg, 2, 2]) * u
        x += coeffs[seg, 3, 0]
        y += coeffs[seg, 3, 1]
        z += coeffs[seg, 3, 2]
        cum[j] = cum[j - 1] + math.sqrt((x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2)
        px, py, pz = x, y, z
    k_joints = out.shape[0]
    total = cum[cum.shape[0] - 1]
    j = 0
    for k in range(k_joints):
        target = total * k / (k_joints - 1)
        while j < cum.shape[0] - 2 and cum[j + 1] < target:
            j += 1
        span = cum[j + 1] - cum[j]
        frac = (target - cum[j]) / span if span > 0.0 else 0.0
        frac = min(1.0, max(0.0, frac))
        seg = min(j // s, n_seg - 1)
        u = (j - seg * s + frac) / s
        if k == k_joints - 1:
            seg, u = n_seg - 1, 1.0
        for d in range(3):
            a, b, c = coeffs[seg, 0, d], coeffs[seg, 1, d], coeffs[seg, 2, d]
            out[k, d] = ((a * u + b) * u + c) * u + coeffs[seg, 3, d]
            tangents[k, d] = (3.0 * a * u + 2.0 * b) * u + c
        norm = math.sqrt(
            tangents[k, 0] ** 2 + tangents[k, 1] ** 2 + tangents[k, 2] ** 2
        )
        if norm > 0.0:
            for d in range(3):
                tangents[k, d] /= norm
    # The ends are the solved points themselves, bit for bit.
    for d in range(3):
        out[0, d] = points[0, d]
        out[k_joints - 1, d] = points[points.shape[0] - 1, d]


class HermiteSpine:
    """Per-frame stage: K joints along the Hermite curve through P spine points.

    Args:
        n_points: solved spine points P (>= 2), e.g. pelvis top, lumbar, thorax,
            neck base.
        n_joints: joints K (>= 2) the target's spine has, first and last on the end
            points.
        samples_per_segment: chords per segment for the arc-length table.

    Raises:
        ValueError: a count out of range.
    """

    def __init__(
        self,
        n_points: int,
        n_joints: int,
        samples_per_segment: int = SAMPLES_PER_SEGMENT,
    ) -> None:
        for name, value, low in (
            ("n_points", n_points, 2),
            ("n_joints", n_joints, 2),
            ("samples_per_segment", samples_per_segment, 1),
        ):
            if int(value) != value or value < low:
                raise ValueError(f"{name} must be an integer >= {low}; got {value!r}")
        self.n_points = int(n_points)
        self.n_joints = int(n_joints)
        #: (P-1, 4, 3) float64: (a, b, c, d) per segment and axis, from the last call.
        self.coeffs = np.zeros((self.n_points - 1, 4, 3))
        #: (K, 3) float64: unit tangent of the curve at each joint, last call.
        self.joint_tangents = np.zeros((self.n_joints, 3))
        self._cum = np.zeros((self.n_points - 1) * int(samples_per_segment) + 1)

    def apply(self, points: F64Array, out: F64Array) -> F64Array:
        """Fit the curve and place the joints.

        Args:
            points: (P, 3) float64, metres, any frame (e.g. world): the solved spine
                points, lowest first, distinct.
            out: (K, 3) float64 destination: the joints, same unit and frame.

        Returns:
            ``out``.
        """
        _fit(points, self.coeffs)
        _place(points, self.coeffs, self._cum, out, self.joint_tangents)
        return out

    def evaluate(self, segment: int, u: F64Array | float) -> tuple[F64Array, F64Array]:
        """Point and tangent (5.60, 5.61) of the last fitted curve (not for the loop).

        Args:
            segment: segment index, 0 .. P-2.
            u: (...) float64 parameter(s) in [0, 1].

        Returns:
            ``(point, tangent)``: (..., 3) float64 each.
        """
        a, b, c, d = self.coeffs[segment]
        u = np.asarray(u, dtype=np.float64)[..., None]
        return ((a * u + b) * u + c) * u + d, (3.0 * a * u + 2.0 * b) * u + c


def _unit(v: F64Array) -> F64Array:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.asarray(v / np.where(n > 0.0, n, 1.0), dtype=np.float64)


def _shortest_arc(a: F64Array, b: F64Array) -> F64Array:
    """(..., 4) rotations taking unit ``a`` onto unit ``b`` (..., 3); (w, x, y, z).

    Exactly opposite directions (a bone half a turn from its equal-spread reference,
    which a spine never is) give the identity rather than an undefined axis."""
    dot = np.sum(a * b, axis=-1, keepdims=True)
    q = np.concatenate([1.0 + dot, np.cross(a, b)], axis=-1)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    ok = n > 1e-12
    q = np.where(ok, q / np.where(ok, n, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
    return np.asarray(q, dtype=np.float64)


def hermite_chain(
    glob: F64Array,
    source_pos: F64Array,
    source_path: list[int],
    target_path: list[int],
    target_rest_pos: F64Array,
) -> F64Array:
    """A target spine chain along the Hermite curve through the source's spine points.

    Per frame, the curve goes through the source joints ``source_path`` (P >= 2
    points, lowest first); the K = ``len(target_path)`` target joints are placed on it
    at equal arc length (:class:`HermiteSpine`; the first and last on the end points).
    Each chain joint ``u_k`` between the ends (k = 1 .. K-2), in order, gets the
    world rotation

        G_k = arc(R_k d_k -> x_{k+1} - y_k) ⊗ R_k,
        R_k = G_top ⊗ slerp(1, conj(G_top) G_bottom, s_k)

    with ``d_k`` its rest bone direction (to the next chain joint), ``x`` the placed
    joints, ``y_k`` where the target's joint ``u_k`` actually is (forward kinematics
    from the curve's first point, the target's rest lengths scaled to the placed
    polyline's) and ``s_k`` its rest arc-length fraction along the chain: the equal
    spread of the chain's rotation (which carries the twist about the spine) swung so
    the bone points at the next placed joint, so an offset of one joint from the
    curve is not passed on down the chain. The ends (``top``: its rotation drives
    the legs; ``bottom``: mapped) keep theirs, so the first bone runs where ``top``
    points it; only directions are written, so the skeletons' sizes may differ.

    Args:
        glob: (T, J', 4) float64 (w, x, y, z) target world rotations (file axes),
            the ends set; the chain's inner joints are written.
        source_pos: (T, J, 3) float64 source joint positions (file axes, its unit).
        source_path: the source joints through which the curve runs, lowest first.
        target_path: the target chain ``top, u_1 .. u_{K-2}, bottom``.
        target_rest_pos: (J', 3) float64 target rest joint positions (file axes).

    Returns:
        ``glob``.

    Raises:
        ValueError: fewer than 2 points or 3 chain joints.
    """
    if len(source_path) < 2 or len(target_path) < 3:
        raise ValueError(
            "hermite_chain needs >= 2 source points and >= 3 target chain joints; got "
            f"{len(source_path)} and {len(target_path)}"
        )
    n_frames = glob.shape[0]
    k_joints = len(target_path)
    spine = HermiteSpine(len(source_path), k_joints)
    placed = np.empty((n_frames, k_joints, 3))
    for t in range(n_frames):
        spine.apply(np.ascontiguousarray(source_pos[t, source_path]), placed[t])
    rest = np.asarray(target_rest_pos, dtype=np.float64)[target_path]
    seg = np.linalg.norm(np.diff(rest, axis=0), axis=-1)
    frac = np.concatenate([[0.0], np.cumsum(seg)]) / max(float(seg.sum()), 1e-300)
    top, bottom = glob[:, target_path[0]], glob[:, target_path[-1]]
    rel = rot.quat_mul(rot.quat_conj(top), bottom)
    ident = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (n_frames, 1))
    # The target's joints in the curve's unit: its rest lengths scaled to the
    # placed polyline's, walked from the curve's first point down the chain.
    chords = np.linalg.norm(np.diff(placed, axis=1), axis=-1).sum(axis=1)
    scale = (chords / max(float(seg.sum()), 1e-300))[:, None]
    at = placed[:, 0] + scale * rot.quat_rotate(top, rest[1] - rest[0])
    for k in range(1, k_joints - 1):
        ref = rot.quat_mul(top, rot.slerp(ident, rel, float(frac[k])))
        bone = rest[k + 1] - rest[k]
        now = rot.quat_rotate(ref, _unit(bone))
        aim = _unit(placed[:, k + 1] - at)
        g = rot.quat_mul(_shortest_arc(_unit(now), aim), ref)
        glob[:, target_path[k]] = g
        at = at + scale * rot.quat_rotate(g, bone)
    return glob
