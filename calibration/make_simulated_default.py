"""Write the simulated station's shipped radiometric record (calibration/simulated_radiometric.json).

Until the daily radiometric calibration has run, the simulated station linearises its fringes with the
twin's known inverse response: the twin's display emits floor + (1 - floor) (v/255)^gamma and its camera
responds linearly, so the normalised response (L(v) - L(0)) / (L(255) - L(0)) = (v/255)^gamma and the
table is level^(1/gamma). Its exposure (1/60 s, one refresh period) and gain (1) are the twin's reference
sensor settings (TwinOptics.reference_exposure_s), at which white reads white_dn. Run it again if the
twin's default display gamma changes. A station's own records come from 'sofast-station calibrate
radiometric' (docs/calibration.md).
"""

import json
from pathlib import Path

import numpy as np

GAMMA = 2.2          # the twin's default display gamma (sofast_station.twin.parameters.TwinOptics)
N = 1024

if __name__ == "__main__":
    level = np.linspace(0.0, 1.0, N)
    record = {"schema": 1, "kind": "radiometric", "record_id": "simulated-default",
              "created": "2026-11-25T00:00:00+00:00",
              "source": "shipped default for the simulated station: the twin's known inverse display response "
                        f"(gamma {GAMMA}); exempt from staleness",
              "lut": [round(float(v), 9) for v in level ** (1.0 / GAMMA)],
              "floor_level": 0.01, "max_level": 1.0, "exposure_s": 1 / 60, "gain": 1.0}
    out = Path(__file__).with_name("simulated_radiometric.json")
    out.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {out}")
