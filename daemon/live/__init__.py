"""``retargetd.daemon.live``: the live daemon.

How the live daemon is put together (README "How the live daemon is put together" has
the table): ``loop.Daemon`` composes parts, each owning its state, passed in rather
than mixed in (``tests/test_layout.py`` checks that no class here inherits from a class
of another of these modules):

- inputs: ``inputs.Inputs`` (OSC, ZeroMQ: sockets, buffers, a ``MarkerStream`` each)
  and ``sources.CaptureSource`` (QTM, NatNet); each decodes and sequences into its
  stream and hands accepted frames to the loop;
- performers: ``performers.Performers`` over each ``performer.Performer``, whose
  frame path (``send.BodyPath`` or ``face_only.FacePath``) solves, post-processes,
  retargets, encodes and sends its frame (its live validator:
  ``validation.Validation``), and whose ``calibrate.LiveCalibration``
  collects live calibrations and face captures;
- outputs: ``outputs.Outputs`` (the pose stream, each performer's ``VmcOut``) and
  the recording (``recording.LiveRecording``);
- control: ``control.Control`` (``ctl`` and show control: commands become calls on
  the parts); status: ``status.Health`` (reads every part's counters).

What the loop lends every performer's parts is ``shared.Shared``. A frame's path is
``Daemon._service``: receive (``inputs.drain_*``) -> accept (``Daemon._accept``) ->
solve (``performers.solve`` -> ``path.process``) -> send (``outputs``). A new input is
a part like ``Inputs`` drained in ``_service``; a new output is a call on ``Outputs``
from ``BodyPath._emit``. Config, stats, live recording and the live face stage live
here too.
"""
