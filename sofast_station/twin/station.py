"""The digital twin of the station: the facet's trace, the renderer of what the camera sees, and its sensor.

:class:`TwinStation` composes three parts, each in its own module:

- the facet (:class:`~sofast_station.twin.trace.FacetTrace`, :mod:`sofast_station.twin.trace`): where the true
  facet is, and which screen point every camera pixel sees in it, traced once; the geometry queries (the
  measured distance, the corners, the reflected footprint);
- the renderer (:class:`~sofast_station.twin.render.TwinRenderer`, :mod:`sofast_station.twin.render`): the
  display's light sampled through each pixel's reflection, as linear DN (display response, reflectance,
  ambient, background, vignetting, the lens's blur);
- the sensor (:class:`~sofast_station.twin.sensor.TwinSensor`, :mod:`sofast_station.twin.sensor`): exposure and
  gain, the display's flicker, read and shot noise, the knee and the rounding.

Frames and screen coordinates: :mod:`sofast_station.twin.trace`.
"""

from __future__ import annotations

import copy
import math
import time
from functools import cached_property

import numpy as np

from ..facet import FacetDesign
from ..geometry import StationGeometry
from . import edges
from .noise import scratch_f32
from .parameters import TrueFacet, TwinOptics
from .marks import mark_coverage
from .render import TwinRenderer
from .sensor import TwinSensor, exposure_scale, flicker_factor
from .trace import MAX_KEPT_EDGE_SHIFT_PX, TRACE_ARRAYS, FacetTrace, facet_to_fixture_pose, rotation_zyx

__all__ = ["TwinStation", "FacetTrace", "TRACE_ARRAYS", "MAX_KEPT_EDGE_SHIFT_PX", "facet_to_fixture_pose",
           "rotation_zyx", "rook_lattice"]

#: The attributes of the facet's trace a TwinStation shows as its own (the heliostat's twin sets them itself).
_FACET_ATTRIBUTES = ("geometry", "screen_shape", "design", "facet", "camera", "surface", "facet_to_fixture",
                     "facet_to_camera", "camera_to_facet", "screen_to_facet", "facet_to_screen")

#: The image-shaped views a TwinStation keeps once asked (dropped when the trace changes).
_VIEWS = ("screen_position_m", "surface_point_facet_m", "slope_true", "on_screen", "rim_screen_position_m")


def rook_lattice(n: int) -> np.ndarray:
    """``n*n`` sub-pixel sample offsets in (-1/2, 1/2)^2, one per row and per column of an n^2 x n^2 grid.

    A rank-1 lattice ``((j + 1/2) / N, ((g j) mod N + 1/2) / N)``, N = n^2, with the generator g that
    maximises the smallest toroidal distance between samples. Every sample has its own column and row, so
    a nearly axis-aligned edge is located to 1/(2N) pixel (a plain n x n grid: 1/(2n)).

    Returns
    -------
    (N, 2) array of (du, dv) offsets, pixels.
    """
    count = n * n
    j = np.arange(count)
    best_g, best_d = 1, -1.0
    for g in range(1, count):
        if math.gcd(g, count) != 1:
            continue
        pts = np.column_stack([j, (g * j) % count]) / count
        diff = np.abs(pts[:, None, :] - pts[None, :, :])
        diff = np.minimum(diff, 1.0 - diff)
        dist = np.hypot(diff[..., 0], diff[..., 1])
        np.fill_diagonal(dist, np.inf)
        if dist.min() > best_d + 1e-12:
            best_g, best_d = g, float(dist.min())
    return np.column_stack([(j + 0.5) / count - 0.5, ((best_g * j) % count + 0.5) / count - 0.5])


class TwinStation:
    """Digital twin of the station: camera, LCD and the true facet, ray traced once, captured many times.

    It composes the facet's trace (:attr:`trace`, :class:`~sofast_station.twin.trace.FacetTrace`: every
    camera pixel centre traced to the true surface, its coverage and the screen point it sees), the renderer
    of what the camera sees (:attr:`renderer`, :class:`~sofast_station.twin.render.TwinRenderer`: the display's
    light through each pixel's reflection, precomputed so that :meth:`capture` is a few vector operations)
    and the camera's sensor (:attr:`sensor`, :class:`~sofast_station.twin.sensor.TwinSensor`: exposure, gain,
    flicker, noise, knee, rounding).

    Parameters
    ----------
    geometry, design, facet, edge_band_px, screen_shape
        The station, the facet's design, the true facet and how its edge is traced: as
        :class:`~sofast_station.twin.trace.FacetTrace`'s. With *screen_shape* (the panel as it really is,
        :mod:`sofast_station.twin.assembly`), *geometry* holds the stated screen (the units the fringes encode
        positions in) and the true poses.
    optics : TwinOptics
        Display, reflection, ambient, camera response, noise, vignetting, and the edge model
        (``edge_sampling``, ``edge_grid``, ``blur_px``, ``defocus_px``, ``bevel_*``; see
        :mod:`sofast_station.twin.edges`).
    trace_only : bool
        Only trace (no renderer, no sensor): it cannot capture.
    marks : FixtureMarks or None
        The fixture's marks (``[marks]``), drawn in every frame where the true fixture pose puts them
        (:mod:`sofast_station.twin.marks`); None: the fixture has none.

    Attributes
    ----------
    trace : FacetTrace
    renderer : TwinRenderer or None
    sensor : TwinSensor or None
    camera : TwinCamera
    surface : TrueSurface
    facet_to_fixture, facet_to_camera, facet_to_screen, camera_to_facet, screen_to_facet : Pose
        Where the true facet frame lies relative to the others (the trace's).
    gain_dn : float
        DN per unit radiance (fraction of white) at vignetting factor 1, at the reference exposure and gain 1.
    trace_seconds : float
        Wall time of the trace and of the renderer's preparation, seconds.
    """

    #: No marks unless given (a heliostat's twin, which sets up its own traces, has none).
    marks = None
    mark_coverage = None

    def __init__(self, geometry: StationGeometry, design: FacetDesign, facet: TrueFacet = TrueFacet(),
                 optics: TwinOptics = TwinOptics(), edge_band_px: float = 2.0, trace_only: bool = False,
                 screen_shape=None, marks=None):
        start = time.perf_counter()
        self.optics = optics
        self._show(FacetTrace(geometry, design, facet, optics, edge_band_px=edge_band_px, screen_shape=screen_shape))
        self.marks = marks
        #: The marks' share of each pixel (H, W), or None (they do not move with the facet: made once).
        self.mark_coverage = None if marks is None else mark_coverage(
            marks, geometry.fixture_to_camera, self.trace.camera, geometry.camera.shape)
        self.renderer = self.sensor = None
        if not trace_only:
            self._light(TwinRenderer(self.trace, optics, self.mark_coverage))
        self.trace_seconds = time.perf_counter() - start

    def _show(self, trace: FacetTrace) -> None:
        """Make *trace* this station's facet (its geometry as this station's attributes)."""
        self.trace = trace
        for name in _FACET_ATTRIBUTES:
            setattr(self, name, getattr(trace, name))
        for name in _VIEWS:
            self.__dict__.pop(name, None)

    def _light(self, renderer: TwinRenderer, sensor: TwinSensor | None = None) -> None:
        """Make *renderer* this station's (and *sensor*, else a sensor reading the renderer's dark level)."""
        self.renderer = renderer
        self.sensor = sensor or TwinSensor(self.optics, renderer.dn_base)
        self.gain_dn = renderer.gain_dn

    def adopt_trace(self, coverage: np.ndarray, seen_idx: np.ndarray, arrays: dict) -> None:
        """Take the trace of another picture (several traces merged: :mod:`sofast_station.twin.heliostat`)
        and prepare the captures from it: *coverage* (H, W), the seen pixels' flat indices *seen_idx*, and
        each of :data:`~sofast_station.twin.trace.TRACE_ARRAYS` for them, in that order. This station's own
        design, facet and poses stay as they are."""
        self.trace = FacetTrace.merged(self.geometry, coverage, seen_idx, arrays, self.optics)
        for name in _VIEWS:
            self.__dict__.pop(name, None)
        self._light(TwinRenderer(self.trace, self.optics, self.mark_coverage))

    # ------------------------------------------------------------- the next facet, other optics
    def with_facet(self, facet: TrueFacet) -> "TwinStation":
        """The same station with another facet in the fixture (a production line's next facet).

        :meth:`FacetTrace.with_facet <sofast_station.twin.trace.FacetTrace.with_facet>` traces it: with the
        placement unchanged and the outline's image moved by less than
        :data:`~sofast_station.twin.trace.MAX_KEPT_EDGE_SHIFT_PX`, only the pixels that saw the facet, keeping
        each edge pixel's coverage (the renderer then only samples the new screen points, the sensor is
        shared); otherwise anew. Every figure of the twin's truth is the new surface's, exactly. Shares the
        unchanged read-only arrays.
        """
        start = time.perf_counter()
        trace = self.trace.with_facet(facet)
        twin = copy.copy(self)
        twin._show(trace)
        if self.renderer is not None:
            if self.trace.keeps_outline(trace):
                twin._light(self.renderer.with_trace(trace), self.sensor)
            else:
                twin._light(TwinRenderer(trace, self.optics, self.mark_coverage))
        twin.trace_seconds = time.perf_counter() - start
        return twin

    def with_optics(self, optics: TwinOptics) -> "TwinStation":
        """The same traced station with other optics (exposure, noise, display, blur, vignetting): no new trace.

        The returned station shares the trace's (read-only) arrays with this one. Optics whose edge model
        changes the trace (:data:`sofast_station.twin.edges.TRACE_FIELDS`: sampling, a bevelled rim) give a
        newly traced station.
        """
        if any(getattr(optics, name) != getattr(self.optics, name) for name in edges.TRACE_FIELDS):
            return TwinStation(self.geometry, self.design, self.facet, optics, edge_band_px=self.trace.edge_band_px,
                               screen_shape=self.screen_shape, marks=self.marks)
        twin = copy.copy(self)
        twin.optics = optics
        twin._light(self.renderer.with_optics(optics))
        for name in _VIEWS:
            twin.__dict__.pop(name, None)
        return twin

    # ---------------------------------------------------------------- capture
    def sensor_scale(self, exposure_s: float | None = None, gain: float | None = None) -> float:
        """Signal multiplier of an exposure and gain relative to the reference: ``(exposure_s /
        reference_exposure_s) * gain`` (:func:`~sofast_station.twin.sensor.exposure_scale`)."""
        return exposure_scale(self.optics, exposure_s, gain)

    def flicker_factor(self, exposure_s: float | None = None, phase: float | None = None) -> float:
        """Mean backlight factor seen by an exposure starting at *phase* of a refresh period
        (:func:`~sofast_station.twin.sensor.flicker_factor`)."""
        return flicker_factor(self.optics, exposure_s, phase)

    def linear_dn(self, display_image: np.ndarray, exposure_s: float | None = None, gain: float | None = None,
                  flicker_phase: float | None = None) -> np.ndarray:
        """The noise-free camera signal before the knee, rounding and clipping, DN (float32).

        The same image formation as :meth:`capture` without its random terms, for tests that need the
        exact forward model (the analytically known optimum exposure and gain).
        """
        renderer = self.renderer
        return renderer.linear(renderer.display_sample(display_image), self.optics.ambient,
                               self.sensor_scale(exposure_s, gain), self.flicker_factor(exposure_s, flicker_phase))

    def capture(self, display_image: np.ndarray, rng: np.random.Generator | None = None, *,
                exposure_s: float | None = None, gain: float | None = None,
                flicker_phase: float | None = None, ambient_z: float | None = None) -> np.ndarray:
        """The camera frame while the display shows *display_image*.

        The renderer forms the light each pixel gathers, the sensor reads it out
        (:class:`~sofast_station.twin.sensor.TwinSensor`): DN = black level + (exposure / reference exposure) x
        gain x (the light the pixel gathers, display light times the flicker factor); read noise x gain and
        shot noise (variance signal x gain / ``electrons_per_dn``) are added, then the knee, rounding and
        clipping to 0..255. At the reference exposure, gain 1 and a whole number of refresh periods the
        signal is exactly the one the twin has always formed (a noise-free frame is the same bits). The
        noise of each half of the image comes from its own generator seeded from *rng*, so the two halves
        are drawn in parallel; a given *rng* state still gives the same frame.

        Parameters
        ----------
        display_image : (screen height_px, screen width_px) uint8 array
            Command values the display shows, row 0 = top row.
        rng : numpy Generator or None
            Source of the ambient jitter and the sensor noise; None gives the noise-free frame.
        exposure_s : float or None
            Exposure time, seconds; None is ``optics.reference_exposure_s``.
        gain : float or None
            Linear gain factor; None is 1.
        flicker_phase : float or None
            Phase of the display's refresh cycle at the start of the exposure, periods (0..1); None is 0.
            Matters only for exposures that are not a whole number of refresh periods.
        ambient_z : float or None
            This frame's ambient jitter as a standard normal value (ambient x (1 + ``ambient_jitter`` z));
            None draws it from *rng* when there is one. Given, it is not drawn, so the sensor noise comes
            from the state *rng* is in: drawing z from *rng* first and passing it gives the same frame as
            passing nothing, and ``0.0`` with a copy of that state gives the same sensor noise at the
            nominal ambient (what the frame-to-frame brightness leaves in a figure, ``benchmarks/uncertainty_coverage.py
            --split-brightness``).

        Returns
        -------
        (camera height_px, camera width_px) uint8 array
        """
        optics, renderer, sensor = self.optics, self.renderer, self.sensor
        scale = sensor.scale(exposure_s, gain)
        flicker = sensor.flicker_factor(exposure_s, flicker_phase)
        sample = renderer.cached_sample(display_image)
        ambient = optics.ambient
        if ambient_z is None and rng is not None and optics.ambient_jitter > 0:
            ambient_z = float(rng.standard_normal())
        if ambient_z is not None and optics.ambient_jitter > 0:
            ambient = max(0.0, ambient * (1.0 + optics.ambient_jitter * float(ambient_z)))
        light = renderer.cached_light(display_image) if scale == 1.0 and flicker == 1.0 else None
        if light is not None and sensor.is_noisy(rng) and not edges.has_psf(optics):
            # a kept pattern's noisy frame: formed by the sensor on the box of pixels that see the facet
            signal = renderer.boxed(ambient, light)
        else:
            # (the signal is formed in this thread's scratch frame: it is read out into the frame and dropped)
            signal = renderer.linear(sample, ambient, scale, flicker, light,
                                     out=scratch_f32("twin.frame", self.geometry.camera.shape))
        return sensor.read_out(signal, rng, gain)

    # ------------------------------------------------------------- geometry
    def measured_distance_m(self) -> float:
        """Distance (m) from the true screen centre to the true surface point at ``design.measure_point_m``."""
        return self.trace.measured_distance_m()

    def corner_pixels(self) -> np.ndarray:
        """Image positions (N, 2) = (u, v) pixels of the true outline corners on the true surface."""
        return self.trace.corner_pixels()

    def footprint_check(self, max_slope_error_mrad: float) -> dict:
        """:meth:`FacetTrace.footprint_check <sofast_station.twin.trace.FacetTrace.footprint_check>`: the facet's
        reflected footprint, widened by ``2 * max_slope_error * path length``, must lie on the screen
        (``min_margin_m``, ``max_widening_m``, ``n_pixels``; GeometryError otherwise)."""
        return self.trace.footprint_check(max_slope_error_mrad)

    # ------------------------------------------------------- test support
    @property
    def coverage(self) -> np.ndarray:
        """Fraction (H, W) of each pixel's area covered by the facet (0 outside, 1 inside)."""
        out = self.trace.coverage.view()
        out.setflags(write=False)
        return out

    @property
    def rim_coverage(self) -> np.ndarray:
        """Fraction (H, W) of each pixel's area on the facet's bevelled rim (zero without one)."""
        out = self.trace.rim_coverage.view()
        out.setflags(write=False)
        return out

    @cached_property
    def rim_screen_position_m(self) -> np.ndarray:
        """Screen coordinates (H, W, 2) of the screen point each rim pixel's rim reflects; NaN elsewhere."""
        return self.trace.image(self.trace.rim_u_scr_m, np.nan, at=self.trace.rim_pos)

    @cached_property
    def screen_position_m(self) -> np.ndarray:
        """Screen coordinates (H, W, 2) = (u_x, u_y) metres of each facet pixel's centre ray; NaN elsewhere."""
        return self.trace.image(self.trace.u_scr_m, np.nan)

    @cached_property
    def surface_point_facet_m(self) -> np.ndarray:
        """True surface point (H, W, 3), true facet frame, metres, of each facet pixel's centre ray; NaN elsewhere."""
        return self.trace.image(self.trace.x_facet_m, np.nan)

    @cached_property
    def slope_true(self) -> np.ndarray:
        """Exact slopes (H, W, 2) = (dz/dx, dz/dy) of the true surface at :attr:`surface_point_facet_m`."""
        return self.trace.image(self.trace.slope, np.nan)

    @cached_property
    def on_screen(self) -> np.ndarray:
        """Whether (H, W) a facet pixel's centre ray lands on the screen's active area."""
        return self.trace.image(self.trace.on_screen, False)

    @property
    def vignetting_factor(self) -> np.ndarray:
        """Relative irradiance (H, W) after vignetting, 1 at the principal point."""
        out = self.renderer.vignetting.view()
        out.setflags(write=False)
        return out
