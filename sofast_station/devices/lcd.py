"""The real LCD display: a borderless window covering one monitor, fringes drawn by the shader renderer.

The window is an undecorated, non-resizable, always-on-top window of exactly the monitor's size, placed
at the monitor's position (not exclusive full screen, which window managers handle less predictably).
Its OpenGL 3.3 core context draws every image with the same :class:`~.renderer.FringeRenderer` (and
shader) as the simulated station, at the monitor's native resolution, so that display pixel (column c,
row r) of a pattern is the LCD's pixel (c, r).

Presentation is two GPU passes. The renderer's shader writes one channel (``out float``), which into
the window's RGBA framebuffer would light the red sub-pixels only and leave green, blue and alpha
undefined (Mesa writes 0). So the renderer draws into a one-channel 8-bit texture, and a second
trivial shader copies it to the window as grey, ``(v, v, v, 1)``, with ``texelFetch`` (no filtering,
8-bit values copied exactly). The window then shows, in each of R, G and B, exactly the command values
``FringeRenderer.render`` returns offscreen.

glfw and OpenGL contexts belong to a thread: create, use and close an :class:`LcdDisplay` from one
thread (the station's). glfw is process-global; several displays (or :func:`list_monitors` while a
display is open) share one initialisation, terminated when the last display closes.

The window system is X11 (on a Wayland desktop: XWayland), the only one that lets a client place its
window on a given monitor; ``DISPLAY`` must be set.
"""

from __future__ import annotations

import ctypes
import logging
import math
import os
import threading
import time

import moderngl
import numpy as np

from ..errors import DisplayError
from ..fringes import Pattern
from .renderer import FringeRenderer

log = logging.getLogger(__name__)

#: How long the window manager gets to map and place the window, seconds.
PLACEMENT_TIMEOUT_S = 2.0

_VERTEX = """
#version 330
in vec2 in_pos;
void main() { gl_Position = vec4(in_pos, 0.0, 1.0); }
"""

_PRESENT_FRAGMENT = """
#version 330
uniform sampler2D image;     // the renderer's one-channel image, same size as the window
out vec4 frag;
void main() {
    float v = texelFetch(image, ivec2(gl_FragCoord.xy), 0).r;
    frag = vec4(v, v, v, 1.0);
}
"""

_SETUP_HINT = ("install the glfw Python package (pip install glfw; its wheel bundles the glfw library) and "
               "the X client libraries it loads (Debian: libx11-6 libxrandr2 libxinerama1 libxcursor1 libxi6)")

# glfw state shared by every LcdDisplay of the process (glfw itself is process-global).
_lock = threading.RLock()
_users = 0                                   # open LcdDisplay windows holding glfw initialised
_messages: list[tuple[int, str]] = []        # glfw errors since the last _take_messages()
_previous_callback = None
_egl_unbinds = 0                             # how often an EGL context had to be unbound (logged once)


def _import_glfw():
    try:
        # optional: glfw is the hardware extra (the LCD's window)
        import glfw
    except ImportError as exc:
        raise DisplayError(f"the LCD display cannot load glfw ({exc}): {_SETUP_HINT}") from exc
    return glfw


def _on_glfw_error(code: int, description) -> None:
    text = description.decode("utf-8", "replace") if isinstance(description, bytes) else str(description)
    _messages.append((int(code), text))
    log.debug("glfw error 0x%X: %s", code, text)


def _take_messages() -> str:
    text = "; ".join(f"{msg} (glfw 0x{code:X})" for code, msg in _messages) or "no details from glfw"
    _messages.clear()
    return text


def _error_codes() -> set[int]:
    return {code for code, _ in _messages}


def _release_egl_context_of_this_thread() -> None:
    """Unbind an EGL context current on this thread, if any, before a GLX context is made current.

    With libglvnd, making a GLX context current on a thread that still has an EGL context current (an
    offscreen :class:`~.renderer.FringeRenderer`: moderngl leaves it bound even after ``release``)
    fails with a BadAccess X error, and Xlib's default handler then exits the whole process. The EGL
    context itself survives; its owner must make it current again before drawing with it.
    """
    try:
        egl = ctypes.CDLL("libEGL.so.1", mode=os.RTLD_NOLOAD)
    except OSError:
        return                                   # libEGL not loaded: no EGL context can be current
    global _egl_unbinds
    egl.eglGetCurrentContext.restype = ctypes.c_void_p
    if egl.eglGetCurrentContext():
        _egl_unbinds += 1
        log.log(logging.WARNING if _egl_unbinds == 1 else logging.DEBUG,
                "an EGL (offscreen) OpenGL context was current on this thread; unbinding it so that the LCD "
                "window's context can be made current (an offscreen renderer and the LCD share this thread)")
        egl.eglReleaseThread()


def _check_display_variable() -> str:
    display = os.environ.get("DISPLAY", "")
    if not display:
        wayland = " (WAYLAND_DISPLAY is set: enable XWayland, which sets DISPLAY)" \
            if os.environ.get("WAYLAND_DISPLAY") else ""
        raise DisplayError(
            "DISPLAY is not set: the LCD window needs an X server" + wayland + ". Run the station inside the "
            "LCD's desktop session, or set DISPLAY to that session's X display (e.g. DISPLAY=:0) and make "
            "sure this user may connect to it (XAUTHORITY)")
    return display


def _glfw_acquire(glfw) -> None:
    """Initialise glfw (X11) for one more user; the first user initialises it."""
    global _users, _previous_callback
    if _users == 0:
        display = _check_display_variable()
        _messages.clear()
        _previous_callback = glfw.set_error_callback(_on_glfw_error)
        # glfw 3.4 may pick Wayland; only X11 lets a window be placed on a given monitor.
        if glfw.get_version() >= (3, 4, 0) and hasattr(glfw, "PLATFORM"):
            glfw.init_hint(glfw.PLATFORM, glfw.PLATFORM_X11)
        if not glfw.init():
            codes, details = _error_codes(), _take_messages()
            glfw.set_error_callback(_previous_callback)
            if getattr(glfw, "PLATFORM_UNAVAILABLE", None) in codes or "display" in details.lower():
                raise DisplayError(
                    f"cannot open the X display DISPLAY={display} ({details}). Check that the X server of "
                    "the LCD is running and that this user may connect to it (XAUTHORITY, xhost)")
            raise DisplayError(f"glfw could not initialise on DISPLAY={display} ({details}); {_SETUP_HINT}")
    _users += 1


def _glfw_release(glfw) -> None:
    """One user less; the last one terminates glfw (destroying every remaining window)."""
    global _users
    _users = max(0, _users - 1)
    if _users == 0:
        glfw.terminate()
        glfw.set_error_callback(_previous_callback)
        _messages.clear()


def _monitor_info(glfw, monitor) -> dict:
    name = glfw.get_monitor_name(monitor)
    name = name.decode("utf-8", "replace") if isinstance(name, bytes) else str(name)
    x, y = glfw.get_monitor_pos(monitor)
    mode = glfw.get_video_mode(monitor)
    width, height = (int(mode.size.width), int(mode.size.height)) if mode is not None else (0, 0)
    return {"name": name, "x": int(x), "y": int(y), "width_px": width, "height_px": height}


def list_monitors() -> list[dict]:
    """The monitors of the X display ``DISPLAY``, as glfw sees them.

    Returns
    -------
    list of dict
        One per monitor, primary first: ``name`` (str, the name :class:`LcdDisplay` is given, e.g. an
        output name such as ``"DP-1"``; Xvfb's single monitor is ``"screen"``), ``x`` and ``y`` (int,
        position of its top-left corner on the virtual desktop, pixels) and ``width_px`` and
        ``height_px`` (int, its current video mode, pixels; 0 when it reports no mode).

    Raises
    ------
    DisplayError
        glfw is missing, ``DISPLAY`` is not set or the X display cannot be opened.
    """
    glfw = _import_glfw()
    with _lock:
        _glfw_acquire(glfw)
        try:
            return [_monitor_info(glfw, m) for m in (glfw.get_monitors() or [])]
        finally:
            _glfw_release(glfw)


def _describe(monitors: list[dict]) -> str:
    return ", ".join(f"{m['name']!r} ({m['width_px']} x {m['height_px']} px at {m['x']}, {m['y']})"
                     for m in monitors) or "none"


class LcdDisplay:
    """The fringe display on a real monitor (implements :class:`~.protocols.Display`).

    Parameters
    ----------
    monitor : str
        Name of the monitor the LCD is (see :func:`list_monitors`; glfw's ``glfwGetMonitorName``).
    width_px, height_px : int
        The LCD's native resolution, pixels. The monitor's current video mode must have this size.
    lut : (N,) array or None
        Linearising lookup table, command/255 as a function of linear response level 0..1 (see
        :class:`~.renderer.FringeRenderer`); None for the identity.
    floor_level, max_level : float
        Linear response levels (0..1) of the fringe minimum and maximum.
    settle_s : float
        Time to wait after an image is presented before :meth:`show` returns, seconds (the LCD's
        latency and response time; the display-latency calibration's value when there is one).

    Raises
    ------
    DisplayError
        glfw cannot be loaded, ``DISPLAY`` is unset or unreachable, no monitor has that name, the
        monitor's video mode is not ``width_px`` x ``height_px``, the window manager would not place
        the window over the monitor, or there is no OpenGL 3.3 core context. The message says what to do.

    Notes
    -----
    Create, use and close the display from one thread.
    """

    def __init__(self, monitor: str, width_px: int, height_px: int, lut: np.ndarray | None,
                 floor_level: float, max_level: float, settle_s: float):
        settle_s = float(settle_s)
        if not (math.isfinite(settle_s) and settle_s >= 0):
            raise DisplayError(f"the display settle time must be a finite number of seconds >= 0, got {settle_s}")
        if int(width_px) <= 0 or int(height_px) <= 0:
            raise DisplayError(f"display size must be positive, got {width_px} x {height_px}")
        self.monitor = str(monitor)
        self.width_px, self.height_px = int(width_px), int(height_px)
        self.settle_s = settle_s
        self.renderer: FringeRenderer | None = None
        self.ctx = None
        self._window = None
        self._gl_objects: list = []
        self._thread = threading.get_ident()
        self._glfw = glfw = _import_glfw()
        with _lock:
            _glfw_acquire(glfw)
            try:
                self._open(glfw, lut, float(floor_level), float(max_level))
            except BaseException:
                self._teardown()
                raise

    # -- creation ------------------------------------------------------------------------------------

    def _open(self, glfw, lut, floor_level: float, max_level: float) -> None:
        monitors = glfw.get_monitors() or []
        infos = [_monitor_info(glfw, m) for m in monitors]
        found = [i for i, info in enumerate(infos) if info["name"] == self.monitor]
        if not found:
            raise DisplayError(
                f"no monitor named {self.monitor!r} on DISPLAY={os.environ.get('DISPLAY')}; found: "
                f"{_describe(infos)}. Set the display's monitor name in station.toml to one of these")
        info = infos[found[0]]
        if (info["width_px"], info["height_px"]) != (self.width_px, self.height_px):
            raise DisplayError(
                f"monitor {self.monitor!r} runs at {info['width_px']} x {info['height_px']} px but the station "
                f"is configured for {self.width_px} x {self.height_px} px: the fringes must be drawn at the "
                f"screen's native resolution. If {self.width_px} x {self.height_px} is the LCD's native "
                f"resolution, set that video mode (display settings, or xrandr --output {self.monitor} --mode "
                f"{self.width_px}x{self.height_px}); otherwise correct the screen's width_px, height_px (and "
                "pitch) in station.toml")
        x, y = info["x"], info["y"]
        self._position = (x, y)

        glfw.default_window_hints()
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 3)
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
        glfw.window_hint(glfw.DOUBLEBUFFER, True)
        glfw.window_hint(glfw.SAMPLES, 0)
        glfw.window_hint(glfw.SRGB_CAPABLE, False)
        glfw.window_hint(glfw.DECORATED, False)
        glfw.window_hint(glfw.RESIZABLE, False)
        glfw.window_hint(glfw.FLOATING, True)          # always on top, where the window manager allows it
        glfw.window_hint(glfw.AUTO_ICONIFY, False)
        glfw.window_hint(glfw.VISIBLE, False)          # placed first, then shown
        if glfw.get_version() >= (3, 4, 0) and hasattr(glfw, "POSITION_X"):
            glfw.window_hint(glfw.POSITION_X, x)
            glfw.window_hint(glfw.POSITION_Y, y)
        _take_messages()
        _release_egl_context_of_this_thread()   # glfw makes the new context current while creating it
        window = glfw.create_window(self.width_px, self.height_px, "sofast-station fringes", None, None)
        if not window:
            codes, details = _error_codes(), _take_messages()
            if codes & {glfw.VERSION_UNAVAILABLE, glfw.API_UNAVAILABLE, glfw.FORMAT_UNAVAILABLE}:
                raise DisplayError(
                    f"the X display offers no OpenGL 3.3 core context ({details}). Install the GPU's OpenGL "
                    "driver, or Mesa (Debian: libgl1 libglx-mesa0 libgl1-mesa-dri); glxinfo -B shows what "
                    "the display offers")
            raise DisplayError(f"cannot create the fringe window ({details})")
        self._window = window
        glfw.set_window_pos(window, x, y)
        glfw.show_window(window)
        glfw.make_context_current(window)
        glfw.swap_interval(1)
        glfw.set_input_mode(window, glfw.CURSOR, glfw.CURSOR_HIDDEN)
        self._wait_for_placement(glfw, window)

        try:
            self.ctx = ctx = moderngl.create_context(require=330)
        except Exception as exc:
            raise DisplayError(
                f"cannot use the window's OpenGL context ({exc}); the LCD needs OpenGL 3.3 core. Install the "
                "GPU's OpenGL driver, or Mesa (Debian: libgl1 libglx-mesa0 libgl1-mesa-dri)") from exc
        log.info("LCD display on monitor %r (%d x %d px at %d, %d): %s, %s", self.monitor, self.width_px,
                 self.height_px, x, y, ctx.info.get("GL_RENDERER"), ctx.info.get("GL_VERSION"))
        try:
            self.renderer = FringeRenderer(self.width_px, self.height_px, lut, floor_level, max_level, ctx=ctx)
            self._image = ctx.texture((self.width_px, self.height_px), 1, dtype="f1")
            self._image_fbo = ctx.framebuffer(color_attachments=[self._image])
            self._present_prog = ctx.program(vertex_shader=_VERTEX, fragment_shader=_PRESENT_FRAGMENT)
            self._present_prog["image"].value = 0
            quad = np.array([-1, -1, 1, -1, -1, 1, 1, 1], dtype="f4")
            self._present_vbo = ctx.buffer(quad.tobytes())
            self._present_vao = ctx.vertex_array(self._present_prog, [(self._present_vbo, "2f", "in_pos")])
            self._gl_objects = [self._present_vao, self._present_vbo, self._present_prog, self._image_fbo,
                                self._image]
            # Start dark rather than with whatever the framebuffer held.
            ctx.screen.use()
            ctx.viewport = (0, 0, self.width_px, self.height_px)
            ctx.clear(0.0, 0.0, 0.0, 1.0)
            glfw.swap_buffers(window)
            ctx.finish()
        except DisplayError:
            raise
        except Exception as exc:
            raise DisplayError(f"cannot set up the fringe shaders in the LCD window ({exc})") from exc

    def _wait_for_placement(self, glfw, window) -> None:
        """Wait until the window manager has put the window over the whole monitor, else refuse."""
        want_pos, want_size = self._position, (self.width_px, self.height_px)
        deadline = time.perf_counter() + PLACEMENT_TIMEOUT_S
        while True:
            glfw.poll_events()
            pos, size = tuple(glfw.get_window_pos(window)), tuple(glfw.get_window_size(window))
            fb = tuple(glfw.get_framebuffer_size(window))
            if pos == want_pos and size == want_size and fb == want_size:
                return
            if time.perf_counter() > deadline:
                raise DisplayError(
                    f"the window manager put the fringe window at {pos} with size {size} (framebuffer {fb}) "
                    f"instead of {want_pos} with size {want_size}: the fringes would not cover the LCD pixel "
                    "for pixel. Remove panels/docks from the LCD's monitor, disable display scaling, or run "
                    "the LCD's X session without a window manager")
            time.sleep(0.01)

    # -- use -----------------------------------------------------------------------------------------

    def _check_usable(self, what: str) -> None:
        if threading.get_ident() != self._thread:
            raise DisplayError(f"LcdDisplay.{what} was called from another thread than the one that opened "
                               "it; glfw windows and OpenGL contexts belong to one thread")

    def show(self, pattern: Pattern) -> float:
        """Draw *pattern*, present it, and wait the settle time.

        Parameters
        ----------
        pattern : Pattern
            The image to show.

        Returns
        -------
        float
            ``time.perf_counter()`` (seconds) when the image was presented: after the buffer swap and
            ``glFinish``, before the settle wait. For the caller's logs.

        Raises
        ------
        DisplayError
            The display is closed, used from another thread, the pattern is invalid, the window was
            minimised, or OpenGL failed.
        """
        if self._window is None:
            raise DisplayError("the LCD display is closed; open a new LcdDisplay")
        self._check_usable("show")
        glfw, ctx, window = self._glfw, self.ctx, self._window
        viewport = (0, 0, self.width_px, self.height_px)
        try:
            _release_egl_context_of_this_thread()
            glfw.make_context_current(window)
            self._image_fbo.use()
            ctx.viewport = viewport
            self.renderer.draw(pattern)
            ctx.screen.use()
            ctx.viewport = viewport
            self._image.use(location=0)
            self._present_vao.render(mode=ctx.TRIANGLE_STRIP)
            glfw.swap_buffers(window)
            ctx.finish()
            presented = time.perf_counter()
            glfw.poll_events()
        except DisplayError:
            raise
        except Exception as exc:
            raise DisplayError(f"drawing {pattern.label!r} on the LCD failed ({exc}); "
                               "restart the station if it persists") from exc
        if glfw.get_window_attrib(window, glfw.ICONIFIED):
            raise DisplayError("the fringe window was minimised: the LCD is not showing the fringes. Keep "
                               "the LCD's desktop free of other windows and restore the station's window")
        if glfw.window_should_close(window):
            log.warning("the fringe window was asked to close (window manager or keyboard); keeping it open")
            glfw.set_window_should_close(window, False)
        deadline = presented + self.settle_s
        now = time.perf_counter()
        while now < deadline:
            time.sleep(deadline - now)
            now = time.perf_counter()
        log.debug("showed %s: settled %.4f s after presentation", pattern.label, now - presented)
        return presented

    # -- closing -------------------------------------------------------------------------------------

    def close(self) -> None:
        """Release the renderer, destroy the window and, if it was the last user, terminate glfw.

        Idempotent: closing a closed display does nothing.
        """
        if self._glfw is None:
            return
        self._check_usable("close")
        with _lock:
            self._teardown()

    def _teardown(self) -> None:
        glfw, self._glfw = self._glfw, None
        if glfw is None:
            return
        try:
            if self._window is not None:
                _release_egl_context_of_this_thread()
                glfw.make_context_current(self._window)
            for obj in ([self.renderer] if self.renderer is not None else []) + self._gl_objects:
                try:
                    obj.release()
                except Exception as exc:  # the context is going away anyway
                    log.debug("releasing %r: %s", obj, exc)
            if self.ctx is not None:
                self.ctx.release()
        finally:
            self.renderer, self.ctx, self._gl_objects = None, None, []
            if self._window is not None:
                glfw.make_context_current(None)
                glfw.destroy_window(self._window)
                self._window = None
                log.info("LCD display on monitor %r closed", self.monitor)
            _glfw_release(glfw)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
