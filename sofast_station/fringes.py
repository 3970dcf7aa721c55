"""The fringe definition: which images the display shows, in which order (configuration data).

A capture is a dark frame, a white frame, then for x and then y each period count in increasing order,
``phase_steps`` images with shifts d_k = 2 pi k / phase_steps. With the defaults (periods 1 and 4, four
steps) that is 2 + 16 = 18 frames. Image k of a set shows I_k = a + b cos(phi - d_k), phi = 2 pi p u / L
(docs/conventions.md#phase).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from dataclasses import dataclass, field

import numpy as np

from .errors import ConfigError


class DisplayImage:
    """A fixed image of display commands (uint8, rows x columns, row 0 at the top), e.g. fiducials.

    Hashable by its content, so a :class:`Pattern` that shows it can be cached like the others.
    """

    __slots__ = ("pixels", "name", "_digest")

    def __init__(self, pixels, name: str = "image"):
        arr = np.ascontiguousarray(pixels)
        if arr.dtype != np.uint8 or arr.ndim != 2 or arr.size == 0:
            raise ConfigError(f"a display image must be a 2-D uint8 array of commands, got {arr.dtype} {arr.shape}")
        arr = arr.copy()
        arr.setflags(write=False)
        self.pixels = arr
        self.name = str(name)
        self._digest = hashlib.sha256(arr.tobytes() + repr(arr.shape).encode()).hexdigest()

    @property
    def shape(self) -> tuple[int, int]:
        return self.pixels.shape

    def __hash__(self) -> int:
        return hash(self._digest)

    def __eq__(self, other) -> bool:
        return isinstance(other, DisplayImage) and other._digest == self._digest

    def __repr__(self) -> str:
        return f"DisplayImage({self.name!r}, {self.shape[1]} x {self.shape[0]}, {self._digest[:8]})"


@dataclass(frozen=True)
class Pattern:
    """One display image.

    ``kind == "uniform"``: every pixel shows ``command`` (0..255).
    ``kind == "fringe"``: a sinusoid along ``axis`` with ``periods`` cycles across the screen, shifted by
    ``shift_rad``, spanning the calibrated floor..maximum through the linearising lookup table.
    ``kind == "image"``: the commands of ``image`` (a :class:`DisplayImage` of the display's size) as they
    are, not through the lookup table (fiducials are black and white).
    """

    kind: str
    axis: str = ""
    periods: float = 0.0
    shift_rad: float = 0.0
    command: int = 0
    image: DisplayImage | None = None

    @property
    def label(self) -> str:
        if self.kind == "uniform":
            return {0: "dark", 255: "white"}.get(self.command, f"uniform {self.command}")
        if self.kind == "image":
            return self.image.name if self.image is not None else "image"
        return f"{self.axis} p={self.periods:g} shift={self.shift_rad:.4f}"


@dataclass(frozen=True)
class FringeSet:
    """Periods (cycles across the active extent) per axis, increasing, and the number of phase steps.

    ``drawn`` is how the station's display draws them, not part of the definition (not compared): the
    radiometric record's lookup table the fringes go through and the display's size,
    ``(lut, floor_level, max_level, width_px, height_px)`` (:meth:`drawn_through`), or empty when unknown.
    From it the analysis knows the phase error each set shows from its rounding to whole 8-bit commands
    (:func:`~sofast_station.measure.phase.drawn_phase_error`) and takes it off the screen positions.
    """

    periods_x: tuple[float, ...] = (1.0, 4.0)
    periods_y: tuple[float, ...] = (1.0, 4.0)
    phase_steps: int = 4
    drawn: tuple = field(default=(), compare=False, hash=False, repr=False)

    def __post_init__(self):
        for name in ("periods_x", "periods_y"):
            p = tuple(float(v) for v in getattr(self, name))
            if not p or any(not (math.isfinite(v) and v > 0) for v in p):
                raise ConfigError(f"fringes.{name} must be a non-empty list of positive periods, got {list(p)}")
            if any(b <= a for a, b in zip(p, p[1:])):
                raise ConfigError(f"fringes.{name} must increase (coarse to fine), got {list(p)}")
            object.__setattr__(self, name, p)
        if int(self.phase_steps) != 4:
            raise ConfigError(f"fringes.phase_steps must be 4 (the phase and consistency formulas assume "
                              f"quarter-period shifts), got {self.phase_steps}")
        object.__setattr__(self, "phase_steps", int(self.phase_steps))

    def drawn_through(self, lut, floor_level: float, max_level: float, width_px: int, height_px: int) -> "FringeSet":
        """This definition as a display of *width_px* x *height_px* pixels draws it through the lookup table
        *lut* (command / 255 against linear level 0..1) between *floor_level* and *max_level*."""
        drawn = (tuple(float(v) for v in lut), float(floor_level), float(max_level), int(width_px), int(height_px))
        return dataclasses.replace(self, drawn=drawn)

    def samples_per_period(self, axis: str, periods: float) -> float | None:
        """Display pixels per period of the set (*axis*, *periods*) as drawn, or None when not known."""
        if not self.drawn:
            return None
        return float(self.drawn[3 if axis == "x" else 4]) / float(periods)

    @property
    def n_frames(self) -> int:
        return 2 + self.phase_steps * (len(self.periods_x) + len(self.periods_y))

    def patterns(self) -> list[Pattern]:
        """The display images in capture order."""
        out = [Pattern("uniform", command=0), Pattern("uniform", command=255)]
        for axis, periods in (("x", self.periods_x), ("y", self.periods_y)):
            for p in periods:
                for k in range(self.phase_steps):
                    out.append(Pattern("fringe", axis=axis, periods=p, shift_rad=2 * math.pi * k / self.phase_steps))
        return out

    def slices(self) -> dict[str, list[slice]]:
        """Frame index ranges of each phase-step set, per axis, in the order of ``periods_*``."""
        out: dict[str, list[slice]] = {"x": [], "y": []}
        i = 2
        for axis, periods in (("x", self.periods_x), ("y", self.periods_y)):
            for _ in periods:
                out[axis].append(slice(i, i + self.phase_steps))
                i += self.phase_steps
        return out

    def to_dict(self) -> dict:
        out = {"periods_x": list(self.periods_x), "periods_y": list(self.periods_y), "phase_steps": self.phase_steps}
        if self.drawn:
            lut, floor_level, max_level, width_px, height_px = self.drawn
            out["drawn"] = {"lut": list(lut), "floor_level": floor_level, "max_level": max_level,
                            "display_px": [width_px, height_px]}
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "FringeSet":
        """From :meth:`to_dict` (or station.toml's [fringes], which has no ``drawn``: the station adds it)."""
        unknown = set(d) - {"periods_x", "periods_y", "phase_steps", "drawn"}
        if unknown:
            raise ConfigError(f"[fringes] has unknown keys: {', '.join(sorted(unknown))}")
        out = cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k != "drawn"})
        drawn = d.get("drawn")
        if drawn:
            try:
                out = out.drawn_through(drawn["lut"], drawn["floor_level"], drawn["max_level"], *drawn["display_px"])
            except (KeyError, TypeError, ValueError) as exc:
                raise ConfigError(f"[fringes] drawn must hold lut, floor_level, max_level and display_px, got "
                                  f"{sorted(drawn) if isinstance(drawn, dict) else drawn!r} ({exc})") from None
        return out
