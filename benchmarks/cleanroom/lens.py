"""The clean-room lens: per-channel best-focus surfaces (T and S), spherical aberration, F-number, breathing.

Coordinates: sensor pixels (x right, y down, pixel centres at integers), stage position z in µm. A field
point's tangential focus z_T and sagittal focus z_S are paraxial (no spherical aberration); the MTF peaks the
truth reports are computed from the pupil, so the W040 shift of the sharpest position is in the truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

WAVELENGTH_NM = {"R": 610.0, "G": 540.0, "B": 470.0, "Y": 540.0}


@dataclass(frozen=True)
class CleanLens:
    """One lens, in the terms a lens designer would give it.

    Surfaces are in µm against the normalised field radius ``u = r / r_corner`` measured from the optical
    centre ``(cx, cy)`` (frame centre + ``decentre_px``): mean focus
    ``z0[ch] + c2 u² + c4 u⁴ + tilt_x_um·(x−x0)/W·2 + tilt_y_um·(y−y0)/H·2`` (the tilt terms give the focus
    change from centre to the frame's edge), astigmatism ``z_T − z_S = astig_um·u²``.
    """

    name: str
    f_number: float
    width_px: int = 320
    height_px: int = 240
    pitch_um: float = 3.0
    z0_um: dict = field(default_factory=lambda: {"R": 2.0, "G": 0.0, "B": -2.5, "Y": 0.0})
    c2_um: float = 10.0
    c4_um: float = 0.0
    channel_c2_scale: dict = field(default_factory=lambda: {"R": 1.05, "G": 1.0, "B": 0.93})
    decentre_px: tuple = (0.0, 0.0)
    tilt_x_um: float = 0.0
    tilt_y_um: float = 0.0
    astig_um: float = 0.0
    w040_waves: float = 0.0           # primary spherical aberration, waves at 540 nm (same µm in every channel)
    breathing_per_um: float = 0.0     # magnification m(z) = 1 + b (z − z_mid), about the frame centre
    channels: tuple = ("R", "G", "B")

    @property
    def centre_px(self) -> tuple[float, float]:
        return (0.5 * (self.width_px - 1) + self.decentre_px[0], 0.5 * (self.height_px - 1) + self.decentre_px[1])

    @property
    def r_corner_px(self) -> float:
        return float(np.hypot(0.5 * self.width_px, 0.5 * self.height_px))

    def wavelength_um(self, ch: str) -> float:
        return WAVELENGTH_NM[ch] * 1e-3

    def w040_um(self) -> float:
        return self.w040_waves * 0.540

    def focus_ts_um(self, x, y, ch: str):
        """Paraxial tangential and sagittal focus (µm) at sensor position(s) (x, y)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        cx, cy = self.centre_px
        u2 = ((x - cx) ** 2 + (y - cy) ** 2) / self.r_corner_px ** 2
        s = self.channel_c2_scale.get(ch, 1.0)
        x0, y0 = 0.5 * (self.width_px - 1), 0.5 * (self.height_px - 1)
        mean = (self.z0_um[ch] + s * (self.c2_um * u2 + self.c4_um * u2 * u2)
                + self.tilt_x_um * (x - x0) / (0.5 * self.width_px)
                + self.tilt_y_um * (y - y0) / (0.5 * self.height_px))
        a = self.astig_um * u2
        return mean + 0.5 * a, mean - 0.5 * a

    def radial_unit(self, x: float, y: float) -> tuple[float, float]:
        """Unit vector from the optical centre to (x, y) (x axis at the centre itself)."""
        cx, cy = self.centre_px
        dx, dy = float(x) - cx, float(y) - cy
        r = np.hypot(dx, dy)
        return (1.0, 0.0) if r < 1e-9 else (dx / r, dy / r)

    def magnification(self, z_um: float, z_mid_um: float) -> float:
        return 1.0 + self.breathing_per_um * (float(z_um) - float(z_mid_um))

    def pupil_coefficients_waves(self, x: float, y: float, ch: str, z_um: float):
        """(W_T, W_S, W040) in waves at the channel's wavelength for the sensor at z: the wavefront is
        ``W_T (ρ·r̂)² + W_S (ρ·â)² + W040 ρ⁴`` with r̂ radial, â azimuthal, ρ the unit pupil coordinate.
        Defocus Δz gives W020 = Δz / (8 N²) (paraxial, Goodman)."""
        zt, zs = self.focus_ts_um(x, y, ch)
        lam = self.wavelength_um(ch)
        k = 1.0 / (8.0 * self.f_number ** 2 * lam)
        return float((z_um - zt) * k), float((z_um - zs) * k), self.w040_um() / lam

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["decentre_px"] = list(self.decentre_px)
        d["channels"] = list(self.channels)
        return d


# δ(80 cy/mm, q = 0.05) on axis at 540 nm, 3 µm pixels, from truth.node_truth (diffraction and pixel included):
# lens surfaces are given in these units so every stack spans a similar number of δ
DELTA_NOMINAL_UM = {2.0: 5.6, 2.8: 8.2, 4.0: 12.4, 5.6: 19.7, 8.0: 31.7}


def lens_in_delta(name: str, f_number: float, *, c2: float, c4: float = 0.0, astig: float = 0.0,
                  tilt: tuple = (0.0, 0.0), colour: tuple = (0.5, -0.6), **kw) -> CleanLens:
    """A lens whose surface terms are given in units of its nominal δ (see DELTA_NOMINAL_UM)."""
    d = DELTA_NOMINAL_UM[f_number]
    return CleanLens(name, f_number, c2_um=c2 * d, c4_um=c4 * d, astig_um=astig * d, tilt_x_um=tilt[0] * d,
                     tilt_y_um=tilt[1] * d, z0_um={"R": colour[0] * d, "G": 0.0, "B": colour[1] * d, "Y": 0.0}, **kw)


def benchmark_lenses() -> list[CleanLens]:
    """The benchmark's lenses: F/2–F/8; symmetric, spherical aberration 0.3–0.8 waves, astigmatic, breathing.
    Each spans ~4–6 δ of best focus over the field and channels."""
    return [
        lens_in_delta("sym-f4", 4.0, c2=4.0),
        lens_in_delta("sa05-f2.8", 2.8, c2=3.0, c4=-1.0, w040_waves=0.5, decentre_px=(14.0, -9.0), tilt=(0.5, 0.0)),
        lens_in_delta("astig-f4", 4.0, c2=3.0, astig=2.0, decentre_px=(-10.0, 6.0)),
        lens_in_delta("sa08-astig-f5.6", 5.6, c2=2.5, c4=1.0, w040_waves=0.8, astig=1.5, tilt=(0.0, 0.6)),
        lens_in_delta("breath-sa03-f2", 2.0, c2=3.5, w040_waves=0.3, breathing_per_um=1e-4),
        lens_in_delta("f8-tilt-astig", 8.0, c2=3.0, c4=-1.0, astig=1.5, w040_waves=0.3, decentre_px=(20.0, 10.0),
                      tilt=(0.6, -0.4), colour=(0.6, -0.8)),
    ]
