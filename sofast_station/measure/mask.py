"""The active-pixel mask: the facet region that reflects the screen.

docs/conventions.md#measurement-sequence, step 1.
"""

from __future__ import annotations

import cv2
import numpy as np

from .kernels import fill_holes, label_areas


def facet_region(dark: np.ndarray, white: np.ndarray, threshold_dn: float,
                 max_hole_px: int = 2000) -> np.ndarray:
    """The facet's region in the image: the largest connected set of responsive pixels, small holes filled.

    Parameters
    ----------
    dark, white : (H, W) arrays
        Frames taken with the screen dark (command 0) and white (command 255), DN.
    threshold_dn : float
        A pixel is responsive when white - dark exceeds this, DN.
    max_hole_px : int
        Enclosed unresponsive areas up to this many pixels (dust, a scratch) belong to the region;
        larger ones (a label on the facet) stay out.

    Returns
    -------
    (H, W) bool array
        Empty when nothing responds.
    """
    if white.dtype == dark.dtype and white.dtype in (np.uint8, np.uint16) and threshold_dn >= 0:
        # white - dark clipped at zero (OpenCV, one pass in the counts' own type) against the threshold's
        # whole part: for integer differences and a threshold >= 0, d > t exactly when max(d, 0) > floor(t).
        whole = min(int(np.floor(threshold_dn)), int(np.iinfo(white.dtype).max))
        responsive = np.greater(cv2.subtract(white, dark), whole)
    else:
        wide = np.int16 if white.dtype == np.uint8 else np.int64       # no overflow for 16-bit counts
        responsive = (white.astype(wide) - dark.astype(wide)) > threshold_dn
    # The labelling without OpenCV's statistics (they cost four times the labelling itself): the areas
    # by one compiled count, the box from the region's rows and columns.
    n, labels = cv2.connectedComponents(responsive.view(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros(responsive.shape, dtype=bool)
    largest = 1 + int(np.argmax(label_areas(labels, n)[1:]))
    region = labels == largest
    # Holes: connected unresponsive areas that do not touch the image border. They lie inside the region's
    # bounding box, and an unresponsive area of the box that touches the box's edge reaches the border
    # through the unresponsive pixels around the box (4-connected): so the holes are the box's own
    # unresponsive areas that do not touch the box's edge (the same pixels as over the whole image, for
    # less than half the labelling).
    rows, cols = np.flatnonzero(region.any(axis=1)), np.flatnonzero(region.any(axis=0))
    c0, r0 = int(cols[0]), int(rows[0])
    bw0, bh0 = int(cols[-1]) - c0 + 1, int(rows[-1]) - r0 + 1
    box = region[r0:r0 + bh0, c0:c0 + bw0]
    # (the labelling alone, the holes' areas and whether they touch the box's edge by one compiled pass:
    # OpenCV's statistics cost three times the labelling)
    n_h, labels_h = cv2.connectedComponents((~box).view(np.uint8), connectivity=4)
    fill_holes(labels_h, n_h, max_hole_px, box)
    return region
