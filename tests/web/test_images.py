"""The page's slope-error map: oriented as the facet (+x right, +y up), coloured by the report's scale."""

import io

import cv2
import numpy as np

from sofast_station.web.images import _MAP_BOX_PX, MAP_SIZE_PX, map_png


def _picture(high):
    """A picture file's arrays for a 200 x 200 px camera seeing a 0.2 m square facet, one camera pixel in
    2 kept; *high(x, y)* marks where the design residual is 1 mrad (elsewhere 0.1 mrad), along x."""
    rows, cols = np.meshgrid(np.arange(0, 200, 2), np.arange(0, 200, 2), indexing="ij")
    rows, cols = rows.ravel(), cols.ravel()
    x = cols * 0.001 - 0.1                 # camera columns run along facet +x
    y = 0.1 - rows * 0.001                 # camera rows run down, facet +y up
    e = np.where(high(x, y), 1.0, 0.1)
    res = np.vstack([e, np.zeros_like(e)]).astype(np.float32)
    buf = io.BytesIO()
    np.savez(buf, white=np.zeros((100, 100), np.uint8), step_px=np.int32(2), crop_box=np.array([0, 0, 200, 200]),
             map_step_px=np.int32(2), map_rows=rows, map_cols=cols,
             map_points_xy_m=np.vstack([x, y]).astype(np.float32), corners_px=np.zeros((4, 2)),
             camera_shape=np.array([200, 200]),
             **{f"map_residuals_{m}": res for m in ("design", "parabola", "higher_order")})
    buf.seek(0)
    return np.load(buf)


def _quadrant_colours(png):
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape[1::-1] == MAP_SIZE_PX
    bx, by, bw, bh = _MAP_BOX_PX
    out = {}
    for name, fx, fy in (("upper left", 0.25, 0.25), ("upper right", 0.75, 0.25), ("lower left", 0.25, 0.75),
                         ("lower right", 0.75, 0.75)):
        cx, cy = int(bx + fx * bw), int(by + fy * bh)
        patch = img[cy - 12:cy + 12, cx - 12:cx + 12].reshape(-1, 3)
        out[name] = np.median(patch, axis=0)          # the arrows drawn over the map do not move a median
    return out


def test_map_shows_the_high_error_where_it_is_on_the_facet():
    # viridis: the top of the scale is yellow (BGR blue low, red and green high), the bottom dark violet
    for corner, high in (("upper left", lambda x, y: (x < 0) & (y > 0)),
                         ("lower right", lambda x, y: (x > 0) & (y < 0))):
        with _picture(high) as pic:
            colours = _quadrant_colours(map_png(pic))
        for name, bgr in colours.items():
            yellow = bgr[2] > 180 and bgr[1] > 180 and bgr[0] < 120
            assert yellow == (name == corner), (corner, name, bgr)


def test_map_needs_per_pixel_results():
    buf = io.BytesIO()
    np.savez(buf, white=np.zeros((10, 10), np.uint8))
    buf.seek(0)
    with np.load(buf) as pic:
        assert map_png(pic) is None
