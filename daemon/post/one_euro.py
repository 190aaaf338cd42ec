"""The One Euro filter (Casiez, Roussel & Vogel, CHI 2012), quaternion-aware.

Per channel, with the time step ``dt`` and ``a(f) = 1 / (1 + 1 / (2π f dt))``:

    velocity    v̂ <- v̂ + a(d_cutoff) (v - v̂),     v = (x - x̂) / dt
    cutoff      f = min_cutoff + beta |v̂|
    value       x̂ <- x̂ + a(f) (x - x̂)

so slow motion is smoothed hard (jitter) and fast motion followed closely (lag).
Channels are each bone's rotation and the root position. A rotation is filtered in
the tangent space of the current estimate: ``δ = log(q̂⁻¹ q)`` (a rotation vector,
``q`` first put in ``q̂``'s hemisphere so the short way round is taken), ``v = δ / dt``
the angular velocity in the bone frame, and ``q̂ <- q̂ ⊗ exp(a δ)``, which is
``slerp(q̂, q, a)``: always a unit quaternion, independent of the sign of the input.

Parameters (off by default in the pipeline): the defaults are the paper's starting
point for tuning, ``min_cutoff = 1 Hz``, ``beta = 0``, ``d_cutoff = 1 Hz``; raise
``beta`` until the lag on fast moves is acceptable, then lower ``min_cutoff`` until the
jitter at rest is. ``bench/bench_post.py`` prints lag and jitter on a real take.
"""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon.compiled import kernel
from retargetd.daemon.post._kernels import qmul
from retargetd.daemon.post.pose import PoseBuffer
from retargetd.protocols.frames import F64Array

#: Casiez et al. 2012, section "Tuning": start at 1 Hz minimum cutoff, beta 0, and a
#: 1 Hz cutoff for the derivative.
DEFAULT_MIN_CUTOFF_HZ = 1.0
DEFAULT_BETA_ROT = 0.0  # Hz per rad/s
DEFAULT_BETA_POS = 0.0  # Hz per m/s
DEFAULT_D_CUTOFF_HZ = 1.0


@kernel
def _alpha(cutoff_hz: float, dt: float) -> float:  # pragma: no cover - compiled
    return 1.0 / (1.0 + 1.0 / (2.0 * math.pi * cutoff_hz * dt))


@kernel
def _filter(
    q: F64Array,
    pos: F64Array,
    q_hat: F64Array,
    w_hat: F64Array,
    pos_hat: F64Array,
    vel_hat: F64Array,
    dt: float,
    params: F64Array,
) -> None:  # pragma: no cover - compiled
    min_cutoff, beta_rot, beta_pos, d_cutoff = (
        params[0],
        params[1],
        params[2],
        params[3],
    )
    a_d = _alpha(d_cutoff, dt)
    for b in range(q.shape[0]):
        hw, hx, hy, hz = q_hat[b, 0], q_hat[b, 1], q_hat[b, 2], q_hat[b, 3]
        # δq = q̂⁻¹ ⊗ q, in q̂'s hemisphere.
        dw, dx, dy, dz = qmul(hw, -hx, -hy, -hz, q[b, 0], q[b, 1], q[b, 2], q[b, 3])
        if dw < 0.0:
            dw, dx, dy, dz = -dw, -dx, -dy, -dz
        s = math.sqrt(dx * dx + dy * dy + dz * dz)
        theta = 2.0 * math.atan2(s, dw)
        k = theta / s if s > 1e-12 else 2.0
        vx, vy, vz = k * dx / dt, k * dy / dt, k * dz / dt
        w_hat[b, 0] += a_d * (vx - w_hat[b, 0])
        w_hat[b, 1] += a_d * (vy - w_hat[b, 1])
        w_hat[b, 2] += a_d * (vz - w_hat[b, 2])
        speed = math.sqrt(w_hat[b, 0] ** 2 + w_hat[b, 1] ** 2 + w_hat[b, 2] ** 2)
        a = _alpha(min_cutoff + beta_rot * speed, dt)
        # q̂ ⊗ exp(a δ): a turn of a θ about δ's axis.
        half = 0.5 * a * theta
        sh = math.sin(half) / s if s > 1e-12 else 0.5 * a * k
        r = qmul(hw, hx, hy, hz, math.cos(half), sh * dx, sh * dy, sh * dz)
        n = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3])
        q_hat[b, 0], q_hat[b, 1] = r[0] / n, r[1] / n
        q_hat[b, 2], q_hat[b, 3] = r[2] / n, r[3] / n
    speed = 0.0
    for d in range(3):
        vel_hat[d] += a_d * ((pos[d] - pos_hat[d]) / dt - vel_hat[d])
        speed += vel_hat[d] * vel_hat[d]
    a = _alpha(min_cutoff + beta_pos * math.sqrt(speed), dt)
    for d in range(3):
        pos_hat[d] += a * (pos[d] - pos_hat[d])


class OneEuroFilter:
    """Per-frame stage: the One Euro filter on every bone rotation and the root.

    Args:
        n_bones: bones B of the stream.
        min_cutoff_hz: cutoff at rest, Hz (> 0).
        beta_rot: cutoff increase per unit angular speed, Hz per rad/s (>= 0).
        beta_pos: the same for the root, Hz per m/s (>= 0).
        d_cutoff_hz: cutoff of the velocity estimate, Hz (> 0).

    Raises:
        ValueError: naming a bad parameter.
    """

    def __init__(
        self,
        n_bones: int,
        *,
        min_cutoff_hz: float = DEFAULT_MIN_CUTOFF_HZ,
        beta_rot: float = DEFAULT_BETA_ROT,
        beta_pos: float = DEFAULT_BETA_POS,
        d_cutoff_hz: float = DEFAULT_D_CUTOFF_HZ,
    ) -> None:
        for name, value, strict in (
            ("min_cutoff_hz", min_cutoff_hz, True),
            ("beta_rot", beta_rot, False),
            ("beta_pos", beta_pos, False),
            ("d_cutoff_hz", d_cutoff_hz, True),
        ):
            ok = math.isfinite(value) and (value > 0.0 if strict else value >= 0.0)
            if not ok:
                bound = "> 0" if strict else ">= 0"
                raise ValueError(f"{name} must be finite and {bound}; got {value!r}")
        self._params = np.array([min_cutoff_hz, beta_rot, beta_pos, d_cutoff_hz])
        self._state = PoseBuffer.new(n_bones)
        self._w_hat = np.zeros((n_bones, 3))
        self._vel_hat = np.zeros(3)
        self._started = False

    def reset(self) -> None:
        """Forget the history: the next pose passes through and restarts the filter."""
        self._started = False

    def apply(self, pose: PoseBuffer, out: PoseBuffer) -> PoseBuffer:
        """Filter one pose.

        Args:
            pose: the pose; ``pose.t_s`` gives the time step. A pose not later than
                the last one leaves the estimate as it is.
            out: the destination (may be ``pose``).

        Returns:
            ``out``: the filtered pose, ``t_s`` that of ``pose``.
        """
        state = self._state
        if not self._started:
            state.copy_from(pose)
            self._w_hat[:] = 0.0
            self._vel_hat[:] = 0.0
            self._started = True
        else:
            dt = pose.t_s - state.t_s
            if dt > 0.0:
                _filter(
                    pose.parent_from_bone_quat,
                    pose.root_pos,
                    state.parent_from_bone_quat,
                    self._w_hat,
                    state.root_pos,
                    self._vel_hat,
                    dt,
                    self._params,
                )
                state.t_s = pose.t_s
        t_s = pose.t_s
        out.copy_from(state)
        out.t_s = t_s
        return out
