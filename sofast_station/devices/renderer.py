"""The fringe renderer: display images drawn by a fragment shader (moderngl).

One shader serves the real LCD (drawn into a full-screen window's framebuffer) and the simulated station
(drawn offscreen through EGL on Mesa and read back). Every display pixel is computed independently from
its centre position, so the image does not depend on the GPU:

* fringe: ``t = (1 + cos(2 pi p u / L - shift)) / 2``, ``y = floor + (maximum - floor) t``, the command
  value is the linearising lookup table evaluated at ``y`` (linear interpolation between entries) and
  rounded to the nearest of 0..255;
* uniform: every pixel shows the given command value;
* image: every pixel shows its command of a fixed image (fiducials), not through the lookup table.

``u`` is the position along the fringe axis measured from the left edge (x) or the bottom edge (y) of the
active area (docs/conventions.md#screen-positions): display column c is at
``u_x / W = (c + 1/2) / width_px``, display row r (0 = top) at ``u_y / H = (height_px - r - 1/2) / height_px``, which
are ``gl_FragCoord / size``.
"""

from __future__ import annotations

import logging

import moderngl
import numpy as np

from ..errors import DisplayError
from ..fringes import Pattern

log = logging.getLogger(__name__)

_VERTEX = """
#version 330
in vec2 in_pos;
void main() { gl_Position = vec4(in_pos, 0.0, 1.0); }
"""

_FRAGMENT = """
#version 330
uniform int mode;            // 0: uniform command, 1: fringe, 2: image
uniform float command;       // uniform mode: command / 255
uniform int axis;            // 0: x fringes, 1: y fringes
uniform float periods;       // cycles across the active extent
uniform float shift;         // radians
uniform float floor_level;   // linear response at the fringe minimum, 0..1
uniform float max_level;     // linear response at the fringe maximum, 0..1
uniform vec2 size;           // active area in display pixels
uniform sampler2D lut;       // N x 1, command / 255 as a function of linear response
uniform float lut_n;
uniform sampler2D picture;   // image mode: the commands / 255, row 0 at the bottom (OpenGL's)
out float frag;
void main() {
    float value;
    if (mode == 0) {
        value = command;
    } else if (mode == 2) {
        value = texelFetch(picture, ivec2(gl_FragCoord.xy), 0).r;
    } else {
        float frac = (axis == 0) ? gl_FragCoord.x / size.x : gl_FragCoord.y / size.y;
        float t = 0.5 + 0.5 * cos(6.283185307179586 * periods * frac - shift);
        float y = clamp(floor_level + (max_level - floor_level) * t, 0.0, 1.0);
        value = texture(lut, vec2((y * (lut_n - 1.0) + 0.5) / lut_n, 0.5)).r;
    }
    frag = floor(clamp(value, 0.0, 1.0) * 255.0 + 0.5) / 255.0;
}
"""


def identity_lut(n: int = 1024) -> np.ndarray:
    """A lookup table for an already linear display: command/255 equals the requested level."""
    return np.linspace(0.0, 1.0, n)


def create_offscreen_context():
    """A headless OpenGL 3.3 context through EGL (Mesa llvmpipe when there is no GPU)."""
    try:
        return moderngl.create_standalone_context(backend="egl", require=330)
    except Exception as exc:
        raise DisplayError(
            f"cannot create an offscreen OpenGL context through EGL ({exc}). Install Mesa's EGL and DRI "
            "drivers (Debian: libegl1 libegl-mesa0 libgl1-mesa-dri), as the README's setup command does") from exc


class FringeRenderer:
    """Draws :class:`~sofast_station.fringes.Pattern` images at the display's native resolution.

    Parameters
    ----------
    width_px, height_px : int
        Native display resolution.
    lut : (N,) array, optional
        Command/255 as a function of linear response level, sampled at N >= 2 equally spaced levels
        0..1 and increasing. Defaults to the identity (a display that is already linear).
    floor_level, max_level : float
        Linear response levels (0..1, as indexed by the table) of the fringe minimum and maximum.
    ctx : moderngl.Context, optional
        Context to draw with (a window's, for the LCD); an offscreen EGL context by default.
    """

    def __init__(self, width_px: int, height_px: int, lut: np.ndarray | None = None,
                 floor_level: float = 0.0, max_level: float = 1.0, ctx=None):
        if width_px <= 0 or height_px <= 0:
            raise DisplayError(f"display size must be positive, got {width_px} x {height_px}")
        lut = identity_lut() if lut is None else np.asarray(lut, dtype=np.float64)
        if lut.ndim != 1 or lut.size < 2 or not np.all(np.isfinite(lut)):
            raise DisplayError("the display lookup table must be a 1-D array of at least 2 finite values")
        if np.any(np.diff(lut) < 0) or lut.min() < 0 or lut.max() > 1:
            raise DisplayError("the display lookup table must increase and stay within 0..1 (command / 255); "
                               "rerun the radiometric calibration")
        if not (0.0 <= floor_level < max_level <= 1.0):
            raise DisplayError(f"fringe levels must satisfy 0 <= floor < maximum <= 1, got "
                               f"{floor_level}, {max_level}")
        self.width_px, self.height_px = int(width_px), int(height_px)
        self.floor_level, self.max_level = float(floor_level), float(max_level)
        self._own_ctx = ctx is None
        self.ctx = create_offscreen_context() if ctx is None else ctx
        self._prog = self.ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
        quad = np.array([-1, -1, 1, -1, -1, 1, 1, 1], dtype="f4")
        self._vbo = self.ctx.buffer(quad.tobytes())
        self._vao = self.ctx.vertex_array(self._prog, [(self._vbo, "2f", "in_pos")])
        self._lut = self.ctx.texture((lut.size, 1), 1, lut.astype("f4").tobytes(), dtype="f4")
        self._lut.filter = (self.ctx.LINEAR, self.ctx.LINEAR)
        self._lut.repeat_x = self._lut.repeat_y = False
        self._prog["lut"].value = 0
        self._prog["picture"].value = 1
        self._picture = None            # (DisplayImage, texture) of the last image drawn
        self._prog["lut_n"].value = float(lut.size)
        self._prog["size"].value = (float(self.width_px), float(self.height_px))
        self._fbo = None

    def draw(self, pattern: Pattern) -> None:
        """Draw *pattern* into the context's current framebuffer (the window's, on the LCD)."""
        p = self._prog
        if pattern.kind == "uniform":
            if not 0 <= pattern.command <= 255:
                raise DisplayError(f"uniform command must be 0..255, got {pattern.command}")
            p["mode"].value = 0
            p["command"].value = pattern.command / 255.0
        elif pattern.kind == "fringe":
            if pattern.axis not in ("x", "y"):
                raise DisplayError(f"fringe axis must be 'x' or 'y', got {pattern.axis!r}")
            p["mode"].value = 1
            p["axis"].value = 0 if pattern.axis == "x" else 1
            p["periods"].value = float(pattern.periods)
            p["shift"].value = float(pattern.shift_rad)
            p["floor_level"].value = self.floor_level
            p["max_level"].value = self.max_level
        elif pattern.kind == "image":
            image = pattern.image
            if image is None or image.shape != (self.height_px, self.width_px):
                raise DisplayError(f"an image pattern must be {self.width_px} x {self.height_px} commands, got "
                                   f"{None if image is None else image.shape[::-1]}")
            if self._picture is None or self._picture[0] != image:
                if self._picture is not None:
                    self._picture[1].release()
                tex = self.ctx.texture((self.width_px, self.height_px), 1,
                                       (image.pixels[::-1].astype("f4") / 255.0).tobytes(), dtype="f4")
                tex.filter = (self.ctx.NEAREST, self.ctx.NEAREST)
                self._picture = (image, tex)
            self._picture[1].use(location=1)
            p["mode"].value = 2
        else:
            raise DisplayError(f"unknown pattern kind {pattern.kind!r}")
        self._lut.use(location=0)
        self._vao.render(mode=self.ctx.TRIANGLE_STRIP)

    def render(self, pattern: Pattern) -> np.ndarray:
        """Draw *pattern* offscreen and return it as uint8 (height_px, width_px), row 0 at the top."""
        if self._fbo is None:
            self._fbo = self.ctx.simple_framebuffer((self.width_px, self.height_px), components=1)
        self._fbo.use()
        self.ctx.viewport = (0, 0, self.width_px, self.height_px)
        self.draw(pattern)
        raw = self._fbo.read(components=1, alignment=1)
        img = np.frombuffer(raw, dtype=np.uint8).reshape(self.height_px, self.width_px)
        return np.ascontiguousarray(img[::-1])

    def render_all(self, patterns: list[Pattern]) -> np.ndarray:
        """Render a sequence; returns uint8 (n, height_px, width_px)."""
        return np.stack([self.render(p) for p in patterns])

    def release(self) -> None:
        if self._picture is not None:
            self._picture[1].release()
            self._picture = None
        for obj in (self._fbo, self._vao, self._vbo, self._lut, self._prog):
            if obj is not None:
                obj.release()
        self._fbo = None
        if self._own_ctx:
            self.ctx.release()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()
