"""The lens's defocus measured from the stack itself: how much the blur disc grows per frame step.

A stack without a lens profile records neither the F-number nor (often) the stage positions, so the multi-frame
Wiener combination of :mod:`.depth_wiener` has no defocus OTF to work with. Geometric defocus gives one from two
numbers: the blur disc's diameter is proportional to the distance from best focus, ``D = r |k - k_b|`` px for
frame ``k`` of a pixel in focus at frame ``k_b`` (sub-frame), ``r`` px per frame step. ``r`` is measured here:

1. **Patches**: blocks of :data:`PATCH_PX` px where the depth map (:func:`.fusion.depth_map`) is confident and
   uniform (no depth edge inside) and lies within :data:`NEAR_FRAME` of a frame ``k``, the sharpest frame there;
   at most :data:`PATCHES_PER_FRAME` per frame, the most confident.
2. **Relative blur**: for each patch and each frame ``j = k +- 1, k +- 2`` the disc diameter ``D`` that takes frame
   ``k``'s patch to frame ``j``'s, ``min_D sum_f |Y_j(f) - J(D f) Y_k(f)|^2`` (``J`` the disc's OTF
   ``2 J1(pi D f) / (pi D f)``, Hann-windowed patches, grey) on radial frequency bins where frame ``k``'s power
   is at least :data:`SIGNAL_TO_NOISE` times its noise (the noise power subtracted: noise in the sharper patch
   would otherwise read as extra blur). That is the least-squares (maximum likelihood under white noise) fit.
3. **Rate**: each pair gives ``D / |j - k_b|``; the rate is their median, its uncertainty the MAD over the square
   root of their number; the medians at one and at two frames' distance are kept apart as a check that the blur
   grows linearly, as geometric defocus does.

The estimate is **unreliable** (and compositing falls back to choosing frames, saying why) when too few patches
pass (:data:`MIN_PAIRS`: too little texture), the disc barely grows (:data:`MIN_RATE_PX`: frames that do not change
focus), the disc two frames apart is wider than the patches resolve (:data:`MAX_DISC_PATCH_FRACTION`: read short,
and a Wiener step with it rings beside depth edges on real bokeh), the uncertainty is above :data:`MAX_REL_SD` of
the rate, or the rates at one and two frames' distance disagree by more than :data:`MAX_LINEARITY` (the blur does
not grow as geometric defocus does).

The frames' in-focus blur (aberrations, diffraction, demosaicing) is common to every frame, so the relative blur
is what the Wiener combination needs: its target is the image as the sharpest frame records it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ParameterError
from .source import image_size, read_roi, z_positions

#: Square patches (px) the relative blur is fitted on: an eighth of the image's shorter side within these bounds
#: (a two-frame disc of a few px fits well inside the smallest).
PATCH_PX = (32, 64)
#: A patch counts as in focus at frame k when its depth lies within this many frames of k ...
NEAR_FRAME = 0.5
#: ... and the median depths of its four quarters spread over at most this many frames (no depth edge inside).
MAX_DEPTH_SPREAD = 0.5
#: Patches kept per frame (the most confident).
PATCHES_PER_FRAME = 40
#: Frequency bins used: the sharp frame's power at least this many times its noise power there.
SIGNAL_TO_NOISE = 4.0
#: Fewer usable patch pairs than this: too little texture to measure the defocus.
MIN_PAIRS = 16
#: A disc growing by less than this (px per frame step): the frames barely change focus.
MIN_RATE_PX = 0.3
#: The rate's standard error above this fraction of it: unreliable.
MAX_REL_SD = 0.15
#: The rates measured at one and at two frames' distance differ by more than this fraction: not geometric.
MAX_LINEARITY = 0.35
#: The disc two frames apart wider than this fraction of the patch: not resolved. A Hann-windowed patch sees a
#: disc through a window whose full width at half maximum is half the patch; wider discs are fitted on its tails.
#: On the real board (64-px patches) every other frame, downscaled 0.6-1.0 (15-25 px per step), read its
#: two-step disc 20-40 % short against the one-step one, the rate 12-20 % short, and passed below 0.9 of full
#: size; the Wiener step with it rang in the defocused board beside depth edges, which choosing frames does not
#: (docs/benchmarks.md, bench_ring_s14). An ideal disc is still read right a little beyond this; the check
#: cannot tell the two apart, and choosing frames is the safe side.
MAX_DISC_PATCH_FRACTION = 0.5
#: Largest disc (px) searched for.
MAX_DISC_PX = 40.0
#: Nodes of the Gauss-Hermite quadrature over the depth's error (:meth:`MeasuredDefocus.defocus_otf_moments`).
GAUSS_HERMITE_NODES = 9


@dataclass(frozen=True)
class DefocusRate:
    """The blur disc's growth per frame step measured on a stack (:func:`estimate_defocus_rate`).

    ``disc_px_per_step`` the diameter's growth (px per frame step), ``sd_px_per_step`` its standard error;
    ``by_distance`` the median rate and number of pairs at 1 and 2 frames' distance; ``n_patches`` and
    ``n_pairs`` what it rests on; ``spacing_um`` the frames' median spacing (µm as the stack records it);
    ``reliable`` whether compositing may use it, ``reason`` why not.
    """

    disc_px_per_step: float
    sd_px_per_step: float
    by_distance: dict = field(default_factory=dict)
    n_patches: int = 0
    n_pairs: int = 0
    spacing_um: float = 1.0
    noise_sigma: float = 0.0
    depth_sd_steps: float = 0.0
    reliable: bool = False
    reason: str = ""

    @property
    def um_per_disc_px(self) -> float:
        """Defocus (µm of the stack's z) that widens the blur disc's diameter by 1 px: ``N x pitch``."""
        return self.spacing_um / self.disc_px_per_step

    def info(self) -> dict:
        """A JSON-ready summary (a rate not measured is None: the composite's metadata is written as JSON)."""
        def num(v: float) -> float | None:
            return round(float(v), 3) if np.isfinite(v) else None

        return {"disc_px_per_step": num(self.disc_px_per_step), "sd_px_per_step": num(self.sd_px_per_step),
                "by_distance": {str(k): {"disc_px_per_step": num(v[0]), "pairs": int(v[1])}
                                for k, v in self.by_distance.items()},
                "depth_sd_steps": num(self.depth_sd_steps),
                "patches": self.n_patches, "pairs": self.n_pairs, "reliable": self.reliable,
                "reason": self.reason}


@dataclass(frozen=True)
class MeasuredDefocus:
    """A lens model for :func:`.depth_wiener.wiener_composite` from a measured :class:`DefocusRate`: the
    geometric disc OTF with the measured growth, no in-focus blur (the target is the sharpest frame as recorded).

    ``pixel_pitch_um`` is the stack's (1 when unknown: frequencies are then in cycles per 1000 px, consistently);
    ``f_number`` the working F-number the rate implies, ``um_per_disc_px / pixel_pitch_um`` (with dummy stage
    positions a number in the stack's own units, used only through that product).
    """

    rate: DefocusRate
    pixel_pitch_um: float = 1.0
    depth_sd_steps: float = 0.0

    @property
    def f_number(self) -> float:
        return self.rate.um_per_disc_px / self.pixel_pitch_um

    def defocus_otf(self, f_cyc_per_mm, dz_um: float, channel=None) -> np.ndarray:
        """Disc OTF at spatial frequency ``f`` (cycles/mm) for a defocus ``dz_um`` (signed, real: it goes negative)."""
        rho = np.asarray(f_cyc_per_mm, dtype=np.float64) * self.pixel_pitch_um * 1e-3  # cycles/px
        return disc_otf(rho, abs(float(dz_um)) / self.rate.um_per_disc_px)

    def defocus_otf_moments(self, f_cyc_per_mm, dz_um: float, channel=None) -> tuple[np.ndarray, np.ndarray]:
        """Mean and mean square of the disc OTF when the defocus is ``dz_um`` plus a Gaussian error of
        ``depth_sd_steps`` frame steps (the depth map's, :attr:`DefocusRate.depth_sd_steps`): Gauss-Hermite
        quadrature over the error."""
        sd_um = max(float(self.depth_sd_steps), 0.0) * self.rate.spacing_um
        if sd_um <= 0:
            h = self.defocus_otf(f_cyc_per_mm, dz_um)
            return h, h * h
        t, wts = np.polynomial.hermite_e.hermegauss(GAUSS_HERMITE_NODES)
        wts = wts / wts.sum()
        m1 = m2 = 0.0
        for ti, wi in zip(t, wts):
            h = self.defocus_otf(f_cyc_per_mm, float(dz_um) + sd_um * float(ti))
            m1 = m1 + wi * h
            m2 = m2 + wi * h * h
        return m1, m2


def disc_otf(rho_cyc_per_px, diameter_px) -> np.ndarray:
    """OTF of a uniform disc of ``diameter_px`` at radial frequencies ``rho`` (cycles/px): ``2 J1(x)/x``, ``x = pi D rho``
    (broadcasts; :func:`fieldcal.optics.defocus.disc_otf`)."""
    from ..optics.defocus import disc_otf as jinc

    return jinc(np.pi * np.asarray(diameter_px, dtype=np.float64) * np.asarray(rho_cyc_per_px, dtype=np.float64))


def _select_patches(kd: np.ndarray, confidence: np.ndarray, n_frames: int, patch: int) -> list[tuple[int, int, int, float]]:
    """``(x0, y0, k, k_b)`` of patches (half-overlapping) of uniform, confident depth ``k_b``, sharpest in frame
    ``k`` (the nearest), the most confident first per frame."""
    h, w = kd.shape
    stride = max(1, patch // 2)
    ys = np.arange(0, h - patch + 1, stride)
    xs = np.arange(0, w - patch + 1, stride)
    if ys.size == 0 or xs.size == 0:
        return []
    # statistics over each patch from half-patch cells (patches are 2 x 2 cells)
    ny, nx = ys.size + 1, xs.size + 1
    cells = kd[:ny * stride, :nx * stride].reshape(ny, stride, nx, stride)
    cconf = confidence[:ny * stride, :nx * stride].reshape(ny, stride, nx, stride)
    # per-pixel depths are noisy (a frame or more where texture is faint): each quarter's median
    # (the two medians at once on the compositor's threads: NumPy's partition releases the GIL, and each took
    # ~45 ms on the 2048 x 1536 board with a core idle)
    from .dff import map_in_order

    qmed, cmed = map_in_order(lambda a: np.median(a, axis=(1, 3)), [cells, cconf])

    def pool(a, fn):
        return fn(fn(a[:-1, :-1], a[1:, :-1]), fn(a[:-1, 1:], a[1:, 1:]))

    spread = pool(qmed, np.maximum) - pool(qmed, np.minimum)
    med = 0.25 * (qmed[:-1, :-1] + qmed[1:, :-1] + qmed[:-1, 1:] + qmed[1:, 1:])
    conf = pool(cmed, np.minimum)  # every quarter of the patch textured
    positive = conf[conf > 0]
    if positive.size == 0:
        return []
    floor = float(np.median(positive))  # the upper half of the textured patches
    k = np.clip(np.rint(med), 0, n_frames - 1).astype(int)
    ok = (np.abs(med - k) <= NEAR_FRAME) & (spread <= MAX_DEPTH_SPREAD) & (conf >= floor) & (conf > 0)
    out = []
    for kk in range(n_frames):
        iy, ix = np.nonzero(ok & (k == kk))
        chosen: list[tuple[int, int]] = []
        for o in np.argsort(-conf[iy, ix], kind="stable"):
            y, x = int(iy[o]), int(ix[o])
            if any(abs(y - cy) < 2 and abs(x - cx) < 2 for cy, cx in chosen):
                continue  # no two patches sharing pixels: independent measurements
            chosen.append((y, x))
            out.append((int(xs[x]), int(ys[y]), kk, float(med[y, x])))
            if len(chosen) == PATCHES_PER_FRAME:
                break
    return out


def _radial_bins(patch: int, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Bin index of each rfft2 coefficient of a ``patch`` square (-1 outside 0 < rho <= 0.5) and the bins' centres."""
    fy = np.fft.fftfreq(patch)[:, None]
    fx = np.fft.rfftfreq(patch)[None, :]
    rho = np.hypot(fy, fx)
    edges = np.linspace(0.0, 0.5, n_bins + 1)
    idx = np.minimum(np.digitize(rho, edges) - 1, n_bins - 1)
    idx[(rho <= 0) | (rho > 0.5)] = -1
    return idx, 0.5 * (edges[:-1] + edges[1:])


def _grey(a: np.ndarray) -> np.ndarray:
    from .._numeric import channel_mean

    return channel_mean(np.asarray(a, dtype=np.float32))


def _disc_fit_tables(n: int, window=None, bins=None) -> tuple:
    """What :func:`fit_disc_px` needs of a patch size, window and bins, whatever the patches: the window, the bins
    (index of each coefficient, centres), the mask of binned coefficients with their bins, the half-plane's column
    weights there, each bin's coefficient count, the window's power, the grid of discs searched and their OTFs at
    every bin's centre (a bin set's OTFs are these columns: the same numbers)."""
    if window is None:
        hann = np.hanning(n)
        window = np.outer(hann, hann)
    idx, centres = bins if bins is not None else _radial_bins(n, n // 2)
    m = idx >= 0
    nb = len(centres)
    # rfft2 counts the half-plane once: weight interior columns twice so the sums are the full plane's
    wcol = np.full(idx.shape, 2.0)
    wcol[:, 0] = 1.0
    if n % 2 == 0:
        wcol[:, -1] = 1.0
    grid = np.arange(0.0, MAX_DISC_PX + 1e-9, 0.1)
    return (window, centres, m, idx[m], wcol[m], np.bincount(idx[m], wcol[m], minlength=nb),
            float(np.sum(window ** 2)), grid, disc_otf(centres[None, :], grid[:, None]))


def fit_disc_px(sharp: np.ndarray, blurred: np.ndarray, noise_sigma: float, *, window=None,
                bins=None, tables=None) -> float:
    """Diameter (px) of the uniform disc that best takes ``sharp`` to ``blurred`` (two grey patches of the same
    square size; least squares on radial frequency bins where ``sharp`` is well above its noise). NaN when no bin
    qualifies or the best disc lies at the search's end. ``tables``: :func:`_disc_fit_tables` of the same size,
    window and bins, made once for many patches."""
    n = sharp.shape[0]
    if tables is None:
        tables = _disc_fit_tables(n, window, bins)
    window, centres, m, idx_m, wcol_m, count, window_power, grid, hd_all = tables
    ys = np.fft.rfft2((sharp - sharp.mean()) * window)
    yb = np.fft.rfft2((blurred - blurred.mean()) * window)
    nb = len(centres)
    cross = np.bincount(idx_m, wcol_m * (yb * np.conj(ys)).real[m], minlength=nb)
    power = np.bincount(idx_m, wcol_m * (np.abs(ys) ** 2)[m], minlength=nb)
    noise = noise_sigma ** 2 * window_power * count
    use = power >= SIGNAL_TO_NOISE * noise
    use[0] = False  # the lowest bin holds the window's own leakage of the patch's gradients
    if use.sum() < 3:
        return float("nan")
    hd = np.compress(use, hd_all, axis=1)  # C order, as computed on the bins alone (the products' sums alike)
    sse = -2.0 * hd @ cross[use] + (hd * hd) @ (power[use] - noise[use])
    i = int(np.argmin(sse))
    if i == 0 or i == len(grid) - 1:
        return 0.0 if i == 0 else float("nan")
    a, b, c = sse[i - 1], sse[i], sse[i + 1]
    den = a - 2 * b + c
    shift = 0.5 * (a - c) / den if den > 0 else 0.0
    return float(grid[i] + 0.1 * np.clip(shift, -0.5, 0.5))


def _depth_error_steps(sides, rate: float) -> float:
    """The depth map's error (frame steps) at the patches: each patch's depth from the blur towards its two
    neighbouring frames, ``k_b = k - (D+^2 - D-^2) / (4 r^2)`` (geometric defocus:
    ``D+-^2 = r^2 ((k +- 1 - k_b)^2 - (k - k_b)^2)``), against the depth map's; the robust RMS of the
    differences (their median, which is a bias, and 1.4826 MAD about it). The fits' own noise only adds to it."""
    if len(sides) < 3 or not rate > 0:
        return 0.0
    e = np.array([k - (dp * dp - dm * dm) / (4.0 * rate * rate) - kb for dm, dp, kb, k in sides])
    med = float(np.median(e))
    return float(np.hypot(med, 1.4826 * np.median(np.abs(e - med))))


def estimate_defocus_rate(stack, frames, depth_index: np.ndarray, confidence: np.ndarray, *,
                          noise_sigma: float | None = None, patch_px: int | None = None) -> DefocusRate:
    """Measure the blur disc's growth per frame step from registered frames and their depth map.

    Parameters
    ----------
    stack : FrameSource
        Registered frames (the output geometry).
    frames : array of int
        File indices used, any order (sorted here by z).
    depth_index : H x W float array
        Per-pixel best focus as a sub-frame index into ``frames`` sorted by z.
    confidence : H x W float array
        The depth map's confidence (~0 without texture).
    noise_sigma : float, optional
        Grey pixel noise (frame units); default: Immerkaer's estimate, the least over the frames' patches.
    patch_px : int, optional
        Patch size (px); default an eighth of the shorter side, within :data:`PATCH_PX`.
    """
    frames = np.asarray(frames, dtype=int)
    if frames.size < 3:
        return DefocusRate(float("nan"), float("nan"), reason="fewer than 3 frames")
    order = frames[np.argsort(z_positions(stack)[frames], kind="stable")]
    z = z_positions(stack)[order]
    spacing = float(np.median(np.diff(z)))
    w, h = image_size(stack)
    kd = np.asarray(depth_index, dtype=np.float32)
    if kd.shape != (h, w) or np.shape(confidence) != (h, w):
        raise ParameterError(f"depth map is {kd.shape}, frames are {(h, w)}", field="depth_index",
                             fix="give the depth map of these frames")
    if not (np.isfinite(spacing) and spacing > 0):
        return DefocusRate(float("nan"), float("nan"), reason="frames at one stage position")
    if patch_px is None:
        patch_px = int(np.clip(16 * round(min(w, h) / 128), *PATCH_PX))
    patches = _select_patches(kd, np.asarray(confidence, dtype=np.float32), len(order), patch_px)
    # read each patch from its frame and its neighbours out to 2 frames
    need: dict[int, list[int]] = {}
    for p, (_, _, k, _) in enumerate(patches):
        for j in range(max(0, k - 2), min(len(order), k + 3)):
            need.setdefault(j, []).append(p)
    grey: dict[tuple[int, int], np.ndarray] = {}
    for j, ps in need.items():
        for p in ps:
            x0, y0 = patches[p][:2]
            grey[(p, j)] = _grey(read_roi(stack, int(order[j]), x0, y0, x0 + patch_px, y0 + patch_px))
    if noise_sigma is None:
        from .sweep import estimate_noise_sigma
        sig = [estimate_noise_sigma(g) for g in grey.values()]
        noise_sigma = float(np.percentile(sig, 10)) if sig else 0.0
    tables = _disc_fit_tables(patch_px)
    def patch_discs(p: int) -> dict[int, float]:
        """Patch p's blur disc (px) from its frame k to each neighbour j, by ``j - k`` (finite ones only)."""
        _, _, k, _ = patches[p]
        side = {}
        for j in range(max(0, k - 2), min(len(order), k + 3)):
            if j != k:
                disc = fit_disc_px(grey[(p, k)], grey[(p, j)], noise_sigma, tables=tables)
                if np.isfinite(disc):
                    side[j - k] = disc
        return side

    from .dff import map_in_order

    rates: dict[int, list[float]] = {1: [], 2: []}
    sides: list[tuple[float, float, float, int]] = []  # (disc to k - 1, disc to k + 1, depth map's k_b, k)
    # patches fitted on the compositor's threads (FFTs and NumPy release the GIL), gathered in patch order
    for (_, _, k, kb), side in zip(patches, map_in_order(patch_discs, list(range(len(patches))))):
        for dj in sorted(side):
            # blur variances add (a disc of diameter D has D^2/16 per axis): the disc from frame k to frame j
            # has D^2 = r^2 (|j - k_b|^2 - |k - k_b|^2), whatever blur the two share (in-focus aberrations)
            d = np.sqrt((k + dj - kb) ** 2 - (k - kb) ** 2)
            rates[abs(dj)].append(side[dj] / d)
        if -1 in side and 1 in side:
            sides.append((side[-1], side[1], kb, k))
    allr = np.array(rates[1] + rates[2])
    by = {d: (float(np.median(r)) if r else float("nan"), len(r)) for d, r in rates.items()}
    common = dict(by_distance=by, n_patches=len(patches), n_pairs=int(allr.size), spacing_um=spacing,
                  noise_sigma=float(noise_sigma))
    if allr.size:
        common["depth_sd_steps"] = _depth_error_steps(sides, float(np.median(allr)))
    if allr.size < MIN_PAIRS:
        return DefocusRate(float("nan"), float("nan"), **common,
                           reason=f"too little texture: {allr.size} patch pairs, fewer than {MIN_PAIRS}")
    rate = float(np.median(allr))
    sd = float(1.4826 * np.median(np.abs(allr - rate)) * 1.2533 / np.sqrt(allr.size))
    # the one-step discs are the better resolved: a rate read short at two steps is not taken for the true one
    resolved = max(rate, by[1][0]) if by[1][1] >= MIN_PAIRS // 2 else rate
    reason = ""
    if rate < MIN_RATE_PX:
        reason = f"the blur disc grows by {rate:.2f} px per frame, less than {MIN_RATE_PX}: frames barely change focus"
    elif 2.0 * resolved > MAX_DISC_PATCH_FRACTION * patch_px:
        reason = (f"the blur disc grows by {resolved:.1f} px per frame: the disc two frames apart ({2 * resolved:.0f} px) "
                  f"is wider than the {patch_px}-px patches resolve ({MAX_DISC_PATCH_FRACTION * patch_px:.0f} px), "
                  "so it is read short and its Wiener step would ring")
    elif sd > MAX_REL_SD * rate:
        reason = f"uncertain: {rate:.2f} +- {sd:.2f} px per frame"
    elif by[1][1] >= MIN_PAIRS // 2 and by[2][1] >= MIN_PAIRS // 2 and \
            abs(by[2][0] - by[1][0]) > MAX_LINEARITY * rate:
        reason = (f"the blur does not grow linearly: {by[1][0]:.2f} px per frame at one frame's distance, "
                  f"{by[2][0]:.2f} at two")
    return DefocusRate(rate, sd, **common, reliable=not reason, reason=reason)
