"""Slanted-edge MTF of frames and stacks: the ``fieldcal-mtf/1`` document and :func:`measure_mtf`.

Per frame: edges are found once on the mean of the colour planes (:mod:`.esfr_detect`), then every plane is
analysed in the same regions by the e-SFR core (:mod:`.esfr`), all planes of an edge in one call. A raw mosaic
(``cfa="RGGB"`` ...) is split into its four colour sub-lattices (:mod:`.bayer`); each is measured on its own grid
and its frequencies converted to cycles per *sensor* pixel (a plane pixel is two sensor pixels). Each edge is
classified tangential or sagittal about the optical centre, and edges are linked into tracks across frames.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._numeric import channel_mean
from ..errors import FieldcalError, ParameterError, SpecError
from ..formats import documents
from .bayer import extract_plane, plane_layouts
from .esfr import esfr_regions
from .esfr_detect import find_edges

FORMAT = documents.format_id("mtf")


def default_grid(max_cy_per_px: float = 1.0, step_cy_per_px: float = 0.01) -> np.ndarray:
    """The stored frequency grid: 0 .. max in steps (cycles per sensor pixel)."""
    if not (0 < step_cy_per_px < max_cy_per_px <= 2.0):
        raise ParameterError(f"grid step {step_cy_per_px} / max {max_cy_per_px} invalid", field="grid",
                             fix="use 0 < step < max <= 2 cycles/px, e.g. step 0.01, max 1.0")
    n = int(round(max_cy_per_px / step_cy_per_px))
    return np.round(np.arange(n + 1) * step_cy_per_px, 10)


def classify_orientation(x_px: float, y_px: float, angle_deg: float, centre_px: tuple[float, float]
                         ) -> tuple[str, float]:
    """("tangential" | "sagittal", radial angle in degrees).

    The radial angle is between the edge *normal* and the radius from the optical centre, in [0, 90]: 0 is a
    tangential edge (it lies along the circle about the centre; its normal is radial, so it measures the
    tangential/meridional MTF), 90 a sagittal edge (it lies along the radius). Below 45 is tangential.
    """
    rx, ry = x_px - centre_px[0], y_px - centre_px[1]
    if rx == 0 and ry == 0:
        return "tangential", math.nan
    radial = math.degrees(math.atan2(ry, rx))
    normal = angle_deg + 90.0
    phi = abs((normal - radial + 90.0) % 180.0 - 90.0)
    return ("tangential" if phi < 45.0 else "sagittal"), phi


@dataclass
class MtfResult:
    """A ``fieldcal-mtf/1`` document in memory: one frequency grid, one record per edge, channel and frame."""

    frequencies_cy_per_px: np.ndarray
    edges: list[dict]
    provenance: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        from ..formats.atomic import jsonable
        return jsonable({"format": FORMAT, "frequencies_cy_per_px": self.frequencies_cy_per_px,
                         "edges": self.edges, "provenance": self.provenance})

    def save(self, path) -> Path:
        """Write atomically as JSON."""
        from ..formats import documents
        path = Path(path)
        documents.write(path, self.to_dict(), "mtf", indent=None)
        return path

    @classmethod
    def load(cls, path) -> "MtfResult":
        from ..formats import documents
        path = Path(path)
        d = documents.read(path, "mtf")  # validated here: not again in from_dict
        return cls._from_valid(d, path)

    @classmethod
    def from_dict(cls, d: dict, path=None) -> "MtfResult":
        from ..formats import documents
        documents.validate(d, "mtf", path)  # the schema checks types; the grid length is checked here
        return cls._from_valid(d, path)

    @classmethod
    def _from_valid(cls, d: dict, path=None) -> MtfResult:
        f = np.asarray(d["frequencies_cy_per_px"], dtype=np.float64)
        for i, e in enumerate(d["edges"]):
            if len(e.get("mtf", [])) != f.size:
                raise SpecError(f"has {len(e.get('mtf', []))} values on a grid of {f.size}", path=path,
                                field=f"edges[{i}].mtf", fix="re-run `fieldcal mtf`")
        return cls(f, list(d["edges"]), dict(d.get("provenance", {})))

    # ---------------------------------------------------------------------------------------- queries
    def mtf_at(self, fs_cy_per_px: float) -> np.ndarray:
        """MTF of every edge record at one frequency (linear interpolation on the grid; None -> NaN)."""
        rows = [e["mtf"] for e in self.edges]
        if rows and all(isinstance(r, np.ndarray) for r in rows):  # in memory (measure_mtf): no None to map
            m = np.stack(rows).astype(np.float64, copy=False)
        else:
            m = np.array([[np.nan if v is None else v for v in r] for r in rows], dtype=np.float64)
        if m.size == 0:
            return np.zeros(0)
        return np.array([np.interp(fs_cy_per_px, self.frequencies_cy_per_px, row) for row in m])

    def column(self, key: str) -> np.ndarray:
        return np.array([e.get(key) for e in self.edges])


def _plane_stack(frame: np.ndarray, channels: tuple[str, ...], cfa: str | None):
    """(H' x W' x K float32 planes, per-plane (channel, plane label, stride, offset_x, offset_y))."""
    if cfa is None:
        a = frame if frame.ndim == 3 else frame[:, :, None]
        if a.shape[2] != len(channels):
            raise ParameterError(f"frame has {a.shape[2]} channels but {len(channels)} names were given "
                                 f"({', '.join(channels)})", field="channels", fix="name each channel once")
        return np.ascontiguousarray(a, dtype=np.float32), [(c, None, 1, 0, 0) for c in channels]
    lays = plane_layouts(channels, cfa)
    planes = [extract_plane(frame, lay) for lay in lays]
    h = min(p.shape[0] for p in planes)
    w = min(p.shape[1] for p in planes)
    info = []
    for lay in lays:
        label = lay.name
        if lay.name == "G":  # the green on the red rows is Gr, on the blue rows Gb
            row = cfa[2 * lay.offset_y: 2 * lay.offset_y + 2]
            label = "Gr" if "R" in row else "Gb"
        info.append((lay.name, label, 2, lay.offset_x, lay.offset_y))
    return np.stack([p[:h, :w] for p in planes], axis=2), info


def measure_frame(frame: np.ndarray, *, channels=("Y",), cfa: str | None = None, centre_px=None,
                  grid: np.ndarray | None = None, frame_index: int = 0, z_um: float | None = None,
                  detect: dict | None = None, esfr: dict | None = None) -> tuple[list[dict], list[tuple]]:
    """Slanted-edge MTF of every edge in one normalised frame (H x W x C, or H x W mosaic with ``cfa``).

    Returns the edge records of ``fieldcal-mtf/1`` (one per edge and plane) and, per detected edge, its
    ``(x_px, y_px, angle_deg)`` in full-frame pixels (for tracking).
    """
    frame = np.asarray(frame)
    channels = tuple(channels)
    grid = default_grid() if grid is None else np.asarray(grid, dtype=np.float64)
    planes, info = _plane_stack(frame, channels, cfa)
    H, W = frame.shape[:2]
    if centre_px is None:
        centre_px = ((W - 1) / 2.0, (H - 1) / 2.0)
    cands = find_edges(channel_mean(planes), **(detect or {}))
    esfr = dict(esfr or {})
    if cfa is not None:  # a plane pixel is 2 sensor pixels: 8 bins per plane pixel keep 1/4-sensor-pixel bins
        esfr.setdefault("oversample", 8)
    records, detections = [], []
    # every edge of the frame in one batched e-SFR pass
    results = esfr_regions([planes[c.roi[0]:c.roi[1], c.roi[2]:c.roi[3], :] for c in cands],
                           vertical=[c.vertical for c in cands], line_init=[c.line_init for c in cands],
                           half_width_px=[c.half_width_px for c in cands], **esfr) if cands else []
    for ci, (cand, res) in enumerate(zip(cands, results)):
        y0, y1, x0, x1 = cand.roi
        det = None
        # Python floats of the per-plane values once (the same values as indexing NumPy scalars, faster)
        xms, yms, angs, f50s = res.x_mid.tolist(), res.y_mid.tolist(), res.angle_deg.tolist(), \
            res.mtf50_cy_per_px.tolist()
        for k, (ch, label, stride, ox, oy) in enumerate(info):
            q = res.quality[k]
            xm, ym = xms[k], yms[k]
            if not math.isfinite(xm):  # no edge in this plane: report the detection's position
                xm, ym = cand.x_px - x0, cand.y_px - y0
            xf, yf = stride * (x0 + xm) + ox, stride * (y0 + ym) + oy
            ang = angs[k] if math.isfinite(angs[k]) else cand.angle_deg
            orient, phi = classify_orientation(xf, yf, ang, centre_px)
            # 5 decimals: far below the measurement noise, and the file is half the size
            m = np.round(np.interp(grid * stride, res.freq_cy_per_px, res.mtf[k], right=np.nan), 5)
            qd = q.to_dict()
            for key in ("half_width_px", "rise_px", "edge_rms_px"):
                qd[key] = qd[key] * stride
            r_px = math.hypot(xf - centre_px[0], yf - centre_px[1])
            qd["radial_angle_deg"] = phi
            qd["orientation_clear"] = bool(np.isfinite(phi) and abs(phi - 45.0) >= 15.0 and
                                           r_px >= 0.05 * math.hypot(W, H) / 2)
            qd["roi"] = [int(v) for v in cand.roi]
            records.append({"frame": int(frame_index), "z_um": None if z_um is None else float(z_um),
                            "edge": ci, "channel": ch, "plane": label, "x_px": xf, "y_px": yf, "angle_deg": ang,
                            "orientation": orient, "mtf": m, "mtf50_cy_per_px": f50s[k] / stride,
                            "quality": qd})
            if det is None:
                det = (xf, yf, ang, stride * float(cand.length_px))
        detections.append(det)
    return records, detections


def _read_single(path: Path) -> tuple[np.ndarray, tuple[str, ...]]:
    from ..formats.imageio import ImageFileError, check_finite, read_image
    try:
        img = read_image(path)
        check_finite(img)
    except FileNotFoundError:
        raise ParameterError("not found", path=path, fix="give an image file or a stack folder") from None
    except ImageFileError as exc:
        raise ParameterError(exc.what, path=path, fix=exc.fix) from None
    if img.dtype.kind == "u":
        img = img.astype(np.float32) / float(np.iinfo(img.dtype).max)
    img = np.asarray(img, dtype=np.float32)
    if img.ndim == 2:
        img = img[:, :, None]
    if img.shape[2] == 4:
        img = img[:, :, :3]
    names = ("R", "G", "B") if img.shape[2] == 3 else tuple(f"C{i}" for i in range(img.shape[2])) \
        if img.shape[2] > 1 else ("Y",)
    return img, names


def measure_mtf(source, *, channels=None, cfa: str | None = None, centre_px=None,
                grid_max_cy_per_px: float = 1.0, grid_step_cy_per_px: float = 0.01,
                max_shift_px: float = 6.0, detect: dict | None = None, esfr: dict | None = None,
                quiet: bool = True) -> MtfResult:
    """Slanted-edge (ISO 12233 e-SFR) MTF of every edge in an image or through a focal stack.

    Parameters
    ----------
    source : path, Stack, ArrayStack or array
        An image file (PNG/TIFF), a ``fieldcal-stack/1`` folder, an opened stack, or one frame as an array
        (float, normalised to [0, 1]; H x W, H x W x C, or an H x W mosaic with ``cfa``).
    channels : names of the array's channels (arrays only; default R, G, B for 3 channels, else Y).
    cfa : Bayer pattern of a raw mosaic array or image ("RGGB", ...); stacks carry their own.
    centre_px : (x, y) optical centre for the tangential/sagittal split; default the frame centre.
    grid_max_cy_per_px, grid_step_cy_per_px : the stored frequency grid (cycles per sensor pixel).
    max_shift_px : largest frame-to-frame movement of an edge for it to stay one track.
    detect, esfr : options of :func:`fieldcal.measure.esfr_detect.find_edges` and
        :func:`fieldcal.measure.esfr.esfr_vertical`.

    Returns
    -------
    MtfResult
        ``edges`` records: frame, z_um, track, edge, channel, plane, x_px, y_px, angle_deg, orientation, mtf,
        mtf50_cy_per_px, quality.
    """
    from ..formats.stack import Stack
    from ..progress import progress

    grid = default_grid(grid_max_cy_per_px, grid_step_cy_per_px)
    prov = {"software": _software(), "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "method": "ISO 12233:2017 e-SFR (4x oversampled ESF, Hamming window, derivative and binning "
                      "corrections)", "detect": detect or {}, "esfr": esfr or {}}
    frames: list[tuple[int, float | None, np.ndarray]] | None = None
    stack = None
    if isinstance(source, (str, Path)):
        p = Path(source)
        if p.is_dir():
            if cfa is not None:  # never ignore a flag
                raise ParameterError(f"cfa {cfa!r} is given for a stack, which records its own CFA pattern",
                                     path=p, field="cfa", fix="drop --cfa for a stack (set 'cfa' in its "
                                                                 "stack.json if its frames are mosaics)")
            stack = Stack.open(p)
        else:
            img, names = _read_single(p)
            if cfa is not None and img.shape[2] != 1:
                raise ParameterError(f"cfa {cfa!r} is given for an image with {img.shape[2]} channels; a raw "
                                     "Bayer mosaic has one", path=p, field="cfa",
                                     fix="drop --cfa for a demosaiced (colour) image, or give the raw mosaic")
            if cfa is not None:
                img = img[:, :, 0]
                names = ("R", "G", "B")
            frames = [(0, None, img)]
            channels = tuple(channels or names)
        prov["source"] = str(p)
    elif isinstance(source, np.ndarray):
        a = np.asarray(source, dtype=np.float32)
        if not np.isfinite(a).all():
            raise ParameterError("the image holds NaN or infinite values", field="source",
                                 fix="replace non-finite pixels before measuring")
        if channels is None:
            channels = ("R", "G", "B") if (cfa is not None or (a.ndim == 3 and a.shape[2] == 3)) else \
                tuple("Y" if a.ndim == 2 or a.shape[2] == 1 else f"C{i}" for i in range(1 if a.ndim == 2
                                                                                        else a.shape[2]))
        frames = [(0, None, a)]
        prov["source"] = "array"
    else:
        stack = source
    if stack is not None:
        channels = tuple(stack.channels)
        cfa = getattr(stack, "cfa", None)
        prov["source"] = str(getattr(stack, "path", "stack"))
        prov["pixel_pitch_um"] = getattr(stack, "pixel_pitch_um", None)
    if centre_px is not None:
        centre_px = (float(centre_px[0]), float(centre_px[1]))
    prov.update({"channels": list(channels), "cfa": cfa, "centre_px": centre_px})

    records: list[dict] = []
    dets: list[tuple] = []
    det_frame: list[int] = []
    det_z: list[float] = []

    def measure(i, z, frame):
        return measure_frame(frame, channels=channels, cfa=cfa, centre_px=centre_px, grid=grid, frame_index=i,
                             z_um=z, detect=detect, esfr=esfr)

    def run(i, z, frame):
        add(i, z, *measure(i, z, frame))

    def add(i, z, recs, d):
        base = len(dets)
        for r in recs:
            r["_det"] = base + r["edge"]
        records.extend(recs)
        dets.extend(d)
        det_frame.extend([i] * len(d))
        det_z.extend([0.0 if z is None else z] * len(d))

    if stack is not None:
        if len(stack) == 0:
            raise FieldcalError("the stack has no frames", path=getattr(stack, "path", None), field="frames",
                                fix="capture or simulate frames first")
        order = [int(k) for k in stack.order_by_z]

        def read_and_measure(k):
            z = float(stack.frames[k].z_um) if hasattr(stack, "frames") else float(stack.z_um[k])
            return (k, z) + measure(k, z, stack.read_normalized(k))

        workers = max(1, min(len(order), os.cpu_count() or 1, 2))
        h, w = stack.shape
        from . import esfr_pool
        if (workers > 1 and type(stack) is Stack and len(order) >= PROCESS_MIN_FRAMES and
                len(order) * h * w >= PROCESS_MIN_MPX * 1e6 and esfr_pool.processes_allowed()):
            # two processes: the e-SFR core holds the GIL, so two threads give ~1.2-1.4x, two processes ~1.9x
            # (fieldcal/measure/esfr_pool.py); each reads its frames from the folder
            options = {"channels": channels, "cfa": cfa, "centre_px": centre_px, "grid": grid, "detect": detect,
                       "esfr": esfr}
            pooled = _measure_in_processes(stack, order, workers, options, add, quiet)
        else:
            pooled = False
        if not pooled:
            # a small job (or an in-memory stack): two threads (decoding, NumPy's array passes and OpenCV
            # release the GIL), each holding one frame; results are added in z order, so tracks and records
            # are as from one thread
            with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="fieldcal-esfr") as pool:
                futures = [pool.submit(read_and_measure, k) for k in order]
                it = futures if quiet else progress(futures, total=len(order), desc="e-SFR", unit="frame")
                try:
                    for fut in it:
                        add(*fut.result())
                except BaseException:  # a bad frame (or Ctrl-C): do not measure the rest before saying so
                    for fut in futures:
                        fut.cancel()
                    raise
        if centre_px is None:
            h, w = stack.shape
            prov["centre_px"] = [(w - 1) / 2.0, (h - 1) / 2.0]
    else:
        for i, z, frame in frames:
            run(i, z, frame)
        if centre_px is None:
            h, w = frames[0][2].shape[:2]
            prov["centre_px"] = [(w - 1) / 2.0, (h - 1) / 2.0]
    if dets:
        # imported here, not at the top: the e-SFR workers (esfr_pool) never need scipy
        from .esfr_focus import link_tracks
        tr = link_tracks(np.asarray(det_frame), np.array([d[0] for d in dets]), np.array([d[1] for d in dets]),
                         np.array([d[2] for d in dets]), np.asarray(det_z), max_shift_px=max_shift_px,
                         length_px=np.array([d[3] for d in dets]))
        for r in records:
            r["track"] = int(tr[r.pop("_det")])
    return MtfResult(grid, records, prov)


#: a stack's frames are measured in worker processes (not threads) from this many frames and megapixels in all
#: (:func:`_measure_in_processes`). The e-SFR costs ~0.27 s CPU per Mpx of a chart frame (0.55 s a 1080p frame);
#: two threads run it ~1.2-1.4x faster than one, two processes ~1.9x, whose start-up costs ~0.25 s CPU of imports per
#: worker and ~0.5-0.8 s wall to the first frame: processes pay from ~3 s of e-SFR CPU (~11 Mpx); 16 Mpx and 8
#: frames (eight 1080p frames) keep a margin
PROCESS_MIN_FRAMES = 8
PROCESS_MIN_MPX = 16.0


def _measure_in_processes(stack, order: list[int], workers: int, options: dict, add, quiet: bool) -> bool:
    """Measure ``stack``'s frames (indices ``order``, by z) in ``workers`` processes, each reading its frames from
    the stack folder; ``add`` takes each frame's result in ``order``, as the threads' path does. False (nothing
    measured) when this system cannot make a process pool.

    A frame's FieldcalError reaches the caller as it would from the thread path (its traceback in the worker is
    dropped); an error or Ctrl-C cancels the frames not started and waits for the running ones (each well under
    a second), so no worker process is left behind."""
    from concurrent.futures.process import BrokenProcessPool

    from ..errors import ResourceError
    from ..progress import progress
    from . import esfr_pool

    expect = [(f.file, float(f.z_um)) for f in stack.frames]
    # the absolute path: a forkserver may have started in another working directory
    with esfr_pool.process_pool(workers, esfr_pool.init_worker,
                                (os.path.abspath(stack.path), expect, options)) as pool:
        if pool is None:  # no process pool on this system: the threads instead
            return False
        futures = [pool.submit(esfr_pool.measure_index, k) for k in order]
        it = futures if quiet else progress(futures, total=len(order), desc="e-SFR", unit="frame")
        for fut in it:
            try:
                result = fut.result()
            except FieldcalError as exc:
                raise exc from None  # the worker's own traceback says nothing the message does not
            except BrokenProcessPool:
                raise ResourceError("an e-SFR worker process ended abruptly (killed, or out of memory)",
                                    path=stack.path, fix="free memory and run the command again") from None
            add(*result)
    return True


def _software() -> str:
    from .. import __version__
    return f"fieldcal {__version__}"
