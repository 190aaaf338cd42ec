"""Capture systems as marker sources of the live loop: Qualisys QTM, OptiTrack Motive.

``[input] source = "qtm://HOST[:PORT]"`` or ``"natnet://HOST[:PORT][?...]"`` (or
``retargetd run --listen URL``) makes the daemon connect to the capture system itself,
beside its OSC and ZeroMQ inputs. The protocol side is ``protocols/natnet.py`` and
``protocols/qtm.py`` (PROTOCOLS.md sections 9 and 10); this module wires them into the
one loop thread, which never blocks on them:

- NatNet: non-blocking UDP sockets polled with the others; :meth:`NatNetClient.tick`
  on every wake-up and poll timeout sends the connect / model-definition requests and
  the keep-alive, and notices a silent server.
- QTM: ``qtm-rt`` runs on its own thread (connect, parameters, reconnect with
  backoff) and hands every RT packet over a socketpair whose read end is polled here.

Every packet is recorded as it came (envelope form ``natnet`` = 5 / ``qtm`` = 6) when a
recording runs, then fed to the input's decoder; accepted frames go through the
loop's usual book-keeping (``_accept``: solved at once or latest wins). The last
control packets (NatNet server info and model definitions, QTM's parameters XML) are
kept and written first into a recording started mid-stream, so the file decodes on
its own.

Faults, each a line on the daemon's output and a counter in ``status["capture"]``:
a server that vanishes or stops sending (no accepted frame for
:data:`SOURCE_SILENT_NS`) turns the source ``lost``: the last good pose is sent again
every :data:`HOLD_RESEND_NS`, flagged ``held`` and ``source_lost``, and VMC hears
``/VMC/Ext/OK 1 3 0 0`` (calibrated, tracking lost) as often, until frames come back;
an unknown protocol version, labels the rig does not know and a flood (frames drained
in one wake-up) are said and counted; reconnecting is the client's job
(NatNet: a request per second; QTM: the client thread's backoff), never the loop's.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zmq

from retargetd.daemon.body.calibration import match_markers
from retargetd.daemon.live.inputs import Accept
from retargetd.daemon.live.performer import Performer
from retargetd.daemon.live.performers import Performers
from retargetd.daemon.live.ratelog import OncePer
from retargetd.daemon.live.shared import Shared
from retargetd.protocols import natnet, natnet_client, qtm
from retargetd.protocols.marker_input import ACCEPTED, RESTART, RESTART_GAP_NS
from retargetd.replay import recording as rf

logger = logging.getLogger(__name__)

#: No accepted frame for this long: the source is lost. It is the frame sequencer's
#: restart gap (1 s): after it a frame number that goes back is taken as a restarted
#: source, so the stream is treated as broken off at that point anyway.
SOURCE_SILENT_NS = RESTART_GAP_NS
#: While lost, the last good pose is sent again this often: 10 Hz, the loop's default
#: poll timeout (``loop.poll_timeout_ms`` = 100), so a subscriber that joins late or
#: watches for liveness sees the flagged pose within one poll period.
HOLD_RESEND_NS = 100_000_000
#: Frames drained in one wake-up beyond which the capture input is said to flood:
#: 10 frames is ~40 ms of Motive's and QTM's common 240 Hz arriving at once, far past
#: the jitter of a healthy stream (one or two frames arriving together).
FLOOD_FRAMES = 10
#: ... or when a window of this many frames arrived in less than FLOOD_RATIO of the
#: time their source timestamps span: frames faster than twice the capture rate. Over
#: 50 frames (~0.2 s at 240 Hz) network jitter averages out; a healthy stream arrives
#: at its capture rate (ratio ~1).
FLOOD_WINDOW = 50
FLOOD_RATIO = 0.5

SCHEMES = ("natnet", "qtm")


def parse_source(url: str) -> tuple[str, Any]:
    """``("natnet", NatNetOptions)`` or ``("qtm", (host, port))`` for a source URL.

    Raises:
        ValueError: naming what is wrong.
    """
    scheme = url.split("://", 1)[0] if "://" in url else ""
    if scheme == "natnet":
        return "natnet", natnet_client.parse_natnet_url(url)
    if scheme == "qtm":
        return "qtm", qtm.parse_qtm_url(url)
    raise ValueError(
        f"expected qtm://HOST[:PORT] or natnet://HOST[:PORT][?...]; got {url!r}"
    )


@dataclass(slots=True, eq=False)
class CaptureInput:
    """One capture system's input and its book-keeping (loop thread only).

    Attributes:
        system: ``"natnet"`` or ``"qtm"``.
        url: what was configured.
        form: the recording envelope form (``rf.FORM_NATNET`` / ``rf.FORM_QTM``).
        inp: the :class:`NatNetInput` / :class:`QtmInput`.
        client: the NatNet client (None for QTM).
        source: the QTM source (None for NatNet).
        readers: (fd, read) pairs: poll ``fd``, ``read()`` until None.
        counts: ``frames`` accepted, ``control`` packets, ``lost`` (times the source
            fell silent), ``held_poses`` (last good poses sent again on the pose
            stream), ``held_vmc`` (VMC "calibrated, tracking lost" states sent),
            ``unknown_label_sets`` (label sets with labels the rig does not know),
            ``floods`` (wake-ups that drained more than :data:`FLOOD_FRAMES` frames).
    """

    system: str
    url: str
    form: int
    inp: Any
    client: natnet_client.NatNetClient | None = None
    source: qtm.QtmSource | None = None
    readers: list[tuple[int, Callable[[], memoryview | None]]] = field(
        default_factory=list
    )
    counts: dict[str, int] = field(
        default_factory=lambda: dict.fromkeys(
            (
                "frames",
                "control",
                "lost",
                "held_poses",
                "held_vmc",
                "unknown_label_sets",
                "floods",
            ),
            0,
        )
    )
    last_frame_ns: int = 0
    lost: bool = False
    lost_since_ns: int = 0
    next_hold_ns: int = 0
    last_stream: Any = None  # the stream of the last accepted frame
    labels_seen: Any = None  # the label set last checked against the rig
    unknown_labels: tuple[str, ...] = ()
    control_packets: dict[int, bytes] = field(default_factory=dict)
    recorder_seen: Any = None
    window_n: int = 0  # frames in the flood window so far
    window_t_ns: int = 0  # receive time and source time at the window's start
    window_src_s: float = 0.0

    @property
    def where(self) -> str:
        if self.client is not None:
            host, port = self.client.server
            return f"{host}:{port}"
        assert self.source is not None
        return f"{self.source.host}:{self.source.port}"

    def state(self) -> str:
        """``connecting``, ``waiting`` (connected, nothing streamed yet: NatNet model
        definitions, QTM no measurement), ``streaming`` or ``lost``."""
        if self.lost:
            return "lost"
        if self.client is not None:
            session = self.client.session
            if session.info is None:
                return "connecting"
            if session.decoder is None or not self.last_frame_ns:
                return "waiting"
            return "streaming"
        assert self.source is not None
        st = self.source.state
        if st == "streaming" and not self.last_frame_ns:
            return "waiting"
        return "waiting" if st == "idle" else st

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
        if self.source is not None:
            self.source.close()


def open_capture(url: str, out: Callable[[str], None]) -> CaptureInput:
    """Build (and for QTM start) the input for ``url``; never blocks.

    Raises:
        ValueError: a bad URL. OSError: a socket cannot be bound.
    """
    system, opts = parse_source(url)
    if system == "natnet":
        client = opts.client(out)
        cap = CaptureInput(
            "natnet", url, rf.FORM_NATNET,
            natnet_client.NatNetInput(client, opts.up_axis),
            client=client,
        )  # fmt: skip
        for sock in client.fds():
            cap.readers.append((sock.fileno(), _natnet_reader(client, sock)))
        return cap
    host, port = opts
    source = qtm.QtmSource(host, port, out=out)
    cap = CaptureInput(
        "qtm", url, rf.FORM_QTM, qtm.QtmInput(source, out), source=source
    )
    cap.readers.append((source.fileno(), source.read))
    source.start()
    return cap


def _natnet_reader(
    client: natnet_client.NatNetClient, sock: Any
) -> Callable[[], memoryview | None]:
    return lambda: client.read(sock)


class CaptureSource:
    """The capture-system input of the loop ([input] source: QTM or NatNet), one
    part: open, drain, tick, hold, status.

    Args:
        shared: the loop's side (config, counters, outputs, recording, out).
        performers: whose rigs the labels are checked against and whose last poses
            are sent again, held, while the source is lost.
        poller: the loop's poller (the capture's descriptors are polled).
        endpoints: what is listening where.
        warn: the loop's once-per-interval gate for warning lines.
        accept: the loop's hand-off of a decoded frame (``inputs.Accept``).
        stale: called when an accepted frame is superseded before it was solved.
    """

    def __init__(
        self,
        shared: Shared,
        performers: Performers,
        poller: zmq.Poller,
        endpoints: dict[str, str],
        warn: OncePer,
        accept: Accept,
        stale: Callable[[], None],
    ) -> None:
        self.shared = shared
        self.out = shared.out
        self.recording = shared.recording
        self.performers = performers
        self._poller = poller
        self.endpoints = endpoints
        self._warn = warn
        self._accept = accept
        self._stale = stale
        self._capture: CaptureInput | None = None
        self.on = False  # a capture system is connected (or being connected)

    @property
    def stream(self) -> Any:
        """The capture input's stream (``on`` only)."""
        assert self._capture is not None
        return self._capture.inp.stream

    def open(self) -> None:
        """Start connecting to ``[input] source`` (nothing when it is unset)."""
        url = self.shared.config.input.source
        if not url:
            return
        cap = open_capture(url, self.out)
        self._capture = cap
        self.on = True
        for fd, _ in cap.readers:
            self._poller.register(fd, zmq.POLLIN)
        name = "Motive (NatNet)" if cap.system == "natnet" else "QTM (qtm-rt)"
        self.endpoints[f"{cap.system} markers"] = url
        self.out(
            f"connecting to {url}: {cap.system} markers from {name}; retargetd "
            "connects and reconnects by itself, the loop never waits for it"
        )

    def close(self) -> None:
        """Disconnect (idempotent)."""
        cap = self._capture
        if cap is None:
            return
        for fd, _ in cap.readers:
            with contextlib.suppress(KeyError):
                self._poller.unregister(fd)
        cap.close()
        self._capture = None
        self.on = False

    def drain(self, events: list[tuple[Any, int]], every: bool) -> int:
        """Read, record and decode every waiting packet; the receive time of the
        newest accepted frame left unsolved (latest wins), else 0."""
        cap = self._capture
        assert cap is not None
        rec = self.recording.packets
        if rec is not None and rec is not cap.recorder_seen:
            # A recording started mid-stream: the control packets first.
            cap.recorder_seen = rec
            t0 = time.monotonic_ns()
            for _, kept in sorted(cap.control_packets.items()):
                rec.record_packet(cap.system, cap.form, t0, kept)
        inp = cap.inp
        newest = 0
        superseded = 0
        frames = 0
        for fd, read in cap.readers:
            ready = False
            for sock, _flags in events:  # a scan of the poll result, no allocation
                if sock == fd:
                    ready = True
                    break
            if not ready:
                continue
            while (pkt := read()) is not None:
                t_ns = time.monotonic_ns()
                if rec is not None:
                    rec.record_packet(cap.system, cap.form, t_ns, pkt)
                code = inp.feed(pkt, t_ns)
                if code < 0:  # a control message: kept for a later recording
                    cap.counts["control"] += 1
                    self._keep_control(cap, pkt)
                    continue
                stream = inp.stream
                if stream.label_set is not cap.labels_seen:
                    self._check_capture_labels(cap, stream)
                if code in (ACCEPTED, RESTART):
                    frames += 1
                    cap.window_n += 1
                    if cap.window_n >= FLOOD_WINDOW:
                        self._check_flood_window(cap, stream, t_ns)
                    cap.counts["frames"] += 1
                    cap.last_frame_ns = t_ns
                    cap.last_stream = stream
                    if cap.lost:
                        self._capture_back(cap, t_ns)
                got = self._accept(stream, code, t_ns, every)
                if got:
                    if newest:  # a newer frame supersedes the unsolved one: stale
                        self._stale()
                        superseded += 1
                    newest = got
        if frames > FLOOD_FRAMES:
            self._flood(
                cap,
                f"{frames} frames in one wake-up (caught up for a frame period, "
                f"then the latest wins: {superseded} stale here)",
            )
        return newest

    def _check_flood_window(self, cap: CaptureInput, stream: Any, t_ns: int) -> None:
        """Every FLOOD_WINDOW frames: did they come faster than the source's clock?"""
        src_s = stream.current.frame.source_time_s
        if cap.window_t_ns:
            src_dt = src_s - cap.window_src_s
            rx_dt = (t_ns - cap.window_t_ns) * 1e-9
            if src_dt > 0 and rx_dt < src_dt * FLOOD_RATIO:
                self._flood(
                    cap,
                    f"{cap.window_n} frames spanning {src_dt:.3f} s of its clock "
                    f"arrived in {rx_dt:.3f} s",
                )
        cap.window_n = 0
        cap.window_t_ns = t_ns
        cap.window_src_s = src_s

    def _flood(self, cap: CaptureInput, what: str) -> None:
        cap.counts["floods"] += 1
        self._say_limited(
            f"{cap.system}.flood",
            time.monotonic_ns(),
            f"{cap.system}: {cap.where} floods: {what}; counted (status capture)",
        )

    @staticmethod
    def _keep_control(cap: CaptureInput, pkt: memoryview) -> None:
        if cap.system == "natnet":
            if (
                len(pkt) >= 2
                and pkt[1] == 0
                and pkt[0]
                in (
                    natnet.NAT_SERVERINFO,
                    natnet.NAT_MODELDEF,
                )
            ):
                cap.control_packets[pkt[0]] = bytes(pkt)
        elif qtm.packet_type(pkt) == qtm.PACKET_XML:
            cap.control_packets[qtm.PACKET_XML] = bytes(pkt)

    def _check_capture_labels(self, cap: CaptureInput, stream: Any) -> None:
        """A new label set: its pipelines' builds start (off the loop), and say
        which labels the rig does not know (not hot)."""
        cap.labels_seen = stream.label_set
        if stream.label_set is None:
            return
        self.performers.prepare(stream, stream.label_set)  # pipelines built now
        labels = stream.label_set.labels
        known: set[int] = set()  # the labels some performer's rig matches
        for p in self.performers.all:
            mine = [i for i, lb in enumerate(labels) if lb.startswith(p.prefix)]
            cols = match_markers(p.rig, [labels[i][len(p.prefix) :] for i in mine])
            known.update(mine[c] for c in cols if c >= 0)
        unknown = tuple(lb for i, lb in enumerate(labels) if i not in known)
        if unknown and unknown != cap.unknown_labels:
            cap.counts["unknown_label_sets"] += 1
            shown = ", ".join(unknown[:8]) + (" ..." if len(unknown) > 8 else "")
            self.out(
                f"{cap.system}: {len(unknown)} of {len(stream.label_set.labels)} "
                f"labels are not markers of rig "
                f"{', '.join(sorted({p.rig.name for p in self.performers.all}))} "
                f"(ignored): {shown}"
            )
        cap.unknown_labels = unknown

    def _capture_back(self, cap: CaptureInput, t_ns: int) -> None:
        cap.lost = False
        self.out(
            f"{cap.system}: frames from {cap.where} again after "
            f"{(t_ns - cap.lost_since_ns) * 1e-9:.1f} s; streaming"
        )

    def tick(self) -> None:
        """Every wake-up and poll timeout: the NatNet client's requests, the lost
        check, and the held pose while lost. Never blocks."""
        cap = self._capture
        assert cap is not None
        if cap.client is not None:
            cap.client.tick()
        now = time.monotonic_ns()
        if (
            not cap.lost
            and cap.last_frame_ns
            and (now - cap.last_frame_ns >= SOURCE_SILENT_NS)
        ):
            cap.lost = True
            cap.lost_since_ns = cap.last_frame_ns
            cap.counts["lost"] += 1
            cap.next_hold_ns = now
            self.out(
                f"{cap.system}: no frame from {cap.where} for "
                f"{SOURCE_SILENT_NS * 1e-9:g} s ({cap.state()}); sending the last "
                "good pose flagged held + source_lost until frames come back"
            )
        if cap.lost and now >= cap.next_hold_ns:
            cap.next_hold_ns = now + HOLD_RESEND_NS
            for perf in self.performers.all:  # each performer's last pose
                self._resend_held(cap, now, perf, perf.key_of(cap.last_stream))

    def _resend_held(
        self, cap: CaptureInput, now_ns: int, perf: Performer, key: int
    ) -> None:
        """``perf``'s last pose on the pipeline ``key`` sent again, flagged held and
        source_lost (``BodyPath.resend_held``); counted."""
        vmc_sent, pose_sent = perf.path.resend_held(key, now_ns)
        cap.counts["held_vmc"] += vmc_sent
        cap.counts["held_poses"] += pose_sent

    def status(self) -> dict[str, Any] | None:
        """``status["capture"]``: the source's state, counters and drops."""
        cap = self._capture
        if cap is None:
            return None
        inp = cap.inp
        stream = inp.stream
        doc: dict[str, Any] = {
            "system": cap.system,
            "url": cap.url,
            "server": cap.where,
            "state": cap.state(),
            "counts": dict(cap.counts),
            "drops": stream.counters.as_dict() if stream is not None else {},
            "labels": len(stream.label_set.labels)
            if stream is not None and stream.label_set is not None
            else 0,
            "unknown_labels": list(cap.unknown_labels),
        }
        if cap.client is not None:
            session = cap.client.session
            info = session.info
            doc["client"] = {
                **session.counts,
                "timeouts": cap.client.timeouts,
                "natnet_version": str(info.natnet_version) if info else None,
                "last_error": session.last_error.reason if session.last_error else None,
            }
            dec = session.decoder
            doc["timecode"] = dec.timecode if dec is not None else None
        if cap.source is not None:
            doc["client"] = dict(cap.source.counts)
            params = inp.params
            doc["up_axis"] = params.up_axis if params is not None else None
        return doc

    def _say_limited(self, key: str, t_ns: int, line: str) -> None:
        """``out(line)`` at most once per 10 s for ``key`` (counters hold the rest)."""
        if self._warn.due(key, t_ns):
            self.out(line)


def capture_stats(doc: dict[str, Any] | None) -> str:
    """The stats line's capture part (" | natnet streaming ...") or ""."""
    if doc is None:
        return ""
    c = doc["counts"]
    dropped = sum(v for k, v in doc["drops"].items() if k != "accepted")
    return (
        f" | {doc['system']} {doc['state']} frames {c['frames']} dropped {dropped}"
        f" lost {c['lost']} held {c['held_poses']}"
    )
