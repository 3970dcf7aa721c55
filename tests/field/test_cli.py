"""``sofast-station field orientation`` and ``field canting`` on a campaign the twin writes as files (a site
file, its layout CSV, photos with their notes, a factory record), and their clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sofast_station.cli import main
from sofast_station.field.study import TwinSite, write_campaign


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    out = tmp_path_factory.mktemp("campaign")
    return write_campaign(out, seed=3, photos=6, site=TwinSite(width_px=640, height_px=480))


def test_orientation_command(campaign, capsys):
    """The photo's notes name the heliostat and the time: the command finds it in the layout, the sun by pvlib,
    and prints the normal and tracking error with U; its JSON's normal lies within its U of the twin's truth
    (written beside the photo by the twin, not read by the command), and a PNG is written."""
    photo = campaign["orientation"]
    assert main(["field", "orientation", str(photo), "--site", str(campaign["site"]), "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    o = record["orientation"]
    truth = np.array(json.loads(photo.with_suffix(".json").read_text())["truth"]["normal"])
    from sofast_station.field.geometry import pointing_error_mrad
    err = pointing_error_mrad(np.array(o["normal"]), truth)
    assert abs(err["azimuth_mrad"]) <= o["pointing_U_mrad"]["azimuth"]
    assert abs(err["elevation_mrad"]) <= o["pointing_U_mrad"]["elevation"]
    assert record["heliostat"] == "H-0042" and "tracking_error_mrad" in o and o["facets_used"] >= 20
    assert (photo.parent / "orientation-orientation.png").stat().st_size > 10000
    assert main(["field", "orientation", str(photo), "--site", str(campaign["site"])]) == 0
    text = capsys.readouterr().out
    assert "tracking error" in text and "± " in text and "normal" in text


def test_canting_command(campaign, capsys):
    """Six photos and the factory record: every facet measured, each within its U (k = 2) of the twin's truth
    (written beside the photos by the twin, not read by the command) in at least 90 % of facets on both axes,
    the factory's difference for every facet, the table and the PNG written. (Whether the knocked facet is
    flagged depends on the photos' U: tests/field/test_canting.py.)"""
    args = ["field", "canting", *map(str, campaign["canting"]), "--site", str(campaign["site"]), "--factory",
            str(campaign["factory"])]
    assert main(args + ["--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert len(doc["canting"]["facets"]) == 25 and len(doc["factory"]["facets"]) == 25
    out_dir = Path(campaign["site"]).parent
    truth = json.loads((out_dir / "truth.json").read_text())["canting_mrad"]
    inside = [abs(f["canting_mrad"][a] - truth[f["label"]][a]) <= f["canting_mrad_U"][a]
              for f in doc["canting"]["facets"] for a in "xy"]
    assert np.mean(inside) >= 0.9
    assert (out_dir / "H-0042-canting.png").stat().st_size > 10000
    assert (out_dir / "H-0042-canting.json").exists()


def test_clear_errors(campaign, tmp_path, caplog):
    """A missing site file, a photo of the wrong size, an unreadable photo, a serial not in the layout: exit
    2 with one line saying what is wrong, never a traceback."""
    site, photo = str(campaign["site"]), str(campaign["orientation"])
    cases = [(["field", "orientation", photo, "--site", str(tmp_path / "none.toml")], "does not exist")]
    import cv2
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), cv2.imread(photo)[:-10])
    cases.append((["field", "orientation", str(small), "--site", site, "--heliostat", "H-0042",
                   "--commanded", "180,40"], "camera's intrinsics are for"))
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"\x89PNG not really")
    cases.append((["field", "orientation", str(broken), "--site", site, "--heliostat", "H-0042"],
                  "cannot be read as an image"))
    cases.append((["field", "orientation", photo, "--site", site, "--heliostat", "H-9999"], "H-9999"))
    for args, words in cases:
        caplog.clear()
        assert main(args) == 2, args
        assert words in caplog.text and "Traceback" not in caplog.text, caplog.text
