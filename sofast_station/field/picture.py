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

from ..errors import ReportError

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


def _panel(values: np.ndarray, extent_m: tuple, size: int, colour_map: int | None) -> tuple[np.ndarray, callable]:
    """*values* (row 0 at the lowest y) drawn *size* pixels square with the highest y on top, and the map from
    target metres (x, y) to the panel's pixels."""
    x0, x1, y0, y1 = extent_m
    v = np.asarray(values, dtype=np.float64)[::-1]
    top = float(np.percentile(v, 99.9)) if np.any(v > 0) else 1.0
    grey = np.clip(255.0 * v / max(top, 1e-12), 0, 255).astype(np.uint8)
    grey = cv2.resize(grey, (size, size), interpolation=cv2.INTER_AREA)
    img = cv2.applyColorMap(grey, colour_map) if colour_map is not None else cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)

    def to_px(x: float, y: float) -> tuple[int, int]:
        return int(round((x - x0) / (x1 - x0) * size)), int(round((y1 - y) / (y1 - y0) * size))
    return img, to_px


def _mark(img, to_px, fig: dict, colour, size: int) -> None:
    c = fig["centroid_m"]
    cx, cy = to_px(c["x"], c["y"])
    cv2.drawMarker(img, (cx, cy), colour, cv2.MARKER_CROSS, 18, 2, cv2.LINE_AA)
    r_px = abs(to_px(c["x"] + fig["spot_radius_m"], c["y"])[0] - cx)
    cv2.circle(img, (cx, cy), max(r_px, 1), colour, 1, cv2.LINE_AA)


def spot_png(path, predicted: dict, photo: dict | None, title: str, lines: list) -> Path:
    """The predicted spot (its flux map) and, when given, the photographed one side by side on the same
    scale: each with its centroid (cross) and its 90 % circle; the other's centroid in white on each.

    *predicted*: :func:`~.spot.predict_spot`'s dict; *photo*: ``{"image": (H, W) array of the background-
    subtracted photo, "extent_m": (x0, x1, y0, y1), "figures": ...}``."""
    size = 520
    hw = predicted["origin_m"][0]
    n = predicted["flux_w_m2"].shape[0]
    ext = (hw, hw + n * predicted["cell_m"], hw, hw + n * predicted["cell_m"])
    left, to_px = _panel(predicted["flux_w_m2"], ext, size, cv2.COLORMAP_INFERNO)
    _mark(left, to_px, predicted["figures"], GREEN, size)
    panels = [left]
    labels = ["predicted from the factory record"]
    if photo is not None:
        # the photo resampled onto the prediction's extent
        img = np.asarray(photo["image"], dtype=np.float64)
        px0, px1, py0, py1 = photo["extent_m"]
        h, w = img.shape
        xs = np.linspace(ext[0], ext[1], size)
        ys = np.linspace(ext[3], ext[2], size)
        cols = np.clip(((xs - px0) / (px1 - px0) * w).astype(int), -1, w)
        rows = np.clip(((py1 - ys) / (py1 - py0) * h).astype(int), -1, h)
        grid = np.zeros((size, size))
        ok_c, ok_r = (cols >= 0) & (cols < w), (rows >= 0) & (rows < h)
        grid[np.ix_(ok_r, ok_c)] = img[np.ix_(rows[ok_r], cols[ok_c])]
        right, _ = _panel(grid[::-1], ext, size, cv2.COLORMAP_INFERNO)
        _mark(right, to_px, photo["figures"], ORANGE, size)
        pc = predicted["figures"]["centroid_m"]
        cv2.drawMarker(right, to_px(pc["x"], pc["y"]), WHITE, cv2.MARKER_TILTED_CROSS, 12, 1, cv2.LINE_AA)
        oc = photo["figures"]["centroid_m"]
        cv2.drawMarker(left, to_px(oc["x"], oc["y"]), WHITE, cv2.MARKER_TILTED_CROSS, 12, 1, cv2.LINE_AA)
        panels.append(right)
        labels.append("photographed (BCS)")
    for img, text in zip(panels, labels):
        cv2.putText(img, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, WHITE, 1, cv2.LINE_AA)
        cv2.putText(img, f"{ext[1] - ext[0]:.2f} m wide; cross: centroid, circle: 90 % of the power",
                    (8, size - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.42, WHITE, 1, cv2.LINE_AA)
    gap = np.zeros((size, 6, 3), np.uint8)
    body = panels[0] if len(panels) == 1 else np.hstack([panels[0], gap, panels[1]])
    return _write(path, _band(body, [title, *lines]))


def hazard_chart(path, points: list, reference: dict, title: str, note: str) -> Path:
    """The glare chart: retinal irradiance (W/cm^2) against the subtended source angle (mrad), log-log, each
    observer's point labelled, the sun seen directly as a reference (``points``: dicts of ``name``,
    ``omega_rad``, ``retinal_w_m2``; those without glare are listed below the plot)."""
    # lazy: Matplotlib, ~530 ms CPU; the other pictures here are drawn with OpenCV
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.0, 6.0), dpi=110)
    ax = fig.add_subplot(1, 1, 1)
    seen = [p for p in points if p.get("omega_rad")]
    for p in seen:
        x, y = 1e3 * p["omega_rad"], 1e-4 * p["retinal_w_m2"]
        ax.plot(x, y, "o", color="tab:orange", ms=7)
        ax.annotate(p["name"], (x, y), textcoords="offset points", xytext=(6, 4), fontsize=8)
    ax.plot(1e3 * reference["omega_rad"], 1e-4 * reference["retinal_w_m2"], "*", color="gold", ms=14,
            markeredgecolor="k", label="the sun seen directly")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(0.1, 1000.0)
    ax.set_ylim(1e-6, 1e3)
    ax.set_xlabel("subtended source angle (mrad)")
    ax.set_ylabel("retinal irradiance (W/cm$^2$)")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    none = [p["name"] for p in points if not p.get("omega_rad")]
    text = note + (f"\nno glare (the sun's disc seen in no mirror): {', '.join(none)}" if none else "")
    fig.text(0.01, 0.01, text, fontsize=7, va="bottom")
    fig.subplots_adjust(bottom=0.2)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(str(path))
    return path
