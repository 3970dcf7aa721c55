"""What every report shares: the atomic write of a picture (its error, ReportError, is in errors.py)."""

from __future__ import annotations

import os
from pathlib import Path

from ..files import temp_path_for


def savefig_atomic(fig, path: Path, dpi: int, fmt: str = "png") -> Path:
    """Write a Matplotlib figure to a temporary file beside *path* and rename it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path_for(path)
    try:
        fig.savefig(tmp, format=fmt, dpi=dpi)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path
