"""Constants and helpers of the browser tests (tests/web): paths, Chromium, blank checks."""

from __future__ import annotations

import io
import os
import shutil
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
ARTIFACTS = REPO / "tests" / "artifacts" / "web"
VENDOR_MANIFEST = REPO / "service" / "static" / "vendor" / "three" / "manifest.json"
CHROMIUM_ARGS = [
    "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run",
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--disable-dev-shm-usage", "--hide-scrollbars", "--force-color-profile=srgb",
]
VIEWPORT = {"width": 1400, "height": 900}
SMALL_VIEWPORT = {"width": 1280, "height": 720}


def chromium_path() -> str:
    """``FFS_CHROMIUM``, else chromium on PATH, else /usr/bin/chromium (must exist)."""
    candidates = [os.environ.get("FFS_CHROMIUM"), shutil.which("chromium"),
                  shutil.which("chromium-browser"), "/usr/bin/chromium"]
    for path in candidates:
        if path and Path(path).is_file():
            return path
    pytest.fail("Chromium not found: install Debian's package (apt-get install -y chromium; "
                "scripts/test.sh does it as root) or set FFS_CHROMIUM")


def assert_not_blank(png: bytes, *, min_colors: int = 64, min_colored: float = 0.03) -> None:
    """A screenshot that shows something: many colours, and at least ``min_colored`` of its
    pixels saturated (the mesh's colour map, not the grey background and panels)."""
    import numpy as np
    from PIL import Image

    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)
    pixels = image.reshape(-1, 3)
    distinct = len(np.unique(pixels[:: max(1, len(pixels) // 200_000)], axis=0))
    assert distinct >= min_colors, f"only {distinct} colours: the image looks blank"
    saturated = float(((pixels.max(axis=1) - pixels.min(axis=1)) > 40).mean())
    assert saturated >= min_colored, f"only {saturated:.1%} coloured pixels"
