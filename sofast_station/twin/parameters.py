"""The digital twin's parameters (``[simulation]`` in station.toml): the true facet and the optical
nonidealities.

Two frozen records, each with ``from_dict`` (rejects unknown keys, naming them) and ``to_dict``:

* :class:`TrueFacet` -- the facet's true shape and its true placement in the fixture;
* :class:`TwinOptics` -- display, reflection, ambient light, camera response, noise and vignetting.

Neither record computes anything; :mod:`sofast_station.twin.surface` and
:mod:`sofast_station.twin.station` consume them.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass

from ..errors import ConfigError
from .edges import EDGE_SAMPLING as _EDGE_SAMPLING

_DENT_KEYS = ("x_m", "y_m", "depth_m", "radius_m")


def _number(owner: str, key: str, value, *, allow_inf: bool = False) -> float:
    """Convert *value* to float, rejecting booleans, non-numbers and (unless allowed) infinities."""
    if isinstance(value, str) and allow_inf and value.strip().lower() in ("inf", "+inf", "-inf", "infinity",
                                                                          "+infinity", "-infinity"):
        value = float(value)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{owner}.{key} must be a number, got {value!r}")
    number = float(value)
    if math.isnan(number) or (math.isinf(number) and not allow_inf):
        raise ConfigError(f"{owner}.{key} must be a finite number, got {value!r}")
    return number


def _vector(owner: str, key: str, value, length: int) -> tuple[float, ...]:
    """Convert a sequence of *length* numbers to a tuple of floats."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != length:
        raise ConfigError(f"{owner}.{key} must be a list of {length} numbers, got {value!r}")
    return tuple(_number(owner, f"{key}[{i}]", v) for i, v in enumerate(value))


def _check_keys(owner: str, d: dict, cls) -> None:
    """Raise ConfigError naming the first key of *d* that is not a field of *cls*."""
    if not isinstance(d, dict):
        raise ConfigError(f"{owner} must be a table (dict), got {type(d).__name__}")
    known = [f.name for f in dataclasses.fields(cls)]
    for key in d:
        if key not in known:
            raise ConfigError(f"{owner}: unknown key {key!r}; remove it or use one of {', '.join(known)}")


@dataclass(frozen=True)
class TrueFacet:
    """The true shape of a facet and its true placement in the fixture.

    The true surface, in the true facet frame (origin at the paraboloid vertex, as for the design), is ::

        z = x^2 / (4 f_x) + y^2 / (4 f_y) + E x y + l_x x + l_y y + c
            + c30 u^3 + c21 u^2 v + c12 u v^2 + c03 v^3          (u, v) = (x - cx, y - cy)
            + sum of dents  depth * exp(-r^2 / (2 radius^2))
            + random small-scale height field

    with (cx, cy) the design outline's centroid, and l_x, l_y, c such that the quadratic part touches the
    design surface at (cx, cy) with the same height and normal: placed perfectly, a facet sits in the
    fixture on its middle, and its focal-length error and twist grow away from there. (For an on-axis
    facet, whose middle is the vertex, they vanish.)

    Parameters
    ----------
    focal_length_x_m, focal_length_y_m : float or None
        True focal lengths along x and y, metres. ``None`` means the design focal length; ``math.inf``
        means zero curvature (a flat direction); negative means convex.
    twist_mrad_per_m : float
        Twist 1000 E, mrad/m: dz/dx gets ``+E y`` and dz/dy gets ``+E x``.
    placement_mm : (dx, dy, dz)
        Translation t of the true facet frame relative to the fixture frame, millimetres.
    placement_mrad : (rx, ry, rz)
        Rotation R = R_z(rz) R_y(ry) R_x(rx), milliradians, about the facet's middle
        P_mid = (cx, cy, z_design(cx, cy)): ``x_fixture = R (x_facet - P_mid) + P_mid + t``.
    cubic_per_m2 : (c30, c21, c12, c03)
        Low-order shape error coefficients, 1/m^2 (heights in metres).
    dents : tuple of dict
        Gaussian bumps ``{"x_m", "y_m", "depth_m", "radius_m"}`` (facet frame, metres); a negative depth
        is a dent.
    slope_error_rms_mrad : float
        RMS, per slope component over the outline, of the random small-scale slope error, mrad.
    slope_error_correlation_m : float
        Standard deviation of the Gaussian filter that correlates the random height field, metres.
    surface_seed : int
        Seed of the random height field; a given seed always gives the same surface.
    """

    focal_length_x_m: float | None = None
    focal_length_y_m: float | None = None
    twist_mrad_per_m: float = 0.0
    placement_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    placement_mrad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    cubic_per_m2: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    dents: tuple[dict, ...] = ()
    slope_error_rms_mrad: float = 0.0
    slope_error_correlation_m: float = 0.02
    surface_seed: int = 0

    def __post_init__(self):
        owner = "TrueFacet"
        for key in ("focal_length_x_m", "focal_length_y_m"):
            value = getattr(self, key)
            if value is not None:
                f = _number(owner, key, value, allow_inf=True)
                if f == 0.0:
                    raise ConfigError(f"{owner}.{key} must not be 0 (use math.inf for a flat direction, "
                                      "None for the design focal length)")
                object.__setattr__(self, key, f)
        object.__setattr__(self, "twist_mrad_per_m", _number(owner, "twist_mrad_per_m", self.twist_mrad_per_m))
        object.__setattr__(self, "placement_mm", _vector(owner, "placement_mm", self.placement_mm, 3))
        object.__setattr__(self, "placement_mrad", _vector(owner, "placement_mrad", self.placement_mrad, 3))
        object.__setattr__(self, "cubic_per_m2", _vector(owner, "cubic_per_m2", self.cubic_per_m2, 4))
        if isinstance(self.dents, dict) or not hasattr(self.dents, "__iter__"):
            raise ConfigError(f"{owner}.dents must be a list of tables {{x_m, y_m, depth_m, radius_m}}")
        dents = []
        for i, dent in enumerate(self.dents):
            where = f"dents[{i}]"
            if not isinstance(dent, dict):
                raise ConfigError(f"{owner}.{where} must be a table {{x_m, y_m, depth_m, radius_m}}, got {dent!r}")
            for key in dent:
                if key not in _DENT_KEYS:
                    raise ConfigError(f"{owner}.{where}: unknown key {key!r}; use {', '.join(_DENT_KEYS)}")
            missing = [k for k in _DENT_KEYS if k not in dent]
            if missing:
                raise ConfigError(f"{owner}.{where} is missing {', '.join(missing)}")
            clean = {k: _number(owner, f"{where}.{k}", dent[k]) for k in _DENT_KEYS}
            if clean["radius_m"] <= 0:
                raise ConfigError(f"{owner}.{where}.radius_m must be positive metres, got {clean['radius_m']}")
            dents.append(clean)
        object.__setattr__(self, "dents", tuple(dents))
        rms = _number(owner, "slope_error_rms_mrad", self.slope_error_rms_mrad)
        if rms < 0:
            raise ConfigError(f"{owner}.slope_error_rms_mrad must be >= 0, got {rms}")
        object.__setattr__(self, "slope_error_rms_mrad", rms)
        corr = _number(owner, "slope_error_correlation_m", self.slope_error_correlation_m)
        if not 1e-4 <= corr <= 1.0:
            raise ConfigError(f"{owner}.slope_error_correlation_m must lie in [1e-4, 1] metres, got {corr}")
        object.__setattr__(self, "slope_error_correlation_m", corr)
        seed = self.surface_seed
        if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
            raise ConfigError(f"{owner}.surface_seed must be a non-negative integer, got {seed!r}")
        object.__setattr__(self, "surface_seed", int(seed))

    def to_dict(self) -> dict:
        """Plain-data form (lists for tuples); an infinite focal length stays ``math.inf``."""
        return {"focal_length_x_m": self.focal_length_x_m, "focal_length_y_m": self.focal_length_y_m,
                "twist_mrad_per_m": self.twist_mrad_per_m, "placement_mm": list(self.placement_mm),
                "placement_mrad": list(self.placement_mrad), "cubic_per_m2": list(self.cubic_per_m2),
                "dents": [dict(d) for d in self.dents], "slope_error_rms_mrad": self.slope_error_rms_mrad,
                "slope_error_correlation_m": self.slope_error_correlation_m, "surface_seed": self.surface_seed}

    @classmethod
    def from_dict(cls, d: dict) -> "TrueFacet":
        """Build from plain data; unknown keys raise ConfigError. Focal lengths may be ``"inf"``."""
        _check_keys("TrueFacet", d, cls)
        return cls(**d)


class _ClassOrInstanceMethod:
    """Descriptor: the method receives the instance when called on one, else ``None`` and the class."""

    def __init__(self, func):
        self.func = func
        self.__doc__ = func.__doc__

    def __get__(self, obj, cls):
        def bound(*args, **kwargs):
            return self.func(cls, obj, *args, **kwargs)
        bound.__doc__ = self.__doc__
        return bound


@dataclass(frozen=True)
class TwinOptics:
    """Optical and electronic nonidealities of the simulated station.

    Radiances are fractions of the display's full-white luminance; DN are camera digital numbers.

    Parameters
    ----------
    display_gamma, display_floor : float
        Display luminance of command v (0..255): ``floor + (1 - floor) * (v / 255) ** gamma``.
    reflectance : float
        Specular reflectance of the facet (0, 1].
    ambient : float
        Ambient radiance reflected by the facet, fraction of white.
    ambient_jitter : float
        Relative standard deviation of the ambient level, drawn once per capture from its rng.
    background : float
        Radiance of what surrounds the facet in the image, fraction of white.
    camera_offset_dn : float
        Black level, DN.
    white_dn : float
        Linear (before the knee) DN produced by full white reflected at the brightest facet pixel, with
        the nominal ambient, black level included. This sets the camera's gain.
    knee_dn : float or None
        If set, the response above it bends smoothly (C1, monotone) toward 255 DN.
    read_noise_dn : float
        Read noise standard deviation, DN.
    electrons_per_dn : float
        Conversion gain for shot noise: variance in DN^2 = signal_DN / electrons_per_dn; 0 turns shot
        noise off.
    vignetting : float
        Relative falloff at the farthest image corner, quadratic in the radius from the principal point.
    reference_exposure_s : float
        Exposure time, seconds, at which ``white_dn`` holds at gain 1. The sensor's signal above the black
        level is proportional to exposure x gain (:meth:`TwinStation.capture`); read noise scales with the
        gain, shot noise with the signal, and the counts clip at 255.
    refresh_hz : float
        The display's refresh rate, Hz: its backlight and pixel refresh modulate the light at this
        frequency.
    flicker_depth : float
        Relative amplitude m of that modulation, luminance x (1 + m cos(2 pi (f t + phase))): an exposure of
        a whole number of refresh periods integrates it away; any other exposure sees a brightness error
        that depends on the phase at which it starts (drawn per grab by the simulated camera).
    display_latency_s : float
        Time from the display being asked to show an image to the image being on the panel, seconds. The
        simulated camera sees the previous image until then (:mod:`sofast_station.devices.simulated`),
        unless the display's settle time covers it.
    blur_px : float
        Standard deviation of the lens's Gaussian point-spread function, camera pixels (defocus). 0 (the
        default) gives sharply area-sampled edges: each pixel's value is the light falling on its area.
    edge_sampling : {"area", "point", "grid"}
        How a pixel samples the facet's edge (:mod:`sofast_station.twin.edges`): ``"area"`` its exact
        covered area, ``"point"`` its centre ray only (a staircase edge), ``"grid"`` the mean of
        ``edge_grid**2`` sub-rays on a regular grid.
    edge_grid : int
        Sub-rays per pixel side for ``edge_sampling = "grid"`` (2 to 16).
    defocus_px : float
        Radius of a uniform-disk point-spread function (a defocused lens's blur circle), pixels; 0 is none.
    bevel_width_mm : float
        Width of a bevelled rim inside the facet's outline, millimetres; 0 (the default) is none.
    bevel_tilt_mrad : float
        The rim's surface normal turned outward from the facet's by this angle, mrad (it reflects the screen
        at another angle: other fringes when small, dark when its rays miss the screen).
    bevel_reflectance : float
        The rim's specular reflectance relative to the facet's, [0, 1].
    vignetting_exponent : float
        Shape of the fall-off: ``1 - vignetting (r / r_corner)^vignetting_exponent`` (2: quadratic).
    screen_grid : int
        Sub-rays per pixel side whose display samples a pixel averages (:mod:`sofast_station.twin.edges`,
        model (f)): 1 (the default) samples the display at the screen point of each pixel's centre ray only;
        n (2 to 8) averages the display's light at the screen points of n x n sub-rays on a regular grid over
        the pixel, each traced to the true surface and reflected about its own exact normal: the pixel
        integrates the display over its footprint on the screen, as a camera does.
    mark_radiance : float
        What the fixture's marks (``[marks]``, :mod:`sofast_station.twin.marks`), white discs lit by the hall's
        lights, send the camera, as a fraction of the display's white seen in the facet: the same in every
        frame. A matt white target under 500 lx reads about 150 cd/m^2, half an office LCD's white: 0.5.
    """

    display_gamma: float = 2.2
    display_floor: float = 0.02
    reflectance: float = 0.93
    ambient: float = 0.01
    ambient_jitter: float = 0.2
    background: float = 0.005
    camera_offset_dn: float = 4.0
    white_dn: float = 235.0
    knee_dn: float | None = None
    read_noise_dn: float = 0.8
    electrons_per_dn: float = 40.0
    vignetting: float = 0.15
    reference_exposure_s: float = 1.0 / 60.0
    refresh_hz: float = 60.0
    flicker_depth: float = 0.25
    display_latency_s: float = 0.0
    blur_px: float = 0.0
    edge_sampling: str = "area"
    edge_grid: int = 4
    defocus_px: float = 0.0
    bevel_width_mm: float = 0.0
    bevel_tilt_mrad: float = 0.0
    bevel_reflectance: float = 1.0
    vignetting_exponent: float = 2.0
    mark_radiance: float = 0.5
    screen_grid: int = 1

    def __post_init__(self):
        owner = "TwinOptics"
        if self.edge_sampling not in _EDGE_SAMPLING:
            raise ConfigError(f"{owner}.edge_sampling must be one of {', '.join(map(repr, _EDGE_SAMPLING))}, "
                              f"got {self.edge_sampling!r}")
        grid = self.edge_grid
        if isinstance(grid, bool) or not isinstance(grid, numbers.Integral) or not 2 <= grid <= 16:
            raise ConfigError(f"{owner}.edge_grid must be a whole number of sub-rays per pixel side from 2 to 16, "
                              f"got {grid!r}")
        object.__setattr__(self, "edge_grid", int(grid))
        grid = self.screen_grid
        if isinstance(grid, bool) or not isinstance(grid, numbers.Integral) or not 1 <= grid <= 8:
            raise ConfigError(f"{owner}.screen_grid must be a whole number of sub-rays per pixel side from 1 to 8 "
                              f"(1: the centre ray only), got {grid!r}")
        object.__setattr__(self, "screen_grid", int(grid))
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if (f.name == "knee_dn" and value is None) or f.name in ("edge_sampling", "edge_grid", "screen_grid"):
                continue
            object.__setattr__(self, f.name, _number(owner, f.name, value))
        checks = [
            ("display_gamma", self.display_gamma > 0, "must be positive"),
            ("display_floor", 0 <= self.display_floor < 1, "must lie in [0, 1)"),
            ("reflectance", 0 < self.reflectance <= 1, "must lie in (0, 1]"),
            ("ambient", self.ambient >= 0, "must be >= 0"),
            ("ambient_jitter", self.ambient_jitter >= 0, "must be >= 0"),
            ("background", self.background >= 0, "must be >= 0"),
            ("camera_offset_dn", 0 <= self.camera_offset_dn < 255, "must lie in [0, 255)"),
            ("white_dn", self.white_dn > self.camera_offset_dn, "must exceed camera_offset_dn"),
            ("read_noise_dn", self.read_noise_dn >= 0, "must be >= 0"),
            ("mark_radiance", 0 <= self.mark_radiance <= 1, "must lie in [0, 1]"),
            ("electrons_per_dn", self.electrons_per_dn >= 0, "must be >= 0 (0 turns shot noise off)"),
            ("vignetting", 0 <= self.vignetting < 1, "must lie in [0, 1)"),
            ("reference_exposure_s", self.reference_exposure_s > 0, "must be a positive time in seconds"),
            ("refresh_hz", self.refresh_hz > 0, "must be a positive frequency in Hz"),
            ("flicker_depth", 0 <= self.flicker_depth < 1, "must lie in [0, 1)"),
            ("display_latency_s", self.display_latency_s >= 0, "must be >= 0 seconds"),
            ("blur_px", 0 <= self.blur_px <= 10, "must lie in [0, 10] pixels"),
            ("defocus_px", 0 <= self.defocus_px <= 10, "must lie in [0, 10] pixels"),
            ("bevel_width_mm", 0 <= self.bevel_width_mm <= 50, "must lie in [0, 50] millimetres"),
            ("bevel_tilt_mrad", abs(self.bevel_tilt_mrad) <= 1000, "must lie in [-1000, 1000] mrad"),
            ("bevel_reflectance", 0 <= self.bevel_reflectance <= 1, "must lie in [0, 1]"),
            ("vignetting_exponent", 0.5 <= self.vignetting_exponent <= 16, "must lie in [0.5, 16]"),
        ]
        if self.knee_dn is not None:
            checks.append(("knee_dn", self.camera_offset_dn < self.knee_dn < 255,
                           "must lie between camera_offset_dn and 255 (or be None)"))
        for key, ok, rule in checks:
            if not ok:
                raise ConfigError(f"{owner}.{key} {rule}, got {getattr(self, key)!r}")

    @property
    def has_noise(self) -> bool:
        """True when a capture with an rng draws any random term."""
        return self.read_noise_dn > 0 or self.electrons_per_dn > 0 or self.ambient_jitter > 0

    @_ClassOrInstanceMethod
    def noise_free(cls, self=None) -> "TwinOptics":
        """Optics with every random term off (read noise, shot noise, ambient jitter).

        Called on the class, returns the defaults without noise; called on an instance, a copy of it.
        """
        base = self if self is not None else cls()
        return dataclasses.replace(base, read_noise_dn=0.0, electrons_per_dn=0.0, ambient_jitter=0.0)

    def to_dict(self) -> dict:
        """Plain-data form."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TwinOptics":
        """Build from plain data; unknown keys raise ConfigError naming the key."""
        _check_keys("TwinOptics", d, cls)
        return cls(**d)
