"""Synthetic facial-marker takes with known weights, from real face models riding
on real head motion.

Two linear blendshape models (``../shared/datasets/face``, see its PROVENANCE.md),
both +Y up, +Z forward, +X the subject's left, become ARKit-52 shapes at marker
sites (:class:`FaceModel`, :data:`MODELS`):

- ``ict``: ICT-FaceKit "Light" (MIT), scanned, centimetres;
- ``makehuman``: MakeHuman's base mesh (CC0) with the TalkingHead ARKit-52 targets
  (MIT), artist-made, decimetres; every ARKit name present (``tongueOut`` moves only
  the tongue helper, which no marker can reach).

For either:

- facial markers: one at the peak of each shape (>= ``spacing`` apart), then the 68
  landmark vertices (jaw line, brows, nose, lips), then the most-moving vertices,
  until ``n_markers``; all on the face skin (ICT's face region ``[0, 9409)``;
  MakeHuman's outward-facing body vertices an ARKit target moves), so eyelids,
  cheeks and forehead get markers;
- head markers LFHD RFHD LBHD RBHD: the Plug-in Gait take's own four, in their
  measured layout (:func:`pig_head_layout`), worn as a headband the way Plug-in Gait
  places them: the front pair over the temples, ``BAND_ABOVE_EYES_M`` above the outer
  eye corners and ``FRONT_STANDOFF_M`` proud of the forehead skin, the back pair in
  the same horizontal plane (:func:`place_head_band`). So the head markers of a
  synthetic frame are the take's head markers (same geometry, same motion) and the
  face sits under them where a real face would;
- ARKit names from ICT's: ``x_L`` -> ``xLeft``; ``browInnerUp`` and ``cheekPuff`` are
  the sums of their halves; ``cheekRaiser_*`` and the pupil shapes are dropped;
  ``tongueOut`` has no ICT shape and is a zero column (the solver must report it
  unobservable). MakeHuman's targets carry the ARKit names already.

Head coordinates (``HEAD_FROM_ICT``, the same axes for both models): +X the subject's
right, +Y forward, +Z up, metres, origin at the head-marker centroid (the axes are the
take's anatomical head axes, :func:`pig_head_layout`). Frames are ``neutral + sum_k w_k
delta_k`` in head coordinates, moved by ``world_from_head`` of each frame of a Plug-in
Gait take (the Kabsch fit of its LFHD RFHD LBHD RBHD to their layout), plus Gaussian
noise of ``noise_rms_m`` 3-D RMS on every marker (per-axis sigma ``noise_rms_m / sqrt
3``: the issue's "0.5 mm noise" is read as a 3-D RMS marker error, as capture systems
quote it).

Why the band matters: the stabilization error of a rigid fit is set by the head
markers' geometry and noise alone (see ``solve_face``). An earlier version put the four
markers on rigid crown vertices, 58 mm apart in front and 15 cm above the facial
markers' centroid, unlike the take's layout (86 mm front, 163 mm back, band at temple
height); that geometry alone gave 0.87 mm RMS at the face for 0.5 mm noise.
"""

from __future__ import annotations

import itertools
import json
import logging
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from retargetd.daemon.face.solve import (
    TrainingSet,
    head_layout_from_frames,
    observability,
)
from retargetd.replay.takes import load_take

logger = logging.getLogger(__name__)

F64Array = npt.NDArray[np.float64]

CM_TO_M = 1e-2
DM_TO_M = 1e-1
#: Signed permutation: head coords (x right, y forward, z up) from ICT (x left,
#: y up, z forward). det = +1.
HEAD_FROM_ICT = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
ICT_DIR = "face/ict-facekit"
MAKEHUMAN_DIR = "face/makehuman-arkit"
ICT_FACE_END = 9409  #: vertices [0, 9409) are the face skin
ICT_SKIN_END = 11248  #: [9409, 11248) head and neck
HEAD_NAMES = ("LFHD", "RFHD", "LBHD", "RBHD")
PIG_WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"

ARKIT_52: tuple[str, ...] = (
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft",
    "browOuterUpRight", "cheekPuff", "cheekSquintLeft", "cheekSquintRight",
    "eyeBlinkLeft", "eyeBlinkRight", "eyeLookDownLeft", "eyeLookDownRight",
    "eyeLookInLeft", "eyeLookInRight", "eyeLookOutLeft", "eyeLookOutRight",
    "eyeLookUpLeft", "eyeLookUpRight", "eyeSquintLeft", "eyeSquintRight",
    "eyeWideLeft", "eyeWideRight", "jawForward", "jawLeft", "jawOpen", "jawRight",
    "mouthClose", "mouthDimpleLeft", "mouthDimpleRight", "mouthFrownLeft",
    "mouthFrownRight", "mouthFunnel", "mouthLeft", "mouthLowerDownLeft",
    "mouthLowerDownRight", "mouthPressLeft", "mouthPressRight", "mouthPucker",
    "mouthRight", "mouthRollLower", "mouthRollUpper", "mouthShrugLower",
    "mouthShrugUpper", "mouthSmileLeft", "mouthSmileRight", "mouthStretchLeft",
    "mouthStretchRight", "mouthUpperUpLeft", "mouthUpperUpRight", "noseSneerLeft",
    "noseSneerRight", "tongueOut",
)  # fmt: skip

#: The head-marker band: height above the outer eye corners (Plug-in Gait: front head
#: markers over the temples) and how far the front markers stand off the forehead
#: skin (marker radius + band).
BAND_ABOVE_EYES_M = 0.04
FRONT_STANDOFF_M = 0.01
#: Multi-PIE landmarks (``idx_to_landmark_verts``) of the outer eye corners.
_EYE_CORNERS = (36, 45)


def _arkit_from_ict(name: str) -> str:
    if name.endswith("_L"):
        return name[:-2] + "Left"
    if name.endswith("_R"):
        return name[:-2] + "Right"
    return name


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class FaceModel:
    """A linear blendshape face (ARKit-52 shapes, or a rig's own), in head axes
    (x the subject's right, y forward, z up), metres, in the model's own origin.

    Attributes:
        name: ``"ict"``, ``"makehuman"`` (:data:`MODELS`) or ``"makehuman-units"``.
        expressions: (K,) shape names (:data:`ARKIT_52` for the ARKit models).
        neutral: (V, 3) every vertex of the model.
        deltas: (K, V, 3) in ``expressions`` order; a shape the model lacks is a
            zero column.
        candidates: vertex ids where a facial marker may go (outer face skin).
        landmarks: vertex ids preferred after the shape peaks (may be empty).
        skin: vertex ids of the outer head skin (the head band sits on it).
        eye_level: (2, 3) two points at eye level, left-right symmetric (outer eye
            corners, or the eyeball centres), for the head band's height.
        missing: expression names with no shape in the model.
    """

    name: str
    expressions: tuple[str, ...]
    neutral: F64Array
    deltas: F64Array
    candidates: npt.NDArray[np.int64]
    landmarks: tuple[int, ...]
    skin: npt.NDArray[np.int64]
    eye_level: F64Array
    missing: tuple[str, ...]


def ict_arkit_shapes(datasets: Path) -> tuple[F64Array, F64Array, dict[str, list[int]]]:
    """The ICT model as ARKit 52 shapes.

    Returns:
        neutral (V, 3) cm ICT axes, deltas (52, V, 3) cm ICT axes (ARKIT_52 order),
        and ``vertex_indices.json`` (landmark and rigid vertex lists).
    """
    folder = datasets / ICT_DIR
    with np.load(folder / "ict_expressions_skin.npz", allow_pickle=False) as z:
        names = [str(s) for s in z["names"]]
        neutral = np.asarray(z["neutral"], dtype=np.float64)
        ict = np.asarray(z["deltas"], dtype=np.float64)
    indices = json.loads((folder / "vertex_indices.json").read_text())
    by = {n: i for i, n in enumerate(names)}
    deltas = np.zeros((len(ARKIT_52), *neutral.shape))
    for k, name in enumerate(ARKIT_52):
        if name in ("browInnerUp", "cheekPuff"):
            deltas[k] = ict[by[name + "_L"]] + ict[by[name + "_R"]]
            continue
        src = [n for n in names if _arkit_from_ict(n) == name]
        if src:
            deltas[k] = ict[by[src[0]]]
    return neutral, deltas, indices


def ict_model(datasets: Path) -> FaceModel:
    """ICT-FaceKit "Light" (MIT): scanned, 55 expressions mapped to ARKit 52 (no
    ``tongueOut``); markers on the face region ``[0, 9409)``, the Multi-PIE
    landmarks first after the peaks, the band on face + head skin ``[0, 11248)``,
    eye level at the outer eye corners (landmarks 36 and 45)."""
    neutral, deltas, indices = ict_arkit_shapes(datasets)
    to_head = HEAD_FROM_ICT * CM_TO_M
    landmarks = indices["idx_to_landmark_verts"]
    return FaceModel(
        name="ict",
        expressions=ARKIT_52,
        neutral=neutral @ to_head.T,
        deltas=deltas @ to_head.T,
        candidates=np.arange(ICT_FACE_END),
        landmarks=tuple(int(v) for v in landmarks),
        skin=np.arange(ICT_SKIN_END),
        eye_level=neutral[[landmarks[i] for i in _EYE_CORNERS]] @ to_head.T,
        missing=("tongueOut",),
    )


def read_mh_target(text: str) -> dict[int, F64Array]:
    """A MakeHuman ``.target`` file: ``index dx dy dz`` per moved vertex (``#``
    comments), decimetres. Returns {vertex: (3,) offset}."""
    out: dict[int, F64Array] = {}
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        idx, dx, dy, dz = line.split()
        out[int(idx)] = np.array([float(dx), float(dy), float(dz)])
    return out


def _obj_vertices_and_groups(
    path: Path,
) -> tuple[F64Array, dict[str, npt.NDArray[np.int64]], F64Array]:
    # Vertices (V, 3), each group's vertex ids, and area-weighted vertex normals
    # of the whole mesh (polygons fanned into triangles).
    verts: list[list[float]] = []
    groups: dict[str, set[int]] = {}
    polys: list[list[int]] = []
    group = ""
    with path.open() as f:
        for line in f:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("g "):
                group = line.split()[1]
            elif line.startswith("f "):
                poly = [int(tok.split("/")[0]) - 1 for tok in line.split()[1:]]
                polys.append(poly)
                groups.setdefault(group, set()).update(poly)
    v = np.array(verts)
    normals = np.zeros_like(v)
    for poly in polys:
        for a, b in itertools.pairwise(poly[1:]):
            n = np.cross(v[a] - v[poly[0]], v[b] - v[poly[0]])
            normals[[poly[0], a, b]] += n
    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = normals / np.where(norm > 0, norm, 1.0)
    return v, {g: np.array(sorted(ix)) for g, ix in groups.items()}, normals


def _makehuman(
    datasets: Path, name: str, expressions: tuple[str, ...], targets: dict[str, str]
) -> FaceModel:
    # The MakeHuman mesh with one target text per expression (absent = zero shape).
    folder = datasets / MAKEHUMAN_DIR
    verts, groups, normals = _obj_vertices_and_groups(folder / "base.obj")
    deltas = np.zeros((len(expressions), *verts.shape))
    for k, expr in enumerate(expressions):
        for v, d in read_mh_target(targets.get(expr, "")).items():
            deltas[k, v] = d
    body = groups["body"]
    eyes = np.stack(
        [
            verts[groups["joint-l-eye"]].mean(axis=0),
            verts[groups["joint-r-eye"]].mean(axis=0),
        ]
    )
    moved = np.zeros(len(verts), dtype=bool)
    moved[body] = np.abs(deltas[:, body]).max(axis=(0, 2)) >= 1e-3
    outward = np.einsum("vc,vc->v", normals, verts - eyes.mean(axis=0)) > 0.0
    head = body[verts[body, 1] > eyes[:, 1].mean() - 1.5]  # above the chin-neck line
    to_head = HEAD_FROM_ICT * DM_TO_M
    return FaceModel(
        name=name,
        expressions=expressions,
        neutral=verts @ to_head.T,
        deltas=deltas @ to_head.T,
        candidates=np.flatnonzero(moved & outward),
        landmarks=(),
        skin=head,
        eye_level=eyes @ to_head.T,
        missing=tuple(e for e in expressions if e not in targets),
    )


def makehuman_model(datasets: Path) -> FaceModel:
    """MakeHuman's base mesh (CC0) with the TalkingHead ARKit-52 targets (MIT):
    artist-made, every ARKit name present. Units decimetres, axes as ICT's (x the
    subject's left, y up, z forward).

    Markers may go on vertices of the ``body`` group that a target moves (the face)
    and whose normal faces away from the eyes' midpoint (outer skin, not the mouth
    cavity); ``tongueOut`` moves only the tongue helper, so no marker sees it. Eye
    level: the two eye joint cubes' centres.
    """
    targets: dict[str, str] = {}
    with zipfile.ZipFile(datasets / MAKEHUMAN_DIR / "talkinghead-targets.zip") as z:
        for entry in z.namelist():
            stem = entry.rsplit("/", 1)[-1].removesuffix(".target")
            if not entry.startswith("__MACOSX") and stem in ARKIT_52:
                targets[stem] = z.read(entry).decode()
    return _makehuman(datasets, "makehuman", ARKIT_52, targets)


def makehuman_units_model(
    datasets: Path, expressions: tuple[str, ...] | None = None
) -> FaceModel:
    """The same MakeHuman mesh with MakeHuman's own FACS-like expression units
    (``expression-units-caucasian/*.target``, CC0: ``eye-left-closure``,
    ``mouth-corner-puller``, ...): a second rig whose names are not ARKit's, for
    custom output maps. ``expressions``: which units (default all 34, by name)."""
    folder = datasets / MAKEHUMAN_DIR / "expression-units-caucasian"
    files = {p.stem: p for p in sorted(folder.glob("*.target"))}
    names = tuple(files) if expressions is None else tuple(expressions)
    unknown = [n for n in names if n not in files]
    if unknown:
        raise ValueError(f"makehuman_units_model: no expression unit {unknown[0]!r}")
    targets = {n: files[n].read_text() for n in names}
    return _makehuman(datasets, "makehuman-units", names, targets)


#: The face models, by name.
MODELS = {"ict": ict_model, "makehuman": makehuman_model}
#: Each model's folder under ``../shared/datasets``.
MODEL_DIRS = {"ict": ICT_DIR, "makehuman": MAKEHUMAN_DIR}


def pick_face_vertices(
    model: FaceModel, n_markers: int = 40, spacing_m: float = 0.008
) -> list[int]:
    """Facial marker vertices: shape peaks, then landmarks, then the most-moving,
    all among ``model.candidates``, at least ``spacing_m`` apart."""
    face = model.candidates
    neutral = model.neutral
    mag = np.linalg.norm(model.deltas[:, face], axis=2)  # (K, F)
    chosen: list[int] = []

    def far(v: int) -> bool:
        if not chosen:
            return True
        return bool(
            np.min(np.linalg.norm(neutral[chosen] - neutral[v], axis=1)) >= spacing_m
        )

    allowed = set(face.tolist())
    for k in np.argsort(-mag.max(axis=1)):
        if mag[k].max() < 5e-4 or len(chosen) >= n_markers:
            continue
        for v in face[np.argsort(-mag[k])][:400]:
            if far(int(v)):
                chosen.append(int(v))
                break
    for v in model.landmarks:
        if len(chosen) < n_markers and v in allowed and far(v):
            chosen.append(int(v))
    for i in np.argsort(-mag.sum(axis=0)):
        if len(chosen) >= n_markers:
            break
        if far(int(face[i])):
            chosen.append(int(face[i]))
    return chosen


def place_head_band(
    skin_head: F64Array, eye_corners_head: F64Array, layout: F64Array
) -> F64Array:
    """Put a head-marker layout on the face model as a headband.

    Args:
        skin_head: (V, 3) model skin vertices, metres, head axes (x right, y forward,
            z up).
        eye_corners_head: (2, 3) points at eye level (outer eye corners or eyeball
            centres), same frame.
        layout: (4, 3) LFHD RFHD LBHD RBHD, metres, head axes, centred.

    Returns:
        (4, 3) the layout translated (not rotated or scaled): ``BAND_ABOVE_EYES_M``
        above the eye level, centred left-right on the model, the front pair at
        least ``FRONT_STANDOFF_M`` in front of the forehead skin below each marker
        (the skin within 4 mm of its x and height; 8 or 16 mm on a coarse mesh).
    """
    z = float(eye_corners_head[:, 2].mean()) + BAND_ABOVE_EYES_M
    x = float(eye_corners_head[:, 0].mean())
    y = -np.inf
    for lx, ly, _ in layout[:2]:
        # The skin within a few mm of the marker's (x, z), wider on a coarse mesh.
        for tol in (4e-3, 8e-3, 16e-3):
            near = (np.abs(skin_head[:, 0] - (x + lx)) < tol) & (
                np.abs(skin_head[:, 2] - z) < tol
            )
            if near.any():
                break
        else:
            raise ValueError("place_head_band: no forehead skin at the band height")
        y = max(y, float(skin_head[near, 1].max()) + FRONT_STANDOFF_M - ly)
    return layout + np.array([x, y, z])


def face_training_set(
    datasets: Path, model: str = "ict", n_markers: int = 40
) -> TrainingSet:
    """The ground-truth training set of a synthetic face (ARKit 52, head coords):
    ``n_markers`` facial markers on the model (:func:`pick_face_vertices`) under the
    take's head-marker layout worn as a headband (:func:`place_head_band`), origin
    at the head markers' centroid."""
    return model_training_set(MODELS[model](datasets), datasets, n_markers)


def model_training_set(
    fm: FaceModel,
    datasets: Path,
    n_markers: int = 40,
    head_layout: F64Array | None = None,
) -> TrainingSet:
    """:func:`face_training_set` of a loaded :class:`FaceModel` (its own names);
    ``head_layout``: the band's layout (default :func:`pig_head_layout`; another
    take's from :func:`take_head_motion`)."""
    face_v = pick_face_vertices(fm, n_markers)
    layout = pig_head_layout(datasets) if head_layout is None else head_layout
    head = place_head_band(fm.neutral[fm.skin], fm.eye_level, layout)
    origin = head.mean(axis=0)
    return TrainingSet(
        head_names=HEAD_NAMES,
        marker_names=tuple(f"F{i:02d}_v{v}" for i, v in enumerate(face_v)),
        expression_names=fm.expressions,
        head_layout=head - origin,
        neutral=fm.neutral[face_v] - origin,
        deltas=fm.deltas[:, face_v],
    )


def ict_training_set(datasets: Path, n_markers: int = 40) -> TrainingSet:
    """:func:`face_training_set` of the ICT model."""
    return face_training_set(datasets, "ict", n_markers)


def _pig_head(datasets: Path, take_path: str = PIG_WALK) -> tuple[F64Array, F64Array]:
    # (T, 4, 3) complete frames of the take's head markers (world, m) and their
    # layout (4, 3) in anatomical head axes (x right, y forward, z up), centred.

    take = load_take(datasets / take_path)
    cols = [take.labels.index(n) for n in HEAD_NAMES]
    head_world = take.positions[:, cols]
    complete = np.all(np.isfinite(head_world), axis=(1, 2))
    head_world = head_world[complete]
    layout = head_layout_from_frames(head_world)
    lf, rf, lb, rb = layout
    right = (rf + rb - lf - lb) / 2.0
    fwd = (lf + rf - lb - rb) / 2.0
    x = right / np.linalg.norm(right)
    z = np.cross(x, fwd)
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    return head_world, layout @ np.stack([x, y, z], axis=1)


def pig_head_layout(datasets: Path) -> F64Array:
    """LFHD RFHD LBHD RBHD of the Plug-in Gait walk in anatomical head axes (x right,
    y forward, z up), metres, centred: (4, 3) float64. Averaged over every complete
    frame (:func:`~retargetd.daemon.face.solve.head_layout_from_frames`)."""
    return _pig_head(datasets)[1]


def pig_head_motion(datasets: Path) -> tuple[F64Array, F64Array]:
    """``world_from_head`` per complete frame of the Plug-in Gait walk.

    The head frame is built on the take's LFHD RFHD LBHD RBHD layout (x right,
    y forward, z up, origin at their centroid); each frame is the Kabsch fit of the
    four markers to that layout. Returns quat (T, 4) (w, x, y, z) and pos (T, 3) m.
    """
    from scipy.spatial.transform import Rotation

    head_world, layout = _pig_head(datasets)
    quat = np.zeros((len(head_world), 4))
    pos = np.zeros((len(head_world), 3))
    for t, f in enumerate(head_world):
        c = f.mean(axis=0)
        rot, _ = Rotation.align_vectors(f - c, layout)
        quat[t] = rot.as_quat(scalar_first=True)
        pos[t] = c
    return quat, pos


def take_head_motion(
    datasets: Path, take_path: str
) -> tuple[F64Array, F64Array, F64Array, npt.NDArray[np.bool_]]:
    """The head of any take wearing LFHD RFHD LBHD RBHD (e.g. the tennis serve): its
    layout in anatomical head axes (as :func:`pig_head_layout`), ``world_from_head``
    per complete frame (quat (T, 4) w x y z, pos (T, 3) m, as
    :func:`pig_head_motion`) and which rows of the take are complete (T_all,)."""
    from scipy.spatial.transform import Rotation

    take = load_take(datasets / take_path)
    cols = [take.labels.index(n) for n in HEAD_NAMES]
    complete = np.all(np.isfinite(take.positions[:, cols]), axis=(1, 2))
    head_world, layout = _pig_head(datasets, take_path)
    quat = np.zeros((len(head_world), 4))
    pos = np.zeros((len(head_world), 3))
    for t, f in enumerate(head_world):
        c = f.mean(axis=0)
        rot, _ = Rotation.align_vectors(f - c, layout)
        quat[t] = rot.as_quat(scalar_first=True)
        pos[t] = c
    return layout, quat, pos, complete


def synth_weights(
    rng: np.random.Generator,
    n_frames: int,
    rate_hz: float,
    missing: tuple[str, ...] = ("tongueOut",),
) -> F64Array:
    """Smooth random ARKit-52 weights (T, 52) in [0, 1], about a third at 0 at a
    time, left and right sides independent (asymmetry), ``mouthClose <= jawOpen``,
    the shapes named in ``missing`` = 0 (default ``tongueOut``: no ICT shape)."""
    t = np.arange(n_frames)[:, None] / rate_hz
    k = len(ARKIT_52)
    freq = rng.uniform(0.2, 1.5, k)
    phase = rng.uniform(0, 2 * np.pi, k)
    amp = rng.uniform(0.6, 1.0, k)
    w = np.clip(amp * (0.5 + 0.8 * np.sin(2 * np.pi * freq * t + phase)) - 0.1, 0, 1)
    jaw = ARKIT_52.index("jawOpen")
    close = ARKIT_52.index("mouthClose")
    w[:, close] = np.minimum(w[:, close], w[:, jaw])
    for name in missing:
        w[:, ARKIT_52.index(name)] = 0.0
    return w


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class SynthFace:
    """A synthetic face take.

    Attributes:
        model: the face model's name (:data:`MODELS`).
        training: the ground-truth training set.
        labels: (N,) stream labels: head markers, then facial markers.
        markers_world: (T, N, 3) float64, metres, world, noisy.
        markers_clean_world: (T, N, 3) float64, the same without the noise.
        weights: (T, K) true weights.
        world_from_head_quat: (T, 4) true head pose, (w, x, y, z).
        world_from_head_pos: (T, 3) metres.
        noise_rms_m: 3-D RMS marker noise, metres (per-axis sigma = it / sqrt 3).
    """

    model: str
    training: TrainingSet
    labels: tuple[str, ...]
    markers_world: F64Array
    markers_clean_world: F64Array
    weights: F64Array
    world_from_head_quat: F64Array
    world_from_head_pos: F64Array
    noise_rms_m: float


def synth_face_take(
    datasets: Path,
    rng: np.random.Generator,
    *,
    n_frames: int | None = None,
    noise_rms_m: float = 5e-4,
    n_markers: int = 40,
    rate_hz: float = 100.0,
    model: str = "ict",
    unobservable_still: bool = False,
) -> SynthFace:
    """A face model with known weights on the head motion of the PiG walk.

    Args:
        datasets: the ``../shared/datasets`` folder.
        rng: random generator (weights and noise).
        model: ``"ict"`` or ``"makehuman"`` (:data:`MODELS`). Every ARKit shape the
            model has gets weights, so MakeHuman's ``tongueOut`` moves (unseen).
        n_frames: frames to make (default: every complete frame of the walk).
        noise_rms_m: 3-D RMS Gaussian noise, metres, on every marker.
        n_markers: facial markers.
        rate_hz: time base of the weight curves.
        unobservable_still: the shapes this layout cannot observe
            (``face.solve.observability`` at 0.5 mm) are not performed (weight 0),
            as in issue 32's test; otherwise the performer moves them too and their
            motion, which no marker tells apart, leaks into the shapes solved.
    """
    from scipy.spatial.transform import Rotation

    fm = MODELS[model](datasets)
    training = model_training_set(fm, datasets, n_markers)
    quat, pos = pig_head_motion(datasets)
    if n_frames is not None:
        quat, pos = quat[:n_frames], pos[:n_frames]
    n = len(quat)
    missing = fm.missing
    if unobservable_still:
        missing = (*missing, *observability(training).unobservable)
    w = synth_weights(rng, n, rate_hz, tuple(dict.fromkeys(missing)))
    face = training.neutral + np.einsum("tk,kmc->tmc", w, training.deltas)
    head = np.broadcast_to(training.head_layout, (n, *training.head_layout.shape))
    local = np.concatenate([head, face], axis=1)
    rot = Rotation.from_quat(quat, scalar_first=True).as_matrix()
    clean = np.einsum("tij,tmj->tmi", rot, local) + pos[:, None, :]
    world = clean + rng.normal(0.0, noise_rms_m / np.sqrt(3.0), clean.shape)
    return SynthFace(
        model=model,
        training=training,
        labels=(*training.head_names, *training.marker_names),
        markers_world=world,
        markers_clean_world=clean,
        weights=w,
        world_from_head_quat=quat,
        world_from_head_pos=pos,
        noise_rms_m=noise_rms_m,
    )
