"""VMC output, parsed by python-osc's generic parser and by vmcp (over osc4py3)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_packet import OscPacket

from retargetd.protocols import vmc_out

BLENDS = ("A", "I", "U", "E", "O", "Blink")
EXTRA = tuple(
    f"{side}{finger}{part}"
    for side in ("Left", "Right")
    for finger in ("Thumb", "Index", "Middle", "Ring", "Little")
    for part in ("Proximal", "Intermediate", "Distal")
)


def _frame(rng: np.random.Generator, n: int, k: int) -> tuple:
    quats = rng.normal(size=(n + 1, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    quats *= np.where(quats[:, 3:] < 0, -1.0, 1.0)  # x y z w, w >= 0: sent unchanged
    return (
        rng.normal(size=3),
        quats[0],
        rng.normal(size=(n, 3)) * 0.3,
        quats[1:],
        rng.uniform(size=k),
        12.5,
    )


def _messages(datagrams: list[memoryview]) -> list[tuple[str, list]]:
    out = []
    for dgram in datagrams:
        packet = OscPacket(bytes(dgram))
        out += [(m.message.address, m.message.params) for m in packet.messages]
    return out


@pytest.mark.parametrize(
    "bones", [vmc_out.HUMANOID_BONES, vmc_out.HUMANOID_BONES + EXTRA]
)
def test_python_osc_reads_every_message_in_order(
    rng: np.random.Generator, bones: tuple[str, ...]
) -> None:
    enc = vmc_out.VmcEncoder(bones, BLENDS)
    frame = _frame(rng, len(bones), len(BLENDS))
    datagrams = enc.encode(*frame)
    assert datagrams is enc.datagrams
    assert all(len(d) <= vmc_out.MAX_DATAGRAM for d in datagrams)
    # About 80 bytes per bone: 22 bones already need two datagrams. Packing is
    # greedy: the next datagram's first element would not have fitted.
    assert len(datagrams) > 1
    for this, nxt in itertools.pairwise(datagrams):
        first = 4 + int.from_bytes(nxt[16:20], "big")
        assert len(this) + first > vmc_out.MAX_DATAGRAM
    for d in datagrams:
        assert OscBundle.dgram_is_bundle(bytes(d))
        assert bytes(d)[8:16] == b"\0" * 7 + b"\x01"  # "immediately"
    msgs = _messages(datagrams)
    addresses = [a for a, _ in msgs]
    assert addresses == (
        ["/VMC/Ext/Root/Pos"]
        + ["/VMC/Ext/Bone/Pos"] * len(bones)
        + ["/VMC/Ext/Blend/Val"] * len(BLENDS)
        + ["/VMC/Ext/Blend/Apply", "/VMC/Ext/OK", "/VMC/Ext/T"]
    )
    root_pos, root_q, bone_pos, bone_q, blend, _ = frame
    assert msgs[0][1][0] == "root"
    np.testing.assert_array_equal(msgs[0][1][1:], np.float32([*root_pos, *root_q]))
    names = [p[0] for _, p in msgs[1 : 1 + len(bones)]]
    assert names == list(bones)
    values = np.array([p[1:] for _, p in msgs[1 : 1 + len(bones)]])
    np.testing.assert_array_equal(values[:, :3], bone_pos.astype(np.float32))
    np.testing.assert_array_equal(values[:, 3:], bone_q.astype(np.float32))
    blends = msgs[1 + len(bones) : 1 + len(bones) + len(BLENDS)]
    assert [p[0] for _, p in blends] == list(BLENDS)
    np.testing.assert_array_equal([p[1] for _, p in blends], blend.astype(np.float32))
    assert msgs[-3][1] == [] and msgs[-2][1] == [1, 3, 0, 1] and msgs[-1][1] == [12.5]


def test_no_blendshapes_still_sends_apply(rng: np.random.Generator) -> None:
    enc = vmc_out.VmcEncoder()
    addresses = [a for a, _ in _messages(enc.encode(*_frame(rng, 22, 0)))]
    assert "/VMC/Ext/Blend/Val" not in addresses
    assert addresses[-3:] == ["/VMC/Ext/Blend/Apply", "/VMC/Ext/OK", "/VMC/Ext/T"]


def test_hemisphere_continuity(rng: np.random.Generator) -> None:
    enc = vmc_out.VmcEncoder(("Hips", "Spine"))
    root_pos, _, bone_pos, _, blend, _ = _frame(rng, 2, 0)
    q = np.array([[0.0, 0.0, 0.0, 1.0], [0.1, 0.0, 0.0, 0.995], [0.0, 0.6, 0.0, 0.8]])
    enc.encode(root_pos, q[0], bone_pos, q[1:], blend, 0.0)
    sent_first = np.array([p[4:] for _, p in _messages(enc.datagrams)[:3]])
    np.testing.assert_allclose(sent_first, q, rtol=1e-6)
    # Same rotations, opposite signs for root and Hips: sent back on the same side.
    flipped = q * np.array([[-1.0], [-1.0], [1.0]])
    enc.encode(root_pos, flipped[0], bone_pos, flipped[1:], blend, 0.1)
    sent = np.array([p[4:] for _, p in _messages(enc.datagrams)[:3]])
    np.testing.assert_allclose(sent, q, rtol=1e-6)
    assert (np.sum(sent * sent_first, axis=1) >= 0).all()
    # After a reset (and on the very first frame) the reference is the identity:
    # every quaternion is sent with w >= 0, whatever sign it was given.
    enc.reset_continuity()
    enc.encode(root_pos, flipped[0], bone_pos, flipped[1:], blend, 0.2)
    sent = np.array([p[4:] for _, p in _messages(enc.datagrams)[:3]])
    np.testing.assert_allclose(sent, q, rtol=1e-6)
    assert (sent[:, 3] >= 0).all()


def test_vmcp_reads_the_frame(rng: np.random.Generator) -> None:
    """vmcp's events, fed by its own OSC backend (osc4py3's decoder)."""
    pytest.importorskip("vmcp")
    oscbuildparse = pytest.importorskip("osc4py3.oscbuildparse")
    from vmcp import events

    enc = vmc_out.VmcEncoder(vmc_out.HUMANOID_BONES + EXTRA, BLENDS)
    frame = _frame(rng, len(enc.bone_names), len(BLENDS))
    kinds = {
        e.ADDRESS_PATTERN: e
        for e in (
            events.RootTransformEvent,
            events.BoneTransformEvent,
            events.BlendShapeEvent,
            events.BlendShapeApplyEvent,
            events.StateEvent,
            events.RelativeTimeEvent,
        )
    }
    got = []
    for dgram in enc.encode(*frame):
        bundle = oscbuildparse.decode_packet(bytes(dgram))
        assert isinstance(bundle, oscbuildparse.OSCBundle)
        for msg in bundle.elements:
            got.append(
                kinds[msg.addrpattern].from_message_data(
                    "t", msg.addrpattern, msg.arguments
                )
            )
    _, root_q, bone_pos, bone_q, _, t = frame
    root = got[0]
    assert isinstance(root, events.RootTransformEvent) and root.joint == "root"
    assert root.rotation.w == pytest.approx(root_q[3], rel=1e-6)
    bones = [e for e in got if isinstance(e, events.BoneTransformEvent)]
    assert [b.joint.value for b in bones] == list(enc.bone_names)
    assert bones[3].position.x == pytest.approx(bone_pos[3, 0], rel=1e-6)
    assert bones[3].rotation.y == pytest.approx(bone_q[3, 1], rel=1e-6)
    assert [e.key for e in got if isinstance(e, events.BlendShapeEvent)] == list(BLENDS)
    assert isinstance(got[-1], events.RelativeTimeEvent) and got[-1].delta == t
    assert isinstance(got[-2], events.StateEvent) and got[-2].model_state.value == 1


def test_bad_names_are_refused() -> None:
    with pytest.raises(ValueError, match="unique"):
        vmc_out.VmcEncoder(("Hips", "Hips"))
    with pytest.raises(ValueError, match="cannot fit"):
        vmc_out.VmcEncoder(("X" * 1500,))


def test_a_loopback_receiver_gets_a_frame_in_one_datagram(
    rng: np.random.Generator,
) -> None:
    """To this machine (no MTU below 64 KiB) the limit is python-osc's 8192-byte read:
    22 bones and 52 blendshapes fit one datagram, which python-osc reads whole and
    in order, as the same frame packed for Ethernet."""
    assert vmc_out.datagram_limit(True) == vmc_out.LOOPBACK_MAX_DATAGRAM
    assert vmc_out.datagram_limit(False) == vmc_out.MAX_DATAGRAM
    assert vmc_out.datagram_limit(True, 1000) == 1000
    blends = tuple(f"blend{i:02d}" for i in range(52))
    frame = _frame(rng, 22, len(blends))
    one = vmc_out.VmcEncoder(
        vmc_out.HUMANOID_BONES, blends, max_datagram=vmc_out.LOOPBACK_MAX_DATAGRAM
    )
    lan = vmc_out.VmcEncoder(vmc_out.HUMANOID_BONES, blends)
    got_one, got_lan = one.encode(*frame), lan.encode(*frame)
    assert len(got_one) == 1 and len(got_one[0]) <= vmc_out.LOOPBACK_MAX_DATAGRAM
    assert len(got_lan) == 3
    assert _messages(got_one) == _messages(got_lan)
    # Bundled, the bytes are the Ethernet datagrams' elements back to back.
    elements = b"".join(bytes(d)[16:] for d in got_lan)
    assert bytes(got_one[0]) == bytes(got_one[0])[:16] + elements
    for bad in (vmc_out.MIN_DATAGRAM - 1, 65508):
        with pytest.raises(ValueError, match="max_datagram"):
            vmc_out.VmcEncoder(max_datagram=bad)
