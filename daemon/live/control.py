"""Control and show control: JSON requests on the local ZeroMQ REP socket (status,
calibrate, reload, record, face-capture) and OSC show-control messages on VMC's
performer port (``/VMC/Ext/Set/Calib/Ready``, ``/VMC/Ext/Set/Calib/Exec``,
``/rtd/calibrate``, ``/rtd/reload``).

Calibrate and reload can be switched off per path (``control.calibrate``,
``show_control.calibrate`` ...); arguments are type-checked; with
``show_control.token`` set every show-control address starts with ``/TOKEN``.
Refused show-control messages are counted by reason (status ``show_control``) and
logged through the rate-limited log. ``record start`` writes only under
``record.folder``.
"""

from __future__ import annotations

import hmac
import json
import logging
import os
import re
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zmq

from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.inputs import Inputs, last_endpoint
from retargetd.daemon.live.kernel_drops import udp_kernel_drops
from retargetd.daemon.live.performer import Performer
from retargetd.daemon.live.performers import Performers
from retargetd.daemon.live.props import LiveProps
from retargetd.daemon.live.ratelog import RateLimitedLog
from retargetd.daemon.live.rebuild import Build
from retargetd.daemon.live.recording import (
    input_infos,
)
from retargetd.daemon.live.shared import Shared
from retargetd.daemon.live.stalls import LoopStalls
from retargetd.daemon.live.surface import (
    endpoint_is_local,
    is_loopback_host,
    who_reaches,
)
from retargetd.daemon.live.watch import SocketWatch
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.osc_wire import iter_bundle_elements, parse_message

logger = logging.getLogger(__name__)

#: Largest control request read (bytes): a request is a small JSON object (a path at
#: most). A larger one, up to :data:`CONTROL_TRANSPORT_MAX_BYTES`, is answered
#: ``ok: false`` unread and counted (``control_oversize``).
CONTROL_MAX_BYTES = 65536
#: The control socket's ``ZMQ_MAXMSGSIZE``: past it libzmq drops the connection at the
#: message's header, before buffering it, and the daemon never sees the request (no
#: reply can be sent: ZeroMQ reports it as an ordinary disconnect). 16 MiB answers the
#: 10 MB request of issue 30; libzmq allocates a message at its header but the pages
#: are committed only as its bytes arrive, so a peer that claims 16 MiB and sends
#: little costs little.
CONTROL_TRANSPORT_MAX_BYTES = 16 << 20
#: Requests queued per control connection (``ZMQ_RCVHWM``): a REQ peer sends one at a
#: time; a DEALER pipelining large requests is held back by TCP after this many.
CONTROL_RCVHWM = 4
#: Commands that act for one performer (the others act for the daemon).
PER_PERFORMER_COMMANDS = ("calibrate", "face-capture")


class Control:
    """Control requests (``retargetd ctl``) and OSC show control: their sockets and
    refusal counters; each command becomes a call on the part it is about.

    Args:
        shared: the loop's side (config, counters, recording, out).
        performers: calibrate, face-capture and reload act on them.
        props: a prop's calibration, a camera's field of view.
        inputs: the label sets a recording opens with.
        endpoints: what is listening where (a recording's header names them).
        log: the rate-limited log (refusals).
        stalls: the loop's phase timer (a slow command is counted by name).
        status: the status document and the stats line (``ctl status``).
    """

    def __init__(
        self,
        shared: Shared,
        performers: Performers,
        props: LiveProps,
        inputs: Inputs,
        endpoints: dict[str, str],
        log: RateLimitedLog,
        stalls: LoopStalls,
        status: Callable[[], tuple[dict[str, Any], str]],
    ) -> None:
        self.shared = shared
        self.stats = shared.stats
        self.recording = shared.recording
        self.out = shared.out
        self.performers = performers
        self.props = props
        self.inputs = inputs
        self.endpoints = endpoints
        self._log = log
        self._stalls = stalls
        self._status = status
        config = shared.config
        self._allow = frozenset(config.input.osc.allow)  # the markers' list too
        token = config.show_control.token
        self._show_token_prefix = f"/{token}" if token else ""
        self._ctl: Any = None
        self._show: socket.socket | None = None
        self._show_fd = -2  # the poll result's fd (set by open)
        self._show_buf = bytearray(65536)  # a show-control datagram
        self.show_counters: dict[str, int] = {}  # refused, by reason
        # A reload whose files a worker reads (live/reload.py) and who waits for
        # its outcome: "ctl" (the REP socket's reply, owed until then) or "out"
        # (show control, the console: printed).
        self._reload: Build | None = None
        self._reload_waiters: list[str] = []
        self._serving = False  # a ctl request from the socket is being answered

    @property
    def config(self) -> DaemonConfig:
        """The running configuration."""
        return self.shared.config

    def open(
        self,
        udp_bind: Callable[[str, int], socket.socket],
        server_socket: Callable[[int, str, tuple[str, ...]], Any],
        own: Callable[[Any], None],
        watch: SocketWatch,
        announce: Callable[[str, str], None],
    ) -> None:
        """Bind show control ([show_control] on) and the control socket."""
        c = self.config
        if c.show_control.enabled:
            show = c.show_control
            sock = udp_bind(show.host, show.port)
            self._show, self._show_fd = sock, sock.fileno()
            can = [w for w, on in (("calibrate", show.calibrate),
                                   ("reload", show.reload)) if on]  # fmt: skip
            who = who_reaches(is_loopback_host(show.host), show.host)
            token = ", token required" if show.token else ""
            host, port = sock.getsockname()[:2]
            announce(
                "show control",
                f"udp://{host}:{port} (OSC; "
                f"{' and '.join(can) or 'nothing but status'} from {who}{token})",
            )
        ctl = c.control
        self._ctl = server_socket(zmq.REP, ctl.secret_key, ctl.client_keys)
        self._ctl.setsockopt(zmq.LINGER, 0)
        self._ctl.setsockopt(zmq.MAXMSGSIZE, CONTROL_TRANSPORT_MAX_BYTES)
        self._ctl.setsockopt(zmq.RCVHWM, CONTROL_RCVHWM)
        self._ctl.bind(ctl.endpoint)
        own(self._ctl)
        watch.watch("control", self._ctl, bool(ctl.secret_key))
        ep = last_endpoint(self._ctl)
        who = who_reaches(endpoint_is_local(ctl.endpoint), ep)
        curve = (
            f", CURVE: {len(ctl.client_keys)} client key(s)" if ctl.secret_key else ""
        )
        announce("control", f"{ep} (retargetd ctl --endpoint {ep}; from {who}{curve})")

    def serve(self, events: list[tuple[Any, int]]) -> None:
        """Show-control datagrams and ``ctl`` requests the poll found waiting."""
        ctl, show_fd = self._ctl, self._show_fd
        show = serve = False
        for sock, _flags in events:
            if sock is ctl:
                serve = True
            elif sock == show_fd:
                show = True
        if show:
            self._drain_show_control()
            self._stalls.lap("show_control")
        if serve:
            self._serve_control()  # its lap names the command

    def status(self) -> dict[str, Any]:
        """Show control's refusals by reason and its kernel drops (status)."""
        return {
            "refused": dict(self.show_counters),
            "kernel_drops": udp_kernel_drops(self._show),
        }

    def _serve_control(self) -> None:
        assert self._ctl is not None
        if "ctl" in self._reload_waiters:  # a reply owed: no request read before it
            return
        try:
            # Every part of the request, so the REP socket is always ready to reply
            # (a multipart request read with recv() left it mid-message); as frames,
            # so an oversize one is measured, never copied.
            frames = self._ctl.recv_multipart(zmq.NOBLOCK, copy=False)
        except zmq.Again:
            return
        self._stalls.lap("control.read")
        size = sum(len(f) for f in frames)
        if size > CONTROL_MAX_BYTES:
            reply = self._oversize(size, frames[0])
            phase = "control.oversize"
        else:
            self._serving = True
            try:
                reply = self.control_reply([f.bytes for f in frames])
            finally:
                self._serving = False
            phase = _phase(bytes(frames[0].buffer[:64]))
        if reply is not _LATER:  # (a reload: answered when its files are read)
            self._send_reply(reply)
        self._stalls.lap(phase)

    def _send_reply(self, reply: dict[str, Any]) -> None:
        assert self._ctl is not None
        try:
            self._ctl.send(json.dumps(reply).encode(), zmq.NOBLOCK)
        except zmq.ZMQError as exc:  # the requester vanished: nothing to answer
            logger.warning("control reply not sent: %s", exc)

    def reload_later(self, who: str) -> None:
        """Start a reload, its files read off the loop (``Performers.begin_reload``),
        or join the one under way; its outcome goes to ``who`` ("ctl": the reply
        owed on the control socket; "out": printed) when :meth:`tick` finds it done.

        Raises:
            ValueError: rate limited (counted).
        """
        if self._reload is None:
            self._reload = self.performers.begin_reload()
        else:  # the same files being read: the rate limit still applies
            self.performers.allow_reload()
        self._reload_waiters.append(who)

    def tick(self) -> None:
        """Every loop pass: a reload whose files are read is swapped in (or
        refused) and its outcome answered and printed."""
        job = self._reload
        if job is None or not job.done():
            return
        self._reload = None
        msg = self.performers.end_reload(job)
        ok = "reload failed" not in msg
        for who in self._reload_waiters:
            if who == "ctl":
                if not ok:
                    self.stats.control_errors += 1
                self._send_reply({"ok": ok, "message": msg})
            else:
                self.out(msg)
        self._reload_waiters.clear()
        self._stalls.lap("control.reload")

    def _oversize(self, size: int, frame: Any) -> dict[str, Any]:
        """The reply to a request over :data:`CONTROL_MAX_BYTES` (unread): counted in
        ``control_requests``, ``control_errors`` and ``control_oversize``; one
        rate-limited log line with the peer's address."""
        self.stats.control_requests += 1
        self.stats.control_errors += 1
        self.stats.control_oversize += 1
        try:
            peer = frame.get("Peer-Address")  # tcp: the peer's IP address
        except zmq.ZMQError:
            peer = "an ipc or inproc peer"
        self._log.line(
            "control oversize",
            f"control: refused a request of {size} bytes from {peer} "
            f"(at most {CONTROL_MAX_BYTES})",
            time.monotonic_ns(),
        )
        return {
            "ok": False,
            "error": f"request too large: {size} bytes (at most {CONTROL_MAX_BYTES})",
        }

    def control_reply(self, parts: list[bytes]) -> dict[str, Any]:
        """The reply to one control request (every part of one ZeroMQ message).

        Never raises: a malformed request gets ``{"ok": false, "error": ...}``, and
        so does one that meets a fault of the daemon's own (logged with its
        traceback: a control command never stops the show).
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
            reply = self._control_for(req)  # the performer it names, if any
        except RecursionError:  # nesting deeper than the parser's stack
            reply = {"ok": False, "error": "request nested too deeply"}
        except (ValueError, TypeError) as exc:
            reply = {"ok": False, "error": str(exc)}
        except Exception as exc:  # a fault of ours: answered, logged, never fatal
            logger.exception("control request %r failed", parts[:1])
            reply = {"ok": False, "error": f"internal error ({type(exc).__name__}): "
                     "the daemon's log has the traceback"}  # fmt: skip
        if reply.get("ok") is not True:
            self.stats.control_errors += 1
        return reply

    def _control_for(self, req: dict[str, Any]) -> dict[str, Any]:
        """A control request acting for the performer it names (``performer``);
        commands for the daemon as a whole (status, reload, record) take none."""
        cmd = req.get("cmd")
        name = req.get("performer")
        if cmd == "calibrate" and req.get("prop") is not None:  # a [[prop]]'s
            if not self.config.control.calibrate:
                raise ValueError("calibrate is off on this path (control.calibrate)")
            msg = self.props.request_calibration(req["prop"], req.get("count"), "ctl")
            return {"ok": True, "message": msg, "prop": req["prop"]}
        if cmd not in PER_PERFORMER_COMMANDS:
            if name is not None:
                raise ValueError(
                    f"{cmd!r} acts for the whole daemon: leave out 'performer' "
                    f"(it applies to {', '.join(PER_PERFORMER_COMMANDS)})"
                )
            return self._control(req, self.performers.first)
        perf = self.performers.named(name)
        reply = self._control(req, perf)
        if perf.name:
            reply["performer"] = perf.name
        return reply

    def _control(self, req: dict[str, Any], perf: Performer) -> dict[str, Any]:
        """One command; ``perf``: the performer a per-performer one acts for."""
        cmd = req.get("cmd")
        if cmd == "status":
            status, line = self._status()
            return {"ok": True, "status": status, "line": line}
        if cmd == "calibrate":
            if not self.config.control.calibrate:
                raise ValueError("calibrate is off on this path (control.calibrate)")
            msg = perf.calib.request(req.get("count"), "ctl", req.get("rom_s"))
            # ctl waits for this one's outcome (status: calibration_id / _state)
            return {"ok": True, "message": msg, "calibration_id": perf.calib.id}
        if cmd == "reload":
            if not self.config.control.reload:
                raise ValueError("reload is off on this path (control.reload)")
            if self._serving:  # from the socket: answered when the files are read
                self.reload_later("ctl")
                return _LATER
            msg = self.performers.reload()  # (a direct caller: waits for them)
            return {"ok": "reload failed" not in msg, "message": msg}
        if cmd == "record":
            return {"ok": True, "message": self.record(req)}
        if cmd == "face-capture":
            name, count = req.get("name"), req.get("count")
            if not isinstance(name, str) or not name:
                raise ValueError(f"face-capture needs a 'name' string; got {name!r}")
            if count is not None and (type(count) is not int or count < 1):
                raise ValueError(f"count must be a positive integer; got {count!r}")
            return {
                "ok": True,
                "message": perf.calib.request_face(name, count, "ctl"),
            }
        raise ValueError(
            f"unknown command {cmd!r} (status, calibrate, reload, record, face-capture)"
        )

    def record(self, req: dict[str, Any]) -> str:
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
        path = recording_path(self.config.record.folder, path)
        if type(poses) is not bool:
            raise ValueError(f"'poses' must be true or false; got {poses!r}")
        announcements = self.inputs.label_announcements()
        force = req.get("force", False)
        if type(force) is not bool:
            raise ValueError(f"'force' must be true or false; got {force!r}")
        try:
            msg = self.recording.start(
                path, poses, input_infos(self.config, self.endpoints), announcements,
                force=force, rig=self.performers.first.rig,
            )  # fmt: skip
        except ValueError as exc:
            if str(exc).startswith("rate limited"):
                self.stats.rate_limited += 1
            raise
        self.performers.announce_names()  # they open the recorded pose stream
        return msg

    def _drain_show_control(self) -> None:
        assert self._show is not None
        while True:
            try:
                n, addr = self._show.recvfrom_into(self._show_buf)
            except (BlockingIOError, InterruptedError):
                break
            if self._allow and addr[0] not in self._allow:
                self.stats.rejected_sources += 1  # the same allow-list as the markers
                continue
            self.stats.show_control_in += 1
            parsed = parse_show_control(
                bytes(self._show_buf[:n]), self._show_token_prefix.encode()
            )
            if parsed.refused:  # the whole datagram, once, before any parsing
                self._show_refused(parsed.refused, parsed.why, addr)
                continue
            if parsed.malformed:
                self.stats.show_control_malformed += 1
                self._show_refused(
                    "malformed", f"{parsed.malformed} malformed OSC", addr
                )
            for address, args in parsed.messages:
                self._show_control(address, args, addr)

    def _show_refused(self, reason: str, why: str, addr: Any = None) -> None:
        """Count a refused show-control message by reason; one rate-limited line."""
        self.show_counters[reason] = self.show_counters.get(reason, 0) + 1
        who = f" from {addr[0]}" if addr is not None else ""
        self._log.line(
            f"show control {reason}",
            f"show control{who}: refused: {why}",
            time.monotonic_ns(),
        )

    def _show_control(self, address: str, args: list[Any], addr: Any) -> None:
        # parse_show_control checked the token on every message of the datagram
        address = address[len(self._show_token_prefix) :]
        cfg = self.config.show_control
        by = f"show control {addr[0]}"
        now = time.monotonic_ns()
        if address == "/VMC/Ext/Set/Calib/Ready":
            self._log.line(
                "show control ready", f"{by}: calibration ready (hold the base pose)",
                now,
            )  # fmt: skip
        elif address in ("/VMC/Ext/Set/Calib/Exec", "/rtd/calibrate"):
            if not cfg.calibrate:
                self._show_refused("calibrate_off", f"{address}: off", addr)
                return
            count = None
            performer = None
            if address == "/rtd/calibrate" and args:
                # [performer name string,] one int32 count; anything else (-5, a
                # bool, more arguments) is refused, never taken as "the default".
                if isinstance(args[0], str):
                    performer, args = args[0], args[1:]
                if len(args) > 1 or (args and type(args[0]) is not int):
                    self._show_refused(
                        "bad_argument", f"{address}: expected [a performer name,] "
                        f"one integer count; got {args!r}"[:200], addr,
                    )  # fmt: skip
                    return
                count = args[0] if args else None
            elif address == "/VMC/Ext/Set/Calib/Exec" and (
                len(args) > 1 or (args and type(args[0]) is not int)
            ):
                # VMC's Calib/Exec carries at most one int (the calibration mode).
                self._show_refused(
                    "bad_argument", f"{address}: expected no argument or one int "
                    f"mode; got {args!r}"[:200], addr,
                )  # fmt: skip
                return
            try:
                msg = self.performers.calibrate(performer, count, by)
            except ValueError as exc:
                limited = str(exc).startswith("rate")
                reason = "rate_limited" if limited else "bad_argument"
                self._show_refused(reason, f"{address}: {exc}", addr)
                return
            self.out(msg)
        elif address == "/rtd/reload":
            if not cfg.reload:
                self._show_refused("reload_off", f"{address}: reload is off", addr)
                return
            try:
                self.reload_later("out")  # printed when its files are read
            except ValueError as exc:
                self._show_refused("rate_limited", f"{address}: {exc}", addr)
        elif self._show_prop_fov(address, args, addr):
            pass  # a camera's fov_osc (live/props.py)
        else:
            self._show_refused("unknown_address", f"unknown address {address!r}"[:200],
                               addr)  # fmt: skip

    def _show_prop_fov(self, address: str, args: list[Any], addr: Any) -> bool:
        try:
            return self.props.set_fov(address, args)
        except ValueError as exc:
            self._show_refused("bad_argument", str(exc)[:200], addr)
            return True


def recording_path(folder: str, path: str) -> str:
    """The absolute path a ``record start`` may write: ``path`` relative to the
    recordings folder, or absolute inside it; never with a ``..`` component, never
    through a symbolic link out of it. Creates the folder when missing.

    Raises:
        ValueError: the path is outside the folder (the message names both).
    """
    if ".." in Path(path).parts:
        raise ValueError(f"a recording path may not contain '..'; got {path!r}")
    root = Path(folder).resolve()
    candidate = Path(path) if os.path.isabs(path) else root / path
    resolved = Path(os.path.realpath(candidate))
    if not resolved.is_relative_to(root):
        raise ValueError(
            f"recordings go under the folder {str(root)!r} (record.folder); "
            f"got {path!r}"
        )
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"cannot create {str(root)!r}: {exc.strerror}") from None
    return str(resolved)


#: Messages a show-control datagram may carry: a show-control command is one message
#: (VMC senders bundle ``Calib/Ready`` with ``Calib/Exec``: two); 16 leaves room and
#: bounds what one datagram can make the daemon do. A datagram with more is refused
#: whole, after reading at most this many element headers (issue 30: bundles of 5,000
#: messages at 200 datagrams/s cut the VMC output to 0 when each was refused alone).
SHOW_MAX_MESSAGES = 16
#: Bundles nested in a show-control datagram at most.
SHOW_MAX_DEPTH = 4


@dataclass(slots=True)
class ShowDatagram:
    """A show-control datagram taken apart (:func:`parse_show_control`).

    Attributes:
        messages: ``[(address, args), ...]`` (addresses with the token prefix).
        malformed: elements that did not parse (a malformed bundle counts 1).
        refused: "" or the reason the whole datagram is refused unparsed
            ("too_many_messages", "nested_too_deep", "bad_token"); ``why`` its line.
    """

    messages: list[tuple[str, list[Any]]] = field(default_factory=list)
    malformed: int = 0
    refused: str = ""
    why: str = ""


def parse_show_control(packet: bytes, token_prefix: bytes = b"") -> ShowDatagram:
    """The OSC messages of a show-control datagram (a message, or a bundle flattened,
    nested at most :data:`SHOW_MAX_DEPTH` deep), refused whole and unparsed when it
    holds more than :data:`SHOW_MAX_MESSAGES` messages or, with ``token_prefix``
    (``b"/TOKEN"``), when any message's address does not start with it (compared in
    constant time on the raw bytes: the token is never parsed out of a refused
    datagram). Refusing costs at most :data:`SHOW_MAX_MESSAGES` element headers.

    Never raises: a malformed message is skipped and counted; a malformed bundle
    (bad element sizes) counts 1 and none of its messages is used.
    """
    raw: list[bytes] = []
    out = ShowDatagram()
    try:
        out.malformed = _osc_messages(packet, raw)
    except _Refused as exc:
        out.refused, out.why = exc.reason, exc.why
        return out
    if token_prefix:
        # constant time on the token; the rest of the address is public
        n = len(token_prefix)
        for message in raw:
            if not (hmac.compare_digest(message[:n], token_prefix)
                    and message[n : n + 1] == b"/"):  # fmt: skip
                out.refused, out.why = "bad_token", "no or wrong token prefix"
                return out
    for message in raw:
        try:
            address, _tags, args = parse_message(message)
        except DecodeError:
            out.malformed += 1
            continue
        out.messages.append((address, args))
    return out


class _Refused(Exception):
    def __init__(self, reason: str, why: str) -> None:
        super().__init__(why)
        self.reason, self.why = reason, why


def _osc_messages(packet: bytes, out: list[bytes], depth: int = 0) -> int:
    """Append the messages of an OSC packet to ``out`` (a bundle flattened; a bundle
    that does not parse whole contributes nothing); returns the number of malformed
    bundles met.

    Raises:
        _Refused: past :data:`SHOW_MAX_MESSAGES` messages or :data:`SHOW_MAX_DEPTH`
            nested bundles (the whole datagram is refused).
    """
    if not packet.startswith(b"#bundle\0"):
        if len(out) >= SHOW_MAX_MESSAGES:
            raise _Refused(
                "too_many_messages", f"more than {SHOW_MAX_MESSAGES} messages"
            )
        out.append(packet)
        return 0
    if depth >= SHOW_MAX_DEPTH:
        raise _Refused("nested_too_deep", f"bundles nested past {SHOW_MAX_DEPTH}")
    mark = len(out)
    bad = 0
    try:
        for element in iter_bundle_elements(packet):
            bad += _osc_messages(bytes(element), out, depth + 1)
    except DecodeError:
        del out[mark:]
        return bad + 1
    return bad


#: The ``cmd`` of a request, read from its first bytes for a stall's name only
#: (``stalls.py``): never trusted, the request is parsed as JSON for its answer.
_CMD = re.compile(rb'"cmd"\s*:\s*"([a-z-]{1,16})"')
_COMMANDS = ("status", "calibrate", "reload", "record", "face-capture")
#: ``_control``'s reply to a reload from the socket: none yet (``Control.tick``
#: answers it once the worker has read the files).
_LATER: dict[str, Any] = {"ok": True, "later": True}


def _phase(head: bytes) -> str:
    """``control.<cmd>`` for a known command in ``head``, else ``control.other``."""
    m = _CMD.search(head)
    cmd = m.group(1).decode() if m else ""
    return f"control.{cmd}" if cmd in _COMMANDS else "control.other"
