"""``retargetd ctl [--endpoint E] status [--json] |
calibrate [--count N] [--rom [--seconds S]] [--performer NAME | --prop NAME] [--no-wait]
[--wait-s S] | reload |
record start FILE.mcap [--no-poses] [--force] | record stop |
face-capture NAME [--count N] [--performer NAME]``.

Talks to a running daemon over its local control socket (ZeroMQ REQ/REP, JSON
requests ``{"cmd": "status"}``, ``{"cmd": "calibrate", "count": N}`` (with
``--rom``: ``"rom_s": S``),
``{"cmd": "reload"}``, ``{"cmd": "record", "action": "start", "path": FILE,
"poses": true}``, ``{"cmd": "record", "action": "stop"}``,
``{"cmd": "face-capture", "name": NAME, "count": N}``; calibrate and face-capture
take ``"performer": NAME``). With several performers (``[[performer]]`` in the
daemon's config) ``calibrate`` and ``face-capture`` act for the one ``--performer``
names (it may be left out when there is one); an unknown name is refused, the reply
naming the daemon's performers; ``status`` lists every performer.
``calibrate`` prints the request's acceptance, then waits (at most ``--wait-s``,
polling ``status``) for that calibration's outcome and prints its line: exit 0 when
it calibrated, 1 when the daemon refused it (a moving, giant, mirrored or degenerate
base pose: the reason is the line), it calibrated but could not save the file (the
daemon uses it; the old file is kept whole), it expired or the wait ran out;
``--no-wait`` returns after the acceptance. ``--prop NAME`` calibrates a
``[[prop]]`` instead (``{"cmd": "calibrate", "prop": NAME}``): its layout from the
next N frames while it lies still, saved and used at once (README "Props and a
virtual camera"). ``--rom``: after the base pose the daemon
collects ``--seconds`` (default 24) of range of motion and places the rig's functional
joints from it (``calibrate --rom`` offline); the wait grows by those seconds.
``record start`` makes the daemon record every marker packet it receives, its pose
stream (unless ``--no-poses``) and control events to a new MCAP file, in the format of
``retargetd record`` (``retargetd replay`` plays it back); FILE must not exist yet and
lies under the daemon's recordings folder (``record.folder``, default ``recordings/``
in the daemon's working directory): a relative FILE is taken inside that folder, an
absolute one must be in it, and ``..`` is refused. ``record stop`` returns at
once; the daemon finishes the file in the background (``status --json``: ``record``).
``face-capture NAME`` (``neutral`` first, then any expression of the face config)
averages the next N frames into the face training set, which the daemon starts
solving with at once and saves (``[face]`` in the daemon config; ``status --json``:
``face``).
With the control socket under CURVE (``control.secret_key`` in the daemon's config),
``--key NAME.key_secret`` is this client's key pair (``retargetd keys NAME``) and
``--server-key`` the daemon's public key (default: ``daemon.key`` beside ``--key``);
a client whose public key the daemon does not list gets no answer.
Exit 0 on success, 1 when the daemon refuses or does not answer within
``--timeout-ms``, 2 for usage errors.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

from retargetd.daemon.live.config import ControlConfig


def add_parser(subparsers: Any) -> None:
    """Register ``ctl``."""
    parser = subparsers.add_parser(
        "ctl",
        help="control a running daemon: status, calibrate, reload, record, "
        "face-capture",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--endpoint",
        default=ControlConfig().endpoint,
        help="the daemon's control endpoint (default %(default)s)",
    )
    parser.add_argument(
        "--timeout-ms", type=int, default=2000,
        help="how long to wait for the daemon's answer (default %(default)s ms)",
    )  # fmt: skip
    parser.add_argument(
        "--key",
        metavar="FILE.key_secret",
        help="CURVE: this client's secret key file (retargetd keys)",
    )
    parser.add_argument(
        "--server-key",
        metavar="FILE.key",
        help="CURVE: the daemon's public key file (default: daemon.key beside --key)",
    )
    sub = parser.add_subparsers(dest="ctl_command", metavar="ACTION", required=True)
    status = sub.add_parser("status", help="fps, drops, latency, occluded markers")
    status.add_argument("--json", action="store_true", help="the full JSON document")
    cal = sub.add_parser("calibrate", help="calibrate live on the next N frames")
    cal.add_argument(
        "--count", type=int, default=None, metavar="N",
        help="base-pose frames to average (default: the performer's calibrate_frames)",
    )  # fmt: skip
    cal.add_argument(
        "--performer",
        metavar="NAME",
        help="the performer to calibrate (several performers: [[performer]] name)",
    )
    cal.add_argument(
        "--prop",
        metavar="NAME",
        help="calibrate the [[prop]] NAME instead: its layout from the next N frames "
        "(default its calibrate_frames) while it lies still",
    )
    cal.add_argument(
        "--rom",
        action="store_true",
        help="after the base pose, a range of motion for the rig's functional joints "
        "(hip centres, knee axes: RIGS.md)",
    )
    cal.add_argument(
        "--seconds",
        type=float,
        default=None,
        metavar="S",
        help="with --rom: seconds of range of motion (default 24)",
    )
    cal.add_argument(
        "--no-wait",
        action="store_true",
        help="return once the request is accepted, without waiting for the outcome",
    )
    cal.add_argument(
        "--wait-s",
        type=float,
        default=30.0,
        metavar="S",
        help="wait at most S seconds for the outcome (default %(default)s)",
    )
    sub.add_parser("reload", help="reload the rig and calibration files")
    rec = sub.add_parser("record", help="record inside the daemon: start FILE | stop")
    rec_sub = rec.add_subparsers(dest="record_action", metavar="ACTION", required=True)
    start = rec_sub.add_parser("start", help="start recording to a new MCAP file")
    start.add_argument(
        "file",
        metavar="FILE.mcap",
        help="the recording, in the daemon's [record] folder",
    )
    start.add_argument(
        "--no-poses", action="store_true", help="record markers and events only"
    )
    start.add_argument(
        "--force", action="store_true", help="replace FILE when it exists"
    )
    rec_sub.add_parser(
        "stop",
        help="stop recording (returns at once; the file is finished in the background)",
    )
    face = sub.add_parser(
        "face-capture",
        help="capture a face training pose live (neutral first, then expressions)",
    )
    face.add_argument("name", metavar="NAME", help="neutral or an expression name")
    face.add_argument(
        "--count", type=int, default=None, metavar="N",
        help="frames of the expression to average (default: the face config's)",
    )  # fmt: skip
    face.add_argument("--performer", metavar="NAME", help="whose face")
    parser.set_defaults(run=run)


def request(
    endpoint: str,
    req: dict[str, Any],
    timeout_ms: int,
    key: str | None = None,
    server_key: str | None = None,
) -> dict[str, Any] | None:
    """Send one request; the reply, or None on timeout. With ``key`` (a secret key
    file) the socket is a CURVE client of ``server_key`` (a public key file).

    Raises:
        KeyFileError: a key file that cannot be used.
    """
    import zmq

    from retargetd.daemon.live.surface import curve_client

    # A context of its own (shut below), but for an inproc:// endpoint, which only
    # the daemon's own (the process's shared) context reaches.
    shared = endpoint.startswith("inproc://")
    ctx: Any = zmq.Context.instance() if shared else zmq.Context()
    sock = ctx.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, timeout_ms)
    sock.setsockopt(zmq.SNDTIMEO, timeout_ms)
    try:
        if key is not None:
            server = server_key or os.path.join(os.path.dirname(key), "daemon.key")
            curve_client(sock, key, server)
        sock.connect(endpoint)
        sock.send(json.dumps(req).encode())
        reply: dict[str, Any] = json.loads(sock.recv())
        return reply
    except zmq.Again:
        return None
    finally:
        sock.close()
        if not shared:
            ctx.term()


def run(args: argparse.Namespace) -> int:
    """Run ``ctl``."""
    from retargetd.daemon.errors import UsageError

    counted = args.ctl_command in ("calibrate", "face-capture")
    if counted and args.count is not None and args.count < 1:
        raise UsageError(f"--count must be >= 1; got {args.count}")
    req: dict[str, Any] = {"cmd": args.ctl_command}
    if counted and args.count is not None:
        req["count"] = args.count
    if counted and args.performer is not None:
        req["performer"] = args.performer
    if args.ctl_command == "calibrate":
        if args.seconds is not None and not args.rom:
            raise UsageError("--seconds needs --rom")
        if args.rom:
            req["rom_s"] = ROM_DEFAULT_S if args.seconds is None else args.seconds
        if args.prop is not None:
            if args.rom or args.performer is not None:
                raise UsageError("--prop calibrates a prop: no --rom or --performer")
            req["prop"] = args.prop
    if args.ctl_command == "face-capture":
        req["name"] = args.name
    if args.ctl_command == "record":
        req["action"] = args.record_action
        if args.record_action == "start":
            if not args.file.lower().endswith(".mcap"):
                raise UsageError(
                    f"record start: FILE must end in .mcap; got {args.file!r}"
                )
            req["path"] = args.file  # relative: inside the daemon's recordings folder
            req["poses"] = not args.no_poses
            if args.force:
                req["force"] = True
    from retargetd.daemon.live.surface import KeyFileError

    try:
        reply = request(args.endpoint, req, args.timeout_ms, args.key, args.server_key)
    except KeyFileError as exc:
        raise UsageError(str(exc)) from None
    if reply is None:
        sys.stderr.write(
            f"retargetd ctl: no daemon answered at {args.endpoint} "
            f"within {args.timeout_ms} ms\n"
        )
        return 1
    if not reply.get("ok"):
        sys.stderr.write(
            f"retargetd ctl: {reply.get('error') or reply.get('message')}\n"
        )
        return 1
    if args.ctl_command == "status":
        if args.json:
            sys.stdout.write(json.dumps(reply["status"], indent=1) + "\n")
        else:
            sys.stdout.write(reply["line"] + "\n")
    else:
        sys.stdout.write(reply["message"] + "\n")
    if args.ctl_command == "calibrate" and not args.no_wait:
        return _wait_calibration(args, reply)
    return 0


#: ``ctl calibrate --rom`` without ``--seconds``: two cycles of the synthetic ``rom``
#: motion (``synth.motion.ROM_PERIOD_S`` 12 s: each leg circles its hip twice), the
#: range of motion ``tests/daemon/test_functional.py`` places the hips and knees from.
ROM_DEFAULT_S = 24.0

#: Between two status polls while ``ctl calibrate`` waits: a calibration of 60 frames
#: at 120 Hz takes 0.5 s, so 50 ms adds at most a tenth to it and costs the daemon 20
#: small requests a second.
_POLL_S = 0.05


def _wait_calibration(args: argparse.Namespace, reply: dict[str, Any]) -> int:
    """Poll ``status`` until the calibration ``reply`` started has an outcome; print
    it (stdout when calibrated, else stderr) and return the exit code."""
    import time

    from retargetd.daemon.errors import UsageError

    if not args.wait_s > 0:
        raise UsageError(f"--wait-s must be > 0; got {args.wait_s}")
    wanted = reply.get("calibration_id")
    name = reply.get("performer")
    prop = reply.get("prop")
    rom_s = (ROM_DEFAULT_S if args.seconds is None else args.seconds) if args.rom else 0
    deadline = time.monotonic() + args.wait_s + rom_s
    while True:
        got = request(
            args.endpoint, {"cmd": "status"}, args.timeout_ms, args.key,
            args.server_key,
        )  # fmt: skip
        doc = _performer_doc(got, name) if prop is None else _prop_doc(got, prop)
        if (
            prop is not None and doc is not None
        ):  # a prop: calibrating, then its outcome
            doc["calibration_state"] = doc.get("calibration")
            doc["calibration_id"] = wanted = None
            if doc["calibration_state"] == "calibrating":
                doc["calibration_state"] = "pending"
        if doc is not None and doc.get("calibration_id") == wanted:
            state = doc.get("calibration_state")
            if state not in ("pending", "rom", "saving", None):
                line = str(doc.get("calibration_message", ""))
                if state == "calibrated":
                    sys.stdout.write(line + "\n")
                    return 0
                sys.stderr.write(f"retargetd ctl: {line}\n")
                return 1
        if time.monotonic() > deadline:
            sys.stderr.write(
                f"retargetd ctl: no calibration outcome within {args.wait_s:g} s "
                "(is the performer's marker stream arriving?); status shows it later\n"
            )
            return 1
        time.sleep(_POLL_S)


def _prop_doc(status: dict[str, Any] | None, name: Any) -> dict[str, Any] | None:
    """The status document of the prop ``name``."""
    if status is None or not status.get("ok"):
        return None
    for doc in status["status"].get("props") or []:
        if doc.get("name") == name:
            return dict(doc)
    return None


def _performer_doc(status: dict[str, Any] | None, name: Any) -> dict[str, Any] | None:
    """The status document of the performer ``name`` (None: the only one)."""
    if status is None or not status.get("ok"):
        return None
    performers = status["status"].get("performers") or []
    for doc in performers:
        if name is None or doc.get("name") == name:
            return dict(doc)
    return None
