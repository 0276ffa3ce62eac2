"""Constants and helpers of the browser tests (tests/web): paths, Chromium, blank checks."""

from __future__ import annotations

import io
import json
import os
import shutil
from pathlib import Path

import pytest

from tests.helpers import REPO

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


def worker_wrapper(prelude: str, *, page_setup: str = "", late: bool = False,
                   url_suffix: str = "''") -> str:
    """An init script that starts the page's workers through a wrapper module that runs
    ``prelude`` (module code) beside the page's own worker module.

    The wrapper resolves the worker's root-relative fetches against the page's origin (a
    worker started from a ``blob:`` URL has no base for "/v1/..."). By default the page's
    module is a static import of the wrapper: it is evaluated (its message handler
    installed) and ``prelude`` runs before the first message is delivered, as with the real
    worker (the page's module only looks ``fetch`` up when it handles a call, so it sees the
    patched one). ``late=True`` runs ``prelude`` first (it may ``await``) and imports the
    page's module afterwards: messages that arrive meanwhile find no handler, which is the
    window a late-starting worker opens. ``page_setup`` runs in the page with ``worker`` (the
    new Worker) in scope; ``url_suffix`` is a JavaScript expression appended to the wrapper's
    URL when a worker starts (a ``#fragment`` that ``prelude`` can read from
    ``import.meta.url``).
    """
    origin_fix = """
      const realFetch = self.fetch.bind(self);
      self.fetch = (input, init) => realFetch(
        typeof input === "string" && input.startsWith("/") ? self.origin + input : input, init);
    """
    return f"""
(() => {{
  const prelude = {json.dumps(origin_fix + prelude)};
  const late = {json.dumps(late)};
  const RealWorker = window.Worker;
  window.Worker = function (url, options) {{
    const target = JSON.stringify(new URL(url, location.href).href);
    const source = late ? `${{prelude}}\nawait import(${{target}});`
      : `import ${{target}};\n${{prelude}}`;
    const blob = new Blob([source], {{ type: "text/javascript" }});
    const worker = new RealWorker(URL.createObjectURL(blob) + ({url_suffix}),
      {{ ...options, type: "module" }});
    {page_setup}
    return worker;
  }};
}})();
"""


def rigid_align(moving, target):
    """``moving`` (n, 3) moved by the rotation and translation that best fit it onto
    ``target`` (n, 3) in the least-squares sense (Kabsch, no reflection): the independent
    check of the page's alignment of a rebuilt mesh."""
    import numpy as np

    moving, target = np.asarray(moving, float), np.asarray(target, float)
    a, b = moving - moving.mean(axis=0), target - target.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    rotation = u @ np.diag([1.0, 1.0, d]) @ vt  # row vectors: x @ rotation
    return a @ rotation + target.mean(axis=0)
