"""The solver of another commit, imported beside the working tree's for paired timings.

On a shared machine the load changes between two runs more than many changes change the
speed; timing the old and the new code alternately in one process compares them under the
same load. :func:`solver_at` extracts ``solver/`` of a git revision (``git archive``) into a
temporary folder as the package ``solver_<sha>`` (every import inside ``solver`` is
relative, so the copy imports its own modules) and imports it.
"""

from __future__ import annotations

import atexit
import importlib
import io
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from types import ModuleType

from bench.common import REPO


def solver_at(revision: str) -> ModuleType:
    """``solver`` as of git ``revision`` (a commit, branch or tag of this repository),
    imported as ``solver_<12 hex digits>``; the temporary copy is removed at exit.

    Raises:
        subprocess.CalledProcessError: an unknown revision.
    """
    sha = subprocess.run(["git", "rev-parse", "--short=12", f"{revision}^{{commit}}"],
                         cwd=REPO, check=True, capture_output=True, text=True).stdout.strip()
    name = f"solver_{sha}"
    if name in sys.modules:
        return sys.modules[name]
    archive = subprocess.run(["git", "archive", sha, "solver"], cwd=REPO, check=True,
                             capture_output=True).stdout
    root = Path(tempfile.mkdtemp(prefix="bench-baseline-"))
    atexit.register(shutil.rmtree, root, ignore_errors=True)
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(root, filter="data")
    (root / "solver").rename(root / name)
    sys.path.insert(0, str(root))
    return importlib.import_module(name)
