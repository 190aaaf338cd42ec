"""BVH hierarchy reading: the shipped test file, and line-numbered errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from retargetd.replay.bvh import parse_bvh, read_bvh_hierarchy

BVH = Path(__file__).resolve().parent.parent / "data" / "target-apose-mixamo.bvh"

SMALL = """HIERARCHY
ROOT Hips
{
  OFFSET 0 90 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine {
    OFFSET 0 10 0
    CHANNELS 3 Yrotation Xrotation Zrotation
    End Site
    {
      OFFSET 0 5 0
    }
  }
}
MOTION
Frames: 1
Frame Time: 0.01
1 90 2 10 20 30 1 2 3
"""


def test_read_test_file() -> None:
    sk = read_bvh_hierarchy(BVH)
    assert len(sk.joint_names) == 23 and sk.joint_names[0] == "mixamorig:Hips"
    assert sk.parents[0] == -1 and all(p < j for j, p in enumerate(sk.parents))
    assert sk.channels[0][:3] == ("Xposition", "Yposition", "Zposition")
    assert set(sk.rotation_orders) == {"ZXY"} and sk.n_channels == 72
    assert sk.n_frames == 2 and sk.frame_time_s == pytest.approx(0.0333333)
    assert sk.frames is None
    np.testing.assert_allclose(sk.offsets[0], [0, 98, 0])
    hand = sk.joint_names.index("mixamorig:LeftHand")
    assert np.isfinite(sk.end_sites[hand]).all()
    assert np.isnan(sk.end_sites[0]).all()
    assert sk.rest_positions()[:, 1].min() == pytest.approx(2.0)
    frames = read_bvh_hierarchy(BVH, read_motion=True).frames
    assert frames is not None and frames.shape == (2, 72) and frames[1, 5] == 30.0


def test_small_inline() -> None:
    sk = parse_bvh(SMALL, read_motion=True)
    assert sk.joint_names == ("Hips", "Spine") and sk.rotation_orders == ("ZXY", "YXZ")
    assert sk.channel_offsets() == (0, 6)
    np.testing.assert_allclose(sk.end_sites[1], [0, 5, 0])
    assert sk.frames is not None and sk.frames.tolist() == [
        [1, 90, 2, 10, 20, 30, 1, 2, 3]
    ]
    assert parse_bvh(SMALL.split("MOTION")[0]).n_frames == 0  # no MOTION at all


@pytest.mark.parametrize(
    ("old", "new", "line", "message"),
    [
        ("HIERARCHY", "HIERARCH", 1, "expected HIERARCHY"),
        ("OFFSET 0 90 0", "OFFSET 0 90", 4, "needs 3 numbers"),
        ("OFFSET 0 10 0", "OFFSET 0 x 0", 7, "not a number"),
        ("CHANNELS 3 Yrotation", "CHANNELS 3 Wrotation", 8, "unknown channel"),
        ("CHANNELS 3", "CHANNELS 4", 8, "lists 3 channels"),
        ("JOINT Spine {", "JOINT Hips {", 6, "duplicate joint"),
        ("  }\n}\nMOTION", "  }\nMOTION", 14, "unexpected 'MOTION'"),
        ("Frames: 1", "Frames: one", 16, "Frames: <count>"),
        ("1 90 2 10 20 30 1 2 3", "1 90 2 10 20 30 1 2", 18, "needs 9 numbers"),
        ("Frame Time: 0.01", "Frame Time: 0", 17, "must be > 0"),
    ],
)
def test_errors_name_the_line(old: str, new: str, line: int, message: str) -> None:
    assert old in SMALL
    with pytest.raises(ValueError, match=f"^<text>:{line}: .*{message}"):
        parse_bvh(SMALL.replace(old, new, 1), read_motion=True)


def test_truncated_and_unreadable(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unexpected end of file"):
        parse_bvh(SMALL[: SMALL.index("  JOINT")])
    with pytest.raises(ValueError, match="cannot read BVH"):
        read_bvh_hierarchy(tmp_path / "missing.bvh")
