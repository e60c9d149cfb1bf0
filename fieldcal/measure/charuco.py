"""Point correspondences for the geometry maps: ChArUco corners matched by id, or texture tracked on a grid.

Both produce :class:`fieldcal.fit.geometry_map.Correspondences`: the point at ``p`` of the z_ref geometry (the
reference channel of the reference frame) seen at ``q`` in channel c of frame k.

* ChArUco (:func:`charuco_correspondences`): OpenCV's ``CharucoDetector`` per channel of every frame finds the
  corners and their ids (on an 8-bit copy); each corner is then refined by ``cv2.cornerSubPix``'s method on
  the float plane (:func:`refine_corners`: no 8-bit quantisation). Corners are matched across frames and channels by id.
  Corners the detector misses on a blurred board are located from the frames where they were found
  (:func:`track_blurred_corners`: prediction from the neighbouring frame, Lucas-Kanade against the corner's patch).
* Absolute distortion (:func:`measure_geometry`): the corners' z_ref positions against the board's own
  coordinates (:mod:`fieldcal.fit.distortion`).
* Texture (:func:`texture_correspondences`): Lucas-Kanade (:func:`track_patches`, float, cubic splines) tracks
  a grid of textured points from the reference plane into every channel of every frame, frame after frame
  outward from the reference (each track starts from the previous frame's answer) but always against the
  reference plane, so errors do not accumulate along the scan.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import cv2
import numpy as np

from ..charts.targets import CharucoSpec, detect_charuco
from ..errors import ParameterError
from ..fit.geometry_map import Correspondences



def _corner_spacing_px(xy: np.ndarray) -> float:
    """The board's square in the image: the median distance from each corner to its nearest neighbour."""
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


def subpix_window_px(spec: CharucoSpec, xy: np.ndarray | None = None) -> int:
    """Half-size of the corner-refinement window: the white gap between a corner and its markers' bit cells.

    The window sees the chessboard saddle only; marker edges inside it would pull the corner. The square's
    size in the image comes from the detected corners' spacing when given (a stack's chart record has no pixel
    size), else from ``spec``.
    """
    square = float(spec.square_px)
    if xy is not None and len(xy) >= 2:
        square = _corner_spacing_px(xy)
    gap = square * (1.0 - spec.marker_px / spec.square_px) / 2.0
    return int(max(2, min(12, round(gap - 1))))


def refine_corners(plane: np.ndarray, xy: np.ndarray, half_px: int, iterations: int = 30,
                   tol_px: float = 1e-4, return_sigma: bool = False):
    """Sub-pixel saddle corners on a float plane: ``cv2.cornerSubPix``'s gradient-orthogonality estimate.

    Every gradient in the window around a corner is orthogonal to the vector from the corner to its own
    position, so the corner solves ``sum w g g^T (q - p) = 0``. Done here in float64 for all corners at once
    (OpenCV's version takes 8-bit images only in 5.x, and 8 bits quantise a blurred corner's gradients).
    A blurred saddle keeps its point symmetry, so the estimate stays at its centre (the equations' odd terms
    cancel over the symmetric window): the method works through focus while the window sees the saddle.

    ``return_sigma``: also return each corner's 1-sigma (px), the sandwich (heteroscedasticity-robust)
    covariance of the normal equations' solution -- large where the saddle is weak, blurred or disturbed
    (a marker's edge in the window); inf where the solve failed or did not converge.
    """
    from scipy import ndimage
    f = np.asarray(plane, dtype=np.float64)
    # Pixel locking: a sharp (aliased) corner pulls the estimate towards the pixel grid, so small motions are
    # measured short. Gradients sampled by cubic splines, not bilinearly, and of the plane smoothed with
    # sigma 1.5 px: a 1e-3 scale change of the simulator's aliased board is measured 0.3 % short, against
    # 13 % with bilinear sampling of unsmoothed gradients (tests/test_geometry_maps.py).
    gy, gx = (ndimage.spline_filter(g, order=3) for g in np.gradient(ndimage.gaussian_filter(f, 1.5)))
    off = np.arange(-half_px, half_px + 1, dtype=np.float64)
    oy, ox = (a.ravel() for a in np.meshgrid(off, off, indexing="ij"))
    # Gaussian window (sigma = half size) as cornerSubPix uses, the centre cell kept (gradients vanish there)
    wt = np.exp(-(ox ** 2 + oy ** 2) / (2.0 * max(half_px, 1) ** 2))
    q = np.asarray(xy, dtype=np.float64).reshape(-1, 2).copy()
    step = np.full(len(q), np.inf)
    for _ in range(iterations):
        px = q[:, 0:1] + ox[None, :]
        py = q[:, 1:2] + oy[None, :]
        ax = ndimage.map_coordinates(gx, [py.ravel(), px.ravel()], order=3, mode="nearest", prefilter=False).reshape(px.shape)
        ay = ndimage.map_coordinates(gy, [py.ravel(), px.ravel()], order=3, mode="nearest", prefilter=False).reshape(px.shape)
        a11 = np.sum(wt * ax * ax, axis=1)
        a12 = np.sum(wt * ax * ay, axis=1)
        a22 = np.sum(wt * ay * ay, axis=1)
        b1 = np.sum(wt * (ax * ax * px + ax * ay * py), axis=1)
        b2 = np.sum(wt * (ax * ay * px + ay * ay * py), axis=1)
        det = a11 * a22 - a12 * a12
        good = det > 1e-12 * (a11 + a22) ** 2
        nx = np.where(good, (a22 * b1 - a12 * b2) / np.where(good, det, 1.0), q[:, 0])
        ny = np.where(good, (a11 * b2 - a12 * b1) / np.where(good, det, 1.0), q[:, 1])
        step = np.where(good, np.hypot(nx - q[:, 0], ny - q[:, 1]), np.inf)
        q = np.column_stack([nx, ny])
        if np.max(step, initial=0.0) < tol_px:
            break
    if not return_sigma:
        return q
    # residual of each sample's orthogonality equation g . (q - p), and the sandwich A^-1 B A^-1
    r = ax * (q[:, 0:1] - px) + ay * (q[:, 1:2] - py)
    w2r2 = (wt * r) ** 2
    b11, b12, b22 = (np.sum(w2r2 * u * v, axis=1) for u, v in ((ax, ax), (ax, ay), (ay, ay)))
    det = np.where(good, det, np.nan)
    i11, i12, i22 = a22 / det, -a12 / det, a11 / det
    c11 = i11 * i11 * b11 + 2 * i11 * i12 * b12 + i12 * i12 * b22
    c22 = i12 * i12 * b11 + 2 * i12 * i22 * b12 + i22 * i22 * b22
    sigma = np.sqrt(np.clip(0.5 * (c11 + c22), 0, None))
    sigma = np.where(np.isfinite(sigma) & (step < 1e-2), np.maximum(sigma, 1e-6), np.inf)
    return q, sigma


def charuco_corners(plane: np.ndarray, spec: CharucoSpec) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel ChArUco corners of one plane (H x W, any dtype): (N x 2 px, N ids)."""
    xy, ids = detect_charuco(plane, spec)
    if ids.size == 0:
        return xy, ids
    win = subpix_window_px(spec, xy)
    refined = refine_corners(plane, xy, win)
    # a refinement that wandered off (a blurred-away saddle) keeps the detector's corner
    moved = ~np.all(np.isfinite(refined), axis=1) | (np.hypot(*(refined - xy).T) > 0.5 * win)
    refined[moved] = xy[moved]
    return refined, ids


def _similarity(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """2x3 least-squares similarity (scale, rotation, shift) taking ``src`` to ``dst``; identity for < 3 points."""
    if len(src) < 3:
        return np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    M, _ = cv2.estimateAffinePartial2D(src.astype(np.float32), dst.astype(np.float32), method=cv2.LMEDS)
    return np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]) if M is None else M.astype(np.float64)


def track_blurred_corners(read_planes: Callable[[int], Sequence[np.ndarray]], n_frames: int, ref_index: int,
                          found: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]], square_px: float,
                          smooth_px: float = 1.5, max_sigma_ratio: float = 5.0,
                          passes: int = 3) -> dict[tuple[int, int], int]:
    """Corners the detector missed (a blurred board), located from frames where they were found.

    Frames are visited outward from the reference, then inward, then outward again (``passes``), so a corner
    found anywhere reaches every frame. In each frame a channel's missing corners are predicted from the
    previous frame of the walk through the similarity that takes the corners both frames share (the identity
    when they share fewer than 3: neighbouring frames differ by focus breathing, ~1e-3), then registered by
    Lucas-Kanade (:func:`track_patches`: gain and offset per patch, float, cubic splines) against the corner's
    patch -- saddle and marker cells, ~0.8 square across -- in the reference frame where it was found there,
    else in the previous frame of the walk. A blurred image of a patch correlates best with the sharp patch at
    zero shift for any point-symmetric blur (the correlation is the patch's autocorrelation convolved with
    the blur), which the saddle alone does not give once the blur reaches the markers. The quality flag: a
    corner is kept when the registration converged within a quarter square of the prediction and its
    sigma (Gauss-Newton, scaled by the patch residual) is within ``max_sigma_ratio`` of the frame's median.
    ``found[(k, ci)] = (xy, ids, sigma, tracked)`` is extended in place (``tracked`` marks the corners added
    here); returns the corners added per (frame, channel).
    """
    from scipy import ndimage
    prep = lambda a: ndimage.gaussian_filter(np.asarray(a, dtype=np.float64), smooth_px)  # noqa: E731
    half = int(max(4, round(0.4 * square_px)))
    added: dict[tuple[int, int], int] = {}
    up = list(range(ref_index + 1, n_frames))
    down = list(range(ref_index - 1, -1, -1))
    walks = []
    for p in range(passes):
        walks += ([[ref_index] + up, [ref_index] + down] if p % 2 == 0 else
                  [up[::-1] + [ref_index], down[::-1] + [ref_index]])
    n_ch = 1 + max((ci for _, ci in found), default=0)
    empty = (np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0), np.zeros(0, bool))
    ref_planes = [prep(a) for a in read_planes(ref_index)]
    for walk in walks:
        if len(walk) < 2:
            continue
        prev_planes = ref_planes if walk[0] == ref_index else None
        for prev, k in zip(walk[:-1], walk[1:]):
            cur_planes = ref_planes if k == ref_index else None
            for ci in range(n_ch):
                p_xy, p_ids, _, _ = found.get((prev, ci), empty)
                k_xy, k_ids, k_sig, k_tr = found.get((k, ci), empty)
                missing = ~np.isin(p_ids, k_ids)
                if not missing.any():
                    continue
                common = ~missing
                M = _similarity(p_xy[common], k_xy[np.searchsorted(k_ids, p_ids[common])])
                pred = p_xy[missing] @ M[:, :2].T + M[:, 2]
                if cur_planes is None:
                    cur_planes = [prep(a) for a in read_planes(k)]
                plane = cur_planes[ci]
                h, w = plane.shape
                inside = ((pred[:, 0] > half + 2) & (pred[:, 0] < w - half - 3) &
                          (pred[:, 1] > half + 2) & (pred[:, 1] < h - half - 3))
                mids, pred = p_ids[missing][inside], pred[inside]
                if not mids.size:
                    continue
                r_xy, r_ids, _, _ = found.get((ref_index, ci), empty)
                in_ref = np.isin(mids, r_ids)
                q = np.full_like(pred, np.nan)
                sig = np.full(len(pred), np.inf)
                for use_ref in (True, False):
                    sel = in_ref if use_ref else ~in_ref
                    if not sel.any():
                        continue
                    if use_ref:
                        tmpl, t_xy = ref_planes[ci], r_xy[np.searchsorted(r_ids, mids[sel])]
                    else:
                        if prev_planes is None:
                            prev_planes = [prep(a) for a in read_planes(prev)]
                        tmpl, t_xy = prev_planes[ci], p_xy[missing][inside][sel]
                    q[sel], sig[sel] = track_patches(tmpl, plane, t_xy, pred[sel], half)
                ok = np.isfinite(sig) & np.all(np.isfinite(q), axis=1) & (np.hypot(*(q - pred).T) <= 0.25 * square_px)
                if ok.any():
                    ok &= sig <= max_sigma_ratio * float(np.median(sig[ok]))
                if not ok.any():
                    continue
                ids = np.concatenate([k_ids, mids[ok]])
                xy = np.concatenate([k_xy, q[ok]])
                sg = np.concatenate([k_sig, sig[ok]])
                tr = np.concatenate([k_tr, np.ones(int(ok.sum()), bool)])
                o = np.argsort(ids, kind="stable")
                found[(k, ci)] = (xy[o], ids[o], sg[o], tr[o])
                added[(k, ci)] = added.get((k, ci), 0) + int(ok.sum())
            prev_planes = cur_planes
    return added


def charuco_correspondences(read_plane: Callable[[int, int], np.ndarray], z_um: Sequence[float],
                            channels: Sequence[str], spec: CharucoSpec, ref_index: int,
                            reference_channel: str, min_corners: int = 6, track_blurred: bool = True,
                            stats: dict | None = None) -> Correspondences:
    """Corners of every channel of every frame, matched to the reference plane's corners by id.

    ``read_plane(k, ci)`` returns channel ``ci`` of frame ``k`` (any dtype). The reference positions ``p`` are
    the corners found in the reference plane (re-estimated by the fit from all observations). Frames with
    fewer than ``min_corners`` detected corners contribute only what ``track_blurred`` finds in them
    (:func:`track_blurred_corners`: corners located from the neighbouring frames where the board is too
    blurred for the detector). Each correspondence carries its corner's sigma (a relative weight). ``stats``
    (a dict) receives per-frame counts: detected and tracked corners.
    """
    channels = list(channels)
    n_ch = len(channels)
    ref_ci = channels.index(reference_channel)
    found: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    square = None
    detected: dict[tuple[int, int], int] = {}
    for k in range(len(z_um)):
        for ci in range(n_ch):
            plane = read_plane(k, ci)
            xy, ids = detect_charuco(plane, spec)
            if ids.size < min_corners:
                detected[(k, ci)] = 0
                continue
            if square is None or (k, ci) == (ref_index, ref_ci):
                square = _corner_spacing_px(xy)
            q, sig = refine_corners(plane, xy, subpix_window_px(spec, xy), return_sigma=True)
            # a refinement that wandered off (a blurred-away saddle) is dropped: the detector's own corner is
            # 8-bit and pixel-locked, worse than no corner for a 0.05 px map
            ok = np.isfinite(sig) & (np.hypot(*(q - xy).T) <= 0.5 * subpix_window_px(spec, xy))
            found[(k, ci)] = (q[ok], ids[ok], sig[ok], np.zeros(int(ok.sum()), bool))
            detected[(k, ci)] = int(ok.sum())
    if square is not None and track_blurred:
        added = track_blurred_corners(lambda k: [read_plane(k, ci) for ci in range(n_ch)], len(z_um), ref_index,
                                      found, square)
    else:
        added = {}
    if stats is not None:
        stats.update({"detected": {f"{k},{channels[ci]}": v for (k, ci), v in detected.items()},
                      "tracked": {f"{k},{channels[ci]}": v for (k, ci), v in added.items()},
                      "square_px": square})
    if (ref_index, ref_ci) not in found or found[(ref_index, ref_ci)][1].size < min_corners:
        raise ParameterError(f"no ChArUco board found in the reference frame (z = {z_um[ref_index]:g} µm, "
                             f"channel {reference_channel})", field="chart",
                             fix="check the stack's chart description (stack.json 'chart') and that the board "
                                 "is near focus at the reference frame")
    ref_xy, ref_ids, _, _ = found[(ref_index, ref_ci)]
    lut = {int(i): xy for i, xy in zip(ref_ids, ref_xy)}
    # Relative weights. The detected corners' sandwich sigmas and the tracked ones' Lucas-Kanade sigmas are
    # on different scales: each kind is divided by its own median over the stack, so a corner counts less
    # the worse it is within its kind (a tracked corner in a badly blurred frame), and the kinds count alike
    # at their typical quality (both measure ~0.015 px median against the simulator's truth through focus).
    kinds = {}
    for tracked in (False, True):
        v = np.concatenate([sg[tr == tracked] for _, _, sg, tr in found.values()] or [np.zeros(0)])
        v = v[np.isfinite(v) & (v > 0)]
        kinds[tracked] = float(np.median(v)) if v.size else 1.0
    P, Q, Z, C, I, S = [], [], [], [], [], []
    for (k, ci), (xy, ids, sg, tr) in found.items():
        for i, q, g, t in zip(ids, xy, sg, tr):
            p = lut.get(int(i))
            if p is None:
                continue
            P.append(p)
            Q.append(q)
            Z.append(float(z_um[k]))
            C.append(channels[ci])
            I.append(int(i))
            S.append(g / kinds[bool(t)])
    n = len(Z)
    # floored at half the typical: no corner dominates the fit on a fortunate residual
    sig = np.clip(np.nan_to_num(np.asarray(S, dtype=np.float64), nan=1.0, posinf=1.0), 0.5, None)
    return Correspondences(np.asarray(P, dtype=np.float64).reshape(n, 2), np.asarray(Q, dtype=np.float64).reshape(n, 2),
                           np.asarray(Z), np.asarray(C), sig, np.asarray(I, dtype=np.int64))


def _texture_grid(ref: np.ndarray, step_px: int, border_px: int, min_quality: float = 0.05) -> np.ndarray:
    """Grid points with enough texture to track (min eigenvalue of the structure tensor)."""
    h, w = ref.shape
    eig = cv2.cornerMinEigenVal(np.ascontiguousarray(ref, dtype=np.float32), blockSize=9)
    ys, xs = np.mgrid[border_px:h - border_px:step_px, border_px:w - border_px:step_px]
    xs, ys = xs.ravel(), ys.ravel()
    ok = eig[ys, xs] >= min_quality * float(np.percentile(eig, 99))
    return np.column_stack([xs[ok], ys[ok]]).astype(np.float64)


def track_patches(ref: np.ndarray, img: np.ndarray, grid: np.ndarray, start: np.ndarray, half_px: int,
                  iterations: int = 30, tol_px: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """Lucas-Kanade translation of every grid patch of ``ref`` into ``img`` (float planes, already smoothed).

    Gauss-Newton with the template's gradients, the image sampled by cubic splines at exact positions (no 8-bit
    quantisation, no bilinear pixel locking as in ``cv2.calcOpticalFlowPyrLK``), a gain and offset per patch
    (neighbouring frames differ in blur and so in contrast). Returns (positions N x 2, 1-sigma N: the
    Gauss-Newton covariance scaled by the patch's residual variance; inf where it did not converge).
    """
    from scipy import ndimage
    off = np.arange(-half_px, half_px + 1, dtype=np.float64)
    oy, ox = (a.ravel() for a in np.meshgrid(off, off, indexing="ij"))
    wt = np.exp(-(ox ** 2 + oy ** 2) / (2.0 * (0.5 * half_px) ** 2))
    gy_ref, gx_ref = np.gradient(ref)
    gxs, gys = grid[:, 0:1] + ox[None, :], grid[:, 1:2] + oy[None, :]
    T = ndimage.map_coordinates(ref, [gys.ravel(), gxs.ravel()], order=1).reshape(gxs.shape)  # integer grid
    gx = ndimage.map_coordinates(gx_ref, [gys.ravel(), gxs.ravel()], order=1).reshape(gxs.shape)
    gy = ndimage.map_coordinates(gy_ref, [gys.ravel(), gxs.ravel()], order=1).reshape(gxs.shape)
    tm = np.sum(wt * T, axis=1, keepdims=True) / wt.sum()
    T0 = T - tm
    tn = np.sqrt(np.sum(wt * T0 * T0, axis=1, keepdims=True))
    a11, a12, a22 = (np.sum(wt * u * v, axis=1) for u, v in ((gx, gx), (gx, gy), (gy, gy)))
    det = a11 * a22 - a12 * a12
    coeffs = ndimage.spline_filter(np.asarray(img, dtype=np.float64), order=3)
    q = np.asarray(start, dtype=np.float64).copy()
    done = np.zeros(len(q), bool)
    for _ in range(iterations):
        px, py = q[:, 0:1] + ox[None, :], q[:, 1:2] + oy[None, :]
        I = ndimage.map_coordinates(coeffs, [py.ravel(), px.ravel()], order=3, prefilter=False,
                                    mode="nearest").reshape(px.shape)
        I0 = I - np.sum(wt * I, axis=1, keepdims=True) / wt.sum()
        gain = tn / np.maximum(np.sqrt(np.sum(wt * I0 * I0, axis=1, keepdims=True)), 1e-12)
        r = I0 * gain - T0
        b1, b2 = np.sum(wt * gx * r, axis=1), np.sum(wt * gy * r, axis=1)
        dx = -(a22 * b1 - a12 * b2) / np.where(det > 0, det, np.inf)
        dy = -(a11 * b2 - a12 * b1) / np.where(det > 0, det, np.inf)
        q[:, 0] += dx
        q[:, 1] += dy
        done = np.hypot(dx, dy) < tol_px
        if done.all():
            break
    s2 = np.sum(wt * r * r, axis=1) / wt.sum()
    sigma = np.sqrt(s2 * 0.5 * (a11 + a22) / np.where(det > 0, det, np.inf) * wt.sum() / np.sum(wt))
    sigma = np.where(done | (np.hypot(dx, dy) < 1e-2), sigma, np.inf)
    return q, sigma


def texture_correspondences(read_plane: Callable[[int, int], np.ndarray], z_um: Sequence[float],
                            channels: Sequence[str], ref_index: int, reference_channel: str,
                            step_px: int = 16, half_window_px: int = 12, smooth_px: float = 1.5,
                            max_sigma_ratio: float = 5.0) -> Correspondences:
    """Grid points of the reference plane tracked into every channel of every frame (:func:`track_patches`).

    Frames are visited outward from the reference (``ref_index`` up, then down); each frame's track starts at
    the previous frame's answer and is measured against the reference plane itself, so errors do not
    accumulate along the scan. Both planes are smoothed by ``smooth_px`` (against pixel locking, as for the
    corners). Tracks that did not converge or whose sigma exceeds ``max_sigma_ratio`` times the frame's
    median are dropped.
    """
    from scipy import ndimage
    channels = list(channels)
    ref_ci = channels.index(reference_channel)
    ref_raw = np.asarray(read_plane(ref_index, ref_ci), dtype=np.float64)
    lo, hi = (float(v) for v in np.percentile(ref_raw, [0.5, 99.5]))
    prep = lambda a: ndimage.gaussian_filter((np.asarray(a, dtype=np.float64) - lo) / max(hi - lo, 1e-12),  # noqa: E731
                                             smooth_px)
    ref = prep(ref_raw)
    grid = _texture_grid(ref, step_px, half_window_px + 8)
    if grid.shape[0] < 8:
        raise ParameterError(f"only {grid.shape[0]} textured points in the reference frame", field="frames",
                             fix="use a textured chart (fieldcal targets) or the ChArUco board with --chart")
    P, Q, Z, C, S = [], [], [], [], []
    order = list(range(ref_index, len(z_um))) + list(range(ref_index - 1, -1, -1))
    for ci, ch in enumerate(channels):
        prev: dict[int, np.ndarray] = {}
        for k in order:
            start = grid if k == ref_index else prev[k - 1 if k > ref_index else k + 1]
            q, sig = track_patches(ref, prep(read_plane(k, ci)), grid, start, half_window_px)
            ok = np.isfinite(sig) & np.all(np.isfinite(q), axis=1)
            if ok.any():
                ok &= sig <= max_sigma_ratio * np.median(sig[ok])
            prev[k] = np.where(ok[:, None], q, start)
            if k == ref_index and ci == ref_ci:
                continue  # the identity by definition
            P.append(grid[ok])
            Q.append(q[ok])
            Z.append(np.full(int(ok.sum()), float(z_um[k])))
            C.append(np.full(int(ok.sum()), ch))
            S.append(np.maximum(sig[ok], 1e-4))
    n = sum(len(z) for z in Z)
    return Correspondences(np.concatenate(P).reshape(n, 2), np.concatenate(Q).reshape(n, 2), np.concatenate(Z),
                           np.concatenate(C), np.concatenate(S), np.full(n, -1, dtype=np.int64))


def measure_geometry_map(stack, z_ref_um: float, **kw):
    """Dense geometry maps of a stack (:class:`fieldcal.fit.geometry_map.GeometryMap`): :func:`measure_geometry`
    without the absolute distortion."""
    return measure_geometry(stack, z_ref_um, **kw)[0]


def measure_geometry(stack, z_ref_um: float, *, chart: dict | None = None, reference_channel: str | None = None,
                     source: str = "auto", max_order: int = 2, quiet: bool = True):
    """Dense geometry maps of a stack and, from a ChArUco board, the absolute distortion of its z_ref geometry.

    Returns ``(GeometryMap, AbsoluteDistortion or None)`` (:mod:`fieldcal.fit.geometry_map`,
    :mod:`fieldcal.fit.distortion`); z_ref is a frame of the stack. The absolute distortion is fitted to every
    corner's z_ref position estimated from all its observations through the maps (:func:`reference_points`)
    against the board's own coordinates; texture gives none (no straight lines to compare with).

    ``chart``: the stack's ``chart`` record (default: stack.json's); a ChArUco record makes ``source="auto"``
    use the board's corners, anything else the texture. Raw Bayer stacks are measured on each colour's own
    sub-lattice (no demosaicing) and reported in full-frame pixels.
    """
    from ..charts.targets import board_from_record
    from ..fit.geometry_map import fit_geometry_map
    from ..formats.stack import stack_chart
    from ..progress import status
    from .bayer import extract_plane, plane_layouts

    chart = stack_chart(stack.meta, stack.json_path) if chart is None else chart
    if source == "auto":
        source = "charuco" if chart and chart.get("kind") == "charuco" else "texture"
    if source not in ("charuco", "texture"):
        raise ParameterError(f"unknown geometry source {source!r}", field="source", fix="use auto, charuco or texture")
    order = np.asarray(stack.order_by_z)
    z = np.asarray(stack.z_um, dtype=np.float64)[order]
    ref_index = int(np.argmin(np.abs(z - float(z_ref_um))))
    channels = tuple(stack.channels)
    ref_ch = reference_channel or ("G" if "G" in channels else channels[0])
    layouts = {}
    for lay in plane_layouts(channels, getattr(stack, "cfa", None)):
        layouts.setdefault(lay.name, lay)  # one plane per colour (the first G site of a mosaic)
    names = [c for c in channels if c in layouts]
    cache: dict[int, np.ndarray] = {}

    def read_plane(k: int, ci: int) -> np.ndarray:
        if k not in cache:
            cache.clear()  # frames are visited one at a time per channel loop: keep one
            cache[k] = stack.read_normalized(int(order[k]))
        return extract_plane(cache[k], layouts[names[ci]])

    h, w = stack.shape[:2]
    status(f"geometry maps from {'ChArUco corners' if source == 'charuco' else 'texture'}: {len(z)} frames",
           quiet=quiet)
    if source == "charuco":
        if not chart or chart.get("kind") != "charuco":
            raise ParameterError("the stack records no ChArUco chart", path=stack.json_path, field="chart",
                                 fix="record it with --chart targets.json (simulate, capture, import)")
        lay0 = layouts[names[0]]
        board = board_from_record(chart, *(np.array([w, h]) // lay0.stride), path=stack.json_path)
        det_stats: dict = {}
        corr = charuco_correspondences(read_plane, z, names, board, ref_index, ref_ch, stats=det_stats)
    else:
        corr = texture_correspondences(read_plane, z, names, ref_index, ref_ch,
                                       step_px=max(8, int(min(h, w) / layouts[names[0]].stride // 24)))
    # plane pixels -> frame pixels (identity for demosaiced stacks)
    ref_lay = layouts[ref_ch]
    p = np.column_stack(ref_lay.to_full(*corr.p_px.T))
    q = corr.q_px.copy()
    sig = corr.sigma_px.copy()
    for c in names:
        m = corr.channel == c
        q[m] = np.column_stack(layouts[c].to_full(*corr.q_px[m].T))
        sig[m] = sig[m] * layouts[c].stride
    from ..fit.geometry_map import Correspondences
    corr = Correspondences(p, q, corr.z_um, corr.channel, sig, corr.point_id)
    gmap = fit_geometry_map(corr, float(z[ref_index]), (int(w), int(h)), reference_channel=ref_ch,
                            max_order=max_order, source=source, path=stack.json_path)
    if source != "charuco":
        return gmap, None
    gmap.diagnostics["charuco_corners"] = det_stats
    from ..fit.distortion import fit_absolute_distortion, reference_points, reference_points_map_cov
    ids, p_ref, sd = reference_points(corr, gmap)
    dist = fit_absolute_distortion(board.corner_px(ids), p_ref, (int(w), int(h)), sigma_px=sd,
                                   shared_cov_px2=reference_points_map_cov(corr, gmap, ids, p_ref),
                                   reference_channel=ref_ch, z_um=float(z[ref_index]), path=stack.json_path)
    status(f"absolute distortion: {', '.join(dist.terms) or 'none'} from {dist.n_points} corners, "
           f"rms {dist.rms_px:.3f} px", quiet=quiet)
    return gmap, dist
