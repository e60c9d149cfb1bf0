"""Focal sweeps: emulate a sweep image from a dense stack, and deconvolve a sweep image with the integrated PSF.

A pixel exposed while the sensor moves through ``[z_b - alpha, z_b + alpha]`` (paper eq. 2) records the scene
blurred by the integrated PSF, whose OTF ``H_s`` is the mean of the lens model's signed OTF over that defocus
range (:func:`fieldcal.optics.integrated_otf`, the same function the sweep planner uses). Because the
integration window is centred on each pixel's own best focus, one ``H_s`` per channel serves the whole field
(paper Fig. 7).

Deconvolution restores the lens's *in-focus* image (the target OTF is ``H_0 = OTF(f, 0)``, so the result is
comparable with a stack composite and with the all-in-focus truth), by Wiener filtering with a noise model
(the noise variance estimated from the image, a power-law signal spectrum fitted to it), or by
Richardson-Lucy as an option (scikit-image's iteration, started from the observed image; docs/dependencies.md
says why neither is ``skimage.restoration``'s). The noise gain — how much white pixel noise the filter amplifies,
``sqrt(mean |G|^2)`` — is reported per channel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ParameterError
from ..optics import LensModel
from ..optics.sweep import integrated_otf, radial_on_grid, rfft_radial_grid, sweep_psf_kernel
from .source import image_size, z_positions
from .stack_profile import check_profile_matches, select_frames
from .stream import DEFAULT_TILE_PX, accumulate
from .surface import profile_focus_map
from .weights import SweepKernel


@dataclass
class SweepResult:
    """A (deconvolved) sweep image in float32 raw units plus what was done."""

    image: np.ndarray
    info: dict = field(default_factory=dict)


def estimate_noise_sigma(channel_image: np.ndarray, max_samples: int | None = None) -> float:
    """Pixel noise std (image units): Immerkaer's (1996) Laplacian-difference operator, robust MAD.

    The 3x3 operator cancels smooth image content up to second order; its L2 norm is 6, so the median
    absolute response / 0.6745 / 6 is the noise std where texture is sparse. ``max_samples``: the median over
    about that many responses spread evenly over the image (its standard error ~1.25 / sqrt(n) relative: 0.1 %
    at a million), not all of them.
    """
    import cv2
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)
    r = cv2.filter2D(np.asarray(channel_image, dtype=np.float32), -1, k, borderType=cv2.BORDER_REFLECT)[1:-1, 1:-1]
    if max_samples is not None and r.size > max_samples:
        # every step-th response of the interior in row-major order: the interior made contiguous, then a strided
        # view (10x faster than gathering by computed row and column indices, the same samples)
        r = np.ascontiguousarray(r).ravel()[::int(np.ceil(r.size / max_samples))]
    return immerkaer_sigma(r)


def immerkaer_sigma(responses: np.ndarray) -> float:
    """Noise std from Immerkaer's 3x3 operator's responses (:func:`estimate_noise_sigma`): the median absolute
    response / 0.6745 (a Gaussian's MAD) / 6 (the operator's L2 norm). Overwrites ``responses`` when it owns
    its data."""
    r = np.asarray(responses)
    return float(np.median(np.abs(r, out=r if r.flags.owndata and r.flags.writeable else None)) / 0.6745 / 6.0)


def sensor_noise_sigma(image: np.ndarray, gain_dn_per_e: float, read_noise_e: float,
                       black_dn: float = 0.0) -> list[float]:
    """RMS pixel noise (DN) per channel of a recorded image under a camera's noise model (photon + read):
    ``sqrt(mean(g (DN - black) + (g read)^2))``.

    ``gain_dn_per_e`` and ``read_noise_e`` are what a camera's photon-transfer calibration (EMVA 1288) states.
    A deconvolution given them does not estimate the noise from the image, which texture inflates
    (:func:`estimate_noise_sigma` reads about 2x high on a chart, costing ~0.7 dB after Wiener filtering).

    >>> sensor_noise_sigma(np.full((4, 4, 1), 1100.0), gain_dn_per_e=0.5, read_noise_e=4.0, black_dn=100.0)
    [22.44...]
    """
    for name, v in (("gain_dn_per_e", gain_dn_per_e), ("read_noise_e", read_noise_e), ("black_dn", black_dn)):
        if not np.isfinite(v) or v < 0 or (name == "gain_dn_per_e" and v == 0):
            raise ParameterError(f"camera noise {name} = {v!r} must be a finite number"
                                 f"{' > 0' if name == 'gain_dn_per_e' else ' >= 0'}", field="camera_noise",
                                 fix="give the camera's gain (DN per electron) and read noise (electrons), e.g. 0.5 4")
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 2:
        img = img[..., None]
    g = float(gain_dn_per_e)
    var = g * np.clip(img - float(black_dn), 0.0, None) + (g * float(read_noise_e)) ** 2
    return [float(np.sqrt(var[..., c].mean())) for c in range(img.shape[2])]


def _pad(img: np.ndarray, pad: int) -> tuple[np.ndarray, tuple[int, int]]:
    from scipy import fft  # imported when needed: ~0.15 s saved on stack composites

    h, w = img.shape
    hp = fft.next_fast_len(h + 2 * pad, real=True)
    wp = fft.next_fast_len(w + 2 * pad, real=True)
    return np.pad(img, ((pad, hp - h - pad), (pad, wp - w - pad)), mode="symmetric"), (hp, wp)


def _signal_spectrum_model(power: np.ndarray, f: np.ndarray, hs2: np.ndarray, noise_power: float,
                           fmin: float, map_rows=None) -> tuple[float, float]:
    """Fit ``P_x(f) = A f^-beta`` to the observed power where the sweep passes signal well above noise.

    ``map_rows(fn, n_rows)``, when given, returns ``[fn(a, b), ...]`` over row bands ``a:b`` covering the
    arrays' ``n_rows`` rows in order (on threads): the samples' selection and logarithms are made per band and
    joined in row order, the same arrays as made whole, so the same fit bit for bit."""
    def samples(a: int, b: int, loose: bool) -> tuple[np.ndarray, np.ndarray]:
        fr, hr, pr = f[a:b], hs2[a:b], power[a:b]
        ok = (fr > fmin) & (hr > 0.01) if loose else (fr > fmin) & (hr > 0.05) & (pr > 3.0 * noise_power)
        # the selected samples in float64 (float32 spectra: the least-squares sums below over ~10^6 points)
        lp = np.log(np.maximum(np.asarray(pr[ok], np.float64) - noise_power, 1e-30) / np.asarray(hr[ok], np.float64))
        return lp, np.log(np.asarray(fr[ok], np.float64))

    rows = map_rows if map_rows is not None else (lambda fn, n: [fn(0, n)])
    parts = rows(lambda a, b: samples(a, b, False), power.shape[0])
    if sum(len(lp) for lp, _ in parts) < 20:
        parts = rows(lambda a, b: samples(a, b, True), power.shape[0])
    if sum(len(lp) for lp, _ in parts) < 2:
        raise ParameterError("the sweep's integrated PSF passes almost nothing (MTF below 0.1 at every frequency): "
                             "alpha is too large to deconvolve", field="sweep_alpha_um",
                             fix="use a smaller alpha (see the sweep trade table in docs/benchmarks.md)")
    lp = parts[0][0] if len(parts) == 1 else np.concatenate([p for p, _ in parts])
    lf = parts[0][1] if len(parts) == 1 else np.concatenate([q for _, q in parts])
    # the least-squares line in closed form (np.polyfit's Vandermonde + SVD cost ~0.15 s per million points,
    # on the compositor's serial path)
    lf_c = lf - lf.mean()
    slope = float(np.dot(lf_c, lp - lp.mean()) / max(float(np.dot(lf_c, lf_c)), 1e-300))
    beta = float(np.clip(-slope, 1.0, 4.0))
    loga = float(np.mean(lp + beta * lf))
    return float(np.exp(loga)), beta


def wiener_deconvolve(channel_image: np.ndarray, profile: LensModel, alpha_um: float, channel: str, pitch_um: float,
                      noise_sigma: float | None = None, target_focus: bool = True) -> tuple[np.ndarray, dict]:
    """Wiener-deconvolve one channel of a sweep image; returns ``(image, info)`` with the noise gain.

    The filter is ``G = H_0 conj(H_s) P_x / (|H_s|^2 P_x + sigma^2)`` with ``P_x`` a power law fitted to the
    image's own spectrum and ``sigma`` the pixel noise (estimated if not given).
    """
    from scipy import fft  # imported when needed: ~0.15 s saved on stack composites

    img = np.asarray(channel_image, dtype=np.float64)
    mean = float(img.mean())
    sigma = estimate_noise_sigma(img) if noise_sigma is None else float(noise_sigma)
    sigma = max(sigma, 1e-6 * max(abs(mean), 1e-12), 1e-12)
    blur_px = alpha_um / float(profile.f_number) / pitch_um
    # mirror padding against wrap-around edges; beyond the image size a wider pad adds nothing (the mirror
    # repeats), and alpha >> D would otherwise ask for gigabytes
    pad = min(int(np.ceil(2 * blur_px)) + 16, max(img.shape[0], img.shape[1]))
    padded, shape = _pad(img - mean, pad)
    y = fft.rfft2(padded, workers=-1)
    f = rfft_radial_grid(shape, pitch_um)
    hs = radial_on_grid(lambda t: integrated_otf(profile, t, alpha_um, channel), f)
    h0 = radial_on_grid(lambda t: integrated_otf(profile, t, 0.0, channel), f) if target_focus else np.ones_like(hs)
    npix = shape[0] * shape[1]
    power = (np.abs(y) ** 2) / npix
    noise_power = sigma * sigma
    fmin = 4.0 / (max(shape) * pitch_um * 1e-3)
    a, beta = _signal_spectrum_model(power, f, hs * hs, noise_power, fmin)
    px = a * np.maximum(f, fmin) ** (-beta)
    g = h0 * hs * px / (hs * hs * px + noise_power)
    g[0, 0] = 1.0  # keep the mean
    out = fft.irfft2(y * g, s=shape, workers=-1)
    h, w = img.shape
    p0 = int(np.ceil(2 * blur_px)) + 16
    res = out[p0:p0 + h, p0:p0 + w] + mean
    # Noise gain over the full rfft2 grid (count the mirrored half twice).
    wts = np.full(g.shape, 2.0)
    wts[:, 0] = 1.0
    if shape[1] % 2 == 0:
        wts[:, -1] = 1.0
    gain = float(np.sqrt(np.sum(wts * g * g) / np.sum(wts)))
    return res.astype(np.float32), {"noise_sigma": sigma, "noise_gain": gain, "signal_beta": beta}


def rl_deconvolve(channel_image: np.ndarray, profile: LensModel, alpha_um: float, channel: str, pitch_um: float,
                  black: float, white: float, iterations: int = 30) -> tuple[np.ndarray, dict]:
    """Richardson-Lucy with the integrated PSF, then the in-focus PSF applied to land on the lens's in-focus
    image (the same target as the Wiener filter).

    The iteration is scikit-image's, started from the observed image instead of its flat 0.5 image (which
    needs hundreds of iterations to recover fine detail), with OpenCV's filter2D for the convolutions.
    """
    import cv2

    blur_px = alpha_um / float(profile.f_number) / pitch_um
    size = 2 * int(np.ceil(1.5 * blur_px)) + 9
    psf = sweep_psf_kernel(profile, alpha_um, channel, pitch_um, size).astype(np.float32)
    psf_flip = np.ascontiguousarray(psf[::-1, ::-1])
    focus = sweep_psf_kernel(profile, 0.0, channel, pitch_um, 15).astype(np.float32)
    scale = white - black
    u = np.clip((np.asarray(channel_image, dtype=np.float32) - black) / scale, 0.0, None)
    eps = np.float32(1e-6)
    est = u.copy()
    for _ in range(int(iterations)):
        conv = cv2.filter2D(est, -1, psf, borderType=cv2.BORDER_REFLECT)
        ratio = u / np.maximum(conv, eps)
        est *= cv2.filter2D(ratio, -1, psf_flip, borderType=cv2.BORDER_REFLECT)
    est = cv2.filter2D(est, -1, focus, borderType=cv2.BORDER_REFLECT)
    return (est * scale + black).astype(np.float32), {"iterations": int(iterations), "psf_px": psf.shape[0]}


def deconvolve_sweep(image: np.ndarray, profile: LensModel, alpha_um: float, channels, *, black: float, white: float,
                     method: str = "wiener", rl_iterations: int = 30, noise_sigma=None, breathing: str | None = None,
                     refocus_um: float = 0.0, widen_um: np.ndarray | None = None,
                     zone_px: int | None = None) -> SweepResult:
    """Deconvolve a sweep image (H x W x C, raw units) channel by channel.

    ``noise_sigma``: pixel noise (raw units), one value or one per channel (e.g. ``emulate_sweep``'s
    ``info["noise_sigma"]``); estimated from the image when None.

    ``breathing``: None for a sweep already in the ``z_ref`` geometry without image motion (``emulate_sweep``
    registers every frame before averaging): one kernel for the whole field. For a *captured* sweep (sensor
    geometry, the image moving with the stage) ``"aware"`` deconvolves per field zone with the motion in each
    zone's kernel and then registers the result to ``z_ref`` (:mod:`.sweep_zones`); ``"blind"`` does the same
    without the motion in the kernel (for comparison). ``refocus_um`` (the plan's) moves the window centres;
    ``widen_um`` (H x W or H x W x C) is the per-pixel widening of the half-range of a plan made with a
    confidence; ``zone_px`` the zone size (default 64).
    """
    if method not in ("wiener", "rl"):
        raise ParameterError(f"unknown deconvolution {method!r}", field="deconvolve", fix="use wiener, rl or none")
    if not (np.isfinite(alpha_um) and alpha_um > 0):
        raise ParameterError(f"sweep half-range must be > 0 µm, got {alpha_um}", field="sweep_alpha_um",
                             fix="e.g. 20 (µm)")
    if profile.f_number is None:
        raise ParameterError("the profile has no f-number, which the integrated PSF needs", field="f_number",
                             fix="calibrate with the lens's f-number recorded in the stack (f_number in stack.json)")
    if breathing is not None:
        if method != "wiener":
            raise ParameterError("per-zone (breathing) deconvolution is Wiener only", field="deconvolve",
                                 fix="use --deconvolve wiener for a captured sweep, or no breathing correction")
        return _deconvolve_captured(image, profile, alpha_um, channels, noise_sigma, breathing, refocus_um, widen_um,
                                    zone_px)
    pitch = float(profile.pixel_pitch_um)
    out = np.empty(image.shape, dtype=np.float32)
    info: dict = {"deconvolution": method, "alpha_um": float(alpha_um), "channels": {}}
    for ci, ch in enumerate(channels):
        if method == "wiener":
            sig = noise_sigma[ci] if isinstance(noise_sigma, (list, tuple, np.ndarray)) else noise_sigma
            out[..., ci], inf = wiener_deconvolve(image[..., ci], profile, alpha_um, ch, pitch, sig)
        else:
            out[..., ci], inf = rl_deconvolve(image[..., ci], profile, alpha_um, ch, pitch, black, white,
                                              rl_iterations)
        info["channels"][ch] = inf
    return SweepResult(out, info)


def _deconvolve_captured(image, profile, alpha_um, channels, noise_sigma, breathing, refocus_um, widen_um,
                         zone_px) -> SweepResult:
    """Per-zone Wiener deconvolution of a captured sweep, then registration to z_ref (:mod:`.sweep_zones`)."""
    from scipy import fft

    from . import sweep_zones as sz

    if breathing not in sz.BREATHING:
        raise ParameterError(f"unknown breathing mode {breathing!r}", field="breathing",
                             fix=f"use one of {', '.join(sz.BREATHING)}, or None for an emulated sweep")
    h, w = image.shape[:2]
    pitch = float(profile.pixel_pitch_um)
    widen = None
    if widen_um is not None:
        u = np.asarray(widen_um, dtype=np.float64)
        u = u[..., None] if u.ndim == 2 else u
        if u.shape[:2] != (h, w) or u.shape[2] not in (1, len(channels)) or not np.all(np.isfinite(u) & (u >= 0)):
            raise ParameterError(f"band widening of shape {np.shape(widen_um)} does not fit a {w}x{h} image of "
                                 f"{len(channels)} channel(s), or is not finite and >= 0", field="widen_um",
                                 fix="pass the plan's widen_um (P x H x W moved to H x W x P), NaN set to 0")
        widen = np.broadcast_to(u, (h, w, len(channels)))
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    out = np.empty(image.shape, dtype=np.float32)
    info: dict = {"deconvolution": "wiener", "alpha_um": float(alpha_um), "breathing": breathing,
                  "zone_px": int(zone_px or sz.DEFAULT_ZONE_PX), "channels": {}}
    for ci, ch in enumerate(channels):
        img = np.asarray(image[..., ci], dtype=np.float64)
        sig = noise_sigma[ci] if isinstance(noise_sigma, (list, tuple, np.ndarray)) else noise_sigma
        sigma = estimate_noise_sigma(img) if sig is None else float(sig)
        sigma = max(sigma, 1e-6 * max(abs(float(img.mean())), 1e-12), 1e-12)
        # one signal-spectrum model for every zone, fitted on the whole image with the field's mean kernel
        padded, shape = _pad(img - img.mean(), 16)
        y = fft.rfft2(padded, workers=-1)
        f = rfft_radial_grid(shape, pitch)
        hs = radial_on_grid(lambda t: integrated_otf(profile, t, alpha_um, ch), f)
        power = np.abs(y) ** 2 / (shape[0] * shape[1])
        model = _signal_spectrum_model(power, f, hs * hs, sigma * sigma, 4.0 / (max(shape) * pitch * 1e-3))
        centre = sz.window_centres_um(profile, xx, yy, ch, refocus_um)
        dec, inf = sz.deconvolve_zones(img, profile, alpha_um, ch, noise_sigma=sigma, signal_model=model,
                                       centre_um=centre, widen_um=None if widen is None else widen[..., ci],
                                       breathing=breathing, zone_px=zone_px or sz.DEFAULT_ZONE_PX)
        out[..., ci] = sz.register_to_reference(dec, profile, ch, refocus_um)
        info["channels"][ch] = inf
    return SweepResult(out, info)


def emulate_sweep(stack, profile, alpha_um: float, *, frames=None, lateral_colour: bool = False,
                  tile: int = DEFAULT_TILE_PX, quiet: bool = False) -> SweepResult:
    """Emulate a per-pixel-exposure sweep from a dense stack (paper Fig. 8d), float32 raw units.

    Each pixel and channel averages the frames within ``[z_b - alpha, z_b + alpha]`` of its best focus,
    weighted by the sensor travel each frame stands for (see :class:`SweepKernel`).
    """
    check_profile_matches(stack, profile)
    frames = select_frames(stack, frames)
    z = np.sort(z_positions(stack)[frames])
    kernel = SweepKernel(z, alpha_um)
    if len(z) > 1 and float(np.max(np.diff(z))) > 2.0 * alpha_um:
        raise ParameterError(f"frames are up to {float(np.max(np.diff(z))):g} µm apart, more than the sweep "
                             f"range 2 alpha = {2 * alpha_um:g} µm: that is a stack, not a sweep",
                             field="sweep_alpha_um", fix="use a denser stack or a larger alpha")
    w, h = image_size(stack)
    zb = profile_focus_map(profile, w, h, stack.channels, lateral_colour)
    acc = accumulate(stack, zb, kernel, profile, lateral_colour=lateral_colour, tile=tile, frames=frames,
                     desc="emulating sweep", quiet=quiet)
    spacing = float(np.median(np.diff(z))) if len(z) > 1 else 2.0 * alpha_um
    sigma = sweep_noise_sigma(stack, frames, kernel)
    return SweepResult(acc, {"alpha_um": float(alpha_um), "frames_used": int(len(frames)),
                             "frames_per_pixel": round(2.0 * alpha_um / spacing, 2),
                             "noise_sigma": [round(float(v), 4) for v in sigma]})


def sweep_noise_sigma(stack, frames, kernel: SweepKernel, n_probe: int = 6) -> list[float]:
    """Pixel noise (raw units) per channel of an emulated sweep: frame noise times ``sqrt(sum w_k^2)``.

    Frame noise is measured on the frames at both ends of the stack and a few between, and the smallest
    estimate is kept: texture only ever inflates the estimate, and far from focus a frame is smooth.
    """
    z_all = z_positions(stack)
    order = np.asarray(frames)[np.argsort(z_all[frames], kind="stable")]
    probe = np.unique(np.linspace(0, len(order) - 1, min(n_probe, len(order))).round().astype(int))
    w, h = image_size(stack)
    per = np.array([[estimate_noise_sigma(f[..., c]) for c in range(f.shape[2])]
                    for f in (stack.read(int(order[k])).astype(np.float32) for k in probe)])
    zmid = 0.5 * (kernel.z[0] + kernel.z[-1])
    sum_w2 = float(sum(float(kernel.weight(k, np.array([zmid]))[0]) ** 2 for k in range(len(kernel))))
    return [float(v * np.sqrt(sum_w2)) for v in per.min(axis=0)]
