"""A one-page PDF certificate per facet (``sofast-station report certificate SERIAL``).

Station, date, recipe, serial; every reported figure with ``± U`` where the record has ``name_U``
(expanded uncertainty, k = 2), its limits and the verdict; the slope-error map against the design and
the height-error map against the fitted parabola (when the facet has a data dump); the calibration
record in force; the SHA-256 of the dump. Drawn with Matplotlib's PDF backend.
"""

from __future__ import annotations

import hashlib
import textwrap
from pathlib import Path

from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from ..errors import ReportError
from ..result.formatting import figure_text, method_text
from ..result.record import figure_value
from ._common import savefig_atomic
from .heliostat import draw_facet_map_on
from .maps import MODEL_LABELS, detail_maps, draw_detail


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _limit_text(spec) -> str:
    if spec.lsl is not None and spec.usl is not None:
        return f"{spec.lsl:.6g} to {spec.usl:.6g}"
    if spec.usl is not None:
        return f"at most {spec.usl:.6g}"
    return "-"


def figure_rows(record: dict, specs) -> list[list[str]]:
    """Rows (figure, value ± U, unit, limits, within) of the certificate's table, each figure as every screen
    writes it (:func:`~sofast_station.result.formatting.figure_text`)."""
    rows = []
    for s in specs:
        v = figure_value(record, s.key)
        ok = "-" if v is None else ("yes" if (s.lsl is None or v >= s.lsl) and (s.usl is None or v <= s.usl) else "NO")
        rows.append([s.label, figure_text(record, s.key), s.unit, _limit_text(s), ok])
    return rows


#: The page's margins and rows, in fractions of the A4 page (portrait).
_LEFT, _RIGHT, _ROW = 0.07, 0.93, 0.0175
#: The table's columns: (x, alignment) of figure, value ± U, unit, limits, within.
_COLUMNS = ((0.07, "left"), (0.56, "right"), (0.58, "left"), (0.68, "left"), (0.93, "right"))


def _wrapped(fig, x: float, y: float, text: str, width_chars: int, **style) -> float:
    """*text* wrapped at *width_chars* from (x, y) down; returns the y under its last line."""
    for line in textwrap.wrap(str(text), width_chars) or [""]:
        fig.text(x, y, line, va="top", **style)
        y -= _ROW
    return y


def _rule(fig, y: float, width: float = 0.6, colour: str = "0.6") -> None:
    fig.add_artist(Line2D([_LEFT, _RIGHT], [y, y], lw=width, color=colour))


def refuse_faulted(record: dict) -> None:
    """Refuse a certificate for a facet (or heliostat) whose cycle ended in a fault: ReportError naming it and
    its reasons. Checked on the journal's record before anything heavy (the dump's reprocessing)."""
    if record.get("verdict") in (None, "fault"):
        what = "heliostat" if isinstance(record.get("facets"), list) else "facet"
        raise ReportError(f"{what} {record.get('serial')} has no figures (its cycle ended in a fault: "
                          f"{'; '.join(record.get('reasons', []))}): no certificate")


def write_certificate(record: dict, out_path: Path, *, specs, measured=None, dump_path: Path | None = None,
                      issuer: dict | None = None, dpi: int = 150) -> Path:
    """Write the certificate PDF: one A4 page, every text inside it and none over another (tested on the
    PDF's own text positions).

    Parameters
    ----------
    record : dict
        The facet's journaled result record.
    out_path : Path
        The ``.pdf`` to write.
    specs : list of FigureSpec
        Figures and limits of the facet's recipe (:func:`sofast_station.result.specs.figure_specs`).
    measured : Measured, optional
        The reprocessed dump (for the maps); without it the page says why there are no maps.
    dump_path : Path, optional
        The dump file, whose SHA-256 is printed.
    issuer : dict, optional
        ``[certificate]`` of station.toml: ``issuer``, ``address``, ``signatory`` (all optional).
    """
    refuse_faulted(record)
    issuer = issuer or {}
    fig = Figure(figsize=(8.27, 11.69))               # A4 portrait
    y = certificate_head(fig, record, "Facet inspection certificate", issuer)
    verdict = str(record.get("verdict", "?")).upper()
    # The figures: a table of plain texts in fixed columns (a Matplotlib table clipped its cells).
    y -= 0.008
    coverage = " ± U (k = 2)" if record.get("coverage_factor") else ""
    titles = ("figure", "value" + coverage, "unit", "limits", "within")
    for (x, align), title in zip(_COLUMNS, titles):
        fig.text(x, y, title, fontsize=9, weight="bold", ha=align, va="top")
    y -= _ROW + 0.002
    _rule(fig, y + 0.004)
    for row in figure_rows(record, specs):
        for (x, align), cell in zip(_COLUMNS, row):
            fig.text(x, y, cell, fontsize=9, ha=align, va="top",
                     color="tab:red" if cell == "NO" else "black", weight="bold" if cell == "NO" else "normal")
        y -= _ROW + 0.002
    _rule(fig, y + 0.004)
    y -= 0.006
    reasons = record.get("reasons") or []
    y = _wrapped(fig, _LEFT, y, "Verdict: " + verdict + (": " + "; ".join(reasons) if reasons else
                                                          ": every figure within its limits"), 100, fontsize=9)
    if measured is not None and getattr(measured, "analysis", None) is not None:
        a = measured.analysis
        f_design = getattr(getattr(measured, "design", None), "focal_length_m", None)
        d_design = detail_maps(a.points_facet_m[0], a.points_facet_m[1], a.slopes, a.residuals_mrad, "design",
                               f_design, cells_across=120)
        d_parab = detail_maps(a.points_facet_m[0], a.points_facet_m[1], a.slopes, a.residuals_mrad, "parabola",
                              f_design, cells_across=120)
        # Two square maps, each with its colour bar (which takes a share of its box) and labels: the left
        # one's colour-bar label ends before the right one's y label begins (checked by the layout test).
        side = 0.33
        height = side * 8.27 / 11.69
        bottom = max(0.235, y - 0.06 - height)
        ax1 = fig.add_axes((0.11, bottom, side, height))
        ax2 = fig.add_axes((0.60, bottom, side, height))
        draw_detail(fig, [ax1], d_design, which=("magnitude",))
        draw_detail(fig, [ax2], d_parab, which=("height",))
        ax1.set_title(f"slope error {MODEL_LABELS['design'].replace('compared with the ', 'vs ')}", fontsize=9)
        ax2.set_title(ax2.get_title().replace(" (from slopes, least squares)", ""), fontsize=9)
    else:
        _wrapped(fig, _LEFT, y - 0.02, "No data dump of this facet: no maps (the station dumps every n-th facet, "
                 "failed ones, and on request: sofast-station dump-next).", 100, fontsize=9)
    # Who issues it, and where it is signed.
    fig.text(_LEFT, 0.175, "Issued by " + (issuer.get("issuer") or "-"), fontsize=9, va="top")
    _rule(fig, 0.115, 0.6, "0.2")
    fig.text(_LEFT, 0.108, issuer.get("signatory") or "Signature", fontsize=8.5, va="top")
    fig.text(0.62, 0.108, "Date", fontsize=8.5, va="top")
    certificate_foot(fig, record, dump_path)
    return savefig_atomic(fig, Path(out_path), dpi, fmt="pdf")


def certificate_head(fig, record: dict, title: str, issuer: dict | None = None) -> float:
    """The certificate's issuer, *title*, verdict and head (serial, type, recipe, station, time, software,
    calibration) at the top of the A4 *fig*; returns the height below it (figure fraction)."""
    issuer = issuer or {}
    fig.text(_LEFT, 0.972, issuer.get("issuer") or "Issuer not set ([certificate] issuer in station.toml)",
             fontsize=11, weight="bold", va="top")
    if issuer.get("address"):
        fig.text(_LEFT, 0.953, issuer["address"], fontsize=8.5, color="0.35", va="top")
    fig.text(_RIGHT, 0.972, f"Certificate {record.get('cycle_id', '-')}", fontsize=7.5, color="0.35", ha="right",
             va="top", family="monospace")
    fig.text(_LEFT, 0.93, title, fontsize=17, weight="bold", va="top")
    verdict = str(record.get("verdict", "?")).upper()
    fig.text(_RIGHT, 0.93, verdict, fontsize=17, weight="bold", ha="right", va="top",
             color={"PASS": "tab:green", "FAIL": "tab:red"}.get(verdict, "tab:orange"))
    _rule(fig, 0.897, 1.0, "0.2")
    cal = record.get("calibration") or {}
    head = [("Serial", record.get("serial", "?")), ("Facet type", record.get("facet", "?")),
            ("Recipe", record.get("recipe") or "default"), ("Station", record.get("station", "?")),
            ("Measured by", method_text(record) or "-"),
            ("Measured", str(record.get("time", "?"))[:19].replace("T", " ") + " (local time)"),
            ("Software", f"sofast-station {record.get('software_version', '?')}, configuration "
                         f"{record.get('config_hash', '?')}"),
            ("Calibration in force", ", ".join(f"{k} {v}" for k, v in cal.items() if k != "warnings") or "-")]
    if cal.get("warnings"):
        head.append(("Calibration warnings", "; ".join(cal["warnings"])))
    y = 0.885
    for k, v in head:
        fig.text(_LEFT, y, k, fontsize=9, weight="bold", va="top")
        y = _wrapped(fig, 0.30, y, v, 78, fontsize=9)
    return y


def certificate_foot(fig, record: dict, dump_path: Path | None) -> None:
    """The dump's name and SHA-256 and the cycle id at the foot of the certificate's page."""
    if dump_path:
        fig.text(_LEFT, 0.065, f"Data dump {Path(dump_path).name}", fontsize=7, family="monospace", va="top")
        fig.text(_LEFT, 0.052, f"SHA-256 {sha256_of(Path(dump_path))}", fontsize=7, family="monospace", va="top")
    else:
        fig.text(_LEFT, 0.065, "Data dump: none", fontsize=7, family="monospace", va="top")
    fig.text(_LEFT, 0.039, f"Cycle {record.get('cycle_id', '-')}", fontsize=7, family="monospace", va="top")


def write_heliostat_certificate(record: dict, out_path: Path, *, ensemble, limit_mrad: float | None = None,
                                dump_path: Path | None = None, issuer: dict | None = None, dpi: int = 150) -> Path:
    """Write a heliostat's certificate PDF (:func:`draw_heliostat_certificate`)."""
    fig = draw_heliostat_certificate(record, ensemble=ensemble, limit_mrad=limit_mrad, dump_path=dump_path,
                                     issuer=issuer)
    return savefig_atomic(fig, Path(out_path), dpi, fmt="pdf")


def draw_heliostat_certificate(record: dict, *, ensemble, limit_mrad: float | None = None,
                               dump_path: Path | None = None, issuer: dict | None = None):
    """A heliostat's certificate page (A4, a Matplotlib figure): its head, the heliostat's figures, the map of
    its facets (each with its canting error ± U and verdict) and a table of every facet's figures; the dump's
    SHA-256."""
    refuse_faulted(record)
    fig = Figure(figsize=(8.27, 11.69))
    y = certificate_head(fig, record, "Heliostat inspection certificate", issuer)
    h = record["heliostat"]
    lines = [f"{h['n_measured']} of {h['n_facets']} facets measured; canting RMS {h['canting_rms_mrad']:.3f} mrad, "
             f"largest {h['canting_max_mrad']:.3f} mrad ({h['canting_max_facet']})"
             + (f", limit {limit_mrad:g} mrad" if limit_mrad is not None else ""),
             f"facets' common tilt {figure_text(h, 'common_tilt_mrad.x')}, {figure_text(h, 'common_tilt_mrad.y')} mrad "
             "(where the heliostat points against its corners: not a canting error)"]
    o = record.get("optics")
    if o:
        m = o["measured"]
        lines.append(f"optics at {o['conditions']['slant_range_m']:.1f} m: intercept "
                     f"{figure_text(m, 'intercept')} (design {o['design']['intercept']:.4f}, "
                     f"re-canted {o['corrected']['intercept']:.4f}), 90 % radius "
                     f"{figure_text(m, 'spot_radius_mrad')} mrad")
    reasons = record.get("reasons") or []
    lines.append("Verdict: " + str(record["verdict"]).upper() + (": " + "; ".join(reasons) if reasons else
                                                                 ": every facet within its limits"))
    y -= 0.008
    for line in lines:
        y = _wrapped(fig, _LEFT, y, line, 110, fontsize=8.5) - 0.004
    top = min(y - 0.01, 0.80)
    ax = fig.add_axes((0.10, 0.37, 0.80, top - 0.37))
    draw_facet_map_on(ax, record, ensemble, limit_mrad, fontsize=7 if ensemble.n_facets > 9 else 8)
    rows = []
    for f in record["facets"]:
        if "canting_mrad" not in f:
            rows.append([f["label"], f.get("verdict", f["status"]), f["status"], "", "", "", ""])
            continue
        rows.append([f["label"], f["verdict"], figure_text(f, "canting_mrad.x", sign=True),
                     figure_text(f, "canting_mrad.y", sign=True),
                     figure_text(f, "curvature_x_per_m"), figure_text(f, "curvature_y_per_m"),
                     figure_text(f, "slope_rms_mrad.parabola.magnitude")])
    height = min(0.25, 0.017 * (len(rows) + 1))
    ax_t = fig.add_axes((0.06, 0.32 - height, 0.88, height))
    ax_t.axis("off")
    # each focal power with its U in a column of its own: both in one cell ran past its edge
    table = ax_t.table(cellText=rows, colLabels=["facet", "verdict", "canting x, mrad", "canting y, mrad",
                                                 "focal power x, 1/m", "focal power y, 1/m", "slope RMS, mrad"],
                       loc="upper center", cellLoc="left", colWidths=(0.08, 0.10, 0.14, 0.14, 0.19, 0.19, 0.16))
    table.auto_set_font_size(False)
    table.set_fontsize(6 if len(rows) > 12 else 8)
    certificate_foot(fig, record, dump_path)
    return fig
