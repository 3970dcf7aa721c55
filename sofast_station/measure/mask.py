"""The active-pixel mask: the facet region that reflects the screen.

docs/conventions.md#measurement-sequence, step 1.
"""

from __future__ import annotations

import cv2
import numpy as np


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
    wide = np.int16 if white.dtype == np.uint8 else np.int64       # no overflow for 16-bit counts
    responsive = (white.astype(wide) - dark.astype(wide)) > threshold_dn
    n, labels, stats, _ = cv2.connectedComponentsWithStats(responsive.view(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros(responsive.shape, dtype=bool)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    region = labels == largest
    # Holes: connected unresponsive areas that do not touch the image border.
    n_h, labels_h, stats_h, _ = cv2.connectedComponentsWithStats((~region).view(np.uint8), connectivity=4)
    h, w = region.shape
    x, y, bw, bh, area = (stats_h[:, k] for k in range(5))
    touches_border = (x == 0) | (y == 0) | (x + bw == w) | (y + bh == h)
    fill = ~touches_border & (area <= max_hole_px)
    fill[0] = False
    region |= fill[labels_h]
    return region
