"""A real headless Chromium for the console tests (selenium + Debian's chromium and
chromium-driver), and the pixel tests that read its screenshots. Skipped (outside CI
only) when chromium or its driver is absent; in CI nothing skips."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from paths import IN_CI

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
WIDTH, HEIGHT = 1000, 640


def _require_chromium() -> None:
    missing = [p for p in (CHROMIUM, CHROMEDRIVER) if not Path(p).exists()]
    if missing:
        reason = f"chromium / chromium-driver not installed ({', '.join(missing)})"
        if IN_CI:
            pytest.fail(f"{reason} (CI=true: nothing may skip)")
        pytest.skip(reason)


@pytest.fixture
def driver() -> Iterator[Any]:
    _require_chromium()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in (
        "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
        "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync",
        "--enable-unsafe-swiftshader", f"--window-size={WIDTH},{HEIGHT}",
    ):  # fmt: skip
        opts.add_argument(flag)
    profile = tempfile.mkdtemp(prefix="retargetd-chromium-")
    opts.add_argument(f"--user-data-dir={profile}")
    d = webdriver.Chrome(options=opts, service=Service(CHROMEDRIVER))
    d.set_page_load_timeout(30)
    try:
        yield d
    finally:
        d.quit()
        shutil.rmtree(profile, ignore_errors=True)


def _project(cam: Any, pts: np.ndarray, w: int, h: int) -> np.ndarray:
    """Pinhole projection of world points (N, 3) to pixels (N, 2) with the client's
    camera (vertical fov, position, look-at, up)."""
    pos, look = np.asarray(cam.position), np.asarray(cam.look_at)
    fwd = (look - pos) / np.linalg.norm(look - pos)
    right = np.cross(fwd, np.asarray(cam.up_direction))
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    rel = pts - pos
    z = rel @ fwd
    f = (h / 2) / np.tan(cam.fov / 2)
    return np.stack([w / 2 + f * (rel @ right) / z, h / 2 - f * (rel @ up) / z], -1)


def _near(img: np.ndarray, px: np.ndarray, test: Any, r: int = 3) -> np.ndarray:
    """For each pixel position, whether any pixel within r satisfies ``test``."""
    out = np.zeros(len(px), bool)
    for i, (x, y) in enumerate(np.rint(px).astype(int)):
        patch = img[max(y - r, 0) : y + r + 1, max(x - r, 0) : x + r + 1]
        out[i] = patch.size > 0 and bool(test(patch).any())
    return out


def _blue(p: np.ndarray) -> np.ndarray:
    r, g, b = (p[..., i].astype(int) for i in range(3))
    return (b > r + 50) & (b > g + 25)


def _green(p: np.ndarray) -> np.ndarray:
    r, g, b = (p[..., i].astype(int) for i in range(3))
    return (g > r + 50) & (g > b + 30)


def _red(p: np.ndarray) -> np.ndarray:
    r, g, b = (p[..., i].astype(int) for i in range(3))
    return (r > g + 80) & (r > b + 80)
