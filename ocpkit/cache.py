"""Where ocpkit keeps generated files: ``$OCPKIT_CACHE_DIR`` or ``$XDG_CACHE_HOME/ocpkit`` (~/.cache/ocpkit)."""
from __future__ import annotations

import os
from pathlib import Path


def cache_dir(kind: str) -> Path:
    """The cache folder for one kind of generated file ("taichi" kernels, "compiled" C functions)."""
    root = os.environ.get("OCPKIT_CACHE_DIR")
    if not root:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        root = os.path.join(base, "ocpkit")
    return Path(root) / kind
