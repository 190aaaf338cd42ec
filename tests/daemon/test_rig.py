"""Rig files: shipped rigs parse; a bad rig gets one line naming file, key, value."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from retargetd.daemon.body import rig_fit
from retargetd.daemon.body.rig import (
    HUMANOID_BONES,
    RIG_KEYS,
    LinePoint,
    RigError,
    RigidPoint,
    load_rig,
    parse_linear,
    parse_rig,
    shipped_rigs,
)
from retargetd.daemon.cli.main import main

REPO = Path(__file__).resolve().parents[2]

MINIMAL = """
[rig]
name = "mini"
lateral = ["R", "L"]
[measurements]
W = { default = 100.0 }
[markers]
R = "RM"
L = ["LM", "LEFT"]
B = "BM"
[points.MID]
line = ["R", "L"]
[points.IN]
rigid = ["MID", "L", "B"]
rule = { height = "B", width = "MID", depth = "0.5*MID + 0.5*B" }
[points.OFF]
rigid = ["R", "L", "B"]
offset_mm = ["W/2 + 7", 0, -3]
[bones.root]
origin = "IN"
aim = "B"
up = ["R", "L"]
humanoid = "Hips"
[joints]
CENTRE = "IN"
"""


def _with(extra: str, base: str = MINIMAL) -> str:
    return base + "\n" + extra


def test_shipped_rigs_parse() -> None:
    assert "menache" in shipped_rigs()
    for name in shipped_rigs():
        rig = load_rig(name)
        assert rig.bones[0].parent is None
        assert set(rig.humanoid) <= set(HUMANOID_BONES)


def test_menache_is_the_chapter_point_for_point() -> None:
    rig = load_rig("menache")
    for point in ("PELVIS", "LUMBAR", "THORAX", "LONECK", "UPNECK", "HEAD", "UPTORSO",
                  "LOTORSO", "LCLAVICLE", "LUPARM", "LLOARM", "LFEMUR", "LUPLEG",
                  "LLOLEG", "LUPFOOT", "LLOFOOT"):  # fmt: skip
        assert point in rig.point_names
    femur = next(p for p in rig.points if p.name == "LFEMUR")
    assert isinstance(femur, LinePoint)
    assert (femur.a, femur.b, femur.u) == ("LHIP", "PELVIS", 0.35)
    pelvis = next(p for p in rig.points if p.name == "PELVIS")
    assert isinstance(pelvis, RigidPoint) and pelvis.rule is not None
    assert pelvis.rule["height"].names == ("SACRUM",)
    aims = {b.aim for b in rig.bones if b.origin == "LLOARM"}
    assert aims == {"LIWRIST", "LEWRIST"}  # the two forearm bones
    bilateral = "HIP HEAD SHOULDER SCAPULA IELBOW EELBOW IWRIST EWRIST HAND IKNEE"
    bilateral += " EKNEE HEEL FOOT ANKLE TOE"
    expected = {"SACRUM", "L1", "T7", "T1", "C1", "C7", "STERNUM"}
    expected |= {side + m for m in bilateral.split() for side in "LR"}
    assert set(rig.marker_names) == expected


def test_minimal_rig_structure() -> None:
    rig = parse_rig(MINIMAL, source="mini.toml")
    assert rig.point_names == ("MID", "IN", "OFF")
    assert rig.markers["L"] == ("LM", "LEFT")
    assert rig.markers_of("IN") == ("R", "L", "B")
    off = next(p for p in rig.points if p.name == "OFF")
    assert isinstance(off, RigidPoint) and off.offset_mm is not None
    assert off.offset_mm[0].evaluate({"W": 100.0}) == pytest.approx(57.0)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            _with("[points.X]\nline = ['R', 'NOPE']"),
            "points.X: unknown point or marker 'NOPE'",
        ),
        (
            _with("[points.P]\nline = ['Q', 'R']\n[points.Q]\nline = ['P', 'L']"),
            "cycle P -> Q -> P",
        ),
        (
            _with(
                "[bones.a]\nparent='b'\norigin='R'\naim='L'\nup='B'\n"
                "[bones.b]\nparent='a'\norigin='R'\naim='L'\nup='B'"
            ),
            "cycle",
        ),
        (
            _with(
                "[bones.x]\nparent='root'\norigin='R'\naim='L'\nup='B'\nhumanoid='Feet'"
            ),
            "bones.x.humanoid: unknown humanoid bone 'Feet'",
        ),
        (
            _with("[bones.x]\nparent='ghost'\norigin='R'\naim='L'\nup='B'"),
            "bones.x.parent: unknown bone 'ghost'",
        ),
        (
            _with("[points.Y]\nrigid = ['R', 'L', 'B']\noffset_mm = ['Q*2', 0, 0]"),
            "points.Y.offset_mm[0]: unknown measurement 'Q'",
        ),
        (
            _with("[points.Y]\nrigid = ['R', 'L', 'B']\noffset_mm = ['W*W', 0, 0]"),
            "not a linear expression",
        ),
        (
            _with(
                "[points.Y]\nrigid = ['R', 'L', 'B']\nrule = {height='R', width='L'}"
            ),
            "points.Y.rule: missing axis 'depth'",
        ),
        (
            _with(
                "[points.Y]\nrigid = ['R', 'L', 'B']\n"
                "rule = {height='R', width='L', depth='R + L'}"
            ),
            "affine combination",
        ),
        (
            _with("[points.Y]\nrigid = ['R', 'L', 'B']"),
            "exactly one of 'rule' and 'offset_mm'",
        ),
        (_with("[extra]\nx = 1"), "extra: unknown key"),
        (
            MINIMAL.replace('lateral = ["R", "L"]', 'lateral = ["R", "ZZ"]'),
            "rig.lateral: unknown point or marker 'ZZ'",
        ),
        (
            MINIMAL.replace('humanoid = "Hips"', 'humanoid = "Hips"\ncolour = 1'),
            "bones.root.colour: unknown key",
        ),
        ("[rig\nname=", "not valid TOML"),
    ],
)
def test_bad_rigs_name_file_key_and_value(text: str, message: str) -> None:
    with pytest.raises(RigError) as info:
        parse_rig(text, source="bad.toml")
    line = str(info.value)
    assert "\n" not in line
    assert line.startswith("bad.toml: ")
    assert message in line


def test_linear_expressions() -> None:
    expr = parse_linear("LKneeWidth/2 + 0.5*MarkerDiameter - 3", where="k")
    assert expr.evaluate({"LKneeWidth": 100.0, "MarkerDiameter": 14.0}) == 54.0
    assert parse_linear(2.5, where="k").evaluate({}) == 2.5
    with pytest.raises(RigError, match="k: "):
        parse_linear("A / B", where="k")
    with pytest.raises(RigError, match="k: "):
        parse_linear("__import__('os')", where="k")


def test_unknown_shipped_rig_lists_the_shipped_ones() -> None:
    with pytest.raises(RigError, match="menache"):
        load_rig("no-such-rig")


def test_rig_check_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rig", "check", "menache"]) == 0
    out = capsys.readouterr().out
    assert "LUMBAR: rigid in frame [L1, PELVIS, SACRUM]" in out
    bad = tmp_path / "bad.toml"
    bad.write_text(_with("[points.X]\nline = ['R', 'NOPE']"))
    assert main(["rig", "check", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "points.X: unknown point or marker 'NOPE'" in err[0]
    assert str(bad) in err[0]


def test_rig_check_against_a_take(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    take = tmp_path / "s.c3d"
    assert main(["synth", "--seconds", "1", "--rate", "60", "--out", str(take)]) == 0
    capsys.readouterr()
    assert main(["rig", "check", "menache", str(take)]) == 0
    assert "every bone can be built" in capsys.readouterr().out
    # A take without the head markers leaves the head bone without data: exit 1.
    from retargetd.replay.c3d import write_c3d
    from retargetd.replay.takes import load_take

    full = load_take(take)
    keep = [i for i, lab in enumerate(full.labels) if "HEAD" not in lab]
    part = tmp_path / "nohead.c3d"
    write_c3d(
        part, [full.labels[i] for i in keep], full.positions[:, keep], full.rate_hz
    )
    assert main(["rig", "check", "menache", str(part)]) == 1
    out = capsys.readouterr().out
    assert "missing (occluded in every frame): LHEAD RHEAD" in out
    assert "bones without data (held at rest, flagged): head" in out


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        # A dotted label as a bare TOML key is a table: the error says how to fix it,
        # whether the table's name is new or clashes with a marker (invalid TOML).
        ('S.EIAS = "S.EIAS"', 'SEIAS = "S.EIAS"'),
        ('R.EIAS = "R.EIAS"', 'REIAS = "R.EIAS"'),
        ('"R.EIAS" = "R.EIAS"\n[points.Q]\nline = ["R", "R.EIAS"]', None),
    ],
)
def test_dotted_marker_labels(extra: str, message: str | None) -> None:
    text = MINIMAL.replace('B = "BM"\n', f'B = "BM"\n{extra.split(chr(10))[0]}\n')
    text += "\n".join(extra.split("\n")[1:])
    if message is None:
        rig = parse_rig(text, source="dots.toml")
        assert rig.markers["R.EIAS"] == ("R.EIAS",)
        assert "Q" in rig.point_names
        return
    with pytest.raises(RigError) as info:
        parse_rig(text, source="dots.toml")
    assert message in str(info.value)
    assert "markers.S" in str(info.value) or "not valid TOML" in str(info.value)


def test_rig_errors_suggest_the_fix() -> None:
    # A quoted dotted name cannot appear in an expression: the error says what can.
    text = MINIMAL.replace('B = "BM"\n', 'B = "BM"\n"R.EIAS" = "R.EIAS"\n') + (
        '\n[points.Y]\nrigid = ["R", "L", "B"]\n'
        'rule = { height = "R.EIAS", width = "L", depth = "B" }\n'
    )
    with pytest.raises(RigError, match=r'REIAS = "R.EIAS"'):
        parse_rig(text, source="dots.toml")
    # A misspelt point or marker: the closest name is offered.
    with pytest.raises(
        RigError, match=r"unknown point or marker 'MDI' \(did you mean 'MID'\?\)"
    ):
        parse_rig(MINIMAL.replace('origin = "IN"', 'origin = "MDI"'), source="x.toml")


def test_rig_check_reports_up_levers(
    datasets: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """On the PiG static: every bone's up lever is printed; a bone under 30 mm (the
    left foot's heel marker sits 25 mm off its ankle-toe line) gets a warning."""
    static = datasets / "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
    assert main(["rig", "check", "plug-in-gait", str(static)]) == 0
    out = capsys.readouterr().out
    assert "up levers in the base pose (rows 0:94; at least 30 mm wanted)" in out
    assert "pelvis 200 mm" in out
    warned = [line for line in out.splitlines() if "warning: bone" in line]
    assert warned and all("mm off the bone's axis" in line for line in warned)
    assert any("lfoot" in line for line in warned)
    assert not any("pelvis" in line for line in warned)


def test_rigs_md_documents_every_key_the_parser_takes() -> None:
    """RIGS.md's key tables for ``[rig]``, ``[fit.markers.NAME]`` and
    ``[fit.bones.NAME]`` name exactly the keys the parser accepts."""
    doc = (REPO / "daemon/body/rigs/RIGS.md").read_text()
    for heading, keys in (
        ("### `[rig]`", RIG_KEYS),
        ("### `[fit.markers.NAME]`", rig_fit.MARKER_KEYS),
        ("### `[fit.bones.NAME]`", rig_fit.BONE_KEYS),
    ):
        section = doc.split(heading, 1)[1].split("\n#", 1)[0]
        documented = re.findall(r"^\| `(\w+)` \|", section, re.M)
        assert documented == list(keys), heading
