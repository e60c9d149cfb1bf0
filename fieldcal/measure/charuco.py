"""Point correspondences for the geometry maps: ChArUco corners matched by id, or texture tracked on a grid.

Both produce :class:`fieldcal.fit.geometry_map.Correspondences`: the point at ``p`` of the z_ref geometry (the
reference channel of the reference frame) seen at ``q`` in channel c of frame k.

* ChArUco (:func:`charuco_correspondences`): OpenCV's ``CharucoDetector`` per channel of every frame finds the
  corners and their ids (on an 8-bit copy); each corner is then refined by ``cv2.cornerSubPix``'s method on
  the float plane (:func:`refine_corners`: no 8-bit quantisation). Corners are matched across frames and channels by id.
* Texture (:func:`texture_correspondences`): pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) tracks a
  grid of textured points from the reference plane into every channel of every frame, frame after frame
  outward from the reference (each track starts from the previous frame's answer) and then directly against the
  reference plane, so errors do not accumulate along the scan; a forward-backward check drops bad tracks.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import cv2
import numpy as np

from ..charts.targets import CharucoSpec, detect_charuco
from ..errors import ParameterError
from ..fit.geometry_map import Correspondences



def subpix_window_px(spec: CharucoSpec) -> int:
    """Half-size of the ``cornerSubPix`` window: the white gap between a corner and its markers' bit cells.

    The window sees the chessboard saddle only; marker edges inside it would pull the corner.
    """
    gap = (spec.square_px - spec.marker_px) / 2.0
    return int(max(2, min(12, round(gap - 1))))


def refine_corners(plane: np.ndarray, xy: np.ndarray, half_px: int, iterations: int = 30,
                   tol_px: float = 1e-4) -> np.ndarray:
    """Sub-pixel saddle corners on a float plane: ``cv2.cornerSubPix``'s gradient-orthogonality estimate.

    Every gradient in the window around a corner is orthogonal to the vector from the corner to its own
    position, so the corner solves ``sum w g g^T (q - p) = 0``. Done here in float64 for all corners at once
    (OpenCV's version takes 8-bit images only in 5.x, and 8 bits quantise a blurred corner's gradients).
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
    q = np.asarray(xy, dtype=np.float64).copy()
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
        step = np.hypot(nx - q[:, 0], ny - q[:, 1])
        q = np.column_stack([nx, ny])
        if np.max(step, initial=0.0) < tol_px:
            break
    return q


def charuco_corners(plane: np.ndarray, spec: CharucoSpec) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel ChArUco corners of one plane (H x W, any dtype): (N x 2 px, N ids)."""
    xy, ids = detect_charuco(plane, spec)
    if ids.size == 0:
        return xy, ids
    win = subpix_window_px(spec)
    refined = refine_corners(plane, xy, win)
    # a refinement that wandered off (a blurred-away saddle) keeps the detector's corner
    moved = ~np.all(np.isfinite(refined), axis=1) | (np.hypot(*(refined - xy).T) > 0.5 * win)
    refined[moved] = xy[moved]
    return refined, ids


def charuco_correspondences(read_plane: Callable[[int, int], np.ndarray], z_um: Sequence[float],
                            channels: Sequence[str], spec: CharucoSpec, ref_index: int,
                            reference_channel: str, min_corners: int = 6) -> Correspondences:
    """Corners of every channel of every frame, matched to the reference plane's corners by id.

    ``read_plane(k, ci)`` returns channel ``ci`` of frame ``k`` (any dtype). The reference positions ``p`` are
    the corners found in the reference plane (re-estimated by the fit from all observations). Frames with
    fewer than ``min_corners`` corners are skipped (too far out of focus for the detector).
    """
    channels = list(channels)
    ref_ci = channels.index(reference_channel)
    found: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    for k in range(len(z_um)):
        for ci in range(len(channels)):
            xy, ids = charuco_corners(read_plane(k, ci), spec)
            if ids.size >= min_corners:
                found[(k, ci)] = (xy, ids)
    if (ref_index, ref_ci) not in found:
        raise ParameterError(f"no ChArUco board found in the reference frame (z = {z_um[ref_index]:g} µm, "
                             f"channel {reference_channel})", field="chart",
                             fix="check the stack's chart description (stack.json 'chart') and that the board "
                                 "is near focus at the reference frame")
    ref_xy, ref_ids = found[(ref_index, ref_ci)]
    lut = {int(i): xy for i, xy in zip(ref_ids, ref_xy)}
    P, Q, Z, C, I = [], [], [], [], []
    for (k, ci), (xy, ids) in found.items():
        for i, q in zip(ids, xy):
            p = lut.get(int(i))
            if p is None:
                continue
            P.append(p)
            Q.append(q)
            Z.append(float(z_um[k]))
            C.append(channels[ci])
            I.append(int(i))
    n = len(Z)
    return Correspondences(np.asarray(P, dtype=np.float64).reshape(n, 2), np.asarray(Q, dtype=np.float64).reshape(n, 2),
                           np.asarray(Z), np.asarray(C), np.ones(n), np.asarray(I, dtype=np.int64))


def _texture_grid(ref: np.ndarray, step_px: int, border_px: int, min_quality: float = 0.02) -> np.ndarray:
    """Grid points with enough texture to track (min eigenvalue of the structure tensor)."""
    h, w = ref.shape
    eig = cv2.cornerMinEigenVal(ref, blockSize=7)
    ys, xs = np.mgrid[border_px:h - border_px:step_px, border_px:w - border_px:step_px]
    xs, ys = xs.ravel(), ys.ravel()
    ok = eig[ys, xs] >= min_quality * float(np.percentile(eig, 99))
    return np.column_stack([xs[ok], ys[ok]]).astype(np.float32)


def _as_float01(plane: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return ((np.asarray(plane, dtype=np.float32) - lo) / max(hi - lo, 1e-12)).astype(np.float32)


def texture_correspondences(read_plane: Callable[[int, int], np.ndarray], z_um: Sequence[float],
                            channels: Sequence[str], ref_index: int, reference_channel: str,
                            step_px: int = 16, window_px: int = 31, max_fb_px: float = 0.1) -> Correspondences:
    """Grid points of the reference plane tracked into every channel of every frame (Lucas-Kanade).

    Frames are visited outward from the reference (``ref_index`` up, then down); each frame's track starts at
    the previous frame's answer and is refined against the reference plane itself. Tracks whose forward-backward
    round trip misses by more than ``max_fb_px`` are dropped.
    """
    channels = list(channels)
    ref_ci = channels.index(reference_channel)
    ref_raw = np.asarray(read_plane(ref_index, ref_ci), dtype=np.float32)
    lo, hi = (float(v) for v in np.percentile(ref_raw, [0.5, 99.5]))
    # LK works on 8-bit or float32 images; scale to ~0..255 in float to keep sub-DN precision
    scale = lambda a: 255.0 * _as_float01(a, lo, hi)  # noqa: E731
    ref = scale(ref_raw)
    border = window_px // 2 + 4
    grid = _texture_grid(ref, step_px, border)
    if grid.shape[0] < 8:
        raise ParameterError(f"only {grid.shape[0]} textured points in the reference frame", field="frames",
                             fix="use a textured chart (fieldcal targets) or the ChArUco board with --chart")
    lk = dict(winSize=(window_px, window_px), maxLevel=2,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 60, 1e-4),
              flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    P, Q, Z, C = [], [], [], []
    order = list(range(ref_index, len(z_um))) + list(range(ref_index - 1, -1, -1))
    for ci, ch in enumerate(channels):
        prev = {ref_index: grid.copy()}
        for k in order:
            start = prev.get(k - 1 if k > ref_index else k + 1, grid) if k != ref_index else grid
            img = scale(read_plane(k, ci))
            q, st, _ = cv2.calcOpticalFlowPyrLK(ref, img, grid, start.copy(), **lk)
            back, st2, _ = cv2.calcOpticalFlowPyrLK(img, ref, q, grid.copy(), **lk)
            ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.hypot(*(back - grid).T) <= max_fb_px)
            prev[k] = np.where(ok[:, None], q, start)
            if k == ref_index and ci == ref_ci:
                continue  # the identity by definition
            P.append(grid[ok])
            Q.append(q[ok])
            Z.append(np.full(int(ok.sum()), float(z_um[k])))
            C.append(np.full(int(ok.sum()), ch))
    P = np.concatenate(P).astype(np.float64)
    n = P.shape[0]
    return Correspondences(P, np.concatenate(Q).astype(np.float64), np.concatenate(Z), np.concatenate(C),
                           np.ones(n), np.full(n, -1, dtype=np.int64))
