"""A simulated lens seen through the lens-profile API: the ground truth that tests, oracles and validation use.

:class:`TruthProfile` implements :class:`fieldcal.optics.LensModel` (every question a
:class:`fieldcal.profile.LensProfile` answers) from the :class:`fieldcal.simulate.lens.LensSpec` itself (zero-width
credible bands), in the pixel geometry of a given image size. Planning and compositing code is written against
that protocol (see docs/architecture.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fieldcal.errors import ParameterError
from fieldcal.formats import documents
from fieldcal.simulate.lens import LensSpec

TRUTH_FORMAT = documents.format_id("truth")
TRUTH_JSON = "truth.json"


def _which(orientation: str | None) -> str:
    """LensSpec.best_focus_um's ``which`` for a TruthProfile ``orientation`` (None = the mean surface)."""
    if orientation in (None, "mean"):
        return "mean"
    if orientation in ("tangential", "sagittal"):
        return orientation
    raise ParameterError(f"orientation must be None, 'tangential' or 'sagittal', not {orientation!r}",
                         field="orientation", fix="use orientation='tangential' or 'sagittal' (or None for the mean)")


def truth_lens(doc: dict, path: str | Path | None = None) -> tuple[LensSpec, tuple[int, int]]:
    """The lens spec and render size ``(width_px, height_px)`` of a ``fieldcal-truth/1`` document (validated)."""
    documents.validate(doc, "truth", path)
    spec = LensSpec.from_dict(doc["lens"], path=path, where="lens")
    w, h = doc["size_px"]
    return spec, (int(w), int(h))


def load_truth(path: str | Path) -> TruthProfile:
    """The :class:`TruthProfile` of a simulated stack, at the size it was rendered: ``path`` is the stack folder
    or its ``truth.json``."""
    path = Path(path)
    if path.is_dir():
        path = path / TRUTH_JSON
    doc = documents.read(path, "truth", not_found="truth.json not found",
                         not_found_fix="give a stack folder written by `fieldcal simulate` (it holds truth.json)")
    spec, (w, h) = truth_lens(doc, path)
    # a wave-optics stack's best focus is where its MTF at fs peaks, not the spec's surface (truth.json says so)
    optics = doc.get("optics", "geometric")
    fs = (doc.get("best_focus") or {}).get("fs_cyc_per_mm") or (doc.get("renderer") or {}).get("fs_cyc_per_mm")
    return TruthProfile(spec, w, h, optics=optics, **({"fs_cyc_per_mm": float(fs)} if fs else {}))


class TruthProfile:
    """The exact answers of a simulated lens, in the pixel grid of a ``width_px`` x ``height_px`` image.

    ``optics="wave"``: the lens as the wave-optics renderer shows it — best focus is where the MTF at
    ``fs_cyc_per_mm`` peaks (spherical aberration moves it off the spec's surface, which stays available as
    :meth:`reference_focus_um`); the tolerance is the wave path's own (on axis, :meth:`wave_tolerance_um`), the
    MTF answers are still the geometric model's.
    """

    is_truth = True
    has_measured_tolerance = False

    def __init__(self, spec: LensSpec, width_px: int | None = None, height_px: int | None = None,
                 z_ref_um: float | None = None, source_path: str | Path | None = None,
                 optics: str = "geometric", fs_cyc_per_mm: float = 80.0):
        if width_px is not None or height_px is not None:
            spec = spec.with_sensor_size(width_px or spec.sensor.width_px, height_px or spec.sensor.height_px)
        self.spec = spec
        self.source_path: str | None = None if source_path is None else str(source_path)
        self.image_size_px: tuple[int, int] = (spec.sensor.width_px, spec.sensor.height_px)
        self.pixel_pitch_um: float = spec.sensor.pixel_pitch_um
        self.channels: tuple[str, ...] = spec.channel_names
        self.cfa: str | None = spec.sensor.cfa
        # The reference geometry. A calibrated profile's z_ref is a frame of its stack: compare it with
        # TruthProfile(spec, w, h, z_ref_um=profile.z_ref_um), or pixel coordinates mean different points.
        self.z_ref_um: float = spec.z_ref_um if z_ref_um is None else float(z_ref_um)
        self.f_number: float = spec.f_number
        self.focal_length_mm: float = spec.focal_length_mm
        self.object_distance_mm: float = spec.object_distance_mm
        self.image_height_max_mm: float = spec.image_height_max_mm
        # Wave optics (fieldcal.simulate.wave): the lens's surface is the reference (paraxial, W020 = 0) focus;
        # the sharpest position (MTF at fs peaks) is shifted from it by spherical aberration, computed numerically
        # over field height. Geometric optics: the two coincide.
        if optics not in ("geometric", "wave"):
            raise ValueError(f"optics must be 'geometric' or 'wave', not {optics!r}")
        self.optics = optics
        self.fs_cyc_per_mm = float(fs_cyc_per_mm)
        self._shift: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def with_z_ref(self, z_ref_um: float) -> "TruthProfile":
        """The same lens, image size and optics path in the reference geometry of the frame at ``z_ref_um``
        (a calibrated profile's z_ref): rebuilding without ``optics`` would silently give the geometric truth."""
        out = TruthProfile(self.spec, z_ref_um=z_ref_um, source_path=self.source_path, optics=self.optics,
                           fs_cyc_per_mm=self.fs_cyc_per_mm)
        out._shift = self._shift  # the focus-shift tables do not depend on z_ref (they are per field height)
        return out

    def focus_shift_table(self, channel: str) -> tuple[np.ndarray, np.ndarray]:
        """(rho, shift_um): sharpest position minus the reference surface over normalised field height."""
        if channel not in self._shift:
            if self.optics == "wave":
                from fieldcal.simulate.wave import best_focus_shift_table
                self._shift[channel] = best_focus_shift_table(self.spec, channel, self.fs_cyc_per_mm)
            else:
                self._shift[channel] = (np.array([0.0, 1.0]), np.zeros(2))
        return self._shift[channel]

    def _surface_um(self, x_mm, y_mm, channel: str, reference: bool = False, orientation: str | None = None):
        z = self.spec.best_focus_um(x_mm, y_mm, channel, _which(orientation))
        if self.optics == "geometric" or reference:
            return z
        r, s = self.focus_shift_table(channel)
        return z + np.interp(self.spec.rho(x_mm, y_mm), r, s)

    # -- the DESIGN.md API -------------------------------------------------------------------------
    @property
    def reference_channel(self) -> str:
        """The channel whose frame at z_ref defines the pixel geometry of :meth:`warp_px` (G if there is one)."""
        return "G" if "G" in self.channels else self.channels[0]

    @property
    def has_geometry_map(self) -> bool:
        """Distortion makes the frame maps non-affine: the compositor then warps with :meth:`warp_px`."""
        return not self.spec.distortion.is_zero

    def warp_px(self, x, y, z_um, channel: str, lateral_colour: bool = True):
        """Exact map: where the scene point seen at pixel (x, y) of the z_ref geometry (the reference channel's
        frame at ``z_ref_um``) appears in channel ``channel`` of the frame at ``z_um``: distortion (changing with
        z), breathing, shift and lateral colour (docs/geometry.md). ``lateral_colour=False``: from the channel's
        own frame at z_ref."""
        self.spec.channel(channel)
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        z = np.asarray(z_um, dtype=np.float64)
        if z.ndim:  # one z per point: evaluate per distinct z (scan positions are few)
            z = np.broadcast_to(z, x.shape)
            ox, oy = np.empty(x.shape), np.empty(x.shape)
            for zz in np.unique(z):
                m = z == zz
                ox[m], oy[m] = self.warp_px(x[m], y[m], float(zz), channel, lateral_colour)
            return ox, oy
        sx, sy = self.spec.scene_px(x, y, self.z_ref_um, self.reference_channel if lateral_colour else channel)
        return self.spec.sensor_px(sx, sy, float(z), channel)

    def distortion_px(self, x_u, y_u, z_um=None, channel: str | None = None):
        """Exact absolute distortion of ``channel`` at ``z_um`` (default z_ref): undistorted -> sensor pixel,
        in :meth:`fieldcal.profile.LensProfile.distortion_px`'s convention (the reference channel's map has no
        linear part at the optical centre; other channels keep their lateral colour)."""
        from fieldcal.fit.distortion import distortion_at
        z = self.z_ref_um if z_um is None else float(z_um)
        ch = channel or self.reference_channel
        self.spec.channel(ch)
        return distortion_at(lambda x, y: self.spec.sensor_px(x, y, z, ch),
                             lambda x, y: self.spec.sensor_px(x, y, z, self.reference_channel),
                             self.spec.optical_centre_px(), x_u, y_u)

    def warp_sd_px(self, x, y, z_um, channel: str):
        """The truth is exact: zero uncertainty, shaped like :meth:`warp_px`'s answer."""
        ox, _ = self.warp_px(x, y, z_um, channel)
        return np.zeros_like(ox), np.zeros_like(ox)

    def landing_px(self, x, y, z_um):
        """Where the scene point seen at pixel (x, y) of the z_ref frame appears in the frame at z."""
        if not self.spec.distortion.is_zero:  # the same channel's frames (lateral colour cancels)
            ch = self.reference_channel
            sx, sy = self.spec.scene_px(x, y, self.z_ref_um, ch)
            return self.spec.sensor_px(sx, sy, z_um, ch)
        cx, cy = self.spec.optical_centre_px()
        m = self.magnification(z_um)
        sx, sy = self.shift_px(z_um)
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        return cx + m * (x - cx) + sx, cy + m * (y - cy) + sy

    def best_focus_um(self, x, y, channel: str, orientation: str | None = None):
        """Stage position at which the scene point seen at pixel (x, y) of the z_ref frame is in focus.

        ``orientation``: None (the mean of tangential and sagittal, circle of least confusion), "tangential" or
        "sagittal" (the lens spec's astigmatism ``A(rho)`` splits them by ±A/2).

        The lens's surface z_c is a function of where the point lands on the sensor, and with focus breathing
        that depends on z itself: solve z = z_c(landing(x, y, z)) by fixed-point iteration (the map contracts
        by |dz_c/dh| * h / exit pupil, ~0.03 for the triplet). Without breathing or shift this is z_c(x, y).
        """
        return self._solve_focus(x, y, channel, reference=False, orientation=orientation)

    def reference_focus_um(self, x, y, channel: str):
        """Like :meth:`best_focus_um` for the lens's reference surface: with wave optics the paraxial focus
        (W020 = 0), which spherical aberration moves away from the sharpest position; else the same."""
        return self._solve_focus(x, y, channel, reference=True)

    def _solve_focus(self, x, y, channel: str, reference: bool, orientation: str | None = None):
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        z = self._surface_um(*self.spec.pixel_to_mm(x, y), channel, reference, orientation)
        for _ in range(100):
            z_new = self._surface_um(*self.spec.pixel_to_mm(*self.landing_px(x, y, z)), channel, reference,
                                     orientation)
            done = np.max(np.abs(z_new - z), initial=0.0) < 1e-7
            z = z_new
            if done:
                break
        return z

    def best_focus_interval_um(self, x, y, channel: str, level: float = 0.9):
        z = self.best_focus_um(x, y, channel)
        return z, z.copy()

    def magnification(self, z_um, channel: str | None = None):
        return self.spec.magnification(z_um, channel) / self.spec.magnification(self.z_ref_um, channel)

    def shift_px(self, z_um, channel: str | None = None):
        dx, dy = self.spec.shift_px(z_um)
        rx, ry = self.spec.shift_px(self.z_ref_um)
        return dx - rx, dy - ry

    # -- what planning and compositing also need ---------------------------------------------------
    def optical_centre_px(self) -> tuple[float, float]:
        return self.spec.optical_centre_px()

    def lateral_colour_scale(self, channel: str) -> float:
        return self.spec.lateral_colour_scale(channel)

    def wavelength_nm(self, channel: str) -> float:
        return self.spec.channel(channel).wavelength_nm

    def focus_tolerance_um(self, x, y, channel: str, fs_cyc_per_mm: float, q: float):
        """Half-width of the in-tolerance defocus range (MTF at fs within q of its peak) at each point.

        Wave optics: from the pupil's own through-focus MTF on axis (:meth:`wave_tolerance_um`); geometric: the
        spec's defocus model."""
        if self.optics == "wave":
            tol = self.wave_tolerance_um(channel, fs_cyc_per_mm, q)
        else:
            tol = self.spec.focus_tolerance_um(fs_cyc_per_mm, q, channel)
        return np.full(np.broadcast(np.asarray(x), np.asarray(y)).shape, tol)

    def wave_tolerance_um(self, channel: str, fs_cyc_per_mm: float, q: float) -> float:
        """Wave optics, on axis: the distance from the sharpest position (MTF at fs peaks) to the *nearer* point
        where MTF(fs) has fallen by q. With spherical aberration the through-focus curve is skewed and the
        two sides differ; the nearer one makes ``|z - z_best| <= tol`` a guarantee, as a planner reads it."""
        from scipy.optimize import brentq

        from fieldcal.simulate.wave import ChannelOptics, terms_at

        key = (channel, float(fs_cyc_per_mm), float(q))
        cache = self.__dict__.setdefault("_wave_tol", {})
        if key not in cache:
            opt = ChannelOptics(self.spec, channel)
            terms = terms_at(self.spec, channel, 0.0, 0.0)
            z0 = opt.best_focus_shift_um(terms, fs_cyc_per_mm)
            level = (1.0 - q) * opt.mtf(terms, z0, fs_cyc_per_mm)
            f = lambda dz: opt.mtf(terms, z0 + dz, fs_cyc_per_mm) - level  # noqa: E731
            step = max(float(self.spec.focus_tolerance_um(fs_cyc_per_mm, q, channel)), 1e-3)
            sides = []
            for sign in (-1.0, 1.0):
                a, b = 0.0, sign * 0.5 * step
                for _ in range(40):  # walk out until MTF has fallen below the level (it does: defocus)
                    if f(b) < 0:
                        break
                    a, b = b, 2.0 * b
                sides.append(abs(brentq(f, a, b, xtol=1e-3)) if f(b) < 0 else abs(b))
            cache[key] = float(min(sides))
        return cache[key]

    def defocus_otf(self, f_cyc_per_mm, defocus_um, channel: str):
        """The simulated lens's own signed OTF (defocus disc x diffraction x residual blur) at the sensor: the
        renderer applies it to the magnified scene (docs/simulator.md "Geometry"), so frames and truth agree."""
        return self.spec.otf(f_cyc_per_mm, defocus_um, channel)

    def defocus_mtf(self, f_cyc_per_mm, defocus_um, channel: str):
        return self.spec.mtf(f_cyc_per_mm, defocus_um, channel)
