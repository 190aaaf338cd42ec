"""VMC messages for props: a tracker per prop and a virtual camera.

From the VMC protocol's spec (protocol.vmc.info, ``docs/english.markdown``; the
performer-to-marionette messages EVMC4U, VMC4UE and VMC4B apply):

| address | types | arguments |
|---|---|---|
| ``/VMC/Ext/Tra/Pos`` | ``s fff ffff`` | serial, position x y z, rotation x y z w |
| ``/VMC/Ext/Cam`` | ``s fff ffff f`` | name, position, rotation, field of view |

Both in Unity's frame (``engine_unity``: left-handed, +Y up, metres, x y z w), as
every VMC pose. The serial of a prop's tracker is the prop's name; the camera's name
is too. One bundle per prop per frame (time tag "immediately"): its tracker, then its
camera for a prop of kind "camera". The camera's field of view is Unity's
``Camera.fieldOfView``: vertical, degrees. PROTOCOLS.md section 5 has a worked
example.

:class:`VmcPropEncoder` writes into one preallocated buffer per prop (the address,
type tags and name are fixed; only the floats change), so the per-frame cost is one
``struct.pack_into``.
"""

from __future__ import annotations

import struct

import numpy as np

from retargetd.protocols.engine_unity import (
    unity_pos_from_world,
    unity_quat_xyzw_from_world,
)
from retargetd.protocols.frames import F64Array
from retargetd.protocols.osc_wire import BUNDLE_HEADER, osc_string

TRACKER_ADDRESS = "/VMC/Ext/Tra/Pos"
CAMERA_ADDRESS = "/VMC/Ext/Cam"
_TRACKER_FLOATS = struct.Struct(">7f")
_CAMERA_FLOATS = struct.Struct(">8f")


class VmcPropEncoder:
    """One prop's VMC bundle: ``/VMC/Ext/Tra/Pos`` and, for a camera,
    ``/VMC/Ext/Cam``.

    Args:
        name: the tracker serial and camera name (the prop's name).
        camera: also send the camera message.
    """

    def __init__(self, name: str, *, camera: bool) -> None:
        head_t = (
            osc_string(TRACKER_ADDRESS) + osc_string(",sfffffff") + osc_string(name)
        )
        head_c = (
            osc_string(CAMERA_ADDRESS) + osc_string(",sffffffff") + osc_string(name)
        )
        tracker = len(head_t) + _TRACKER_FLOATS.size
        cam = len(head_c) + _CAMERA_FLOATS.size
        size = len(BUNDLE_HEADER) + 4 + tracker + ((4 + cam) if camera else 0)
        self._buf = bytearray(size)
        off = 0
        self._buf[off : off + 16] = BUNDLE_HEADER
        off += 16
        struct.pack_into(">i", self._buf, off, tracker)
        off += 4
        self._buf[off : off + len(head_t)] = head_t
        self._t_off = off + len(head_t)
        off = self._t_off + _TRACKER_FLOATS.size
        self._c_off = -1
        if camera:
            struct.pack_into(">i", self._buf, off, cam)
            off += 4
            self._buf[off : off + len(head_c)] = head_c
            self._c_off = off + len(head_c)
        self.datagram = memoryview(self._buf)
        self._pos = np.zeros(3)
        self._quat = np.zeros(4)

    def encode(
        self, pos_world: F64Array, quat_wxyz: F64Array, fov_deg: float
    ) -> memoryview:
        """The bundle for one frame (a view of the reused buffer).

        Args:
            pos_world: (3,) the prop's origin, metres, world.
            quat_wxyz: (4,) world_from_prop, w x y z.
            fov_deg: the camera's vertical field of view (ignored for a tracker).
        """
        p = unity_pos_from_world(pos_world, self._pos)
        q = unity_quat_xyzw_from_world(quat_wxyz, self._quat)
        _TRACKER_FLOATS.pack_into(
            self._buf, self._t_off, p[0], p[1], p[2], q[0], q[1], q[2], q[3]
        )
        if self._c_off >= 0:
            _CAMERA_FLOATS.pack_into(
                self._buf, self._c_off, p[0], p[1], p[2], q[0], q[1], q[2], q[3],
                fov_deg,
            )  # fmt: skip
        return self.datagram
