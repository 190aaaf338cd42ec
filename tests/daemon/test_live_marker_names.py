"""The live daemon asks the rig which stream labels are its markers (issue 28 item 5):
never its marker names, which need not be labels (RIGS.md ``[markers]``).

The shipped ``opensim-gait2354`` names every marker apart from its label
(``RASIS = "R.ASIS"``); a face with no facial-marker list takes every label the body
rig does not match, a capture system's label set is checked against what the rig
matches, and the daemon's start-up warm-up streams labels the rig matches (it used
the rig's names, so every marker of such a rig was "not in the stream").
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from paths import DATASETS, require
from renamed_rig import write_renamed_rig

from retargetd.daemon.body.calibration import match_markers
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.cli.main import main
from retargetd.daemon.live.config import FaceSectionConfig
from retargetd.daemon.live.face import LiveFace
from retargetd.daemon.live.sources import CaptureInput, CaptureSource
from retargetd.replay.takes import load_take

OPENSIM_STATIC = "opensim-core/subject01_static.trc"


def _opensim_labels() -> tuple[str, ...]:
    return load_take(require(DATASETS / OPENSIM_STATIC, OPENSIM_STATIC)).labels


def test_face_takes_the_labels_the_body_rig_does_not_match() -> None:
    rig = load_rig("opensim-gait2354")
    body = _opensim_labels()
    assert not set(rig.marker_names) & set(body)  # names are not labels here
    facial = ("BRL1", "BRR1", "MOUTH_L")
    face = LiveFace(FaceSectionConfig(enabled=True), rig)
    head = set(face.face.head_markers)
    got = face.facial_markers((*body, *facial))
    cols = set(match_markers(rig, body))
    unmatched = [lb for i, lb in enumerate(body) if i not in cols and lb not in head]
    assert got == (*unmatched, *facial)
    assert len(unmatched) == len(body) - len(rig.markers)  # the static's extras


def test_capture_label_check_knows_the_rigs_labels_not_its_names() -> None:
    rig = load_rig("opensim-gait2354")
    labels = (*_opensim_labels(), "ghost")
    said: list[str] = []
    prepared: list[Any] = []  # (the pipelines' builds start for the new label set)
    state = SimpleNamespace(
        performers=SimpleNamespace(
            all=[SimpleNamespace(prefix="", rig=rig)],
            prepare=lambda stream, label_set: prepared.append(label_set),
        ),
        out=said.append,
    )
    cap = CaptureInput(system="qtm", url="qtm://127.0.0.1", form=0, inp=None)
    stream = SimpleNamespace(label_set=SimpleNamespace(labels=labels))
    CaptureSource._check_capture_labels(state, cap, stream)  # type: ignore[arg-type]
    assert prepared == [stream.label_set]
    cols = set(match_markers(rig, labels))
    want = tuple(lb for i, lb in enumerate(labels) if i not in cols)
    assert cap.unknown_labels == want and "ghost" in want
    assert not set(want) & {a for al in rig.markers.values() for a in al}
    assert said and f"{len(want)} of {len(labels)} labels" in said[0]


@pytest.mark.timeout(120)
def test_daemon_warm_up_sees_every_marker_of_a_renamed_rig(
    tmp_path: Path, run_daemon: Callable[..., Any]
) -> None:
    """``retargetd run`` with a rig whose names are not labels: the start-up
    pipeline (the warm-up) finds every marker."""
    static = require(DATASETS / "btkdata/PiG_Calibration-FlatFoot-Full.c3d", "PiG")
    rig_path = tmp_path / "pig-renamed.toml"
    write_renamed_rig("plug-in-gait", rig_path)
    cal = tmp_path / "cal.json"
    argv = ["calibrate", str(static), "--rig", str(rig_path), "--out", str(cal)]
    assert main(argv) == 0
    daemon = run_daemon(cal, rig=str(rig_path))
    rc, err = daemon.stop()
    assert rc == 0, err
    assert "not in the stream" not in err, err
