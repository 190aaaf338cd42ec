"""Control and show control: JSON requests on the local ZeroMQ REP socket (status,
calibrate, reload, record, face-capture) and OSC show-control messages on VMC's
performer port (``/VMC/Ext/Set/Calib/Ready``, ``/VMC/Ext/Set/Calib/Exec``,
``/rtd/calibrate``, ``/rtd/reload``).
"""

from __future__ import annotations

import json
import logging
from typing import Any

import zmq

from retargetd.daemon.live.recording import (
    FORM_ZMQ,
    input_infos,
)
from retargetd.daemon.live.state import DaemonState
from retargetd.protocols import osc_in, zmq_wire
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.osc_wire import iter_bundle_elements, parse_message

logger = logging.getLogger(__name__)

#: Largest control request accepted (bytes); ZeroMQ drops the connection of a
#: peer that sends more. A request is a small JSON object (a path at most).
CONTROL_MAX_BYTES = 65536


class ControlMixin(DaemonState):
    """Control requests (``retargetd ctl``) and OSC show control."""

    def _serve_control(self) -> None:
        assert self._ctl is not None
        try:
            # Every part of the request, so the REP socket is always ready to reply
            # (a multipart request read with recv() left it mid-message).
            parts = self._ctl.recv_multipart(zmq.NOBLOCK)
        except zmq.Again:
            return
        reply = self.control_reply(parts)
        try:
            self._ctl.send(json.dumps(reply).encode(), zmq.NOBLOCK)
        except zmq.ZMQError as exc:  # the requester vanished: nothing to answer
            logger.warning("control reply not sent: %s", exc)

    def control_reply(self, parts: list[bytes]) -> dict[str, Any]:
        """The reply to one control request (every part of one ZeroMQ message).

        Never raises: a malformed request gets ``{"ok": false, "error": ...}``.
        Counted: ``control_requests`` every request, ``control_errors`` those whose
        reply is not ok.
        """
        self.stats.control_requests += 1
        try:
            if len(parts) != 1:
                raise ValueError(
                    f"a control request is one JSON message; got {len(parts)} parts"
                )
            req = json.loads(parts[0])
            if not isinstance(req, dict):
                raise ValueError("request must be a JSON object")
            reply = self._control(req)
        except RecursionError:  # nesting deeper than the parser's stack
            reply = {"ok": False, "error": "request nested too deeply"}
        except (ValueError, TypeError) as exc:
            reply = {"ok": False, "error": str(exc)}
        if reply.get("ok") is not True:
            self.stats.control_errors += 1
        return reply

    def _control(self, req: dict[str, Any]) -> dict[str, Any]:
        cmd = req.get("cmd")
        if cmd == "status":
            return {"ok": True, "status": self.status(), "line": self.stats_line()}
        if cmd == "calibrate":
            count = req.get("count")
            if count is not None and (type(count) is not int or count < 1):
                raise ValueError(f"count must be a positive integer; got {count!r}")
            return {"ok": True, "message": self.request_calibration(count, "ctl")}
        if cmd == "reload":
            msg = self.reload()
            return {"ok": not msg.startswith("reload failed"), "message": msg}
        if cmd == "record":
            return {"ok": True, "message": self._record_control(req)}
        if cmd == "face-capture":
            name, count = req.get("name"), req.get("count")
            if not isinstance(name, str) or not name:
                raise ValueError(f"face-capture needs a 'name' string; got {name!r}")
            if count is not None and (type(count) is not int or count < 1):
                raise ValueError(f"count must be a positive integer; got {count!r}")
            return {
                "ok": True,
                "message": self.request_face_capture(name, count, "ctl"),
            }
        raise ValueError(
            f"unknown command {cmd!r} (status, calibrate, reload, record, face-capture)"
        )

    def _record_control(self, req: dict[str, Any]) -> str:
        """``{"cmd": "record", "action": "start", "path": FILE, "poses": bool}`` or
        ``{"cmd": "record", "action": "stop"}``; ValueError names what is wrong."""
        action = req.get("action")
        if action == "stop":
            return self.recording.stop("ctl")
        if action != "start":
            raise ValueError(f"record action must be 'start' or 'stop'; got {action!r}")
        path = req.get("path")
        poses = req.get("poses", True)
        if not isinstance(path, str) or not path:
            raise ValueError(f"record start needs a 'path' string; got {path!r}")
        if type(poses) is not bool:
            raise ValueError(f"'poses' must be true or false; got {poses!r}")
        announcements: list[tuple[str, int, tuple[bytes, ...]]] = []
        if self._osc is not None and self.config.input.osc.form == "compact":
            ls = self.osc_stream.label_set
            if ls is not None:
                announcements.append(
                    ("osc", self._osc_form, (osc_in.encode_labels(ls),))
                )
        if self._zin is not None and self.zmq_stream.label_set is not None:
            parts = tuple(zmq_wire.encode_zmq_labels(self.zmq_stream.label_set))
            announcements.append(("zmq", FORM_ZMQ, parts))
        msg = self.recording.start(
            path, poses, input_infos(self.config, self.endpoints), announcements
        )
        self._last_names_ns = 0  # the names message opens the recorded pose stream
        return msg

    def _drain_show_control(self) -> None:
        assert self._show is not None
        while True:
            try:
                n, addr = self._show.recvfrom_into(self._buf)
            except (BlockingIOError, InterruptedError):
                break
            if self._allow and addr[0] not in self._allow:
                self.stats.rejected_sources += 1  # the same allow-list as the markers
                continue
            self.stats.show_control_in += 1
            messages, malformed = parse_show_control(bytes(self._buf[:n]))
            if malformed:
                self.stats.show_control_malformed += 1
            for address, args in messages:
                self._show_control(address, args, addr)

    def _show_control(self, address: str, args: list[Any], addr: Any) -> None:
        if address == "/VMC/Ext/Set/Calib/Ready":
            self.out(f"show control {addr[0]}: calibration ready (hold the base pose)")
        elif address in ("/VMC/Ext/Set/Calib/Exec", "/rtd/calibrate"):
            count = args[0] if address == "/rtd/calibrate" and args else None
            if type(count) is not int or count < 1:  # bool (OSC T/F) is not a count
                count = None
            self.out(self.request_calibration(count, f"show control {addr[0]}"))
        elif address == "/rtd/reload":
            self.out(self.reload())


def parse_show_control(packet: bytes) -> tuple[list[tuple[str, list[Any]]], int]:
    """The OSC messages of a show-control datagram (a message, or a bundle flattened,
    nested at most 4 deep), and how many of its elements were malformed.

    Never raises: a malformed message is skipped and counted; a malformed bundle
    (bad element sizes, nested too deep) counts 1 and none of its messages is used.

    Returns:
        ``([(address, args), ...], malformed)``.
    """
    raw: list[bytes] = []
    malformed = _osc_messages(packet, raw)
    good: list[tuple[str, list[Any]]] = []
    for message in raw:
        try:
            address, _tags, args = parse_message(message)
        except DecodeError:
            malformed += 1
            continue
        good.append((address, args))
    return good, malformed


def _osc_messages(packet: bytes, out: list[bytes], depth: int = 0) -> int:
    """Append the messages of an OSC packet to ``out`` (a bundle flattened; a bundle
    that does not parse whole contributes nothing); returns the number of malformed
    bundles met."""
    if not packet.startswith(b"#bundle\0"):
        out.append(packet)
        return 0
    if depth > 4:
        return 1
    inner: list[bytes] = []
    bad = 0
    try:
        for element in iter_bundle_elements(packet):
            bad += _osc_messages(bytes(element), inner, depth + 1)
    except DecodeError:
        return bad + 1
    out.extend(inner)
    return bad
