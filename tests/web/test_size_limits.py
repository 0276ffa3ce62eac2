"""The page shows the service's size limits (GET /v1/me) and refuses a file over the body
limit before sending it, in Debian's Chromium against a real uvicorn started with a small
``FFS_MAX_BODY_BYTES``; a mesh over the limit of the operations that solve is flagged."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest

from tests.helpers import DATA
from tests.helpers.servers import uvicorn_server
from tests.web.conftest import VENDOR_MANIFEST

BODY_LIMIT = 300_000


@pytest.fixture(scope="module")
def web_server() -> Iterator[str]:
    """This module's server (the ``web`` fixture's page opens it): bodies up to 300 KB."""
    if not VENDOR_MANIFEST.is_file():
        pytest.fail("the page's three.js modules are not built: run `npm ci --prefix web`")
    with uvicorn_server({"FFS_MAX_BODY_BYTES": str(BODY_LIMIT)}) as base:
        yield base


def test_the_page_shows_the_limits_and_refuses_a_file_over_them(web, tmp_path):
    limits = httpx.get(f"{web.base}/v1/me", timeout=30).json()["size_limits"]
    assert limits["max_body_bytes"] == BODY_LIMIT
    web.open("sample=decimated-knight.off")
    assert web.app("app.state.sizeLimits") == limits
    line = web.page.locator("#service-limits")
    assert f"up to {limits['max_faces']:,} faces" in line.inner_text()
    assert "files up to 293 KB" in line.inner_text()            # 300,000 bytes, rounded up
    assert "over the limit" not in line.inner_text()

    # A file over the limit: refused on the page, named, with the setting; nothing opened.
    big = tmp_path / "big.off"
    text = (DATA / "decimated-knight.off").read_text()
    big.write_text(text + "#" * (BODY_LIMIT - len(text) + 1000) + "\n")
    web.page.set_input_files("#mesh-file", str(big))
    web.wait_for("window.app.state.errors.length > 0", what="the refusal")
    [error] = web.shown_errors()
    assert error["title"] == "413 File too large", error
    assert "big.off" in error["detail"] and "FFS_MAX_BODY_BYTES" in error["detail"], error
    assert web.app("app.state.name") == "decimated-knight.off"

    # The same limits with a solve limit under the mesh's 1000 faces: flagged.
    tight = dict(limits, max_faces_by_operation=dict(limits["max_faces_by_operation"],
                                                     reconstruct=500))
    web.app("app.setSizeLimits(arg)", tight)
    flagged = web.page.locator("#service-limits.over-limit")
    assert flagged.count() == 1
    linear = limits["max_linear_faces_by_operation"]["reconstruct"]
    assert f"(500 to rebuild, {linear:,} for a linear answer" in flagged.inner_text()
    assert "over the limit to rebuild refined" in flagged.inner_text()
