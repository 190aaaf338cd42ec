"""The console in a real headless Chromium (selenium): the page shows the skeleton
where the camera projects it, flagged bones in red, and Calibrate reaches the queue.

Needs Debian's ``chromium`` and ``chromium-driver``; skipped (outside CI only) when
they are absent. ``RETARGETD_DOCS_SCREENSHOT=1`` also writes ``docs/console.png``.
"""

from __future__ import annotations

import io
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from browser import (  # the real headless browser: fixture and pixel tests
    _blue,
    _green,
    _near,
    _project,
    _red,
)

from retargetd.daemon.console import (
    CommandQueue,
    ConsoleLayout,
    SkeletonProgram,
    Snapshot,
    SnapshotSlot,
    bone_endpoints,
)
from retargetd.daemon.synth.performer import synthesize

REPO = Path(__file__).resolve().parents[2]
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
COUNTDOWN_S = 0.6


def _performer_layout() -> tuple[Any, ConsoleLayout, list[tuple[int, int]]]:
    take = synthesize(seconds=1.0, rate_hz=60.0, dropout=0.1, seed=3)
    par = take.segment_parents
    pairs = [(int(par[s]), s) for s in range(len(par)) if par[s] >= 0]
    layout = ConsoleLayout(
        marker_names=take.labels,
        joint_names=take.segment_names,
        bone_names=tuple(take.segment_names[s] for _, s in pairs),
        bone_parents=np.full(len(pairs), -1, np.int64),
        skeleton=SkeletonProgram.from_joint_pairs(pairs),
        bone_lengths=np.full(len(pairs), np.nan),
        humanoid_names=take.segment_names,
        humanoid_pairs=np.asarray(pairs, np.int64),
        humanoid_offset_m=np.array([0.0, -1.9, 0.0]),  # left of it, seen from +X
        face_names=("jawOpen", "mouthSmileLeft", "eyeBlinkLeft"),
        stage_names=("decode", "solve", "send"),
    )
    return take, layout, pairs


def _commit(slot: SnapshotSlot, timeout_s: float = 5.0) -> None:
    """Commit the back buffer as the daemon's writer does: a commit the console's
    reader is copying through is skipped by design (``SnapshotSlot.commit``: the
    back buffer keeps its contents), so it is tried again until it lands."""
    end = time.monotonic() + timeout_s
    while not slot.commit():
        assert time.monotonic() < end, "the snapshot slot stayed locked"
        time.sleep(0.001)


def snap_now(slot: SnapshotSlot) -> Snapshot:
    """A copy of the slot's latest snapshot."""
    out = Snapshot.for_layout(slot.layout, slot.layout_id)
    slot.read(out, -2)
    return out


def test_console_in_chromium(driver: Any) -> None:
    import matplotlib.image as mpimg
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support import expected_conditions as ec
    from selenium.webdriver.support.ui import WebDriverWait

    from retargetd.daemon.console.app import Console

    take, layout, pairs = _performer_layout()
    slot = SnapshotSlot(layout)
    commands = CommandQueue()
    console = Console(
        slot, commands, port=0, calibrate_countdown_s=COUNTDOWN_S, face_capture=True
    )
    frame = 40
    # The bone ending at the left knee (the segment pair thigh -> shank): a long one.
    flagged = layout.bone_names.index("l_shank")
    try:
        console.start()
        root = take.joint_pos_world[frame, 0]
        cam = console.server.initial_camera
        cam.position = root + np.array([4.6, -0.6, 0.2])  # facing it, level with pelvis
        cam.look_at = root + np.array([0.0, -0.6, 0.0])
        cam.up = (0.0, 0.0, 1.0)
        cam.fov = np.deg2rad(50.0)

        def publish() -> None:
            s = slot.begin()
            s.frame, s.t_s = frame, frame / take.rate_hz
            s.marker_pos[:] = take.markers_world[frame]
            s.marker_valid[:] = take.valid[frame]
            s.joint_pos[:] = take.joint_pos_world[frame]
            s.humanoid_pos[:] = take.joint_pos_world[frame]
            s.bone_flags[:] = 0
            s.bone_flags[flagged] = 1
            s.face_on = True
            s.face_weights[:] = (0.7, 0.3, 0.1)
            s.input_rate_hz = take.rate_hz
            s.latency_p50_ms[:] = (0.05, 0.4, 0.02)
            s.latency_p99_ms[:] = (0.1, 0.9, 0.05)
            s.occluded = int(np.count_nonzero(~take.valid[frame]))
            s.calibrated = True
            _commit(slot)

        publish()
        driver.get(console.url)
        wait = WebDriverWait(driver, 60)
        wait.until(ec.presence_of_element_located((By.TAG_NAME, "canvas")))
        deadline = time.monotonic() + 60
        while not console.server.get_clients() and time.monotonic() < deadline:
            time.sleep(0.1)
        client = next(iter(console.server.get_clients().values()))
        # Wait for the client's camera report and the drawn scene.
        while time.monotonic() < deadline:
            publish()
            c = client.camera
            aimed = np.allclose(c.look_at, cam.look_at, atol=1e-3)
            if c.update_timestamp and aimed and console.frames_drawn >= 3:
                break
            time.sleep(0.1)
        time.sleep(2.0)  # let a few frames render
        for b in driver.find_elements(
            By.CSS_SELECTOR, "button.mantine-Notification-closeButton"
        ):
            b.click()
        time.sleep(1.0)  # the notification fades out
        png = driver.get_screenshot_as_png()
        img = (mpimg.imread(io.BytesIO(png), format="png")[..., :3] * 255).astype(
            np.uint8
        )
        if os.environ.get("RETARGETD_DOCS_SCREENSHOT") == "1":
            (REPO / "docs").mkdir(exist_ok=True)
            (REPO / "docs" / "console.png").write_bytes(png)
        c = client.camera
        canvas = driver.execute_script(
            "const r = document.querySelector('canvas').getBoundingClientRect();"
            "return [r.left, r.top, r.width, r.height];"
        )
        left, top, w, h = canvas
        ends = bone_endpoints(layout.skeleton, take.joint_pos_world[frame])
        mid = ends.mean(axis=1)
        px = _project(c, mid, w, h) + np.array([left, top])
        inside = (px[:, 0] > 5) & (px[:, 0] < img.shape[1] - 5) & (px[:, 1] > 5)
        assert inside.sum() >= len(pairs) // 2, "skeleton projected off the page"
        hit_blue = _near(img, px, _blue)
        plain = np.ones(len(pairs), bool)
        plain[flagged] = False
        frac = hit_blue[plain & inside].mean()
        assert frac >= 0.8, f"bone colour at {frac:.0%} of projected bone midpoints"
        # Control: the same test 60 px to the side of every bone finds almost none.
        off = _near(img, px + np.array([60.0, 0.0]), _blue)[plain & inside].mean()
        assert off <= 0.4, f"bone colour also where no bone is ({off:.0%})"
        assert _near(img, px[[flagged]], _red)[0], "flagged bone not drawn red"
        hpx = _project(c, mid + layout.humanoid_offset_m, w, h) + np.array([left, top])
        hin = (hpx[:, 0] > 5) & (hpx[:, 0] < img.shape[1] - 5) & (hpx[:, 1] > 5)
        assert hin.sum() >= len(pairs) // 2, "humanoid projected off the page"
        hfrac = _near(img, hpx, _green)[hin].mean()
        assert hfrac >= 0.8, f"humanoid colour at {hfrac:.0%} of its bone midpoints"

        # Calibrate through the page: a countdown, then one calibrate command.
        assert commands.poll() is None
        button = wait.until(
            ec.element_to_be_clickable(
                (By.XPATH, "//button[contains(normalize-space(.), 'Calibrate')]")
            )
        )
        t_click = time.monotonic()
        button.click()
        cmd = commands.get(timeout_s=15.0)
        assert cmd is not None, "no command arrived after clicking Calibrate"
        assert cmd.kind == "calibrate"
        assert time.monotonic() - t_click >= COUNTDOWN_S * 0.9
        assert commands.poll() is None

        # Record: the file name typed in the page goes with record_start; the button
        # follows the loop's published state, then sends record_stop.
        field = driver.find_element(By.XPATH, "//input[@value='take.mcap']")
        field.clear()
        field.send_keys("walk01.mcap")
        t_end = time.monotonic() + 15
        while console._record_name.value != "walk01.mcap" and time.monotonic() < t_end:
            time.sleep(0.05)
        rec = "//button[contains(normalize-space(.), 'Record {}')]"
        driver.find_element(By.XPATH, rec.format("start")).click()
        cmd = commands.get(timeout_s=15.0)
        assert cmd is not None and (cmd.kind, cmd.arg) == (
            "record_start",
            "walk01.mcap",
        )
        recording = slot.begin()
        recording.copy_from(snap_now(slot))
        recording.recording = True
        _commit(slot)
        stop = wait.until(ec.element_to_be_clickable((By.XPATH, rec.format("stop"))))
        stop.click()
        cmd = commands.get(timeout_s=15.0)
        assert cmd is not None and cmd.kind == "record_stop"

        # Face capture under the pose name typed in the page.
        pose = driver.find_element(By.XPATH, "//input[@value='neutral']")
        pose.clear()
        pose.send_keys("jawOpen")
        t_end = time.monotonic() + 15
        while console._face_name.value != "jawOpen" and time.monotonic() < t_end:
            time.sleep(0.05)
        driver.find_element(
            By.XPATH, "//button[contains(normalize-space(.), 'Face capture')]"
        ).click()
        cmd = commands.get(timeout_s=15.0)
        assert cmd is not None and (cmd.kind, cmd.arg) == ("face_capture", "jawOpen")
    finally:
        console.stop()


@pytest.fixture(scope="module")
def solved(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from retargetd.daemon.cli.main import main

    d = tmp_path_factory.mktemp("view")
    take, npz = d / "s.c3d", d / "s.npz"
    assert main(["synth", "--seconds", "3", "--rate", "60", "--out", str(take)]) == 0
    args = ["solve", str(take), "--rig", "menache", "--calibrate-frames", "0:60"]
    assert main([*args, "--out", str(npz)]) == 0
    return take, npz


def test_view_timeline_in_chromium(driver: Any, solved: tuple[Path, Path]) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support import expected_conditions as ec
    from selenium.webdriver.support.ui import WebDriverWait

    from retargetd.daemon.console import Snapshot
    from retargetd.daemon.console.offline import serve_offline

    take, npz = solved
    viewer = serve_offline(npz, take=take, flagged_frames=[30], port=0, block=False)
    try:
        out = Snapshot.for_layout(viewer.slot.layout)

        def shown(want: int, timeout_s: float = 20.0) -> int:
            t_end = time.monotonic() + timeout_s
            while time.monotonic() < t_end:
                if viewer.slot.read(out, 0) > 0 and out.frame == want:
                    break
                time.sleep(0.05)
            return out.frame

        driver.get(viewer.url)
        wait = WebDriverWait(driver, 60)
        thumb = wait.until(
            ec.element_to_be_clickable((By.CSS_SELECTOR, "[role='slider']"))
        )
        assert shown(0) == 0
        thumb.click()
        for _ in range(5):
            thumb.send_keys(Keys.ARROW_RIGHT)
        assert shown(int(viewer.frame.value)) == viewer.frame.value
        assert viewer.frame.value >= 5, "arrow keys on the slider did not scrub"
        with np.load(npz, allow_pickle=False) as z:
            np.testing.assert_array_equal(out.joint_pos, z["joint_centres"][out.frame])
        # Play, through the page: the frame moves on by itself.
        play = driver.find_element(
            By.XPATH,
            "//label[normalize-space(.)='Play']/ancestor::*[.//input][1]//input",
        )
        driver.execute_script("arguments[0].click();", play)
        t_end = time.monotonic() + 20
        while viewer.play.value is not True and time.monotonic() < t_end:
            time.sleep(0.05)
        assert viewer.play.value is True
        start = int(viewer.frame.value)
        time.sleep(1.0)
        assert int(viewer.frame.value) > start
    finally:
        viewer.stop()


def _page_text(driver: Any) -> str:
    from selenium.webdriver.common.by import By

    return str(driver.find_element(By.TAG_NAME, "body").text)


def _wait_client(server: Any, timeout_s: float = 60.0) -> Any:
    """The first client once it has reported its camera."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        client = next(iter(server.get_clients().values()), None)
        if client is not None and client.camera._state.update_timestamp:
            return client
        time.sleep(0.1)
    raise AssertionError("no client reported its camera")


def _shot(driver: Any) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(screenshot (H, W, 3) uint8, canvas offset (2,), canvas width, height)."""
    import matplotlib.image as mpimg
    from selenium.webdriver.common.by import By

    for b in driver.find_elements(
        By.CSS_SELECTOR, "button.mantine-Notification-closeButton"
    ):
        b.click()
    time.sleep(1.0)
    png = driver.get_screenshot_as_png()
    img = (mpimg.imread(io.BytesIO(png), format="png")[..., :3] * 255).astype(np.uint8)
    left, top, w, h = driver.execute_script(
        "const r = document.querySelector('canvas').getBoundingClientRect();"
        "return [r.left, r.top, r.width, r.height];"
    )
    return img, np.array([left, top]), int(w), int(h)


@pytest.mark.timeout(240)
def test_report_flagged_frame_shows_check_and_red_bone(
    driver: Any, solved: tuple[Path, Path]
) -> None:
    """At a frame a validation report flags, the bone its detail names is red and
    the page names the check and its value; at an unflagged frame neither."""
    from retargetd.daemon.console.offline import (
        OfflineViewer,
        load_sequence,
        with_report,
    )

    take, npz = solved
    seq = load_sequence(npz, take=take)
    ends = bone_endpoints(
        seq.layout.skeleton, seq.joint_pos, seq.world_from_bone_quat, seq.root_pos,
        seq.layout.bone_lengths,
    )  # fmt: skip
    length = np.linalg.norm(ends[:, :, 1] - ends[:, :, 0], axis=-1)  # (T, B)
    ok = np.isfinite(length[[10, 33]]).all(axis=0) & ~seq.bone_flags[[10, 33]].any(0)
    bone = int(np.argmax(np.where(ok, length[33], -1.0)))
    name = seq.layout.bone_names[bone]
    # The shape of validate's report.json (validate.checks.CheckResult.summary).
    doc = {"checks": {
        "limits": {
            "threshold": 10.0, "unit": "deg beyond limit", "frames_flagged": 6,
            "worst_frames": [33, 34], "worst_values": [12.3, 11.0],
            "flagged_runs": [[30, 36]],
            "detail": [f"frame 33: {name} swing (12.3 deg beyond)"],
        },
        "floor_penetration": {
            "threshold": 20.0, "unit": "mm", "frames_flagged": 0,
            "worst_frames": [3], "worst_values": [1.0], "flagged_runs": [],
            "detail": [],
        },
    }}  # fmt: skip
    viewer = OfflineViewer(with_report(seq, doc), port=0)
    try:
        viewer.start()
        viewer.console.follow.value = False  # the first view's camera throughout
        driver.get(viewer.url)
        client = _wait_client(viewer.console.server)
        results = {}
        for f in (33, 10):
            viewer.frame.value = f
            t_end = time.monotonic() + 30
            while f"frame {f}," not in _page_text(driver):
                assert time.monotonic() < t_end, _page_text(driver)
                time.sleep(0.1)
            time.sleep(1.5)  # drawn
            img, at, w, h = _shot(driver)
            mid = ends[f, bone].mean(axis=0)
            px = _project(client.camera, mid[None], w, h) + at
            results[f] = (_near(img, px, _red)[0], _near(img, px, _blue)[0])
            text = _page_text(driver)
            if f == 33:
                assert f"limits: {name} 12.3 deg beyond limit" in text, text
            else:
                assert "limits:" not in text, text
        assert results[33][0], f"{name} not red at the flagged frame 33"
        assert not results[10][0] and results[10][1], f"{name} not blue at frame 10"
    finally:
        viewer.stop()


@pytest.mark.timeout(240)
def test_follow_keeps_a_walking_performer_in_view(driver: Any) -> None:
    """The performer walks 8 m across the view: with "Follow performer" on, its
    bones stay on the page; unticked through the page, a further walk leaves it."""
    from selenium.webdriver.common.by import By

    from retargetd.daemon.console.app import Console

    take, layout, _pairs = _performer_layout()
    layout = ConsoleLayout(
        marker_names=(), joint_names=layout.joint_names,
        bone_names=layout.bone_names, bone_parents=layout.bone_parents,
        skeleton=layout.skeleton, bone_lengths=layout.bone_lengths,
    )  # fmt: skip
    slot = SnapshotSlot(layout)
    console = Console(slot, None, port=0)
    pose = take.joint_pos_world[40]
    root = pose[0].copy()

    def publish(dy: float) -> None:
        s = slot.begin()
        s.joint_pos[:] = pose + np.array([0.0, dy, 0.0])
        s.root_pos[:] = root + np.array([0.0, dy, 0.0])
        _commit(slot)

    def walk(a: float, b: float, seconds: float = 3.0) -> None:
        for dy in np.linspace(a, b, int(seconds * 30)):
            publish(float(dy))
            time.sleep(1 / 30)
        time.sleep(2.0)  # the last moves reach the page

    def blue_pixels() -> int:
        # The middle of the canvas, where the view centres the performer: clear of
        # the axes gizmo (bottom left, blue Z) and the GUI panel (top right).
        img, at, w, h = _shot(driver)
        x, y = int(at[0]), int(at[1])
        return int(_blue(img[y : y + h, x + w * 15 // 100 : x + w * 65 // 100]).sum())

    try:
        console.start()
        cam = console.server.initial_camera
        cam.position = root + np.array([4.6, 0.0, 0.2])  # across the walk (+Y)
        cam.look_at = root
        cam.up = (0.0, 0.0, 1.0)
        cam.fov = np.deg2rad(50.0)
        publish(0.0)
        driver.get(console.url)
        client = _wait_client(console.server)
        time.sleep(2.0)
        at_start = blue_pixels()
        assert at_start > 300, f"performer not drawn at the start ({at_start} px)"
        walk(0.0, 8.0)
        followed = blue_pixels()
        moved = np.asarray(client.camera.look_at) - root
        assert followed > 0.5 * at_start, f"walked out of view ({followed} px)"
        assert abs(moved[1] - 8.0) < 0.1 and abs(moved[2]) < 1e-6, moved
        box = driver.find_element(
            By.XPATH,
            "//label[normalize-space(.)='Follow performer']"
            "/ancestor::*[.//input][1]//input",
        )
        driver.execute_script("arguments[0].click();", box)
        t_end = time.monotonic() + 20
        while console.follow.value and time.monotonic() < t_end:
            time.sleep(0.05)
        assert console.follow.value is False
        walk(8.0, 16.0)
        left = blue_pixels()
        print(f"\nfollow: bone pixels {at_start} at start, {followed} after 8 m")
        print(f"follow: {left} after 8 m more with follow off")
        assert left < 0.02 * at_start, f"still in view with follow off ({left} px)"
    finally:
        console.stop()
