"""The one compiled call per packet (``MarkerStream.feed_packed``: decode, sequencing
and counter in ``kernels.feed_frame``) against :meth:`MarkerStream.feed` with the
Python decoders, and the compiled sequencer against the rules it replaced (kept here,
in Python, as the reference)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from retargetd.protocols import kernels, osc_in, zmq_wire
from retargetd.protocols import marker_input as mi

MS = 1_000_000


class _ReferenceSequencer:
    """``FrameSequencer.check`` as it was in Python before the kernel (2882d7f)."""

    def __init__(self, restart_gap_ns: int, max_rate_hz: float) -> None:
        self.restart_gap_ns = restart_gap_ns
        self._rate_per_ns = max_rate_hz * 1e-9
        self._slack_frames = mi.JUMP_SLACK_NS * self._rate_per_ns + 1.0
        self.last_frame, self.last_label_set_id, self.last_t_ns = -1, 0, 0
        self._cand_n, self._cand_frame, self._cand_t_ns = 0, -1, 0
        self._restart_next = False

    def _plausible(self, advance: int, elapsed_ns: int) -> bool:
        return advance <= elapsed_ns * self._rate_per_ns + self._slack_frames

    def check(self, frame_id: int, label_set_id: int, t_ns: int) -> int:
        code = mi.ACCEPTED
        last = self.last_frame
        if frame_id >= 0 and self._restart_next:
            code = mi.RESTART
        elif frame_id >= 0 and last >= 0:
            new_set = label_set_id != self.last_label_set_id
            if frame_id > last:
                if not self._plausible(frame_id - last, t_ns - self.last_t_ns):
                    if not new_set:
                        return self._candidate(frame_id, t_ns, mi.IMPLAUSIBLE_JUMP)
                    code = mi.RESTART
            elif new_set or t_ns - self.last_t_ns >= self.restart_gap_ns:
                code = mi.RESTART
            elif frame_id == last:
                return mi.DUPLICATE
            else:
                return self._candidate(frame_id, t_ns, mi.BACKWARDS)
        if frame_id >= 0:
            self.last_frame = frame_id
            self._restart_next = False
        self._cand_n = 0
        self.last_label_set_id = label_set_id
        self.last_t_ns = t_ns
        return code

    def _candidate(self, frame_id: int, t_ns: int, code: int) -> int:
        n = self._cand_n
        if (
            n
            and frame_id > self._cand_frame
            and self._plausible(frame_id - self._cand_frame, t_ns - self._cand_t_ns)
        ):
            n += 1
        else:
            n = 1
        if n >= mi.JUMP_CONFIRM_FRAMES:
            self._cand_n = 0
            self.last_frame = frame_id
            self.last_t_ns = t_ns
            return mi.RESTART
        self._cand_n, self._cand_frame, self._cand_t_ns = n, frame_id, t_ns
        return code


def test_kernel_outcomes_are_the_reason_indices() -> None:
    assert (kernels.S_ACCEPTED, kernels.S_RESTART, kernels.S_BACKWARDS,
            kernels.S_DUPLICATE, kernels.S_IMPLAUSIBLE_JUMP) == (
        mi.ACCEPTED, mi.RESTART, mi.BACKWARDS, mi.DUPLICATE, mi.IMPLAUSIBLE_JUMP,
    )  # fmt: skip


@given(
    events=st.lists(
        st.tuples(
            st.integers(-1, 3) | st.integers(-1, 2**62),  # frame step or number
            st.booleans(),  # a step from the last (True) or an absolute number
            st.integers(0, 2),  # label-set id
            st.integers(0, 2_000) | st.just(1_500_000_000),  # ms since the last
            st.booleans(),  # restart_next before it
        ),
        min_size=1,
        max_size=80,
    ),
    rate=st.sampled_from([100.0, 240.0, mi.MAX_RATE_HZ]),
)
def test_compiled_sequencer_equals_the_python_rules(
    events: list[tuple[int, bool, int, int, bool]], rate: float
) -> None:
    """Random frame numbers (steps, strays, restarts, new label sets, gaps): the
    compiled check gives the outcome and the state the Python rules gave."""
    seq = mi.FrameSequencer(max_rate_hz=rate)
    ref = _ReferenceSequencer(mi.RESTART_GAP_NS, rate)
    frame, t_ns = 0, 0
    for value, step, set_id, gap_ms, restart in events:
        t_ns += gap_ms * MS
        # a step past int64 is a number no packet can carry (the wire's int64)
        frame = min(max(frame + value, -1), 2**63 - 1) if step else value
        if restart:
            seq.restart_next()
            ref._restart_next = True
        assert seq.check(frame, set_id, t_ns) == ref.check(frame, set_id, t_ns)
        assert (seq.last_frame, seq.last_label_set_id, seq.last_t_ns) == (
            ref.last_frame, ref.last_label_set_id, ref.last_t_ns,
        )  # fmt: skip


def _state(stream: mi.MarkerStream) -> tuple[object, ...]:
    f = stream.current.frame
    return (
        f.frame_id, np.float64(f.source_time_s).tobytes(), f.t_ns,
        f.markers_world.tobytes(), f.valid.tobytes(), stream.current.label_set_id,
        stream.current.unknown_labels, stream.counters.counts.tobytes(),
        stream.sequencer.q.tobytes(), int(stream.implausible[0]),
    )  # fmt: skip


@pytest.mark.parametrize("form", ["osc", "zmq"])
def test_feed_packed_equals_feed(form: str) -> None:
    """The same packets through both: in order, duplicated, backwards, far ahead
    (three in a row: adopted), after a gap, mutated, with a marker too far, an
    unknown label set, and a new label set announced; each outcome, the current
    frame, the counters and the sequencer state agree after every packet."""
    rng = np.random.default_rng(11)
    names = tuple(f"M{i}" for i in range(5))
    a = mi.MarkerStream(None, "+Y", "mm")
    b = mi.MarkerStream(None, "+Y", "mm")
    head_a = np.zeros(512, dtype=np.uint8)
    pay_a = np.zeros(512, dtype=np.uint8)
    head_b = np.zeros(512, dtype=np.uint8)
    pay_b = np.zeros(512, dtype=np.uint8)
    for s in (a, b):
        s.set_labels(mi.LabelSet(3, names), 0)
    frames = [0, 1, 2, 2, 1, 3, 10_000, 10_001, 10_002, 10_003, 4, 5, 5]
    frames += list(range(10_004, 10_040))
    t_ns, seen = 10 * MS, set()
    for k, fid in enumerate(frames + [10_040 + i for i in range(40)]):
        t_ns += 4 * MS if k != 20 else 1_200 * MS  # one gap past the restart gap
        pos = rng.normal(scale=500.0, size=(5, 3))
        pos[rng.integers(0, 5)] = np.nan
        if k == 7:
            pos[0] = 5e6  # 5 km: occluded, counted implausible
        set_id = 3 if k != 30 else 4  # an unknown label set
        if k == 60:  # a new label set, same size (the spare re-targeted)
            for s in (a, b):
                s.set_labels(mi.LabelSet(4, names[::-1]), t_ns)
        if k >= 60:
            set_id = 4
        if form == "osc":
            head = osc_in.encode_compact_frame(fid, k / 240.0, set_id, pos)
            pay = b""
        else:
            head, pay = zmq_wire.encode_zmq_frame(fid, k / 240.0, set_id, pos)
        if k % 9 == 8:  # a byte changed: refused somewhere, or not
            m = bytearray(head)
            m[int(rng.integers(0, len(m)))] = int(rng.integers(0, 256))
            head = bytes(m)
        head_a[: len(head)] = np.frombuffer(head, np.uint8)
        head_b[: len(head)] = head_a[: len(head)]
        pay_a[: len(pay)] = np.frombuffer(pay, np.uint8)
        pay_b[: len(pay)] = pay_a[: len(pay)]
        if form == "osc":
            want = a.feed(osc_in.decode_compact_into, head_a, len(head), t_ns=t_ns)
            got = b.feed_packed(kernels.FORM_OSC_COMPACT, head_b, len(head), head_b,
                                0, t_ns)  # fmt: skip
            if got < 0:
                got = b.feed(osc_in.decode_compact_into, head_b, len(head), t_ns=t_ns)
        else:
            want = a.feed(zmq_wire.decode_zmq_into, head_a, len(head), pay_a,
                          len(pay), t_ns=t_ns)  # fmt: skip
            got = b.feed_packed(kernels.FORM_ZMQ, head_b, len(head), pay_b,
                                len(pay), t_ns)  # fmt: skip
            if got < 0:
                got = b.feed(zmq_wire.decode_zmq_into, head_b, len(head), pay_b,
                             len(pay), t_ns=t_ns)  # fmt: skip
        assert got == want, k
        assert _state(b) == _state(a), k
        seen.add(mi.REASONS[want])
    # What the sequence was built to meet, met.
    assert {"accepted", "restart", "duplicate", "backwards", "implausible_jump",
            "unknown_label_set"} <= seen, seen  # fmt: skip
    assert int(a.implausible[0]) >= 1
    assert a.counters.dropped() > 0


def test_feed_packed_without_a_label_set_counts_it() -> None:
    s = mi.MarkerStream(None)
    wire = np.zeros(64, dtype=np.uint8)
    assert (
        s.feed_packed(kernels.FORM_ZMQ, wire, 32, wire, 0, 1)
        == (mi.REASON_INDEX["unknown_label_set"])
    )
    assert s.counters["unknown_label_set"] == 1
