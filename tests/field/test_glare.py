"""Issue 45, item 5 (in part): glint and glare of a heliostat seen by observers, from its measured facets and
by the patent's camera route, against closed forms. A flat mirror larger than the sun's image shows the
sun's disc: its subtended angle is the sun's (2 x 4.65 mrad), its corneal irradiance rho DNI, its retinal
irradiance the sun's times rho; the sun's retinal irradiance is written out here from the patent's Eqs.
(47)-(48) (E_r = E_c (d_p / (f omega))^2 tau, f 17 mm, d_p 2 mm, tau 0.5), not taken from the code.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sofast_station.cli import main
from sofast_station.ensemble import load_ensemble
from sofast_station.errors import CaptureError, ConfigError
from sofast_station.field.geometry import direction, heliostat_rotation
from sofast_station.field.glare import Sunlight, camera_glare, facet_glare, heliostat_samples
from sofast_station.field.spot import FacetModel
from sofast_station.twin.glare_images import camera_image, disc_radiance, mirror_image
from tests.conftest import ROOT

RHO, DNI = 0.94, 900.0
SUN_OMEGA = 2 * 4.65e-3
#: The sun's retinal irradiance by the patent's equations, W/m^2.
SUN_RETINAL = DNI * (0.002 / (0.017 * SUN_OMEGA)) ** 2 * 0.5


def test_a_flat_mirrors_glare_is_the_suns_times_its_reflectivity():
    """One flat facet (0.6 m) of the 2x2 heliostat standing at azimuth 200, elevation 30 degrees, the sun at 150,
    45 degrees; observers 12, 20 and 30 m along the ray its middle reflects (the sun's image, 0.11 to 0.28 m,
    inside the facet): the subtended angle within 1 % of the sun's, the corneal irradiance within 1 % of rho
    DNI, the retinal irradiance within 1 % of rho times the sun's (the samples, 40 000 at 3 mm, resolve the
    disc's edge to about 0.3 %)."""
    ens = load_ensemble(ROOT / "fixtures/facets/heliostat_2x2.toml")
    rot = heliostat_rotation(math.radians(200), math.radians(30))
    pts, nrm, areas = heliostat_samples([FacetModel("R1C1", np.zeros(2), np.zeros(2), np.zeros(2))], ens, rot,
                                        np.array([10.0, 50.0, 2.0]), per_facet=40000)
    n = nrm.mean(axis=1) / np.linalg.norm(nrm.mean(axis=1))
    sun = direction(math.radians(150), math.radians(45))
    ray = 2 * (n @ sun) * n - sun
    for distance in (12.0, 20.0, 30.0):
        g = facet_glare(pts, nrm, areas, pts.mean(axis=1) + distance * ray, Sunlight(sun, DNI), RHO)
        assert g["glare"] and abs(g["omega_rad"] / SUN_OMEGA - 1) < 0.01, (distance, g)
        assert abs(g["corneal_w_m2"] / (RHO * DNI) - 1) < 0.01, (distance, g)
        assert abs(g["retinal_w_m2"] / (RHO * SUN_RETINAL) - 1) < 0.01, (distance, g)
    off = facet_glare(pts, nrm, areas, pts.mean(axis=1) + 20.0 * (ray + [0.0, 0.0, 0.02]), Sunlight(sun, DNI), RHO)
    assert not off["glare"] and off["retinal_w_m2"] is None


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_camera_route_gives_a_flat_mirrors_closed_form(seed):
    """The twin's sun image (a limb-darkened disc of 30 to 50 px radius, blur, shot and read noise, 12 bits)
    and its image of a flat mirror of reflectivity 0.94 showing the same disc: the corneal irradiance within 1 %
    of rho DNI, the subtended angle within 1 % of the sun's (the disc's pixel count at half level: the blur's
    and the limb's share of its edge), the retinal irradiance within 2 % of rho times the sun's."""
    rng = np.random.default_rng(seed)
    radius = rng.uniform(30, 50)
    shape = (int(4 * radius), int(4.4 * radius))
    rad = disc_radiance(shape, (shape[1] / 2 + rng.uniform(-3, 3), shape[0] / 2 + rng.uniform(-3, 3)), radius,
                        limb=rng.uniform(0.3, 0.6))
    got = camera_glare(camera_image(rad, rng), mirror_image(rad, RHO, rng), DNI)
    assert abs(got["corneal_w_m2"] / (RHO * DNI) - 1) < 0.01, got
    assert abs(got["omega_rad"] / SUN_OMEGA - 1) < 0.01, got
    assert abs(got["retinal_w_m2"] / (RHO * SUN_RETINAL) - 1) < 0.02, got


def test_the_camera_routes_clear_errors():
    """An overexposed sun, no DNI, and a glare image with no source: each refused with what to do."""
    rng = np.random.default_rng(0)
    rad = disc_radiance((160, 170), (85.0, 80.0), 35.0)
    with pytest.raises(CaptureError, match="sun image is overexposed"):
        camera_glare(camera_image(rad, rng, peak=1.5), mirror_image(rad, RHO, rng), DNI)
    with pytest.raises(ConfigError, match="no DNI"):
        camera_glare(camera_image(rad, rng), mirror_image(rad, RHO, rng), None)
    with pytest.raises(CaptureError, match="no glare source found"):
        camera_glare(camera_image(rad, rng), camera_image(np.zeros_like(rad), rng), DNI)


def test_the_glare_command_for_observers_and_by_camera(tmp_path, capsys, caplog):
    """``field glare`` on the twin's site: the heliostat tracking the aim point, an observer at the aim point sees
    the sun in its four facets (each smaller than the sun's image at 109 m): its retinal irradiance within 1 %
    of rho times the sun's (uniform radiance), its subtended angle within 3 % of the four facets' solid angle
    seen from there (their area, tilted by the view angle, over the range squared); an observer on the ground
    to the east sees none. The camera route writes its JSON and chart; missing inputs exit 2 with one line."""
    import cv2

    from sofast_station.field.study import write_spot_campaign

    c = write_spot_campaign(tmp_path / "site")
    (tmp_path / "obs.csv").write_text("name,x,y,z\ntower,0,0,45\nroad,200,-50,1.5\n")
    when = "2026-06-21T10:00:00+00:00"
    assert main(["field", "glare", str(c["factory"]), "--site", str(c["site"]), "--observers",
                 str(tmp_path / "obs.csv"), "--time", when, "--json", "--out", str(tmp_path)]) == 0
    doc = json.loads(capsys.readouterr().out)
    tower, road = doc["observers"]
    assert tower["glare"] and not road["glare"] and tower["glare_in_draws"] == 1.0
    # the canting's U (0.2 mrad) moves no facet out of the sun's image: the source stays the four facets whole
    assert tower["omega_rad_U"] < 1e-3 * tower["omega_rad"] and road["omega_rad_U"] is None
    assert abs(tower["retinal_w_m2"] / (RHO * SUN_RETINAL) - 1) < 0.01
    pos, aim = np.array([30.0, 95.0, 1.6]), np.array([0.0, 0.0, 45.0])
    from sofast_station.field.sun import sun_direction

    sun = sun_direction(when, 37.094, -2.359, 500.0)
    v = (aim - pos) / np.linalg.norm(aim - pos)
    n = (sun + v) / np.linalg.norm(sun + v)
    solid = 4 * 0.6 * 0.6 * float(n @ v) / float(np.linalg.norm(aim - pos)) ** 2
    assert abs(tower["omega_rad"] / (2 * math.sqrt(solid / math.pi)) - 1) < 0.03, tower
    assert (tmp_path / "H-0042-glare.png").stat().st_size > 10_000
    rng = np.random.default_rng(5)
    rad = disc_radiance((160, 170), (85.0, 80.0), 35.0)
    cv2.imwrite(str(tmp_path / "sun.png"), camera_image(rad, rng))
    cv2.imwrite(str(tmp_path / "glint.png"), mirror_image(rad, RHO, rng))
    assert main(["field", "glare", "--sun-image", str(tmp_path / "sun.png"), "--glare-image",
                 str(tmp_path / "glint.png"), "--dni", "900", "--json"]) == 0
    cam = json.loads(capsys.readouterr().out)
    assert abs(cam["glare"]["corneal_w_m2"] / (RHO * DNI) - 1) < 0.01 and (tmp_path / "glint.png").exists()
    for args, words in ((["field", "glare", "--sun-image", str(tmp_path / "sun.png"), "--glare-image",
                          str(tmp_path / "glint.png")], "no DNI"),
                        (["field", "glare", str(c["factory"]), "--site", str(c["site"]), "--observers",
                          str(tmp_path / "obs.csv")], "give --time")):
        caplog.clear()
        assert main(args) == 2, args
        assert words in caplog.text and "Traceback" not in caplog.text, caplog.text
