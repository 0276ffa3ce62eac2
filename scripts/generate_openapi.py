"""Write the service's OpenAPI document to openapi/openapi.json (sorted keys, indent 2).

Usage: ``python scripts/generate_openapi.py [--check]``. With ``--check`` nothing is written;
the exit status is 1 when the file is stale. tests/service/test_openapi.py runs the check.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TARGET = REPO / "openapi" / "openapi.json"


def render() -> str:
    """The OpenAPI document as text (independent of the FFS_* environment)."""
    sys.path.insert(0, str(REPO))
    from service.app import create_app
    from service.settings import Settings

    app = create_app(Settings(workers=1))
    return json.dumps(app.openapi(), indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--check", action="store_true", help="fail if the file is stale")
    args = parser.parse_args(argv)
    text = render()
    if args.check:
        current = TARGET.read_text(encoding="utf-8") if TARGET.exists() else ""
        if current != text:
            print(f"{TARGET.relative_to(REPO)} is stale: run python scripts/generate_openapi.py")
            return 1
        return 0
    TARGET.parent.mkdir(parents=True, exist_ok=True)
    TARGET.write_text(text, encoding="utf-8")
    print(f"wrote {TARGET.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
