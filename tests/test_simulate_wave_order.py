"""The wave renderer against an exact per-pixel render on a steep, breathing field (session 11, issue 14).

The wave path blends (node, level) kernel images per pixel. Up to session 10 it blurred the fixed scene (kernels
shrunk by the frame's image scale a) and then warped the blend by a (focus breathing, stage-axis shift); the
band-limited warp of a per-pixel blend mixes the levels of pixels up to ~10 px away, which on a steep focus
gradient is not the local PSF (the geometric path's defect, branch s10-corners). It now warps the scene to the
sensor first and blurs it there, each sensor pixel with the PSF of its own defocus (``WaveBlur.warp_first``).

Reference (independent of the renderer's ladder, nodes and warp): every sensor pixel x takes the scene filtered
by the polychromatic pupil OTF of its own defocus ``z - z_c(x)`` (``pupil.otf_radial`` summed over the channel's
band, on a 1 µm defocus ladder, linear between rungs), times the residual blur's and the pixel aperture's OTF, at
sensor frequency f = g / (a p) for scene frequency g, evaluated as a DFT at the scene position the affine map
sends to x. Measure: the tile's mean SML energy (the tiles' focus measure), peak by a parabola in log through the
top three frames.
"""

import numpy as np
import pytest

from fieldcal.measure.focus import sml
from fieldcal.optics import pupil
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.render import Renderer
from fieldcal.simulate.scene import load_scene
from fieldcal.simulate.wave import band, terms_at

W, H = 160, 120
PITCH_UM = 30.0  # 320x240 at 15 µm, at half the pixels: the same field and focus gradient per µm of sensor
TILE = 16
PAD = 4
RUNG_UM = 2.0


def _spec() -> LensSpec:
    """An F/1.6 wave lens with spherical aberration, a strong curved field (~2.6 µm of focus per pixel at the
    corners), focus breathing (exit pupil 34 mm) and a stage-axis shift; symmetric pupil (no astigmatism, no
    coma) so the reference OTF is radial."""
    return LensSpec.from_dict({
        "format": "fieldcal-lens/1", "name": "steep-wave", "focal_length_mm": 16.0, "f_number": 1.6,
        "image_height_max_mm": 3.0,
        "channels": [{"name": "G", "wavelength_nm": 546.1, "focus_offset_um": 0.0, "curvature_um": [-130.0],
                      "astigmatism_um": 0.0, "lateral_colour": 0.0}],
        "sensor": {"width_px": W, "height_px": H, "pixel_pitch_um": PITCH_UM, "bit_depth": 12,
                   "black_level_dn": 0.0, "full_well_e": 10000.0, "read_noise_e": 2.0, "cfa": None,
                   "exposure_ms": 10.0, "signal_fraction": 0.7},
        "object_distance_mm": 1000.0, "decentre_mm": [0.0, 0.0], "tilt_um_per_mm": [0.0, 0.0],
        "exit_pupil_mm": 34.0, "stage_axis_tilt_mrad": [0.3, -0.2], "z_ref_um": 0.0, "residual_blur_um": 0.5,
        "relative_illumination_edge": 1.0,
        "aberrations": {"unit": "waves", "reference_wavelength_nm": 546.1, "spherical": [0.3]},
    })


def _reference(r: Renderer, z_grid, x0: int, y0: int) -> list[np.ndarray]:
    spec = r.spec
    lam_w = band(spec, "G")
    n_f, w040 = spec.f_number, terms_at(spec, "G", 0.5, 0.0).w040_um  # uniform over the field
    sigma = spec.residual_blur_um
    # the scene's band-limited interpolant: its mirrored (period 2W x 2H) extension, whose edges are continuous
    # (a cropped, periodic window's wrap-around jump rings into the tile at every sub-pixel shift)
    ext = np.concatenate([r.scene[:, :, 0], r.scene[::-1, :, 0]], axis=0).astype(np.float64)
    ext = np.concatenate([ext, ext[:, ::-1]], axis=1)
    spectrum = np.fft.fft2(ext)
    gx, gy = np.fft.fftfreq(2 * W), np.fft.fftfreq(2 * H)
    xs = np.arange(x0 - PAD, x0 + TILE + PAD, dtype=float)
    ys = np.arange(y0 - PAD, y0 + TILE + PAD, dtype=float)
    zs = spec.best_focus_um(*spec.pixel_to_mm(*np.meshgrid(xs, ys)), "G")
    f_table = np.linspace(0.0, 0.75 / spec.sensor.pixel_pitch_um, 257)  # sensor cycles/µm, past the corner
    tables: dict[int, np.ndarray] = {}  # rung -> polychromatic OTF on f_table

    def rung(k: int) -> np.ndarray:
        if k not in tables:
            tables[k] = sum(w * pupil.otf_radial(f_table * lam * 1e-3 * n_f,
                                                 k * RUNG_UM / (8.0 * n_f ** 2 * lam * 1e-3), w040 / (lam * 1e-3))
                            for lam, w in lam_w)
        return tables[k]

    out = []
    for z in z_grid:
        aff = r._affine(float(z), "G")
        a = aff[0, 0]
        ex = np.exp(2j * np.pi * np.outer((xs - aff[0, 2]) / a, gx))
        ey = np.exp(2j * np.pi * np.outer((ys - aff[1, 2]) / a, gy))
        f_um = np.hypot(gx[None, :], gy[:, None]) / (a * spec.sensor.pixel_pitch_um)  # sensor cycles/µm
        d_otf = (np.exp(-2.0 * (np.pi * sigma * f_um) ** 2)
                 * np.sinc(gx / a)[None, :] * np.sinc(gy / a)[:, None])
        u = (z - zs) / RUNG_UM
        k0 = np.floor(u).astype(int)
        t = u - k0
        img = np.zeros_like(zs)
        for k in range(int(k0.min()), int(k0.max()) + 2):
            wk = np.where(k0 == k, 1.0 - t, 0.0) + np.where(k0 == k - 1, t, 0.0)
            if wk.any():
                otf = np.interp(f_um, f_table, rung(k))
                img += wk * (ey @ (spectrum * otf * d_otf) @ ex.T).real / spectrum.size
        out.append(img)
    return out


def _tile_peak(crops, z_grid) -> float:
    e = np.array([sml(np.asarray(f, np.float32), energy=True)[PAD:PAD + TILE, PAD:PAD + TILE].mean()
                  for f in crops])
    k = int(np.argmax(e))
    assert 0 < k < len(z_grid) - 1, f"peak at the scan's end ({z_grid[k]} µm)"
    a, b, c = np.log(e[k - 1:k + 2])
    return z_grid[k] + 0.5 * (z_grid[1] - z_grid[0]) * (a - c) / (a - 2 * b + c)


@pytest.mark.slow
def test_wave_render_is_the_local_psf_at_every_sensor_pixel():
    spec = _spec()
    scene = load_scene("chart", W, H, 3)[0]
    tiles = ((16, 16), (W - TILE - 16, H - TILE - 16))  # opposite corners, 12 px inside the frame
    err = {}
    for first in (True, False):
        r = Renderer(spec, scene, seed=3, optics="wave", fs_cyc_per_mm=13.0)
        r._wave.warp_first = first
        zc = float(spec.best_focus_um(*spec.pixel_to_mm(tiles[0][0] + TILE / 2, tiles[0][1] + TILE / 2), "G"))
        z_grid = zc + 3.0 * np.arange(-5, 6)
        frames = [r.render_float(float(z))[:, :, 0] for z in z_grid]
        if first:
            ref = [_tile_peak(_reference(r, z_grid, x0, y0), z_grid) for x0, y0 in tiles]
        err[first] = np.array([_tile_peak([f[y0 - PAD:y0 + TILE + PAD, x0 - PAD:x0 + TILE + PAD] for f in frames],
                                          z_grid) for x0, y0 in tiles]) - ref
    print(err)
    assert np.all(np.abs(err[True]) < 0.1), err
    assert np.max(np.abs(err[False])) > 2 * np.max(np.abs(err[True])), err  # the old order's error is visible
