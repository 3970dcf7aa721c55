"""What the camera sees: the display's light, sampled through each pixel's reflection in the facet.

:class:`TwinRenderer` turns a display image (uint8 commands) into the light every camera pixel gathers, as
linear DN before the sensor's noise and rounding: the display's response (gamma, floor), bilinear sampling
at the screen point each pixel's centre ray reflects to (:class:`~sofast_station.twin.trace.FacetTrace`),
the facet's coverage of the pixel, the reflectance, the room's ambient light and the background, vignetting,
and the lens's point-spread function. The sensor (:mod:`sofast_station.twin.sensor`) adds the noise, the
knee and the rounding.

The sampling indices and weights are precomputed once per trace, so a frame is a few vector operations;
the samples of read-only images (the display's rendered patterns, which never change) are kept.
"""

from __future__ import annotations

import weakref

import numpy as np
from scipy import sparse

from ..errors import DisplayError
from . import edges
from .parameters import TwinOptics
from .trace import FacetTrace


class BoxedSignal:
    """A frame's linear signal that differs from the dark level (:attr:`TwinRenderer.dn_base`) only on the box
    of rows ``r0 .. r1`` and columns ``c0 .. c1`` of the pixels that see the facet: there, the ambient term
    and the display's *light* (the box's (r1 - r0, c1 - c0) float32 array, :meth:`TwinRenderer.cached_light`).

    The sensor forms it a block of rows at a time (:meth:`rows`), outside the box from the dark level alone.
    """

    __slots__ = ("renderer", "ambient", "light", "box")

    def __init__(self, renderer: "TwinRenderer", ambient: float, light: np.ndarray):
        self.renderer, self.ambient, self.light = renderer, ambient, light
        self.box = renderer.seen_box[:4]

    @property
    def dark_dn(self) -> np.ndarray:
        """(H, W) float32: the signal of every pixel outside the box."""
        return self.renderer.dn_base

    def rows(self, i0: int, i1: int, out: np.ndarray) -> np.ndarray:
        """Rows ``i0 .. i1`` (within the box's rows) of the signal, formed in *out* ((i1 - i0, W) float32)
        as :meth:`TwinRenderer.linear_sharp` forms them: ambient term (zero off the facet) and dark level,
        plus the display's light on the box (zero on the pixels that see no screen)."""
        r0, _, c0, c1 = self.box
        dn = np.multiply(self.renderer.dn_per_ambient[i0:i1], np.float32(self.ambient), out=out)
        dn += self.renderer.dn_base[i0:i1]
        dn[:, c0:c1] += self.light[i0 - r0:i1 - r0]
        return dn


class TwinRenderer:
    """The light each camera pixel gathers from the display through the facet, DN before the sensor.

    Parameters
    ----------
    trace : FacetTrace
        Where every seen pixel looks on the screen, and the facet's coverage of each pixel.
    optics : TwinOptics
        Display response, reflectance, ambient, background, black level and white level, vignetting, the
        bevelled rim's reflectance and the point-spread function.

    Attributes
    ----------
    gain_dn : float
        DN per unit radiance (fraction of white) at vignetting factor 1, at the reference exposure and gain 1.
    vignetting : (H, W) array
        Relative irradiance after vignetting, 1 at the principal point.
    dn_base : (H, W) float32 array
        Every pixel's signal without the display's light and the ambient: black level plus the background
        the pixel's uncovered part sees.
    dn_per_ambient : (H, W) float32 array
        DN per unit of ambient light (zero off the facet).
    """

    def __init__(self, trace: FacetTrace, optics: TwinOptics, mark_coverage: np.ndarray | None = None):
        self.trace = trace
        self.optics = optics
        #: The fixture's marks' share of each pixel (:mod:`sofast_station.twin.marks`), or None.
        self.mark_coverage = mark_coverage
        self.screen = trace.geometry.screen
        #: Display samples of the read-only images seen so far (id -> (weak reference, sample, [light])).
        self._samples: dict = {}
        self._prepare_sampling()
        self._prepare_photometry()

    def with_trace(self, trace: FacetTrace) -> "TwinRenderer":
        """The renderer of another trace that kept this one's outline (:meth:`FacetTrace.keeps_outline`): new
        sampling of the new screen points, the same photometry (it depends on the coverage only)."""
        renderer = self._copy()
        renderer.trace = trace
        renderer._prepare_sampling()
        return renderer

    def with_optics(self, optics: TwinOptics) -> "TwinRenderer":
        """The renderer of the same trace under other optics whose edge model does not change the trace."""
        renderer = self._copy()
        renderer.optics = optics
        renderer._prepare_photometry()
        if optics.bevel_reflectance != self.optics.bevel_reflectance:
            renderer._prepare_sampling()
        return renderer

    def _copy(self) -> "TwinRenderer":
        renderer = self.__class__.__new__(self.__class__)
        renderer.__dict__.update(self.__dict__)
        renderer._samples = {}               # the display's response (luminance table) may differ
        renderer.__dict__.pop("_seen_box", None)
        return renderer

    # ------------------------------------------------------------- precompute
    def _prepare_sampling(self) -> None:
        """Bilinear sampling indices/weights into a zero-padded window of the display luminance.

        A pixel on a bevelled rim has a second set (``_rim_idx``, ``_rim_w``) for its rim's screen point;
        each set's weights carry its share of the pixel's facet area (and the rim's relative reflectance).
        """
        trace = self.trace
        screen = self.screen
        pitch_x, pitch_y = screen.pitch_m, screen.pitch_y_m              # columns, rows (may differ)
        n = trace.u_scr_m.shape[0]
        footprint = trace.footprint_u_scr_m               # (n, m, 2): m sub-rays per pixel, averaged
        m = footprint.shape[1]
        u_scr_m = np.concatenate([footprint.transpose(1, 0, 2).reshape(m * n, 2), trace.rim_u_scr_m])
        with np.errstate(invalid="ignore"):
            col = u_scr_m[:, 0] / pitch_x - 0.5                       # continuous display column
            row = (screen.height_m - u_scr_m[:, 1]) / pitch_y - 0.5    # continuous display row
            good = np.isfinite(col) & np.isfinite(row) & (col > -1) & (col < screen.width_px) \
                & (row > -1) & (row < screen.height_px)
        col0 = np.floor(np.where(good, col, 0.0))
        row0 = np.floor(np.where(good, row, 0.0))
        frac_c = np.where(good, col - col0, 0.0)
        frac_r = np.where(good, row - row0, 0.0)
        pad_c = col0.astype(np.int64) + 1          # padded index: display index + 1 (0 = bezel)
        pad_r = row0.astype(np.int64) + 1
        if np.any(good):
            self._win_r0, self._win_r1 = int(pad_r[good].min()), int(pad_r[good].max()) + 1
            self._win_c0, self._win_c1 = int(pad_c[good].min()), int(pad_c[good].max()) + 1
        else:
            self._win_r0 = self._win_r1 = self._win_c0 = self._win_c1 = 0
        win_w = self._win_c1 - self._win_c0 + 1
        base = np.where(good, (pad_r - self._win_r0) * win_w + (pad_c - self._win_c0), 0)
        idx = np.stack([base, base + 1, base + win_w, base + win_w + 1]).astype(np.intp)
        weights = np.stack([(1 - frac_r) * (1 - frac_c), (1 - frac_r) * frac_c,
                            frac_r * (1 - frac_c), frac_r * frac_c])
        weights = np.where(good, weights, 0.0)
        weights[:, :m * n] /= m
        if trace.rim_pos.size:
            for j in range(m):
                weights[:, j * n + trace.rim_pos] *= 1.0 - trace.rim_fraction
            weights[:, m * n:] *= trace.rim_fraction * self.optics.bevel_reflectance
        # (4 m, n): the four bilinear corners of each of the m sub-rays, sub-ray after sub-ray
        self._sample_idx, self._rim_idx = idx[:, :m * n].reshape(4 * m, n), idx[:, m * n:]
        self._sample_w = weights[:, :m * n].reshape(4 * m, n).astype(np.float32)
        self._rim_w = weights[:, m * n:].astype(np.float32)
        self._footprint_matrix = None
        if m > 1:
            # A footprint's 4 m taps fall on a few display pixels (a 9.7 x 0.4 pixel footprint: about 22 of
            # its 64): summed into one sparse row per pixel, a frame's samples are one product, a third of
            # the 4 m passes' cost.
            rows = np.broadcast_to(np.arange(n), (4 * m, n))
            window_size = (self._win_r1 - self._win_r0 + 1) * win_w
            self._footprint_matrix = sparse.csr_matrix(
                (self._sample_w.ravel(), (rows.ravel(), self._sample_idx.ravel())), shape=(n, window_size))
            self._footprint_matrix.sum_duplicates()

    def _prepare_photometry(self) -> None:
        """Vignetting, gain, and the per-pixel affine terms of the linear response."""
        optics = self.optics
        trace = self.trace
        camera = trace.camera
        height, width = trace.geometry.camera.shape
        self.vignetting = edges.vignetting_factor((height, width), camera.cx, camera.cy,
                                                  optics.vignetting, optics.vignetting_exponent)
        full = trace.coverage >= 1.0
        some = trace.coverage > 0
        vig_max = float(self.vignetting[full].max() if full.any()
                        else self.vignetting[some].max() if some.any() else 1.0)
        self.gain_dn = (optics.white_dn - optics.camera_offset_dn) / ((optics.reflectance + optics.ambient) * vig_max)
        scale = self.gain_dn * self.vignetting
        uncovered = 1.0 - trace.coverage
        marks = 0.0
        if self.mark_coverage is not None:
            # the fixture's marks, lit by the hall, in every frame alike (twin/marks.py); they hide the background
            uncovered = uncovered - self.mark_coverage
            marks = self.mark_coverage * optics.mark_radiance
        self.dn_base = (optics.camera_offset_dn + scale * (uncovered * optics.background + marks)).astype(np.float32)
        self.dn_per_ambient = (scale * trace.coverage).astype(np.float32)
        self._dn_per_luminance = (self.dn_per_ambient.ravel()[trace.seen_idx] * optics.reflectance).astype(np.float32)
        levels = np.arange(256, dtype=np.float64) / 255.0
        self._luminance_lut = (optics.display_floor
                               + (1.0 - optics.display_floor) * levels ** optics.display_gamma).astype(np.float32)

    # ---------------------------------------------------------------- samples
    def display_sample(self, display_image: np.ndarray) -> np.ndarray:
        """Display luminance (fraction of white) bilinearly sampled at every seen pixel's screen point."""
        screen = self.screen
        image = np.asarray(display_image)
        if image.dtype != np.uint8 or image.shape != (screen.height_px, screen.width_px):
            raise DisplayError(f"display image must be uint8 of shape {(screen.height_px, screen.width_px)} "
                               f"(rows, columns of the screen), got {image.dtype} {image.shape}")
        trace = self.trace
        sample = np.zeros(trace.seen_idx.size, dtype=np.float32)
        if self._win_r1 > self._win_r0:
            window = np.zeros((self._win_r1 - self._win_r0 + 1, self._win_c1 - self._win_c0 + 1), np.float32)
            r_lo, r_hi = max(self._win_r0, 1), min(self._win_r1, screen.height_px)
            c_lo, c_hi = max(self._win_c0, 1), min(self._win_c1, screen.width_px)
            if r_hi >= r_lo and c_hi >= c_lo:
                window[r_lo - self._win_r0:r_hi - self._win_r0 + 1, c_lo - self._win_c0:c_hi - self._win_c0 + 1] = \
                    self._luminance_lut[image[r_lo - 1:r_hi, c_lo - 1:c_hi]]
            flat = window.ravel()
            if self._footprint_matrix is not None:
                sample += self._footprint_matrix @ flat
            else:
                for k in range(4):
                    sample += self._sample_w[k] * flat[self._sample_idx[k]]
            if trace.rim_pos.size:
                rim = np.zeros(trace.rim_pos.size, dtype=np.float32)
                for k in range(4):
                    rim += self._rim_w[k] * flat[self._rim_idx[k]]
                sample[trace.rim_pos] += rim
        return sample

    def cached_sample(self, display_image: np.ndarray) -> np.ndarray:
        """:meth:`display_sample`, kept for read-only images (the display's rendered patterns, which
        never change): the trace fixes where every pixel looks, so only the image formation is redone."""
        image = display_image
        if not (isinstance(image, np.ndarray) and not image.flags.writeable and image.base is None):
            return self.display_sample(image)
        key = id(image)
        hit = self._samples.get(key)
        if hit is not None and hit[0]() is image:
            return hit[1]
        sample = self.display_sample(image)
        sample.setflags(write=False)
        # The entry goes when its image goes. The callback holds the renderer weakly: holding its dict would
        # make a reference cycle (dict -> weakref -> callback -> dict) that only the cyclic garbage collector
        # frees, so every twin a simulated line drew (one per facet) kept its samples, a hundred MB at full
        # resolution, until a full collection.
        owner = weakref.ref(self)

        def forget(_, k=key):
            renderer = owner()
            if renderer is not None:
                renderer._samples.pop(k, None)

        # (the third item keeps the image's light term once :meth:`cached_light` has formed it)
        self._samples[key] = (weakref.ref(image, forget), sample, [])
        return sample

    @property
    def seen_box(self) -> tuple:
        """(r0, r1, c0, c1, local): the box of camera rows ``r0 .. r1`` and columns ``c0 .. c1`` that holds
        every seen pixel, and each seen pixel's flat index in it."""
        box = self.__dict__.get("_seen_box")
        if box is None:
            width = self.trace.geometry.camera.width_px
            rows, cols = np.divmod(self.trace.seen_idx, width)
            r0, c0 = (int(rows.min()), int(cols.min())) if rows.size else (0, 0)
            r1, c1 = (int(rows.max()) + 1, int(cols.max()) + 1) if rows.size else (0, 0)
            box = self._seen_box = (r0, r1, c0, c1, (rows - r0) * (c1 - c0) + (cols - c0))
        return box

    def cached_light(self, display_image: np.ndarray) -> np.ndarray | None:
        """The display light of a cached read-only image at the reference exposure, laid out on the box of
        camera pixels that see the screen (zero where a pixel sees none), or None for an image not cached.

        Adding it to that box of the frame gives the same bits as adding the light to the seen pixels one by
        one (x + 0 = x), without an indexed scatter per frame (a fifth of a frame's cost)."""
        hit = self._samples.get(id(display_image))
        if hit is None or hit[0]() is not display_image:
            return None
        if not hit[2]:
            r0, r1, c0, c1, local = self.seen_box
            light = np.zeros((r1 - r0, c1 - c0), dtype=np.float32)
            light.ravel()[local] = self._dn_per_luminance * hit[1]
            light.setflags(write=False)
            hit[2].append(light)
        return hit[2][0]

    # ------------------------------------------------------------- the signal
    def linear(self, sample: np.ndarray, ambient: float, scale: float, flicker: float,
               light: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """Noise-free DN before the knee, rounding and clipping (float32, camera shape), through the lens's
        point-spread function when it has one: the display's luminance *sample* at every seen pixel, the
        *ambient* light, the sensor's exposure x gain *scale* and the display's *flicker* factor
        (:class:`~sofast_station.twin.sensor.TwinSensor`). *light*: the sample's :meth:`cached_light`, when
        known; *out*: where the sharp signal may be formed (a float32 array of the camera's shape)."""
        dn = self.linear_sharp(sample, ambient, scale, flicker, light, out)
        if edges.has_psf(self.optics):
            # The light is spread before the sensor integrates it (twin/edges.py: Gaussian, disk).
            dn = edges.apply_psf(dn, self.optics)
        return dn

    def linear_sharp(self, sample: np.ndarray, ambient: float, scale: float, flicker: float,
                     light: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """:meth:`linear` without the point-spread function: every pixel its own area's light."""
        if scale == 1.0 and flicker == 1.0:
            # The reference exposure and gain: exactly the arithmetic the twin has always used.
            dn = np.multiply(self.dn_per_ambient, np.float32(ambient), out=out)
            dn += self.dn_base
            if light is not None:
                r0, r1, c0, c1, _ = self.seen_box
                dn[r0:r1, c0:c1] += light
            else:
                flat = dn.ravel()
                flat[self.trace.seen_idx] += self._dn_per_luminance * sample
            return dn
        offset = np.float32(self.optics.camera_offset_dn)
        dn = (self.dn_base - offset) + np.float32(ambient) * self.dn_per_ambient
        dn.ravel()[self.trace.seen_idx] += self._dn_per_luminance * (sample * np.float32(flicker))
        dn *= np.float32(scale)
        dn += offset
        return dn

    def boxed(self, ambient: float, light: np.ndarray) -> BoxedSignal:
        """The signal of a cached image at the reference exposure (*light*: its :meth:`cached_light`) as a
        :class:`BoxedSignal`, formed by the sensor block by block (no point-spread function)."""
        return BoxedSignal(self, ambient, light)
