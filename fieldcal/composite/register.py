"""Frame geometry measured from the stack itself, for compositing without a profile.

Between neighbouring frames (sorted by z) calibration's registration (:func:`fieldcal.measure.geometry.
register_step`: Gauss-Newton on scale and shift with cubic-spline resampling, unbiased where OpenCV's ECC is
biased by ~10 % of a small scale change) measures a scale and shift on a grey, downsampled copy (neighbours
differ little in focus, so it locks on). The lens model (docs/architecture.md) makes the magnification and
shift linear in z (``m(z) = 1 + a (z - z_ref)``, ``s(z) = b (z - z_ref)``), so the rates ``a`` and ``b`` are
the medians of the per-pair rates: robust to a failed pair, no drift from chaining. A handheld or rail stack
does not follow that model (the camera moves a little between frames): when the chained per-pair steps leave
the linear model by more than half a pixel at the image corner, each frame gets its own chained scale and shift
(:class:`ChainedGeometry`) instead. Either result answers the geometry part of the lens-profile interface.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..measure.geometry import downsample, register_step, registration_plane
from . import photometric
from ..progress import progress
from .source import image_size, read_roi, z_positions


#: Chained per-frame geometry replaces the linear model when the two differ by more than this at the image
#: corner (px): below it the linear model's robustness (a median, no drift) is worth more.
CHAIN_DEVIATION_PX = 0.5


class EstimatedGeometry:
    """Geometry of the lens-profile interface, measured from a stack (``z_ref_um`` = a frame of the stack)."""

    has_measured_tolerance = False
    #: What the richer models would add and how far the frame's halves disagree on it (:func:`choose_model`).
    model_checks: dict | None = None

    def __init__(self, z_ref_um: float, centre_px: tuple[float, float], scale_rate_per_um: float,
                 shift_rate_px_per_um: tuple[float, float], n_pairs: int):
        self.z_ref_um = float(z_ref_um)
        self.centre = (float(centre_px[0]), float(centre_px[1]))
        self.scale_rate_per_um = float(scale_rate_per_um)
        self.shift_rate_px_per_um = (float(shift_rate_px_per_um[0]), float(shift_rate_px_per_um[1]))
        self.n_pairs = int(n_pairs)

    def optical_centre_px(self) -> tuple[float, float]:
        return self.centre

    def magnification(self, z_um, channel=None):
        return 1.0 + self.scale_rate_per_um * (np.asarray(z_um, dtype=np.float64) - self.z_ref_um)

    def shift_px(self, z_um, channel=None):
        dz = np.asarray(z_um, dtype=np.float64) - self.z_ref_um
        return dz * self.shift_rate_px_per_um[0], dz * self.shift_rate_px_per_um[1]

    def lateral_colour_scale(self, channel) -> float:
        return 1.0

    def info(self) -> dict:
        return {"z_ref_um": self.z_ref_um, "scale_rate_per_um": self.scale_rate_per_um,
                "shift_rate_px_per_um": list(self.shift_rate_px_per_um), "pairs_used": self.n_pairs,
                "model": "scale-shift",
                **({"model_checks_px": {k: round(v, 3) for k, v in self.model_checks.items()}}
                   if self.model_checks else {})}


class ChainedGeometry(EstimatedGeometry):
    """Per-frame geometry from chained neighbour registrations (interpolated in z between frames)."""

    def __init__(self, z_ref_um, centre_px, z_um, magnification, shift_x_px, shift_y_px, linear: EstimatedGeometry,
                 deviation_px: float):
        super().__init__(z_ref_um, centre_px, linear.scale_rate_per_um, linear.shift_rate_px_per_um, linear.n_pairs)
        self.z_table = np.asarray(z_um, dtype=np.float64)
        self.m_table = np.asarray(magnification, dtype=np.float64)
        self.sx_table = np.asarray(shift_x_px, dtype=np.float64)
        self.sy_table = np.asarray(shift_y_px, dtype=np.float64)
        self.deviation_px = float(deviation_px)

    def magnification(self, z_um, channel=None):
        return np.interp(np.asarray(z_um, dtype=np.float64), self.z_table, self.m_table)

    def shift_px(self, z_um, channel=None):
        z = np.asarray(z_um, dtype=np.float64)
        return np.interp(z, self.z_table, self.sx_table), np.interp(z, self.z_table, self.sy_table)

    def info(self) -> dict:
        return {**super().info(), "model": "scale-shift, per frame (chained)",
                "linear_model_deviation_px": round(self.deviation_px, 3)}


def _chain(zs, steps, linear: EstimatedGeometry, cs, factor: int, z_ref_um: float):
    """Per-frame (m, sx, sy) relative to the frame at ``z_ref_um`` from neighbour steps (None: the linear model's
    step for that pair). A step maps p in frame k-1 to cs + r (p - cs) + t in frame k (downsampled px)."""
    R, T = [1.0], [np.zeros(2)]
    for k in range(1, len(zs)):
        s = steps[k - 1]
        dz = float(zs[k] - zs[k - 1])
        if s is None:
            r = float(np.exp(linear.scale_rate_per_um * dz))
            tt = np.array(linear.shift_rate_px_per_um) * dz / factor
        else:
            r, tt = float(s.r), np.array([s.tx, s.ty])
        R.append(R[-1] * r)
        T.append(r * T[-1] + tt)
    R, T = np.array(R), np.array(T)
    kr = int(np.argmin(np.abs(np.asarray(zs) - z_ref_um)))
    m = R / R[kr]
    shift = (T - m[:, None] * T[kr]) * factor
    return m, shift[:, 0], shift[:, 1]


def _ecc_affine(prev: np.ndarray, cur: np.ndarray) -> np.ndarray | None:
    """The affine map (3 x 3, px of these planes) taking a point of ``prev`` to ``cur``, from OpenCV's ECC
    (Gaussian-smoothed), or None when it fails.

    Only a start for the Gauss-Newton fits: run on planes halved again (4x fewer pixels) when they are large,
    from the translation phase correlation finds (Hann window): ECC alone has no pyramid and loses a handheld
    step of more than a few px, while the correlation peak stands out under the small rotation and scale
    change between neighbours and under their focus difference.
    """
    import cv2

    f = 2 if min(prev.shape) >= 256 else 1
    if f > 1:
        hh, ww = (prev.shape[0] // 2) * 2, (prev.shape[1] // 2) * 2
        prev, cur = downsample(prev[:hh, :ww], 2), downsample(cur[:hh, :ww], 2)
    prev, cur = prev.astype(np.float32), cur.astype(np.float32)
    warp = np.eye(2, 3, dtype=np.float32)
    try:
        (dx, dy), response = cv2.phaseCorrelate(prev, cur, cv2.createHanningWindow(prev.shape[::-1], cv2.CV_32F))
    except cv2.error:
        response = 0.0
    if response > 0.05 and abs(dx) < prev.shape[1] / 4 and abs(dy) < prev.shape[0] / 4:
        warp[:, 2] = (dx, dy)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
    try:
        _, warp = cv2.findTransformECC(prev, cur, warp, cv2.MOTION_AFFINE, crit, None, 5 if f == 1 else 3)
    except cv2.error:
        return None
    m = np.eye(3)
    m[:2] = warp.astype(np.float64)
    if not np.all(np.isfinite(m)):
        return None
    m = _to_full(m, f)
    r = 0.5 * (m[0, 0] + m[1, 1])
    return m if 0.5 < r < 2.0 else None


def _scale_shift_of(m: np.ndarray, cs) -> tuple[float, float, float]:
    """(r, tx, ty) about ``cs`` of an affine map: its mean scale and the shift it gives the centre."""
    a = m[:2, :2]
    r = 0.5 * (a[0, 0] + a[1, 1])
    t = a @ np.asarray(cs, dtype=np.float64) + m[:2, 2] - np.asarray(cs, dtype=np.float64)
    return float(r), float(t[0]), float(t[1])


def _with_scale_shift(start: np.ndarray | None, step, cs) -> np.ndarray:
    """The scale-and-shift ``step`` (``r``, ``tx``, ``ty`` about ``cs``) as a 3 x 3 map, keeping the rotation and
    shear of the affine ``start`` (ECC's, when there is one): the refined step sets the scale and the centre's
    shift, ECC the roll of a handheld camera, which a start without it can leave the homography fit short of."""
    lin = np.eye(2) * step.r
    if start is not None:
        r0 = 0.5 * (start[0, 0] + start[1, 1])
        lin = start[:2, :2] * (step.r / r0)
    c = np.asarray(cs, dtype=np.float64)
    out = np.eye(3)
    out[:2, :2] = lin
    out[:2, 2] = c + np.array([step.tx, step.ty]) - lin @ c
    return out


def _grey(image: np.ndarray, factor: int) -> np.ndarray:
    """The registration plane of a frame (``H x W x C``): grey, downsampled, lightly blurred, normalised."""
    import cv2

    image = np.asarray(image)
    h, w, n_ch = image.shape
    if n_ch == 1:
        grey = np.asarray(image[..., 0], dtype=np.float32)
    else:
        # the channels' mean (cv2.transform: ~10x faster than ndarray.mean over a short last axis), in bands of
        # rows through one float32 buffer: not a whole float32 frame's fresh pages per frame
        weights = np.full((1, n_ch), 1.0 / n_ch, np.float32)
        grey = np.empty((h, w), np.float32)
        rows = max(1, (4 << 20) // max(1, w * n_ch * 4))
        buf = np.empty((min(rows, h), w, n_ch), np.float32)
        for y0 in range(0, h, rows):
            y1 = min(h, y0 + rows)
            band = buf[:y1 - y0]
            np.copyto(band, image[y0:y1], casting="unsafe")
            cv2.transform(band, weights, dst=grey[y0:y1])
    g = registration_plane(grey, factor)
    return (g - g.mean()) / max(float(g.std()), 1e-12)


#: Registration planes are the frames area-downsampled by the coarsest whole factor that leaves at least this many
#: px on the long side (:func:`_factor`): the scale-and-shift steps, ECC starts and model fits run on them. A
#: 2048-px frame registers on 682-px planes (a third), a 24 MP frame on ~700-px ones, frames below 1280 px at full
#: size. Planes of at most 1024 px (the rule before) took twice the CPU on the 2048 x 1536 board for a registration
#: no better: 7-frame composite as sharp (mean squared Laplacian 1552 against 1551), and with known perturbations
#: (bench_real_robustness, frames registered at half size) every registration error as small or smaller
#: (docs/benchmarks.md ``bench_composite_speed_s17_regstart``).
REGISTRATION_MIN_SIDE_PX = 640
#: ... and at least this many on the short side: a strip (2600 x 48 px) took the long side's factor 4 and
#: registered on 12-row planes, 1.55 px RMS off against 0.39 px on the 16 rows of the rule before (review of
#: session 17); 4:3 and 16:9 frames keep the long side's factor.
REGISTRATION_MIN_SHORT_SIDE_PX = 160


def _factor(w: int, h: int, max_side_px: int | None = None) -> int:
    """The registration planes' downsampling factor: :data:`REGISTRATION_MIN_SIDE_PX`'s rule, or with ``max_side_px``
    the least factor that brings the long side to at most that."""
    if max_side_px is None:
        return max(1, min(max(w, h) // REGISTRATION_MIN_SIDE_PX, min(w, h) // REGISTRATION_MIN_SHORT_SIDE_PX))
    return max(1, int(np.ceil(max(w, h) / max_side_px)))


def _sorted_frames(stack, frames, z_ref_um):
    z_all = z_positions(stack)
    idx = np.arange(len(z_all)) if frames is None else np.asarray(frames, dtype=int)
    order = idx[np.argsort(z_all[idx], kind="stable")]
    zs = z_all[order]
    if z_ref_um is None:
        return order, zs, float(zs[len(zs) // 2])
    z_ref_um = float(z_ref_um)
    # The output geometry is a frame's: the chained per-frame maps are taken relative to the frame nearest
    # z_ref, while the linear model would extrapolate to z_ref itself, so a reference beyond the frames would
    # give a composite in no frame's geometry (and the two models would disagree), without a word.
    lo, hi = float(zs[0]), float(zs[-1])
    slack = 1e-6 * max(hi - lo, 1.0)
    if not (np.isfinite(z_ref_um) and lo - slack <= z_ref_um <= hi + slack):
        from ..errors import ParameterError
        raise ParameterError(f"{z_ref_um:g} µm is outside the z range of the frames used ({lo:g} to {hi:g} µm): "
                             "the output is in the geometry of a frame of the stack",
                             path=getattr(stack, "path", None), field="z_ref_um",
                             fix=f"give a stage position from {lo:g} to {hi:g} µm (e.g. {float(zs[len(zs) // 2]):g}, "
                                 "the middle frame), or leave it unset for the middle frame")
    return order, zs, z_ref_um


def estimate_geometry(stack, frames=None, z_ref_um: float | None = None, max_side_px: int | None = None,
                      quiet: bool = False, planes: list[np.ndarray] | None = None) -> EstimatedGeometry:
    """Measure focus breathing and stage-axis shift from neighbouring frames (one or two in memory).

    ``z_ref_um`` (the output geometry) defaults to the frame at the middle of the z range. ``planes``: the
    frames' registration planes in z order (:func:`_grey` at :func:`_factor`), when already made.
    """
    return _scale_shift(stack, frames, z_ref_um, max_side_px, quiet, planes)[0]


def _map_threads(fn, items: list, desc: str = "", quiet: bool = True, unit: str = "pair") -> list:
    """``[fn(x) for x in items]`` on the compositing threads: OpenCV and SciPy's resampling release the GIL.
    With ``desc`` and not ``quiet``, a progress bar counts the results as they come (a 60-frame stack of 24 MP
    spends minutes here)."""
    from concurrent.futures import ThreadPoolExecutor

    from .source import default_workers

    workers = default_workers()
    if workers == 1 or len(items) < 2:
        return list(progress(map(fn, items), total=len(items), desc=desc, quiet=quiet or not desc, unit=unit))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(progress(pool.map(fn, items), total=len(items), desc=desc, quiet=quiet or not desc, unit=unit))


def _pair_steps(planes, cs, quiet: bool):
    """Scale-and-shift steps between neighbouring planes (None where a pair fails), and each pair's affine
    start (:func:`_ecc_affine`, None where ECC failed), which keeps a handheld camera's roll for the richer
    models (:func:`choose_model`)."""
    # a point at p in prev is at cs + r (p - cs) + t in cur (downsampled px, about the centre).
    # Photographs (not charts): neighbours differ in focus, so the update settles at noise level; a handheld
    # step can be several px, beyond Gauss-Newton's reach from zero: ECC (on a smoothed copy, robust to the
    # focus change) gives the start. Pairs are independent given their start, so they run on threads.
    def ecc_step(k):
        start = _ecc_affine(planes[k - 1], planes[k])
        if start is None:
            return None, None
        return register_step(planes[k - 1], planes[k], cs, init=_scale_shift_of(start, cs), iterations=20,
                             tol_px=1e-3), start

    pairs = list(range(1, len(planes)))
    done = _map_threads(ecc_step, pairs, "registering", quiet)
    steps, starts = [d[0] for d in done], [d[1] for d in done]
    for k in pairs:
        if steps[k - 1] is None:  # no ECC start: the previous step's, else register_step's own fallbacks
            prev = steps[k - 2] if k >= 2 else None
            init = (prev.r, prev.tx, prev.ty) if prev is not None else None
            steps[k - 1] = register_step(planes[k - 1], planes[k], cs, init=init, iterations=20, tol_px=1e-3)
    return steps, starts


def _scale_shift(stack, frames, z_ref_um, max_side_px, quiet, planes):
    """:func:`estimate_geometry`, the neighbour steps it was built from and each pair's affine start."""
    w, h = image_size(stack)
    order, zs, z_ref_um = _sorted_frames(stack, frames, z_ref_um)
    factor = _factor(w, h, max_side_px)
    c = ((w - 1) / 2.0, (h - 1) / 2.0)
    cs = ((w // factor - 1) / 2.0, (h // factor - 1) / 2.0)
    if planes is None:
        planes = [_grey(read_roi(stack, int(i), 0, 0, w, h), factor) for i in order]
    steps, starts = _pair_steps(planes, cs, quiet) if len(planes) > 1 else ([], [])
    rates_m, rates_x, rates_y = [], [], []
    for k, step in enumerate(steps, start=1):
        if step is not None:
            dz = float(zs[k] - zs[k - 1])
            rates_m.append(np.log(step.r) / dz)
            rates_x.append(step.tx * factor / dz)
            rates_y.append(step.ty * factor / dz)
    if not rates_m:
        return EstimatedGeometry(z_ref_um, c, 0.0, (0.0, 0.0), 0), steps, starts
    linear = EstimatedGeometry(z_ref_um, c, float(np.median(rates_m)),
                               (float(np.median(rates_x)), float(np.median(rates_y))), len(rates_m))
    if len(zs) < 3:
        return linear, steps, starts
    m, sx, sy = _chain(zs, steps, linear, cs, factor, float(z_ref_um))
    # how far the chained positions of the image corner leave the linear model, in full-resolution px
    corner = float(np.hypot(w / 2.0, h / 2.0))
    lm = np.asarray(linear.magnification(zs))
    lx, ly = linear.shift_px(zs)
    dev = float(np.max(np.abs(m - lm) * corner + np.hypot(sx - lx, sy - ly)))
    if dev <= CHAIN_DEVIATION_PX:
        return linear, steps, starts
    return ChainedGeometry(z_ref_um, c, zs, m, sx, sy, linear, dev), steps, starts


# ------------------------------------------------------------------------------- beyond scale and shift
#: Registration models, simplest first. ``scale-shift`` is the lens model (breathing, stage-axis shift);
#: ``similarity`` adds a rotation (a handheld camera rolling), ``affine`` shear and unequal scale, ``homography``
#: the perspective of a camera that tilts between frames.
MODELS = ("scale-shift", "similarity", "affine", "homography")
#: A richer model replaces a simpler one only where it moves some frame's image corner (or edge middle) by more
#: than this (full-resolution px) from where the simpler one puts it: below that the difference is within the
#: interpolation error of warping, and the extra parameters would only fit noise.
MODEL_TOLERANCE_PX = 0.5
#: The model check fits its homographies on the coarsest pyramid level whose short side is at least this (px):
#: ~50k samples, precise to a few hundredths of a px there, enough to see a 0.5 px difference at full size.
CHECK_SIDE_PX = 160


def _generators(model: str) -> np.ndarray:
    """(k, 3, 3) infinitesimal generators of ``model``'s warps about the identity (normalised coordinates)."""
    def g(*entries):
        m = np.zeros((3, 3))
        for (r, c), v in entries:
            m[r, c] = v
        return m

    tx, ty = g(((0, 2), 1.0)), g(((1, 2), 1.0))
    if model == "scale-shift":
        return np.stack([g(((0, 0), 1.0), ((1, 1), 1.0)), tx, ty])
    if model == "similarity":
        return np.stack([g(((0, 0), 1.0), ((1, 1), 1.0)), g(((0, 1), -1.0), ((1, 0), 1.0)), tx, ty])
    aff = [g(((0, 0), 1.0)), g(((0, 1), 1.0)), g(((1, 0), 1.0)), g(((1, 1), 1.0)), tx, ty]
    if model == "affine":
        return np.stack(aff)
    if model == "homography":
        return np.stack(aff + [g(((2, 0), 1.0)), g(((2, 1), 1.0))])
    raise ValueError(f"unknown registration model {model!r}")


def _normaliser(w: int, h: int) -> np.ndarray:
    """Pixel -> normalised coordinates (centre 0, half diagonal 1): a well-conditioned parameterisation."""
    c = ((w - 1) / 2.0, (h - 1) / 2.0)
    lev = max(float(np.hypot(w, h)) / 2.0, 1.0)
    return np.array([[1.0 / lev, 0.0, -c[0] / lev], [0.0, 1.0 / lev, -c[1] / lev], [0.0, 0.0, 1.0]])


def _apply(m: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = m[2, 0] * x + m[2, 1] * y + m[2, 2]
    return (m[0, 0] * x + m[0, 1] * y + m[0, 2]) / d, (m[1, 0] * x + m[1, 1] * y + m[1, 2]) / d


class _Level:
    """One pyramid level of a neighbour pair, with what every fit on it shares: ``prev``'s gradients (per
    normalised unit) and ``cur``'s cubic B-spline coefficients (computed once, on first use)."""

    def __init__(self, prev: np.ndarray, cur: np.ndarray):
        self.prev, self.cur = prev, cur
        h, w = prev.shape
        self.n = _normaliser(w, h)
        self._grad = self._coeffs = None

    @property
    def grad(self):
        if self._grad is None:
            gy, gx = np.gradient(self.prev.astype(np.float64))
            self._grad = gx / self.n[0, 0], gy / self.n[0, 0]
        return self._grad

    @property
    def coeffs(self):
        if self._coeffs is None:
            self._coeffs = ndimage.spline_filter(self.cur.astype(np.float64), order=3)
        return self._coeffs


def _fit_level(level: _Level, model: str, m_norm: np.ndarray, iterations: int, tol_px: float, subsample: int,
               part: str | None = None) -> np.ndarray | None:
    """Inverse-compositional Gauss-Newton (Baker & Matthews 2004) on one level: ``m_norm`` (normalised
    coordinates) maps a point of ``prev`` to ``cur``; ``cur`` is resampled by cubic B-splines (no 1/32 px
    quantisation, which biases OpenCV's warps: see :func:`fieldcal.measure.geometry.register_step`)."""
    prev = level.prev
    h, w = prev.shape
    b = 4
    if min(h, w) < 4 * b + 8:
        return None
    n = level.n
    # ``part``: only the top or bottom half of ``prev`` (two independent looks at the same motion)
    ya, yb = {None: (b, h - b), "top": (b, h // 2), "bottom": (h // 2, h - b)}[part]
    ys, xs = np.mgrid[ya:yb:subsample, b:w - b:subsample].astype(np.float64)
    xs, ys = xs.ravel(), ys.ravel()
    gx, gy = (g[ya:yb:subsample, b:w - b:subsample].ravel() for g in level.grad)
    ux, uy = xs * n[0, 0] + n[0, 2], ys * n[1, 1] + n[1, 2]
    gens = _generators(model)
    cols = []
    for G in gens:
        # d/dθ of the warped point at the identity: (G u)_xy - u (G u)_z
        gz = G[2, 0] * ux + G[2, 1] * uy + G[2, 2]
        dx = G[0, 0] * ux + G[0, 1] * uy + G[0, 2] - ux * gz
        dy = G[1, 0] * ux + G[1, 1] * uy + G[1, 2] - uy * gz
        cols.append(gx * dx + gy * dy)
    J = np.stack(cols, axis=1)
    # einsum, not J.T @ J: a threaded BLAS spins its threads after each product (measure/geometry.py)
    H_all = np.einsum("ni,nj->ij", J, J)
    target = prev[ya:yb:subsample, b:w - b:subsample].astype(np.float64).ravel()
    coeffs = level.coeffs
    n_inv = np.linalg.inv(n)
    corners = np.array([[0, 0, w - 1, w - 1], [0, h - 1, 0, h - 1]], dtype=np.float64)
    m = m_norm.copy()
    for _ in range(iterations):
        qx, qy = _apply(n_inv @ m @ n, xs, ys)
        inside = (qx >= 1) & (qx <= w - 2) & (qy >= 1) & (qy <= h - 2)  # points that left cur do not count
        share = float(inside.mean())
        if share < 0.5:
            return None
        if share < 1.0:
            qx, qy, Ji, ti = qx[inside], qy[inside], J[inside], target[inside]
            H = np.einsum("ni,nj->ij", Ji, Ji)
        else:
            Ji, ti, H = J, target, H_all
        back = ndimage.map_coordinates(coeffs, [qy, qx], order=3, prefilter=False, mode="nearest")
        if not np.all(np.isfinite(H)) or np.linalg.cond(H) > 1e12:
            return None
        d = np.linalg.solve(H, np.einsum("ni,n->i", Ji, back - ti))
        md = np.eye(3) + np.tensordot(d, gens, axes=1)
        m = m @ np.linalg.inv(md)
        m /= m[2, 2]
        if not np.all(np.isfinite(m)):
            return None
        # the update's largest displacement at the frame's corners (px of this level)
        cx, cy = _apply(n_inv @ md @ n, corners[0], corners[1])
        if float(np.max(np.hypot(cx - corners[0], cy - corners[1]))) < tol_px:
            break
    return m


class PlanePair:
    """Two neighbouring registration planes and their pyramid (halved per level), shared by the fits of one
    pair (whole frame, halves, several models): each level's gradients and spline coefficients are made once."""

    def __init__(self, prev: np.ndarray, cur: np.ndarray, levels: int = 2):
        if prev.shape != cur.shape:
            raise ValueError(f"planes differ in size: {prev.shape} vs {cur.shape}")
        self.levels = [_Level(prev, cur)]  # finest first
        for _ in range(levels - 1):
            a, b = self.levels[-1].prev, self.levels[-1].cur
            if min(a.shape) < 64:
                break
            hh, ww = (a.shape[0] // 2) * 2, (a.shape[1] // 2) * 2
            self.levels.append(_Level(downsample(a[:hh, :ww], 2), downsample(b[:hh, :ww], 2)))


def fit_pair(prev, cur=None, model: str = "homography", init: np.ndarray | None = None,
             levels: int = 2, iterations: int = 30, tol_px: float = 1e-3, subsample: int = 2,
             part: str | None = None, finest: int = 0) -> np.ndarray | None:
    """The warp of ``model`` taking a point of plane ``prev`` to plane ``cur`` (3 x 3, px of these planes).

    Coarse to fine over ``levels`` (halving the planes each level): the coarse levels widen the reach of the
    fit, the finest sets its precision. ``prev`` may be a :class:`PlanePair` (then ``cur`` is not given and
    ``levels`` is the pair's). ``init`` (px) is the start, e.g. the scale-and-shift step; None when the fit
    fails (too small, lost contrast, diverged). ``part`` ("top", "bottom"): fit on that half of ``prev``
    only. ``finest``: stop that many levels above the full planes (a quick, coarser fit).
    """
    _generators(model)  # an unknown model fails here, before any work
    pair = prev if isinstance(prev, PlanePair) else PlanePair(prev, cur, levels)
    h, w = pair.levels[0].prev.shape
    n = _normaliser(w, h)
    m = np.eye(3) if init is None else n @ np.asarray(init, dtype=np.float64) @ np.linalg.inv(n)
    # normalised coordinates are the same at every level (even sizes, area downsampling: pixel centres nest)
    for k in range(len(pair.levels) - 1, min(finest, len(pair.levels) - 1) - 1, -1):
        fine = k == finest
        # every level but a small coarsest one is sampled every ``subsample`` px (~50k points a fit)
        step = subsample if min(pair.levels[k].prev.shape) >= 256 else 1
        m = _fit_level(pair.levels[k], model, m, iterations, tol_px if fine else 1e-2, step, part)
        if m is None:
            return None
    return np.linalg.inv(n) @ m @ n


def _project(p: np.ndarray, model: str, w: int, h: int) -> np.ndarray:
    """The ``model`` warp nearest (least squares on a grid over the frame) to the homography ``p`` (px)."""
    if model == "homography":
        return p
    ys, xs = np.mgrid[0:h - 1:9j, 0:w - 1:9j]
    xs, ys = xs.ravel(), ys.ravel()
    qx, qy = _apply(p, xs, ys)
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    x, y = xs - cx, ys - cy
    one, zero = np.ones_like(x), np.zeros_like(x)
    if model == "scale-shift":  # q - c = s (p - c) + t
        A = np.block([[x[:, None], one[:, None], zero[:, None]], [y[:, None], zero[:, None], one[:, None]]])
        s, tx, ty = np.linalg.lstsq(A, np.concatenate([qx - cx, qy - cy]), rcond=None)[0]
        lin = np.array([[s, 0.0], [0.0, s]])
    elif model == "similarity":  # q - c = [[a, -b], [b, a]] (p - c) + t
        A = np.block([[x[:, None], -y[:, None], one[:, None], zero[:, None]],
                      [y[:, None], x[:, None], zero[:, None], one[:, None]]])
        a, bb, tx, ty = np.linalg.lstsq(A, np.concatenate([qx - cx, qy - cy]), rcond=None)[0]
        lin = np.array([[a, -bb], [bb, a]])
    else:  # affine
        A = np.stack([x, y, one], axis=1)
        r0 = np.linalg.lstsq(A, qx - cx, rcond=None)[0]
        r1 = np.linalg.lstsq(A, qy - cy, rcond=None)[0]
        lin, (tx, ty) = np.array([r0[:2], r1[:2]]), (r0[2], r1[2])
    c = np.array([cx, cy])
    out = np.eye(3)
    out[:2, :2] = lin
    out[:2, 2] = c + np.array([tx, ty]) - lin @ c
    return out


def _plane_scale(factor: int) -> np.ndarray:
    """Plane px -> full-resolution px (area downsampling: plane pixel i is centred on f i + (f - 1) / 2)."""
    return np.array([[factor, 0.0, (factor - 1) / 2.0], [0.0, factor, (factor - 1) / 2.0], [0.0, 0.0, 1.0]])


def _to_full(p: np.ndarray, factor: int) -> np.ndarray:
    """A plane-px warp in full-resolution px."""
    s = _plane_scale(factor)
    return s @ p @ np.linalg.inv(s)


def chain_to_reference(pairs: list[np.ndarray], ref_index: int) -> np.ndarray:
    """Per frame, the map from the reference frame's px to that frame's px, from neighbour warps
    (``pairs[k]``: frame k -> frame k + 1): ``(n, 3, 3)``."""
    n = len(pairs) + 1
    out = np.zeros((n, 3, 3))
    out[ref_index] = np.eye(3)
    for k in range(ref_index + 1, n):
        out[k] = pairs[k - 1] @ out[k - 1]
    for k in range(ref_index - 1, -1, -1):
        out[k] = np.linalg.inv(pairs[k]) @ out[k + 1]
    return out / out[:, 2:3, 2:3]


def _outline(w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """The frame's corners and edge middles (px), where a model difference shows most."""
    xs = np.array([0, (w - 1) / 2, w - 1, 0, w - 1, 0, (w - 1) / 2, w - 1], dtype=np.float64)
    ys = np.array([0, 0, 0, (h - 1) / 2, (h - 1) / 2, h - 1, h - 1, h - 1], dtype=np.float64)
    return xs, ys


def _rms_outline(d: np.ndarray) -> float:
    """RMS over pairs of each pair's largest outline displacement (``d``: (n, 8, 2) px, from
    :func:`outline_displacements`); 0 for no pairs."""
    if d.size == 0:
        return 0.0
    return float(np.sqrt(np.mean(np.max(np.hypot(d[..., 0], d[..., 1]), axis=1) ** 2)))


def outline_displacements(a: np.ndarray, b: np.ndarray, w: int, h: int) -> np.ndarray:
    """Per frame and outline point, where maps ``a`` put the frame's outline minus where ``b`` do: (n, 8, 2) px."""
    xs, ys = _outline(w, h)
    out = []
    for ma, mb in zip(a, b):
        ax, ay = _apply(ma, xs, ys)
        bx, by = _apply(mb, xs, ys)
        out.append(np.stack([ax - bx, ay - by], axis=1))
    return np.array(out)


def chain_difference_px(a: np.ndarray, b: np.ndarray, w: int, h: int) -> float:
    """Largest distance (px) between where two sets of per-frame maps put the frame's outline."""
    return float(np.max(np.hypot(*np.moveaxis(outline_displacements(a, b, w, h), -1, 0))))


class MatrixGeometry:
    """Per-frame maps (reference px -> frame px) of a registration richer than scale and shift."""

    has_measured_tolerance = False

    def __init__(self, z_ref_um: float, z_um, maps: np.ndarray, model: str, scale_shift: EstimatedGeometry,
                 deviations_px: dict):
        self.z_ref_um = float(z_ref_um)
        self.z_table = np.asarray(z_um, dtype=np.float64)
        self.maps = np.asarray(maps, dtype=np.float64)
        self.model = model
        self.scale_shift = scale_shift
        self.deviations_px = deviations_px

    def map_for(self, z_um: float) -> np.ndarray:
        k = int(np.argmin(np.abs(self.z_table - float(z_um))))
        return self.maps[k]

    def info(self) -> dict:
        return {**self.scale_shift.info(), "model": self.model,
                "model_checks_px": {k: round(v, 3) for k, v in self.deviations_px.items()}}


def frame_map_matrix(geometry, z_um: float) -> np.ndarray:
    """3 x 3 map from output px (the reference frame's) to the frame at ``z_um``'s px."""
    if isinstance(geometry, MatrixGeometry):
        return geometry.map_for(z_um)
    from .warp import affine_for

    m = float(np.asarray(geometry.magnification(z_um)))
    dx, dy = geometry.shift_px(z_um)
    out = np.eye(3)
    out[:2] = affine_for(m, geometry.optical_centre_px(), (float(np.asarray(dx)), float(np.asarray(dy))))
    return out


def choose_model(stack, frames=None, z_ref_um: float | None = None, max_side_px: int | None = None,
                 quiet: bool = False, planes: list[np.ndarray] | None = None, models=MODELS):
    """Register a stack with the simplest model of ``models`` its data support.

    Neighbouring frames (in z) are registered to each other (similar blur), scale and shift first
    (:func:`estimate_geometry`), then with a homography started from that step (:func:`fit_pair`) on the whole
    frame and on its top and bottom halves apart, and the steps are chained to the reference frame
    (``z_ref_um``, default the middle frame). Each model's maps are the homographies' nearest of its kind.
    Going from simple to rich, a model is taken when what it adds moves some frame's outline by more than
    :data:`MODEL_TOLERANCE_PX` and the two halves agree on that addition within half of it; the chosen model
    is then refitted to the images. Scale and shift keeps :func:`estimate_geometry`'s result as it is. With one
    model in ``models`` that model is fitted, whatever the check says.

    Returns an :class:`EstimatedGeometry` (scale and shift) or a :class:`MatrixGeometry`.
    """
    w, h = image_size(stack)
    order, zs, z_ref_um = _sorted_frames(stack, frames, z_ref_um)
    factor = _factor(w, h, max_side_px)
    if planes is None:
        planes = [_grey(read_roi(stack, int(i), 0, 0, w, h), factor) for i in order]
    geo, steps, starts = _scale_shift(stack, frames, z_ref_um, max_side_px, quiet, planes)
    models = [m for m in MODELS if m in models]
    forced = models[0] if len(models) == 1 else None  # one model given: used as it is, no check
    if len(planes) < 2 or models == ["scale-shift"]:
        return geo
    ref = int(np.argmin(np.abs(zs - z_ref_um)))
    cs = ((w // factor - 1) / 2.0, (h // factor - 1) / 2.0)
    s_plane = _plane_scale(factor)

    def looks_of(k):
        """The pair's homography from the whole frame and from each half, on the coarsest level of at least
        :data:`CHECK_SIDE_PX` (the model check needs ~0.1 px at full resolution, a fraction of the cost)."""
        step = steps[k]
        if step is None and starts[k] is None:  # bridged with the scale-and-shift model's own step
            a = frame_map_matrix(geo, float(zs[k + 1])) @ np.linalg.inv(frame_map_matrix(geo, float(zs[k])))
            return False, (a, a, a)
        # a scale-and-shift fit fails on a pair that rolls (a handheld camera): ECC's affine is the start then
        s = starts[k] if step is None else _with_scale_shift(starts[k], step, cs)
        pp = PlanePair(planes[k], planes[k + 1], levels=3)
        check = max(k for k, lev in enumerate(pp.levels) if k == 0 or min(lev.prev.shape) >= CHECK_SIDE_PX)
        full = fit_pair(pp, model=models[-1], init=s, finest=check)
        start = full if full is not None else s
        halves = [fit_pair(pp, model=models[-1], init=start, part=part, finest=check) for part in ("top", "bottom")]
        # the pair's pyramid is not kept for the refit: 60 pairs' pyramids, gradients and splines would hold
        # ~0.5 GB at once (memory growing with the frames); the refit builds each again, a few ms
        return True, tuple(_to_full(m if m is not None else s, factor) for m in (start, *halves))

    done = _map_threads(looks_of, list(range(len(steps))), "choosing the model", quiet)
    fitted = [ok for ok, _ in done]
    looks = {look: [v[j] for _, v in done] for j, look in enumerate(("all", "top", "bottom"))}
    # each pair's map projected once per model: chained to the reference, and compared pair by pair below
    projected = {(m, look): [_project(p, m, w, h) for p in pairs] for m in models for look, pairs in looks.items()}
    chains = {key: chain_to_reference(maps, ref) for key, maps in projected.items()}
    # A richer model is kept when what it adds to the simpler one moves the outline by more than the tolerance,
    # and the frame's two halves, fitted apart, see the same addition (within half of it): a camera that
    # rolls or tilts moves both halves alike; a scene with depth (parallax) or blur changes pull them apart.
    # The halves are compared on the chains to the reference (a steady addition, as a tilted camera's, grows
    # along the chain faster than the fits' noise) and, failing that, pair by pair (RMS over the neighbour
    # pairs): a scene with depth gives the halves a small systematic difference in every pair (~1 px on the
    # real board), which the chains add up over the frames and which would then hide a hand's roll several
    # times larger (0.2 deg a frame: 2.6 px at the outline against 3.9 px of chained halves' difference).
    chosen, deviations = "scale-shift", {}
    for model in models[1:]:
        extra = {look: outline_displacements(chains[(model, look)], chains[(chosen, look)], w, h)
                 for look in looks}
        signal = float(np.max(np.hypot(*np.moveaxis(extra["all"], -1, 0))))
        disagreement = float(np.max(np.hypot(*np.moveaxis(extra["top"] - extra["bottom"], -1, 0))))
        per_pair = {look: outline_displacements(projected[(model, look)], projected[(chosen, look)], w, h)
                    for look in looks}
        pair_signal = _rms_outline(per_pair["all"])
        pair_disagreement = _rms_outline(per_pair["top"] - per_pair["bottom"])
        deviations[f"{model}_over_{chosen}"] = signal
        deviations[f"{model}_halves_disagree"] = disagreement
        deviations[f"{model}_pairs_rms"] = pair_signal
        deviations[f"{model}_pairs_halves_disagree"] = pair_disagreement
        if signal > MODEL_TOLERANCE_PX and (disagreement <= 0.5 * signal or pair_disagreement <= 0.5 * pair_signal):
            chosen = model
    chosen = forced or chosen
    if chosen == "scale-shift":
        geo.model_checks = deviations
        return geo

    def refit(k):  # the chosen model, refitted on the full planes from the check's fit
        p = looks["all"][k]
        init = np.linalg.inv(s_plane) @ _project(p, chosen, w, h) @ s_plane  # in plane px
        fit = None if not fitted[k] else fit_pair(PlanePair(planes[k], planes[k + 1], levels=3), model=chosen,
                                                  init=init)
        return _to_full(fit, factor) if fit is not None else _project(p, chosen, w, h)

    maps = chain_to_reference(_map_threads(refit, list(range(len(steps))), f"fitting {chosen}", quiet), ref)
    # maps[k] takes a reference px to frame k's: the output (reference geometry) samples frame k there
    return MatrixGeometry(z_ref_um, zs, maps, chosen, geo, deviations)


# ----------------------------------------------------------------------------------- registered frames
def warp_frame(image: np.ndarray, output_to_source: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``image`` (``H x W x C``) resampled into the output geometry (same size and dtype; uint8/uint16 rounded and
    clipped by OpenCV): output px p takes the source at ``output_to_source @ p``. Bicubic (OpenCV, as
    :func:`fieldcal.composite.warp.warp_from`), edge pixels repeated outside the frame; an affine map takes
    ``warpAffine``, a homography ``warpPerspective``. ``out``: where to write (default a new array)."""
    import cv2

    src = np.asarray(image)
    h, w = src.shape[:2]
    m = np.asarray(output_to_source, dtype=np.float64) / output_to_source[2, 2]
    flags = cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP
    affine = abs(m[2, 0]) < 1e-15 and abs(m[2, 1]) < 1e-15

    def warp(part: np.ndarray) -> np.ndarray:
        if affine:
            return cv2.warpAffine(part, m[:2], (w, h), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        return cv2.warpPerspective(part, m, (w, h), flags=flags, borderMode=cv2.BORDER_REPLICATE)

    if out is None and src.shape[2] <= 4:  # one call: OpenCV's array is the result (not copied into another)
        return warp(np.ascontiguousarray(src)).reshape(src.shape)
    out = np.empty(src.shape, dtype=src.dtype) if out is None else out
    for k in range(0, src.shape[2], 4):  # cv2 takes at most 4 channels a call and drops a single one's axis
        out[..., k:k + 4] = warp(np.ascontiguousarray(src[..., k:k + 4])).reshape(h, w, -1)
    return out


def storage_dtype(dtype) -> tuple[np.dtype, float]:
    """How registered frames are held, ``(dtype, scale)``: 16-bit integers as they are (a rounding of 1 DN in
    65535 is far below noise); 8-bit as 16-bit fixed point (x 256: 1/256 DN, half float32's memory; rounding to
    whole DN of 255 would add visible noise); anything else as float32 (OpenCV warps no other integers)."""
    dtype = np.dtype(dtype)
    if dtype == np.uint16:
        return dtype, 1.0
    if dtype.kind == "u":
        return np.dtype(np.uint16), 256.0
    return np.dtype(np.float32), 1.0


#: Pixels next to the edge of a frame's recorded area that the bicubic warp already mixes with repeated edge
#: pixels (its kernel reaches 2 px).
SUPPORT_MARGIN_PX = 2


class FrameSupport:
    """Where each registered frame holds recorded pixels: ``support(i)`` is an ``H x W`` bool mask for file index
    ``i`` (``None`` when the frame covers the whole output, e.g. the reference frame).

    Outside it :func:`warp_frame` repeats the frame's edge pixels, which makes streaks with a strong focus
    measure: the compositing passes never choose a frame there (another frame, at least the reference, covers
    every pixel). Masks are made on first use (a nearest-neighbour warp of the frame's rectangle) and kept as
    bits (each call unpacks a new bool array).
    """

    def __init__(self, geometry, z_by_index: dict[int, float], width: int, height: int,
                 margin_px: int = SUPPORT_MARGIN_PX):
        self.geometry, self.z = geometry, dict(z_by_index)
        self.width, self.height, self.margin = int(width), int(height), int(margin_px)
        self._masks: dict[int, np.ndarray | None] = {}

    def __call__(self, i: int) -> np.ndarray | None:
        i = int(i)
        if i not in self._masks and i in self.z:
            import cv2

            w, h, m = self.width, self.height, self.margin
            rect = np.zeros((h, w), np.uint8)
            rect[m:h - m, m:w - m] = 1
            mat = frame_map_matrix(self.geometry, self.z[i])
            mat = np.asarray(mat, dtype=np.float64) / mat[2, 2]
            flags = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
            if abs(mat[2, 0]) < 1e-15 and abs(mat[2, 1]) < 1e-15:
                cover = cv2.warpAffine(rect, mat[:2], (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT)
            else:
                cover = cv2.warpPerspective(rect, mat, (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT)
            # the frame's own border band (within the margin of its edge) stays usable where it maps onto the
            # output's own border band: that is recorded, not repeated
            inside = cover.astype(bool)
            # held as bits (8x smaller: 60 masks of a 24 MP stack would hold 1.4 GB as bools)
            self._masks[i] = None if inside[m:h - m, m:w - m].all() else np.packbits(_grow_to_edges(inside, m))
        bits = self._masks.get(i)
        if bits is None:
            return None
        return np.unpackbits(bits, count=self.width * self.height).view(bool).reshape(self.height, self.width)


def _grow_to_edges(mask: np.ndarray, margin: int) -> np.ndarray:
    """``mask`` with the output's outer ``margin`` px following their inner neighbours (the reference frame's own
    edge band is recorded; only the warp's repeated pixels are cut)."""
    out = mask.copy()
    h, w = out.shape
    out[:margin] = out[margin]
    out[h - margin:] = out[h - margin - 1]
    out[:, :margin] = out[:, margin:margin + 1]
    out[:, w - margin:] = out[:, w - margin - 1:w - margin]
    return out


#: Neighbouring frames, registered, correlate at least this much at a coarse scale (Gaussian sigma 2 px on the
#: registration plane, then a quarter of its size), where focus hardly matters: 0.987-0.996 on the real circuit
#: board (896 px, every pair), handheld or not; -0.02-0.0 against a blank frame or one of another scene.
MIN_NEIGHBOUR_CORRELATION = 0.5


def neighbour_correlations(planes: list[np.ndarray], maps: list[np.ndarray], factor: int) -> list[float]:
    """Per neighbour pair (z order), the correlation of the two registration planes at a coarse scale, the later
    one resampled onto the earlier by the registration (``maps``: reference px -> frame px, full resolution),
    over the part both show (0 where either plane is flat)."""
    import cv2

    s = _plane_scale(factor)

    def coarse(a: np.ndarray) -> np.ndarray:
        a = cv2.GaussianBlur(np.asarray(a, np.float32), (0, 0), 2.0)
        return cv2.resize(a, (max(1, a.shape[1] // 4), max(1, a.shape[0] // 4)), interpolation=cv2.INTER_AREA)

    out = []
    for k in range(len(planes) - 1):
        a = planes[k]
        pair = np.linalg.inv(s) @ maps[k + 1] @ np.linalg.inv(maps[k]) @ s  # plane k px -> plane k + 1 px
        size = (a.shape[1], a.shape[0])
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        b = cv2.warpPerspective(np.asarray(planes[k + 1], np.float32), pair, size, flags=flags)
        cover = cv2.warpPerspective(np.ones(a.shape, np.float32), pair, size, flags=flags)
        ca, cb = coarse(a), coarse(b)
        ok = coarse(cover) > 0.999
        if ok.sum() < 16:
            out.append(0.0)
            continue
        x, y = ca[ok].astype(np.float64), cb[ok].astype(np.float64)
        x -= x.mean()
        y -= y.mean()
        den = float(np.sqrt(np.sum(x * x) * np.sum(y * y)))
        out.append(float(np.sum(x * y)) / den if den > 1e-12 else 0.0)
    return out


def check_frames_belong(stack, order, planes: list[np.ndarray], maps: list[np.ndarray], factor: int) -> None:
    """Refuse a stack with a frame that does not show what its neighbours show (a blank or failed exposure, a
    frame of another scene): registered, neighbours correlate below :data:`MIN_NEIGHBOUR_CORRELATION` at a
    coarse scale. Compositing would chain every later frame's registration through it, and its noise would be
    taken for detail.

    Raises
    ------
    StackError
        Naming the frame (the one whose every neighbour pair fails, else the pair).
    """
    from ..errors import StackError

    if len(planes) < 2:
        return
    corr = neighbour_correlations(planes, maps, factor)
    bad_pair = [c < MIN_NEIGHBOUR_CORRELATION for c in corr]
    if not any(bad_pair):
        return
    # An odd frame out breaks at most two pairs. When most pairs fail, the scene itself has no coarse structure
    # above the noise (a plain card, a tiny subject on a blank ground): nothing marks one frame as foreign, and
    # refusing would reject a real stack.
    if sum(bad_pair) > max(2, len(corr) // 2):
        return
    n = len(planes)
    infos = getattr(stack, "frames", None)

    def name(k: int) -> str:
        i = int(order[k])
        path = getattr(infos[i], "path", None) if infos is not None and not callable(infos) else None
        return f"{path.name if path is not None else f'frame {i}'} (z = {float(stack.z_um[i]):g} µm)"

    def file_of(k: int):
        i = int(order[k])
        return getattr(infos[i], "path", None) if infos is not None and not callable(infos) else None

    # the frame whose every neighbour pair fails: inside the stack, both; at an end, its one pair, where the
    # neighbour's other pair holds
    bad = [k for k in range(1, n - 1) if bad_pair[k - 1] and bad_pair[k]]
    if not bad and n >= 3:
        bad = [0] if bad_pair[0] and not bad_pair[1] else [n - 1] if bad_pair[-1] and not bad_pair[-2] else []
    if bad:
        k = bad[0]
        worst = min(corr[p] for p in (k - 1, k) if 0 <= p < n - 1)
        raise StackError(f"frame {name(k)} does not show what its neighbours in z show (registered, they "
                         f"correlate {worst:.2f} at a coarse scale; real neighbours correlate above 0.9): a blank "
                         "or failed exposure, or a frame of another scene", path=file_of(k), field="frames",
                         fix="remove that frame from the stack (import the others again)")
    p = int(np.argmin(corr))
    raise StackError(f"frames {name(p)} and {name(p + 1)} do not show the same scene (registered, they correlate "
                     f"{corr[p]:.2f} at a coarse scale; real neighbours correlate above 0.9)", path=file_of(p + 1),
                     field="frames", fix="check the stack is one scene shot through focus; remove the frames that "
                                         "are not")


def register_stack(stack, frames=None, z_ref_um: float | None = None, *, max_side_px: int | None = None,
                   models=MODELS, photometric_correction: bool = True, quiet: bool = False):
    """Register a stack once and hold its frames warped into the reference frame's geometry.

    Each frame is decoded once (in parallel); its registration plane is made from that decode, the model is
    chosen (:func:`choose_model`), each frame is brought to the reference frame's exposure and white balance
    (a gain and an offset per channel, :mod:`fieldcal.composite.photometric`; ``photometric_correction=False``
    leaves the frames' levels as they are), and each frame is warped once with its map and held
    (:class:`~fieldcal.composite.source.HeldFrames`, in memory within its budget, else a temporary file), so
    every later pass (focus volume, fusion, depth map, blending) reads registered pixels with no geometry.

    Returns
    -------
    (HeldFrames, geometry)
        The registered frames (file indices as in ``stack``; only ``frames`` are held; ``support``, a
        :class:`FrameSupport`, says where each holds recorded pixels; ``photometric`` summarises the gains and
        offsets) and the geometry (``info()`` describes it).
    """
    from .memory import check_temp_space
    from .source import MEMORY_BUDGET_BYTES, HeldFrames, default_workers, end_prefetch, roi_readable, take_prefetched

    w, h = image_size(stack)
    order, zs, z_ref_um = _sorted_frames(stack, frames, z_ref_um)
    factor = _factor(w, h, max_side_px)
    keep = not all(roi_readable(stack, int(i)) for i in order)  # decoding again would cost a full decode
    storage, scale = storage_dtype(stack.dtype)
    # both temporary files (decoded, registered: the frames beyond those held in memory) checked up front, not
    # after minutes of reading
    frame_bytes = [h * w * len(stack.channels) * np.dtype(d).itemsize for d, used in ((stack.dtype, keep),
                                                                                       (storage, True)) if used]
    to_file = sum((len(order) - min(len(order), MEMORY_BUDGET_BYTES // max(1, b))) * b for b in frame_bytes)
    if to_file:
        check_temp_space(to_file, f"{len(order)} frames of {w}x{h} px, decoded and registered,")
    decoded = HeldFrames(stack, order, stack.dtype) if keep else None
    planes = {}

    def load(i: int):
        """Frame i decoded and its registration plane, on a compositor's thread (both release the GIL)."""
        image = take_prefetched(stack, i)  # decoded while the process was importing (fieldcal composite)
        if image is None:
            image = read_roi(stack, i, 0, 0, w, h)
        return image, _grey(image, factor)

    from .dff import map_in_order

    # at most two frames per thread in flight, as read_frames_parallel keeps
    loaded = map_in_order(load, [int(i) for i in order], ahead=2 * default_workers())
    for i, (image, plane) in progress(zip(order, loaded), total=len(order), desc="reading", quiet=quiet,
                                      unit="frame"):
        planes[int(i)] = plane
        if decoded is not None:
            decoded.put(int(i), image)
        del image
    end_prefetch()
    geo = choose_model(stack, order, z_ref_um, max_side_px, quiet, [planes[int(i)] for i in order], models)
    maps = {int(i): frame_map_matrix(geo, float(z)) for i, z in zip(order, zs)}
    check_frames_belong(stack, order, [planes[int(i)] for i in order], [maps[int(i)] for i in order], factor)
    out = HeldFrames(stack, order, storage, strict=True, scale=scale)
    out.support = FrameSupport(geo, {int(i): float(z) for i, z in zip(order, zs)}, w, h)
    src = decoded if decoded is not None else stack
    # exposure and white-balance flicker: every frame brought to the reference frame's (composite/photometric.py),
    # measured on the registered frames, so the reference frame goes first
    ref = int(order[int(np.argmin(np.abs(zs - geo.z_ref_um)))])
    black, white, cell = float(stack.black_level), float(stack.white_level), photometric.cell_px(w, h)
    corr = {}

    def warp(i: int, ref_cells=None):
        """Frame i read, warped into the reference geometry, (with ``ref_cells``) brought to the reference's
        levels and held in ``out``; its correction (None where not fitted) and its cell means."""
        image = read_roi(src, i, 0, 0, w, h)
        if scale == 256.0:  # 8-bit -> 16-bit fixed point (one pass), then warped in that dtype
            image = np.left_shift(image, 8, dtype=np.uint16)
        elif image.dtype != storage:
            image = image.astype(storage)
        # the reference frame's map is the identity (exactly): the bicubic warp would give back its samples
        warped = image if np.array_equal(maps[i], np.eye(3)) else warp_frame(image, maps[i])
        del image
        fix = cells = None
        if photometric_correction:
            cells = photometric.cell_means(warped, cell, scale)
            if ref_cells is not None:
                fix = photometric.fit_correction(cells, ref_cells, photometric.cells_inside(out.support(i), cell),
                                                 black, white)
                if fix is not None:
                    warped = photometric.apply_correction(warped, fix, scale, black)
        out.put(i, warped, held_units=True)  # its own slot (memory or file offset): safe from any thread
        return fix, cells

    from .dff import map_in_order

    _, ref_cells = warp(ref)
    others = [int(i) for i in order if int(i) != ref]
    # the other frames on the compositor's threads (each depends only on the reference's cells)
    done = map_in_order(lambda i: warp(i, ref_cells), others, ahead=default_workers())  # a frame per thread
    for i, (fix, _) in progress(zip(others, done), total=len(others), desc="warping", quiet=quiet, unit="frame"):
        if photometric_correction:
            corr[i] = fix
    out.photometric = photometric.summary(corr, stack.channels) if photometric_correction else None
    return out, geo
