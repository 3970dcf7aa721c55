"""The pictures people look at: the photo with the corners found, the heliostat's normal, each facet's canting.

Drawn with OpenCV on the photo itself (a copy), so what was found sits on what was photographed: each
facet's outline through its corners (green; a facet left out has its predicted outline dashed in red with
its reason's first words), the measured normal (orange) and the commanded one (white) as arrows from the
heliostat's middle, or each facet's canting as an arrow the way its normal leans (magnified; red when
flagged against the factory record or beyond the limit), and the figures in a band at the top.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

GREEN, RED, ORANGE, WHITE, YELLOW = (60, 220, 60), (60, 60, 235), (0, 150, 255), (255, 255, 255), (0, 230, 255)


def _canvas(image: np.ndarray) -> np.ndarray:
    """An 8-bit BGR copy of the photo, its width at least 900 px (small photos are enlarged)."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = np.clip(img.astype(np.float64) * 255.0 / max(float(img.max()), 1.0), 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    else:
        img = np.ascontiguousarray(img[..., ::-1])
    return img.copy()


def _scale(img: np.ndarray) -> tuple[np.ndarray, float]:
    s = max(1.0, 900.0 / img.shape[1])
    if s > 1.0:
        img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_LINEAR)
    return img, s


def _pt(p, s: float) -> tuple[int, int]:
    return int(round((p[0] + 0.5) * s - 0.5)), int(round((p[1] + 0.5) * s - 0.5))


def _outline(img, corners, s, colour, thickness=1, dashed=False):
    n = len(corners)
    for i in range(n):
        a, b = np.asarray(corners[i], float), np.asarray(corners[(i + 1) % n], float)
        if dashed:
            for t in np.arange(0.0, 1.0, 0.1):
                cv2.line(img, _pt(a + (b - a) * t, s), _pt(a + (b - a) * (t + 0.05), s), colour, thickness,
                         cv2.LINE_AA)
        else:
            cv2.line(img, _pt(a, s), _pt(b, s), colour, thickness, cv2.LINE_AA)
    for c in corners:
        cv2.circle(img, _pt(c, s), 2, colour, -1, cv2.LINE_AA)


def _band(img, lines: list) -> np.ndarray:
    h = 22 * len(lines) + 10
    band = np.zeros((h, img.shape[1], 3), np.uint8)
    for i, text in enumerate(lines):
        cv2.putText(band, text, (8, 22 + 22 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.55, WHITE, 1, cv2.LINE_AA)
    return np.vstack([band, img])


def _write(path, img) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img):
        from ..errors import ReportError
        raise ReportError(f"the picture {path} could not be written")
    return path


def _left_out(img, predicted: dict, detection, s: float) -> None:
    predicted = detection.placed_px or predicted          # where the layout's map puts them, if it was found
    for label, why in detection.left_out.items():
        if label in predicted:
            _outline(img, predicted[label], s, RED, 1, dashed=True)
            c = np.asarray(predicted[label], float).mean(axis=0)
            cv2.putText(img, f"{label}: {why.split('(')[0].strip()[:22]}", _pt(c - [30, 0], s),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.4, RED, 1, cv2.LINE_AA)


def orientation_png(path, image: np.ndarray, detection, figures: dict, arrows_px: dict, predicted: dict,
                    title: str) -> Path:
    """The photo with each facet's corners, and the measured and commanded normals as arrows.

    *arrows_px* maps ``measured`` (and ``commanded``) to a pair of photo pixels (from, to): the normal drawn
    from the heliostat's middle, its length the heliostat's size.
    """
    img, s = _scale(_canvas(image))
    for f in detection.facets.values():
        _outline(img, f.corners_px, s, GREEN)
    _left_out(img, predicted, detection, s)
    for name, colour in (("commanded", WHITE), ("measured", ORANGE)):
        if name in arrows_px:
            a, b = arrows_px[name]
            cv2.arrowedLine(img, _pt(a, s), _pt(b, s), colour, 2, cv2.LINE_AA, tipLength=0.08)
    lines = [title,
             f"normal: azimuth {figures['azimuth_deg']:.3f} +- {figures['azimuth_deg_U']:.3f} deg, elevation "
             f"{figures['elevation_deg']:.3f} +- {figures['elevation_deg_U']:.3f} deg (U, k=2)",
             f"{figures['facets_used']} facets (green), corners' reprojection {figures['reprojection_rms_px']:.2f} px"]
    if "tracking_error_mrad" in figures:
        t, u = figures["tracking_error_mrad"], figures["tracking_error_mrad_U"]
        lines.append(f"tracking error {t['angle']:.2f} +- {u['angle']:.2f} mrad (azimuth {t['azimuth']:+.2f} +- "
                     f"{u['azimuth']:.2f}, elevation {t['elevation']:+.2f} +- {u['elevation']:.2f})")
        lines.append("arrows: the normal measured (orange) and commanded (white)")
    return _write(path, _band(img, lines))


def canting_png(path, image: np.ndarray, detection, figures: dict, comparison: dict | None, predicted: dict,
                title: str, mrad_px: float | None = None) -> Path:
    """The first photo with each facet's corners and its canting error as an arrow the way its normal leans
    (``(ry, -rx)`` in its own frame, magnified), with ``x, y`` in mrad beside it; a flagged facet is red."""
    img, s = _scale(_canvas(image))
    canting = {f["label"]: f for f in figures["facets"]}
    flagged = set((comparison or {}).get("flagged", []))
    sizes = [math.hypot(f["canting_mrad"]["x"], f["canting_mrad"]["y"]) for f in figures["facets"]]
    for label, f in detection.facets.items():
        colour = RED if label in flagged else GREEN
        _outline(img, f.corners_px, s, colour)
        if label not in canting:
            continue
        c = canting[label]["canting_mrad"]
        corners = np.asarray(f.corners_px, float)
        centre = corners.mean(axis=0)
        # the facet's own x and y directions in the photo (corner order of a rectangle: +x-y, +x+y, -x+y, -x-y)
        if len(corners) == 4:
            ex = 0.5 * (corners[0] + corners[1] - corners[2] - corners[3])
            ey = 0.5 * (corners[1] + corners[2] - corners[0] - corners[3])
        else:
            ex, ey = np.array([1.0, 0.0]), np.array([0.0, -1.0])
        size = float(np.hypot(*ex))
        ux, uy = ex / max(size, 1e-9), ey / max(float(np.hypot(*ey)), 1e-9)
        per_mrad = mrad_px or 0.45 * size / max(max(sizes), 1.0)        # pixels per mrad
        tip = centre + per_mrad * (c["y"] * ux - c["x"] * uy)          # its normal leans towards (ry, -rx)
        cv2.arrowedLine(img, _pt(centre, s), _pt(tip, s), RED if label in flagged else YELLOW, 2, cv2.LINE_AA,
                        tipLength=0.2)
        cv2.putText(img, f"{label} {c['x']:+.1f},{c['y']:+.1f}", _pt(centre + 0.25 * ey - 0.45 * ex, s),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.35, WHITE, 1, cv2.LINE_AA)
    _left_out(img, predicted, detection, s)
    lines = [title, f"canting error RMS {figures['canting_rms_mrad']:.2f} mrad, largest "
                    f"{figures['canting_max_mrad']:.2f} mrad ({figures['canting_max_facet']})",
             "arrows: where each facet's normal leans, magnified (x, y in mrad)"]
    if comparison is not None and comparison.get("facets"):
        lines.append(f"against the factory record ({comparison.get('serial')}): "
                     + (f"flagged {', '.join(comparison['flagged'])} (red)" if comparison["flagged"]
                        else "no facet beyond the combined U"))
    return _write(path, _band(img, lines))
