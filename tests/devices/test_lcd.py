"""The LCD window on a virtual X server (Xvfb): placement, pixels on screen, settle time, refusals.

Needs the ``Xvfb`` binary (Debian: xvfb) and the glfw package; both are test requirements, so their
absence fails these tests instead of skipping them.

What is compared: after ``show`` has swapped, the test reads the X server's root window with XGetImage
over a separate X connection: what the screen really shows, which also proves where the window is. It
must equal, in R, G and B, what ``FringeRenderer.render`` gives offscreen through EGL, exactly.

Why not glReadPixels: the back buffer's content after a swap is undefined in GLX, and reading it before
the swap would not test the swap. The front buffer is what the spec suggests for "after the swap", but
Mesa's software GLX (llvmpipe on Xvfb, as in CI) presents by copying the back buffer to the window
(XPutImage) and never updates the GL front buffer: glReadPixels(GL_FRONT) returns zeros there. The root
window read is independent of those buffer semantics and of the GL driver.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import select
import shutil
import signal
import subprocess
import threading
import time

import numpy as np
import pytest

try:
    import glfw
except ImportError as exc:  # a test requirement: fail, do not skip
    raise ImportError(f"the LCD tests need the glfw package (pip install glfw): {exc}") from exc

from sofast_station.devices import lcd as lcd_module
from sofast_station.devices.lcd import LcdDisplay, list_monitors
from sofast_station.devices.renderer import FringeRenderer
from sofast_station.errors import DisplayError
from sofast_station.fringes import Pattern

WIDTH, HEIGHT = 1920, 1080
LUT = np.linspace(0.0, 1.0, 256) ** (1 / 2.2)
FLOOR, MAXIMUM = 0.05, 0.95
PATTERNS = [
    Pattern("fringe", axis="x", periods=4.0, shift_rad=np.pi / 2),
    Pattern("fringe", axis="y", periods=1.0, shift_rad=3 * np.pi / 2),
    Pattern("fringe", axis="x", periods=1.0, shift_rad=0.0),
    Pattern("uniform", command=77),
]


# --- the virtual X server ---------------------------------------------------------------------------

def _die_with_parent():
    """In the Xvfb child: get SIGTERM when the test process dies, even without its teardown."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    libc.prctl(1, signal.SIGTERM)                      # PR_SET_PDEATHSIG


@contextlib.contextmanager
def running_xvfb(log_dir, width=WIDTH, height=HEIGHT):
    """Run an Xvfb with one monitor of *width* x *height* px; yields its DISPLAY string.

    ``-displayfd`` lets Xvfb pick a free display number itself (it tries one number after another) and
    write it to the pipe only once it accepts connections: no guessed numbers, no polling.
    """
    exe = shutil.which("Xvfb")
    if exe is None:
        pytest.fail("Xvfb is not installed: the LCD tests need a virtual X server (Debian: apt-get install xvfb)")
    log_path = log_dir / f"xvfb-{width}x{height}.log"
    read_fd, write_fd = os.pipe()
    with open(log_path, "wb") as log_file:
        proc = subprocess.Popen([exe, "-displayfd", str(write_fd), "-screen", "0", f"{width}x{height}x24",
                                 "-nolisten", "tcp", "-noreset"], pass_fds=(write_fd,), stdout=log_file,
                                stderr=subprocess.STDOUT, preexec_fn=_die_with_parent)
    os.close(write_fd)
    try:
        number = b""
        deadline = time.monotonic() + 10.0
        while not number.endswith(b"\n"):
            ready, _, _ = select.select([read_fd], [], [], max(0.0, deadline - time.monotonic()))
            chunk = os.read(read_fd, 16) if ready else b""
            if not chunk:
                pytest.fail(f"Xvfb did not start within 10 s (exit code {proc.poll()}): "
                            f"{log_path.read_text(errors='replace')}")
            number += chunk
        yield f":{int(number)}"
    finally:
        os.close(read_fd)
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture(scope="module")
def xvfb(tmp_path_factory):
    """An Xvfb with one 1920 x 1080 monitor for the module; yields its DISPLAY string."""
    with running_xvfb(tmp_path_factory.mktemp("xvfb")) as name:
        yield name


@pytest.fixture
def display(xvfb, monkeypatch):
    """DISPLAY points at the Xvfb for this test (and X11 is the only window system offered)."""
    monkeypatch.setenv("DISPLAY", xvfb)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    return xvfb


@pytest.fixture(scope="module")
def references():
    """The offscreen (EGL) images, rendered before any window opens so the two contexts never mix."""
    with FringeRenderer(WIDTH, HEIGHT, LUT, FLOOR, MAXIMUM) as r:
        return [r.render(p) for p in PATTERNS]


# --- reading back what is on the screen -------------------------------------------------------------

class _XImage(ctypes.Structure):
    _fields_ = [("width", ctypes.c_int), ("height", ctypes.c_int), ("xoffset", ctypes.c_int),
                ("format", ctypes.c_int), ("data", ctypes.c_void_p), ("byte_order", ctypes.c_int),
                ("bitmap_unit", ctypes.c_int), ("bitmap_bit_order", ctypes.c_int), ("bitmap_pad", ctypes.c_int),
                ("depth", ctypes.c_int), ("bytes_per_line", ctypes.c_int), ("bits_per_pixel", ctypes.c_int),
                ("red_mask", ctypes.c_ulong), ("green_mask", ctypes.c_ulong), ("blue_mask", ctypes.c_ulong)]


def _xlib():
    x11 = ctypes.CDLL(ctypes.util.find_library("X11") or "libX11.so.6")
    x11.XOpenDisplay.restype = ctypes.c_void_p
    x11.XOpenDisplay.argtypes = [ctypes.c_char_p]
    x11.XDefaultRootWindow.restype = ctypes.c_ulong
    x11.XDefaultRootWindow.argtypes = [ctypes.c_void_p]
    x11.XGetImage.restype = ctypes.POINTER(_XImage)
    x11.XGetImage.argtypes = [ctypes.c_void_p, ctypes.c_ulong, ctypes.c_int, ctypes.c_int, ctypes.c_uint,
                              ctypes.c_uint, ctypes.c_ulong, ctypes.c_int]
    x11.XDestroyImage.argtypes = [ctypes.POINTER(_XImage)]
    x11.XCloseDisplay.argtypes = [ctypes.c_void_p]
    x11.XInternAtom.restype = ctypes.c_ulong
    x11.XInternAtom.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_int]
    x11.XGetWindowProperty.argtypes = [
        ctypes.c_void_p, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_long, ctypes.c_long, ctypes.c_int,
        ctypes.c_ulong, ctypes.POINTER(ctypes.c_ulong), ctypes.POINTER(ctypes.c_int),
        ctypes.POINTER(ctypes.c_ulong), ctypes.POINTER(ctypes.c_ulong), ctypes.POINTER(ctypes.c_void_p)]
    x11.XFree.argtypes = [ctypes.c_void_p]
    return x11


def read_root_window(display_name: str, width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """The X screen's top-left pixels as uint8 (height, width, 3) RGB, through a separate X connection."""
    x11 = _xlib()
    dpy = x11.XOpenDisplay(display_name.encode())
    assert dpy, f"cannot open {display_name}"
    try:
        img = x11.XGetImage(dpy, x11.XDefaultRootWindow(dpy), 0, 0, width, height, ~0 & 0xFFFFFFFFFFFFFFFF, 2)
        assert img, "XGetImage failed"
        try:
            im = img.contents
            assert im.bits_per_pixel == 32 and im.byte_order == 0 and im.red_mask == 0xFF0000, \
                (im.bits_per_pixel, im.byte_order, hex(im.red_mask))
            raw = np.frombuffer(ctypes.string_at(im.data, im.bytes_per_line * im.height), np.uint8)
            bgrx = raw.reshape(im.height, im.bytes_per_line)[:, :4 * im.width].reshape(im.height, im.width, 4)
            return bgrx[:, :, [2, 1, 0]].copy()
        finally:
            x11.XDestroyImage(img)
    finally:
        x11.XCloseDisplay(dpy)


def screen_shows(display_name: str, expected: np.ndarray, timeout_s: float = 2.0) -> np.ndarray:
    """The root window once it equals *expected* in every channel (the server may still be drawing)."""
    deadline = time.monotonic() + timeout_s
    while True:
        rgb = read_root_window(display_name, expected.shape[1], expected.shape[0])
        if all(np.array_equal(rgb[:, :, c], expected) for c in range(3)) or time.monotonic() > deadline:
            return rgb
        time.sleep(0.05)


def motif_decorations(display_name: str, window_id: int) -> int | None:
    """The ``decorations`` field of the window's _MOTIF_WM_HINTS (what window managers obey), or None."""
    x11 = _xlib()
    dpy = x11.XOpenDisplay(display_name.encode())
    try:
        atom = x11.XInternAtom(dpy, b"_MOTIF_WM_HINTS", 1)
        if not atom:
            return None
        type_ret, fmt, n, after, data = (ctypes.c_ulong(), ctypes.c_int(), ctypes.c_ulong(), ctypes.c_ulong(),
                                         ctypes.c_void_p())
        x11.XGetWindowProperty(dpy, window_id, atom, 0, 5, 0, 0, ctypes.byref(type_ret), ctypes.byref(fmt),
                               ctypes.byref(n), ctypes.byref(after), ctypes.byref(data))
        if not data.value:
            return None
        try:
            hints = ctypes.cast(data, ctypes.POINTER(ctypes.c_ulong))[:n.value]
        finally:
            x11.XFree(data)
        flags, decorations = hints[0], hints[2]
        return decorations if flags & 2 else None       # MWM_HINTS_DECORATIONS
    finally:
        x11.XCloseDisplay(dpy)


def open_lcd(settle_s=0.0, width=WIDTH, height=HEIGHT, monitor="screen"):
    return LcdDisplay(monitor, width, height, LUT, FLOOR, MAXIMUM, settle_s)


# --- tests ------------------------------------------------------------------------------------------

def test_list_monitors(display):
    assert list_monitors() == [{"name": "screen", "x": 0, "y": 0, "width_px": WIDTH, "height_px": HEIGHT}]


def test_window_covers_the_monitor_without_decoration_and_shows_the_offscreen_images(display, references):
    lcd = open_lcd()
    try:
        window = lcd._window
        assert glfw.get_window_pos(window) == (0, 0)
        assert glfw.get_window_size(window) == (WIDTH, HEIGHT)
        assert glfw.get_framebuffer_size(window) == (WIDTH, HEIGHT)
        assert glfw.get_window_attrib(window, glfw.DECORATED) == 0
        assert glfw.get_window_attrib(window, glfw.RESIZABLE) == 0
        assert glfw.get_window_attrib(window, glfw.FLOATING) == 1
        assert glfw.get_input_mode(window, glfw.CURSOR) == glfw.CURSOR_HIDDEN
        assert motif_decorations(display, glfw.get_x11_window(window)) == 0
        assert lcd.ctx.version_code >= 330

        for pattern, ref in zip(PATTERNS, references):
            lcd.show(pattern)
            # The whole X screen shows the image, grey, pixel for pixel: the window is at the monitor's
            # origin with its size, and the GLX window path draws what the EGL offscreen path renders.
            on_screen = screen_shows(display, ref)
            for c, channel in enumerate("RGB"):
                diff = np.abs(on_screen[:, :, c].astype(int) - ref)
                assert diff.max() == 0, (pattern.label, channel, int(diff.max()), int(np.count_nonzero(diff)))
    finally:
        lcd.close()


def test_show_waits_the_settle_time(display):
    with open_lcd(settle_s=0.25) as lcd:
        start = time.perf_counter()
        presented = lcd.show(Pattern("uniform", command=255))
        end = time.perf_counter()
        assert start <= presented <= end
        assert end - presented >= 0.25
        assert end - start < 1.5


def test_unknown_monitor_names_the_available_ones(display):
    with pytest.raises(DisplayError, match=r"no monitor named 'HDMI-1'.*'screen' \(1920 x 1080 px at 0, 0\)"):
        open_lcd(monitor="HDMI-1")


def test_resolution_mismatch_is_refused(display):
    with pytest.raises(DisplayError, match=r"runs at 1920 x 1080 px .* configured for 1280 x 720 px.*native"):
        open_lcd(width=1280, height=720)


def test_close_is_idempotent_and_terminates_glfw(display):
    lcd = open_lcd()
    lcd.close()
    lcd.close()
    with pytest.raises(DisplayError, match="closed"):
        lcd.show(Pattern("uniform", command=0))
    # glfw was terminated and can start again.
    with open_lcd() as again:
        again.show(Pattern("uniform", command=0))


def test_missing_display_variable_is_explained(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(DisplayError, match="DISPLAY is not set"):
        open_lcd()


def test_unreachable_display_is_explained(xvfb, monkeypatch):
    # A display number nothing listens on (Xvfb's own number plus a large offset).
    monkeypatch.setenv("DISPLAY", f":{int(xvfb[1:]) + 4321}")
    with pytest.raises(DisplayError, match="cannot open the X display"):
        list_monitors()


def test_an_offscreen_renderer_on_the_same_thread_does_not_break_the_window(display):
    # moderngl leaves its EGL context current; making the GLX context current over it would be a
    # BadAccess X error, which Xlib answers by exiting the process. show() unbinds it first.
    with open_lcd() as lcd:
        lcd.show(Pattern("uniform", command=10))
        with FringeRenderer(64, 32) as offscreen:
            assert np.all(offscreen.render(Pattern("uniform", command=200)) == 200)
        lcd.show(Pattern("uniform", command=200))
        assert np.all(screen_shows(display, np.full((HEIGHT, WIDTH), 200, np.uint8)) == 200)


def test_show_from_another_thread_is_refused(display):
    with open_lcd() as lcd:
        result = {}

        def worker():
            try:
                lcd.show(Pattern("uniform", command=0))
            except DisplayError as exc:
                result["error"] = str(exc)

        thread = threading.Thread(target=worker)
        thread.start()
        thread.join()
        assert "another thread" in result.get("error", "")


def test_bad_settle_time_is_refused():
    with pytest.raises(DisplayError, match="settle time"):
        open_lcd(settle_s=-1.0)


def test_window_is_placed_at_a_monitor_position_off_the_origin(tmp_path, monkeypatch):
    # Xvfb has one monitor at (0, 0). On a 2400 x 1400 screen, pretend the monitor "screen" is a
    # 1920 x 1080 one at (300, 200): the window must land there, and nothing of it anywhere else.
    x0, y0, w, h = 300, 200, 1920, 1080
    real_info = lcd_module._monitor_info

    def shifted(glfw_module, monitor):
        info = real_info(glfw_module, monitor)
        return {**info, "x": x0, "y": y0, "width_px": w, "height_px": h}

    monkeypatch.setattr(lcd_module, "_monitor_info", shifted)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with running_xvfb(tmp_path, 2400, 1400) as name:
        monkeypatch.setenv("DISPLAY", name)
        with LcdDisplay("screen", w, h, None, 0.0, 1.0, 0.0) as lcd:
            assert glfw.get_window_pos(lcd._window) == (x0, y0)
            lcd.show(Pattern("uniform", command=255))
            expected = np.zeros((1400, 2400), np.uint8)
            expected[y0:y0 + h, x0:x0 + w] = 255
            on_screen = screen_shows(name, expected)
            assert all(np.array_equal(on_screen[:, :, c], expected) for c in range(3))
