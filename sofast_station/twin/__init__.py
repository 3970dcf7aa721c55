"""The digital twin: true facet surfaces, ray tracing, image formation and ground truth.

It imports only numpy, scipy, the standard library and ``sofast_station.geometry``, ``.facet``,
``.ensemble`` and ``.errors``: it shares no code with the measurement pipeline it is the oracle for.

Public API
----------
TrueFacet, TwinOptics
    Configuration: the true shape and placement, and the optical nonidealities.
TrueSurface
    The true surface z(x, y) with exact slopes, true facet frame.
TwinCamera
    OpenCV pinhole + 5-term distortion: ``project`` and ``pixel_rays``.
TwinStation
    The traced station: ``capture(display_image, rng)`` and the test-support accessors. It composes the
    facet's trace (``trace.FacetTrace``), the renderer of what the camera sees (``render.TwinRenderer``) and
    the camera's sensor (``sensor.TwinSensor``).
TrueHeliostat, TwinHeliostat, heliostat_truth
    A heliostat: several facets in one picture, each its own shape and canting error, and their truth.
ground_truth
    The fit definitions of docs/conventions.md applied to the exact true surface at the kept pixels, in
    the frame the electronic boresight gives the parabola fitted to them (x, y, rotation about z: the true placement).
"""

from .camera import TwinCamera
from .parameters import TrueFacet, TwinOptics
from .station import TwinStation
from .heliostat import TrueHeliostat, TwinHeliostat, heliostat_truth
from .surface import TrueSurface
from .truth import ground_truth

__all__ = ["TrueFacet", "TwinOptics", "TrueSurface", "TwinCamera", "TwinStation", "ground_truth", "TrueHeliostat",
           "TwinHeliostat", "heliostat_truth"]
