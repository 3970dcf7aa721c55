"""Issue 29: reports a customer accepts, read as a customer reads them.

The certificate is checked where it matters, on the PDF's own text positions (pdfminer.six): every text
inside the page and none over another (axis labels were clipped and overlapping, the map's arrow key cut
off), µm for micrometres, the issuer and the signature line from ``[certificate]``. ``report diff`` prints
its figures and refuses two facet types unless asked; ``report flux`` names its sun and refuses an option
of another sun (``--csr`` without ``--sun buie`` was silently ignored).
"""

from __future__ import annotations

import itertools

import pytest

from sofast_station.reanalysis.cli import main
from tests.conftest import ROOT, SMALL_STATION

ISSUER = """
[certificate]
issuer = "Mirror Works Ltd, quality laboratory"
address = "1 Heliostat Road, Solar Park"
signatory = "A. Engineer, quality engineer"
"""


def _text_boxes(pdf):
    """Every text on the PDF's page as (text, x0, y0, x1, y1) in points, and the page's box: upright text
    line by line; rotated text (a colour bar's label), whose characters come one by one, as the union of
    the characters that touch."""
    from pdfminer.high_level import extract_pages
    from pdfminer.layout import LAParams, LTChar, LTTextLine

    pages = list(extract_pages(str(pdf), laparams=LAParams(char_margin=0.5, line_margin=0.1)))
    assert len(pages) == 1, "the certificate is one page"
    lines, rotated = [], []

    def walk(item):
        if isinstance(item, LTTextLine):
            chars = [c for c in item if isinstance(c, LTChar)]
            if chars and not any(c.upright for c in chars):
                rotated.extend(chars)
            elif item.get_text().strip():
                lines.append((item.get_text().strip(), *item.bbox))
        elif hasattr(item, "__iter__"):
            for child in item:
                walk(child)
    walk(pages[0])
    groups: list[list] = []
    for c in sorted(rotated, key=lambda c: (round(c.x0), c.y0)):
        # one rotated label: its characters share their column (x) and follow one another (y)
        near = [g for g in groups if abs(c.x0 - g[5]) < 0.5 and abs(c.x1 - g[6]) < 0.5 and c.y0 - g[4] < 2]
        if near:
            g = near[0]
            g[0] += c.get_text()
            g[1:5] = [min(g[1], c.x0), min(g[2], c.y0), max(g[3], c.x1), max(g[4], c.y1)]
        else:
            groups.append([c.get_text(), c.x0, c.y0, c.x1, c.y1, c.x0, c.x1])
    return lines + [tuple(g[:5]) for g in groups], pages[0].bbox


def _overlap(a, b, slack: float = 0.5) -> bool:
    return min(a[3], b[3]) - max(a[1], b[1]) > slack and min(a[4], b[4]) - max(a[2], b[2]) > slack


def test_the_certificate_is_laid_out_without_clipping_or_overlap(station_dumps, tmp_path, capsys):
    config = tmp_path / "station.toml"
    config.write_text(SMALL_STATION.format(data_dir=tmp_path / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                           radiometric=ROOT / "calibration/simulated_radiometric.json") + ISSUER)
    assert main(["report", "certificate", "SIM-0002", "--config", str(config), "--journal", str(station_dumps.journal),
                 "--out", str(tmp_path)]) == 0
    pdf = tmp_path / "certificate-SIM-0002.pdf"
    assert capsys.readouterr().out.strip() == str(pdf)
    lines, (px0, py0, px1, py1) = _text_boxes(pdf)
    text = "\n".join(t for t, *_ in lines)
    # what a customer looks for: the issuer, the facet, its figures with U, the maps' keys, a signature line
    for expected in ("Mirror Works Ltd, quality laboratory", "1 Heliostat Road, Solar Park", "SIM-0002",
                     "focal length f_x", "± ", "arrow: ", "A. Engineer, quality engineer",
                     "Date", "SHA-256"):
        assert expected in text, (expected, text)
    assert any(t.startswith("RMS") and t.endswith("µm") for t, *_ in lines), text   # the height map's RMS
    assert " um" not in text and "(um)" not in text
    assert len(lines) > 60                                 # the maps' tick labels are there too
    for t, x0, y0, x1, y1 in lines:                        # nothing beyond the page's edge (A4 in points)
        assert px0 + 5 <= x0 and x1 <= px1 - 5 and py0 + 5 <= y0 and y1 <= py1 - 5, (t, x0, y0, x1, y1)
    crossed = [(a[0], b[0]) for a, b in itertools.combinations(lines, 2) if _overlap(a, b)]
    assert not crossed, crossed


def test_report_diff_prints_its_figures_and_refuses_two_facet_types(station_dumps, tmp_path, capsys, caplog):
    a, b = (str(p) for p in station_dumps.good[:2])
    assert main(["report", "diff", a, b, "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    table, png = out.rsplit("\n", 2)[0], out.strip().splitlines()[-1]
    assert png.endswith(".png")
    assert "focal length f_x" in table and "B - A" in table and "height difference, RMS" in table and "µm" in table
    row = next(ln for ln in table.splitlines() if ln.startswith("focal length f_x"))
    assert row.count("±") == 3 and " m" in row                   # A, B and B - A, each with its U
    opencsp = f"opencsp:{ROOT / 'fixtures/opencsp/test_data'}"
    assert main(["report", "diff", a, opencsp, "--out", str(tmp_path)]) == 2
    assert "their difference is that of their designs" in caplog.text and "--any-design" in caplog.text


def test_report_flux_names_its_sun_and_refuses_an_option_of_another_sun(station_dumps, tmp_path, capsys, caplog):
    dump = str(station_dumps.good[0])
    assert main(["report", "flux", dump, "--csr", "0.1", "--out", str(tmp_path)]) == 2
    assert "--csr applies to the buie sun, but the sun here is pillbox" in caplog.text and "--sun buie" in caplog.text
    assert main(["report", "flux", dump, "--sigma-mrad", "2", "--sun", "buie", "--csr", "0.05",
                 "--out", str(tmp_path)]) == 2
    assert "--sigma-mrad applies to the gaussian sun, but the sun here is buie (from --sun)" in caplog.text
    capsys.readouterr()
    assert main(["report", "flux", dump, "--sun", "buie", "--csr", "0.1", "--out", str(tmp_path)]) == 0
    assert "sun Buie, circumsolar ratio 0.1" in capsys.readouterr().out


@pytest.mark.parametrize("n, extra, message", [
    (1, [], "control limits need at least 10"),
    (12, [], "fewer than the 25 the control limits come from"),
    (12, ["--baseline-n", "5"], "--baseline-n 5 is too few facets"),
])
def test_report_spc_refuses_too_few_facets_for_its_limits(tmp_path, small_station_toml, caplog, n, extra, message):
    """With one facet it drew "limits from the first 25 facets" and exited 0."""
    from tests.report.test_quality_reports import synthetic_journal

    journal = tmp_path / "j.sqlite3"
    synthetic_journal(journal, n)
    assert main(["report", "spc", "--config", str(small_station_toml), "--journal", str(journal),
                 "--out", str(tmp_path), *extra]) == 2
    assert message in caplog.text
