"""What every report shares: its error and the atomic PNG write."""

from __future__ import annotations

import os
from pathlib import Path

from ..archive._common import temp_path_for
from ..errors import StationError


class ReportError(StationError):
    """A picture cannot be made: no analysis (the capture was refused), or no data in the period."""


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
