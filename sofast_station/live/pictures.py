"""Small per-facet pictures for the operator's page: ``data_dir/live/facets/<cycle_id>.npz``.

Right after a facet's answer, the station keeps what the page needs to show it and nothing stores
cheaply elsewhere (dumps exist only for some facets): the camera's white frame around the facet, shrunk to
at most :data:`THUMB_PX` pixels across; the analysis's valid-pixel mask at the same scale (its outline is
the facet the station found) and the corners it found; and a thinned copy of the per-pixel slope errors
(from the analysis worker), from which the monitor draws the slope-error map. Each file is a few hundred
kB, written uncompressed under a temporary name and renamed; the newest ``keep`` files are kept.

The file name is the cycle id the station made, never the facet's serial.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np

from ..files import write_file_atomic

log = logging.getLogger(__name__)

THUMB_PX = 320
#: What a cycle id looks like (station/runner.py: new_cycle_id); anything else is never a file name.
CYCLE_ID = re.compile(r"^[0-9]{8}T[0-9]{6,12}Z?-[0-9a-f]{8}$")


def pictures_dir(data_dir: str | Path) -> Path:
    return Path(data_dir) / "live" / "facets"


def picture_path(data_dir: str | Path, cycle_id: str) -> Path | None:
    """The picture file of *cycle_id*, or None when *cycle_id* is not a cycle id."""
    if not isinstance(cycle_id, str) or not CYCLE_ID.match(cycle_id):
        return None
    return pictures_dir(data_dir) / f"{cycle_id}.npz"


class FacetPictures:
    """The runner hook that writes each facet's picture file and prunes old ones.

    Parameters
    ----------
    data_dir : Path
    keep : int
        How many picture files to keep (the newest).
    """

    def __init__(self, data_dir: str | Path, keep: int = 200):
        self.folder = pictures_dir(data_dir)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.keep = int(keep)
        self._written = 0

    def __call__(self, outcome) -> Path | None:
        path = picture_path(self.folder.parents[1], outcome.cycle_id)
        if path is None or outcome.frames is None:
            return None
        arrays = self._arrays(outcome)
        write_file_atomic(path, lambda fh: np.savez(fh, **arrays))   # nothing left behind on a full disk
        self._written += 1
        if self._written % 20 == 1:
            self.prune()
        return path

    @staticmethod
    def _arrays(outcome) -> dict:
        frames = outcome.frames                      # cropped: (n, h, w), frame 1 the white frame
        box = outcome.record.get("crop_box")         # (row0, col0, row1, col1) in camera pixels, end-exclusive
        white = frames[1] if len(frames) > 1 else frames[0]    # a fixed pattern's one frame: the dots
        step = max(1, int(np.ceil(max(white.shape) / THUMB_PX)))
        out = {"white": np.ascontiguousarray(white[::step, ::step]), "step_px": np.int32(step),
               "crop_box": np.asarray(box if box is not None else [0, 0, *white.shape],
                                      dtype=np.int64)}
        if outcome.valid is not None and box is not None:
            r0, c0, r1, c1 = (int(v) for v in box)
            out["mask"] = np.ascontiguousarray(outcome.valid[r0:r1:step, c0:c1:step]).astype(np.uint8)
        p = outcome.preview
        if p:
            out.update({"map_step_px": np.int32(p["step_px"]), "map_rows": p["rows"], "map_cols": p["cols"],
                        "map_points_xy_m": p["points_xy_m"], "corners_px": p["corners_px"]})
            for model, e in p["residuals_mrad"].items():
                out[f"map_residuals_{model}"] = e
            out["camera_shape"] = np.asarray(outcome.valid.shape if outcome.valid is not None else (0, 0))
        return out

    def prune(self) -> None:
        """Delete all but the newest ``keep`` picture files."""
        try:
            files = sorted(e.name for e in os.scandir(self.folder) if e.name.endswith(".npz"))
        except FileNotFoundError:
            return
        for name in files[:-self.keep] if self.keep > 0 else files:
            (self.folder / name).unlink(missing_ok=True)
