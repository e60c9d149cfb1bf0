"""Robustness of compositing without a profile on real frames with known perturbations (issue 15).

The real circuit-board stack (``../shared/data/real-stacks/pcb-depthmap/``, 10 JPEG frames 2048x1536, see
:mod:`bench_real_stack`) is changed in ways real stacks differ from it, each by a KNOWN transform, and every
variant goes through ``fieldcal import`` + ``fieldcal composite`` (no profile), as a user would run them:

* breathing: magnification ramps of 5 % over the stack (about the centre, and with a rail drift);
* handheld: every frame rotated (up to ±1°), shifted (up to ±16 px) and scaled (±0.5 %) at random;
* flicker: exposure (±10 %) and white balance (±4 % per channel) gains and black offsets (±3 DN) per frame;
* reverse order: the files named far-to-near (and, apart, a negative ``--z`` step);
* EXIF orientation: every frame tagged portrait (6), and tags flipping between 1, 6 and 8 frame to frame (a
  camera looking straight down); a portrait stack whose pixels are rotated by 90°;
* 16-bit TIFF frames; frames upsampled to 24 MP (JPEG), 10 frames; and 30 frames of 24 MP with breathing and
  drift, for time and memory;
* bad inputs, which must end in a FieldcalError (exit 2, a message naming the file or field), not a traceback.

**How the perturbed frames are made.** Geometric perturbations are applied to the full-resolution frames
(Lanczos-4); the central 1792x1280 is kept (every pixel shows recorded scene, not the edge pixels a warp repeats
where the frame was left) and area-downsampled 2x (896x640), and so are the unperturbed frames: the resampling
the perturbation adds is then far finer than the frames' pixels, so what the benchmark measures is the
registration and compositing, not its own interpolation blur. The frame nearest the middle of the z range
(fieldcal's reference, ``--z-ref-um`` given) is left unperturbed in geometry, so each composite is in the
unperturbed composite's geometry (the portrait stack is rotated back exactly). The 24 MP cases upsample the
2048x1536 frames (Lanczos-4) to 5657x4243; their composites are area-downsampled back to 2048x1536 and compared
with the composite of the original JPEGs passed through the same upsampling and back (which alone keeps 0.8 of
the mean squared Laplacian).

**Figures.**

* registration error (px of the perturbed frames): fieldcal's map for each frame (reference px -> frame px,
  :func:`fieldcal.composite.register.choose_model`, the code ``composite`` runs) against the expected map
  ``A_k M_k A_ref^-1``, where ``M_k`` is fieldcal's map on the unperturbed stack, fitted with the model chosen
  for the perturbed one, and ``A_k`` the known perturbation of frame k: RMS and maximum over a 17x13 grid over
  the frame and over all frames. (The real stack's own motion between frames is in ``M_k``; what is measured is
  whether the added transform is found. The unperturbed stack chooses scale and shift per frame; its own small
  roll, within that choice's 0.5 px tolerance, would otherwise count as the error of a case that fits a
  similarity.) The scene has depth, and a scene with depth breathes by different amounts at different depths:
  no global map fits it exactly, and which parts a frame shows (a perturbation changes that at the borders)
  moves the best one. The reference rows give that ambiguity (:func:`model_ambiguity`: a neighbour pair fitted
  on the top or bottom half alone against the whole frame).
* sharpness ratio: mean squared Laplacian (:func:`bench_real_stack.msl`, 96 px border left out) of the
  composite over that of the unperturbed composite.
* difference: PSNR (dB, grey 0-255) of the composite against the unperturbed composite, inside the border.
* halo width at depth edges: depth edges are where the per-pixel sharpest frame of the unperturbed frames
  (local energy of the Laplacian, Gaussian sigma 3 px, median 9x9) changes by 2 frames or more within 3 px, in
  textured places; the mean absolute grey difference between the composite and the unperturbed composite is
  taken in 1-px rings of distance from those edges; the halo width is the largest distance (0-24 px) at which
  the ring's mean exceeds twice the mean 24-48 px from any depth edge ("far diff"), and that mean by 0.5 DN at
  least (0: no ring does; the ring next to the edge counts as 1 px). A ghost (a doubled edge from a
  misregistered frame) or a halo shows as a ring of excess difference next to depth edges.
* time: wall clock of ``fieldcal composite`` and peak RSS (``/usr/bin/time -v``), and of ``fieldcal import``.

``--write`` puts the table into docs/benchmarks.md (section ``real_robustness``). ``--cases a,b`` runs some
cases only; ``--no-large`` leaves out the 24 MP cases (several minutes and ~8 GB of temporary files);
``--merge A.json B.json`` makes the tables from earlier runs' ``results.json`` (``--keep DIR`` keeps them), the
later file's row winning for a case in both.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import tifffile

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO, md_table, write_docs_section  # noqa: E402
from bench_real_stack import DEFAULT_STACK, grey, msl  # noqa: E402

Z_STEP_UM = 50.0
PITCH_UM = 1.12
REF = 5  # the frame nearest the middle of the z range of 10 (fieldcal's default reference: index n // 2)
SEED = 15
BORDER = 96


# ----------------------------------------------------------------------------------------- transforms
def similarity(scale: float = 1.0, angle_deg: float = 0.0, shift=(0.0, 0.0), centre=(0.0, 0.0)) -> np.ndarray:
    """3x3 map of a point p to ``c + s R (p - c) + t``."""
    a = np.deg2rad(angle_deg)
    r = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    c = np.asarray(centre, dtype=np.float64)
    m = np.eye(3)
    m[:2, :2] = r
    m[:2, 2] = c - r @ c + np.asarray(shift, dtype=np.float64)
    return m


def half_to_full(f: int = 2) -> np.ndarray:
    """Area downsampling by ``f``: pixel i of the small image is centred on ``f i + (f - 1) / 2`` of the large."""
    return np.array([[f, 0, (f - 1) / 2], [0, f, (f - 1) / 2], [0, 0, 1.0]])


def warp(img: np.ndarray, m: np.ndarray, size=None) -> np.ndarray:
    """``img`` moved by ``m`` (source px -> output px), Lanczos-4, edges repeated."""
    h, w = img.shape[:2]
    size = size or (w, h)
    return cv2.warpAffine(img, m[:2], size, flags=cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REPLICATE)


def area_half(img: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    return cv2.resize(img, (w // 2, h // 2), interpolation=cv2.INTER_AREA)


def apply(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = pts @ m[:2, :2].T + m[:2, 2]
    d = pts @ m[2, :2] + m[2, 2]
    return q / d[:, None]


# ------------------------------------------------------------------------------------------------ cases
@dataclass
class Case:
    """A perturbed stack: frames in file order, each from original frame ``orig[k]`` moved by ``A[k]``
    (original px -> written px, both at ``base`` resolution)."""

    name: str
    what: str
    frames: list = field(default_factory=list)
    orig: list = field(default_factory=list)
    A: list = field(default_factory=list)
    fmt: str = "png"  # png | jpg | tiff16
    exif_orientation: list | None = None
    z: tuple = (0.0, Z_STEP_UM)
    base: str = "half"  # half: 1024x768; full: 2048x1536 (24 MP cases: compared after area downsampling)
    rotate_back: int = 0  # np.rot90 turns to bring the composite into the unperturbed geometry
    pitch_um: float = 2 * PITCH_UM

    def z_of(self, k: int) -> float:
        return self.z[0] + k * self.z[1]

    kref: int | None = None  # the reference frame's file index (default: the first from frame REF)

    @property
    def ref_index(self) -> int:
        return self.orig.index(REF) if self.kref is None else self.kref

    @property
    def z_ref(self) -> float:
        return self.z_of(self.ref_index)


CASE_NAMES = ["unperturbed", "breathing 5 %", "breathing 5 % + drift", "handheld", "flicker", "reverse order",
              "negative z step", "JPEG", "EXIF portrait tag", "EXIF tags flipping", "portrait pixels", "16-bit TIFF",
              "24 MP", "30 x 24 MP"]


def shift_matrix(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])


#: The 1024 px cases are a central crop of the full frames, 128 px in from every edge (then halved): every
#: perturbed pixel shows recorded scene, not the repeated edge pixels a warp puts where the frame was left.
CROP_PX = 128


def crop(img: np.ndarray) -> np.ndarray:
    return img[CROP_PX:-CROP_PX, CROP_PX:-CROP_PX]


def geometric(name, what, full, mats_full, **kw) -> Case:
    """Frames moved by full-resolution maps ``mats_full[k]``, cropped and area-downsampled (maps in half px)."""
    s = shift_matrix(CROP_PX, CROP_PX) @ half_to_full()  # half px -> full px
    c = Case(name, what, **kw)
    for k, (img, m) in enumerate(zip(full, mats_full)):
        c.frames.append(area_half(crop(warp(img, m))))
        c.orig.append(k)
        c.A.append(np.linalg.inv(s) @ m @ s)
    return c


def make_cases(full: list[np.ndarray], large: bool, only_names: bool = False) -> list[Case]:
    """The perturbed stacks (``only_names``: their names and descriptions only, no frames made)."""
    if only_names:
        return [Case(n, "") for n in CASE_NAMES[:None if large else -2]]
    rng = np.random.default_rng(SEED)
    n = len(full)
    h, w = full[0].shape[:2]
    centre = ((w - 1) / 2, (h - 1) / 2)
    half = [area_half(crop(f)) for f in full]
    cases = []

    c = Case("unperturbed", "the frames as they are (central 1792x1280, area-downsampled 2x, PNG)")
    c.frames, c.orig, c.A = list(half), list(range(n)), [np.eye(3)] * n
    cases.append(c)

    ramp = [1.0 + 0.05 * (k - REF) / (n - 1) for k in range(n)]
    cases.append(geometric("breathing 5 %", "magnification 0.972-1.022 about the centre, linear in z",
                           full, [similarity(s, centre=centre) for s in ramp]))
    cases.append(geometric("breathing 5 % + drift", "as above and a rail drift of (6, -4) px a frame",
                           full, [similarity(s, shift=(6.0 * (k - REF), -4.0 * (k - REF)), centre=centre)
                                  for k, s in enumerate(ramp)]))
    mats = []
    for k in range(n):
        if k == REF:
            mats.append(np.eye(3))
            continue
        mats.append(similarity(1.0 + rng.uniform(-0.005, 0.005), rng.uniform(-1.0, 1.0), rng.uniform(-16, 16, 2),
                               centre=centre))
    cases.append(geometric("handheld", "each frame rotated up to ±1°, shifted up to ±16 px, scaled ±0.5 % "
                                       "(random)", full, mats))

    c = Case("flicker", "per frame: exposure gain 0.9-1.1, white balance ±4 % per channel, offset ±3 DN")
    for k, img in enumerate(half):
        gain = rng.uniform(0.9, 1.1) * (1.0 + rng.uniform(-0.04, 0.04, 3))
        off = rng.uniform(-3.0, 3.0)
        if k == REF:
            gain, off = np.ones(3), 0.0
        c.frames.append(np.clip(np.rint(img.astype(np.float32) * gain[None, None, ::-1].astype(np.float32) + off),
                                0, 255).astype(np.uint8))
    c.orig, c.A = list(range(n)), [np.eye(3)] * n
    cases.append(c)

    c = Case("reverse order", "files named far-to-near (--z 0 50: z ascending over the reversed files)")
    c.frames, c.orig, c.A = half[::-1], list(range(n))[::-1], [np.eye(3)] * n
    cases.append(c)
    c = Case("negative z step", "natural order, --z 450 -50")
    c.frames, c.orig, c.A, c.z = list(half), list(range(n)), [np.eye(3)] * n, ((n - 1) * Z_STEP_UM, -Z_STEP_UM)
    cases.append(c)

    c = Case("JPEG", "the unperturbed frames as JPEG (quality 95): the reference of the two EXIF cases",
             fmt="jpg")
    c.frames, c.orig, c.A = list(half), list(range(n)), [np.eye(3)] * n
    cases.append(c)
    c = Case("EXIF portrait tag", "JPEG q95, every frame tagged Orientation 6 (pixels unchanged)", fmt="jpg",
             exif_orientation=[6] * n)
    c.frames, c.orig, c.A = list(half), list(range(n)), [np.eye(3)] * n
    cases.append(c)
    c = Case("EXIF tags flipping", "JPEG q95, Orientation 1, 6, 8 in turn (camera looking down)", fmt="jpg",
             exif_orientation=[(1, 6, 8)[k % 3] for k in range(n)])
    c.frames, c.orig, c.A = list(half), list(range(n)), [np.eye(3)] * n
    cases.append(c)

    ww = half[0].shape[1]
    rot = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, ww - 1.0], [0.0, 0.0, 1.0]])  # np.rot90 (counter-clockwise)
    c = Case("portrait pixels", "every frame's pixels rotated 90° (640x896)", rotate_back=-1)
    c.frames, c.orig, c.A = [np.ascontiguousarray(np.rot90(f)) for f in half], list(range(n)), [rot] * n
    cases.append(c)

    c = Case("16-bit TIFF", "the frames as 16-bit RGB TIFF (downsampled in float, not rounded to 8 bits)",
             fmt="tiff16")
    c.frames = [np.clip(np.rint(area_half(crop(f).astype(np.float32)) * 257.0), 0, 65535).astype(np.uint16)
                for f in full]
    c.orig, c.A = list(range(n)), [np.eye(3)] * n
    cases.append(c)

    if large:
        size = (5657, 4243)  # 24 MP, the whole 2048 x 1536 frame upsampled (no edge to repeat)
        up = size[0] / w
        m_up = np.array([[up, 0, (up - 1) / 2], [0, up, (up - 1) / 2], [0, 0, 1.0]])  # 2048 px -> 24 MP px
        c = Case("24 MP", "10 frames upsampled to 5657x4243 (JPEG q95)", fmt="jpg", base="full",
                 pitch_um=PITCH_UM / up)
        c.lazy = [(f, m_up, size) for f in full]
        c.orig, c.A = list(range(n)), [m_up] * n
        cases.append(c)
        c = Case("30 x 24 MP", "30 frames of 5657x4243 (each frame 3 times, in z order), drift (0.4, -0.3) px a "
                               "frame", fmt="jpg", base="full", pitch_um=PITCH_UM / up, kref=3 * REF + 1)
        c.lazy, c.orig, c.A = [], [], []
        n3 = 3 * n
        for j in range(n3):
            d = j - 3 * REF - 1  # the middle copy of the reference frame is left alone
            m = shift_matrix(0.4 * d, -0.3 * d) @ m_up
            c.lazy.append((full[j // 3], m, size))
            c.orig.append(j // 3)
            c.A.append(m)
        c.z = (0.0, Z_STEP_UM / 3)
        cases.append(c)
    return cases


# ---------------------------------------------------------------------------------------------- writing
def write_frames(case: Case, folder: Path) -> None:
    from PIL import Image

    folder.mkdir(parents=True)
    frames = case.frames if case.frames else None
    n = len(case.orig)
    for k in range(n):
        if frames is not None:
            img = frames[k]
        else:
            src, m, size = case.lazy[k]
            img = warp(src, m, size)
        name = folder / f"frame_{k:03d}"
        if case.fmt == "png":
            cv2.imwrite(str(name.with_suffix(".png")), img)
        elif case.fmt == "tiff16":
            tifffile.imwrite(name.with_suffix(".tif"), img[..., ::-1], photometric="rgb")
        else:
            pil = Image.fromarray(img[..., ::-1])
            exif = Image.Exif()
            if case.exif_orientation is not None:
                exif[0x0112] = int(case.exif_orientation[k])
            pil.save(name.with_suffix(".jpg"), quality=95, exif=exif.tobytes())


def run_timed(cmd: list[str]) -> tuple[float, float, subprocess.CompletedProcess]:
    """Wall (s) and peak RSS (MB) of a command, by ``/usr/bin/time -v``."""
    r = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True)
    wall = rss = float("nan")
    for line in r.stderr.splitlines():
        if "Elapsed (wall clock)" in line:
            parts = line.rsplit(" ", 1)[-1].split(":")
            wall = sum(float(p) * 60 ** i for i, p in enumerate(reversed(parts)))
        if "Maximum resident set size" in line:
            rss = float(line.rsplit(" ", 1)[-1]) / 1024.0
    return wall, rss, r


# -------------------------------------------------------------------------------------------- measuring
def registration_maps(stack_dir: Path, z_ref: float, model: str | None = None) -> tuple[list[np.ndarray], str]:
    """fieldcal's per-frame maps (reference px -> frame px), file order, and the model it chose (``model``: fit
    that one)."""
    from fieldcal.composite.register import MODELS, MatrixGeometry, choose_model, frame_map_matrix
    from fieldcal.formats.stack import Stack

    st = Stack.open(stack_dir, verify=False)
    geo = choose_model(st, z_ref_um=z_ref, quiet=True, models=MODELS if model is None else (model,))
    name = geo.model if isinstance(geo, MatrixGeometry) else "scale-shift"
    return [frame_map_matrix(geo, float(z)) for z in st.z_um], name


def registration_error(case: Case, maps: list[np.ndarray], base_maps: list[np.ndarray], size) -> tuple[float, float]:
    """RMS and max (px) of fieldcal's maps against ``A_k M_k A_ref^-1`` over a 17x13 grid and all frames."""
    w, h = size
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 17), np.linspace(0, h - 1, 13))
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1)
    kref = case.ref_index
    a_ref_inv = np.linalg.inv(case.A[kref])
    errs = []
    for k, (m, o) in enumerate(zip(maps, case.orig)):
        if k == kref:
            continue
        expect = case.A[k] @ base_maps[o] @ a_ref_inv
        errs.append(np.hypot(*(apply(m, pts) - apply(expect, pts)).T))
    e = np.concatenate(errs)
    return float(np.sqrt(np.mean(e * e))), float(e.max())


def model_ambiguity(stack_dir: Path) -> tuple[float, float]:
    """How far a global registration of this 3-D scene is defined at all: per neighbour pair, the scale-and-shift
    fit on the top or the bottom half alone against the whole frame's, the largest outline displacement (px);
    the median and the maximum over the pairs. A scene with depth breathes by different amounts at different
    depths, so which parts a frame shows moves the best global fit."""
    from fieldcal.composite import register as R
    from fieldcal.formats.stack import Stack

    st = Stack.open(stack_dir, verify=False)
    h, w = st.shape[:2]
    factor = R._factor(w, h, 1024)
    planes = [R._grey(R.read_roi(st, int(i), 0, 0, w, h), factor) for i in np.argsort(st.z_um)]
    devs = []
    for a, b in zip(planes[:-1], planes[1:]):
        pair = R.PlanePair(a, b, levels=3)
        whole = R.fit_pair(pair, model="scale-shift")
        for part in ("top", "bottom"):
            m = R.fit_pair(pair, model="scale-shift", init=whole, part=part)
            if whole is not None and m is not None:
                devs.append(R.chain_difference_px(R._to_full(m, factor)[None], R._to_full(whole, factor)[None], w, h))
    return float(np.median(devs)), float(np.max(devs))


def depth_edges(frames: list[np.ndarray]) -> np.ndarray:
    """Distance (px) to the nearest depth edge of the unperturbed frames (see the module docstring)."""
    energies = []
    for f in frames:
        g = grey(f)
        lap = cv2.Laplacian(g, cv2.CV_32F, ksize=3)
        energies.append(cv2.GaussianBlur(lap * lap, (0, 0), 3.0))
    e = np.stack(energies)
    idx = np.argmax(e, axis=0).astype(np.uint8)
    idx = cv2.medianBlur(idx, 9)
    textured = e.max(axis=0) > np.percentile(e.max(axis=0), 40)
    k = np.ones((7, 7), np.uint8)
    spread = cv2.dilate(idx, k).astype(np.int16) - cv2.erode(idx, k).astype(np.int16)
    edges = (spread >= 2) & textured
    return cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2, 5)


def halo_width(img: np.ndarray, ref: np.ndarray, dist: np.ndarray) -> tuple[float, float]:
    """Halo width (px) and the far level (DN), as the module docstring defines them."""
    d = np.abs(grey(img) - grey(ref))
    sl = (slice(BORDER, -BORDER), slice(BORDER, -BORDER))
    d, dist = d[sl], dist[sl]
    far = float(d[(dist >= 24) & (dist < 48)].mean())
    width = 0.0
    for r in range(25):
        ring = (dist >= r) & (dist < r + 1)
        if ring.any() and float(d[ring].mean()) > 2.0 * far:
            width = float(r + 1)
    return width, far


def psnr(img: np.ndarray, ref: np.ndarray) -> float:
    sl = (slice(BORDER, -BORDER), slice(BORDER, -BORDER))
    e = float(np.mean((grey(img)[sl] - grey(ref)[sl]) ** 2))
    return 10 * np.log10(255.0 ** 2 / max(e, 1e-12))


def to_compare(case: Case, img: np.ndarray) -> np.ndarray:
    """The composite in the unperturbed composite's geometry, 8-bit scale."""
    a = img.astype(np.float32)
    if img.dtype == np.uint16:
        a /= 257.0
    if case.rotate_back:
        a = np.ascontiguousarray(np.rot90(a, case.rotate_back))
    if case.base == "full" and case.name != "originals 2048":  # 24 MP: back to 2048 px
        a = cv2.resize(a, (2048, 1536), interpolation=cv2.INTER_AREA)
    elif case.base == "full":  # the 2048 px reference, through the same upsampling and back (its own blur)
        up = cv2.resize(a, (5657, 4243), interpolation=cv2.INTER_LANCZOS4)
        a = cv2.resize(up, (2048, 1536), interpolation=cv2.INTER_AREA)
    return a


# ---------------------------------------------------------------------------------------------------- bad
def bad_inputs(half: list[np.ndarray], work: Path, py: list[str]) -> list[dict]:
    """Inputs a user may give by mistake: each must end in exit 2 with a message, no traceback."""
    rows = []

    def folder(name, frames, edit=None):
        d = work / "bad" / name
        d.mkdir(parents=True)
        for k, f in enumerate(frames):
            cv2.imwrite(str(d / f"f{k:02d}.jpg"), f)
        if edit:
            edit(d)
        return d

    def truncate(d):
        p = d / "f03.jpg"
        p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])

    def text_file(d):
        (d / "f04.jpg").write_text("not an image\n")

    def other_size(d):
        cv2.imwrite(str(d / "f02.jpg"), cv2.resize(half[2], (800, 600)))

    blank = [f.copy() for f in half[:6]]
    blank[3][:] = 0
    noise = [f.copy() for f in half[:6]]
    noise[3] = np.random.default_rng(1).integers(0, 256, noise[3].shape, dtype=np.uint8)
    cases = [("a truncated JPEG frame", folder("truncated", half[:6], truncate), "composite"),
             ("a text file named .jpg", folder("text", half[:6], text_file), "import"),
             ("one frame of another size", folder("size", half[:6], other_size), "import"),
             ("one frame", folder("one", half[:1]), "import"),
             ("one black frame", folder("black", blank), "composite"),
             ("one frame of pure noise (another scene)", folder("noise", noise), "composite")]
    for what, d, stage in cases:
        stack = work / "bad" / (d.name + "_stack")
        wall, rss, r = run_timed([*py, "import", str(d), "--out", str(stack), "--z", "0", "50", "--pixel-pitch-um",
                                  "2.24", "--quiet"])
        where = "import"
        if r.returncode == 0:
            where = "composite"
            wall, rss, r = run_timed([*py, "composite", str(stack), "--out", str(work / "bad" / (d.name + ".tif")),
                                      "--quiet"])
        err = r.stderr
        traceback = "Traceback" in err
        msg = next((ln.strip() for ln in err.splitlines() if ln.startswith("fieldcal") or "error" in ln.lower()), "")
        msg = msg.replace(str(work / "bad") + os.sep, "")
        rows.append({"input": what, "ends at": where, "exit": r.returncode,
                     "clean": "yes" if (r.returncode == 2 and not traceback) or (r.returncode == 0) else "NO",
                     "message": msg[:160].replace("|", "/")})
    return rows


def report(results: list[dict], bad: list[dict], load: float | None, write: bool) -> None:
    """Print the tables (and write them into docs/benchmarks.md with ``write``)."""
    cols = [("case", "case", ""), ("perturbation", "what", ""), ("frames", "frames", "d"), ("model", "model", ""),
            ("registration RMS (px)", "reg RMS (px)", ".3f"), ("max (px)", "reg max (px)", ".3f"),
            ("sharpness / unperturbed", "sharpness ratio", ".3f"), ("PSNR vs unperturbed (dB)",
                                                                    "PSNR vs unperturbed (dB)", ".1f"),
            ("halo width (px)", "halo width (px)", ".0f"), ("far diff (DN)", "far diff (DN)", ".2f"),
            ("composite (s)", "time (s)", ".2f"), ("peak RSS (MB)", "peak RSS (MB)", ".0f"),
            ("import (s)", "import (s)", ".2f"), ("result", "status", ""),
            ("scene's own registration ambiguity, median / max (px)", "ambiguity (px)", "")]
    lines = md_table(results, cols)
    if bad:
        lines += ["", *md_table(bad, [("bad input", "input", ""), ("ends at", "ends at", ""), ("exit", "exit", "d"),
                                      ("clean", "clean", ""), ("message", "message", "")])]
    where = "" if load is None else f"1-minute load average at the start: {load:.1f} (2 cores shared). "
    lines += ["", where + "Command: `python benchmarks/bench_real_robustness.py --write`."]
    text = "\n".join(lines)
    print(text)
    if write:
        write_docs_section("real_robustness", text)


# ----------------------------------------------------------------------------------------------------- main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stack", type=Path, default=DEFAULT_STACK)
    ap.add_argument("--cases", help="comma-separated case names (default all)")
    ap.add_argument("--no-large", action="store_true", help="leave out the 24 MP cases")
    ap.add_argument("--no-bad", action="store_true", help="leave out the bad inputs")
    ap.add_argument("--keep", type=Path, help="keep the work folder here")
    ap.add_argument("--write", action="store_true", help="put the tables into docs/benchmarks.md")
    ap.add_argument("--merge", nargs="+", type=Path, metavar="RESULTS_JSON",
                    help="make the tables from earlier runs' results.json instead of running")
    a = ap.parse_args()
    if a.merge:
        rows, bad = {}, []
        for p in a.merge:
            doc = json.loads(p.read_text())
            doc = doc if isinstance(doc, dict) else {"results": doc, "bad": [], "load": None}
            rows.update({r["case"]: r for r in doc["results"]})
            bad = doc.get("bad") or bad
        order = ["originals 2048"] + [c.name for c in make_cases([np.zeros((1536, 2048, 3), np.uint8)] * 10, True,
                                                                   only_names=True)]
        report(sorted(rows.values(), key=lambda r: order.index(r["case"])), bad, None, a.write)
        return
    jpegs = sorted(a.stack.glob("*.JPG"))
    if len(jpegs) != 10:
        sys.exit(f"{a.stack}: expected the 10 pcb JPEG frames")
    full = [cv2.imread(str(p)) for p in jpegs]  # BGR, as cv2 writes
    work = a.keep or Path(tempfile.mkdtemp(prefix="robust-"))
    work.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": str(REPO), "FIELDCAL_PROGRESS": "0"}
    os.environ.update(env)
    py = [sys.executable, "-m", "fieldcal"]
    wanted = None if not a.cases else {s.strip() for s in a.cases.split(",")}
    cases = make_cases(full, not a.no_large)
    load = os.getloadavg()[0]
    results, base_maps, base_img, base_stack = [], {}, {}, {}
    dist = {"half": depth_edges([area_half(crop(f)) for f in full]), "full": depth_edges(full)}
    # the references each case is compared with: the unperturbed PNG composite at 1024 px, the JPEG one for the
    # EXIF cases, the original JPEGs' at 2048 px for the 24 MP cases
    refs = {"half": "unperturbed", "jpg": "JPEG", "full": "originals 2048"}
    orig_case = Case("originals 2048", "the original JPEG frames, 2048x1536", base="full", pitch_um=PITCH_UM)
    orig_case.orig, orig_case.A = list(range(10)), [np.eye(3)] * 10
    todo = [orig_case] + [c for c in cases if wanted is None or c.name in wanted or c.name in refs.values()]
    for case in todo:
        src = work / re.sub(r"\W+", "_", case.name)
        stack, out = src.with_name(src.name + "_stack"), src.with_name(src.name + ".tiff")
        for p in (src, stack, out):
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
        if case is orig_case:
            src.mkdir()
            for p in jpegs:
                (src / p.name).symlink_to(p)
        else:
            write_frames(case, src)
            case.frames = []  # written: free the memory
        t_imp, rss_imp, r = run_timed([*py, "import", str(src), "--out", str(stack), "--z", str(case.z[0]),
                                       str(case.z[1]), "--pixel-pitch-um", f"{case.pitch_um:.4f}", "--quiet"])
        if r.returncode:
            results.append({"case": case.name, "what": case.what, "status": f"import failed: {r.stderr[-300:]}"})
            print(results[-1], flush=True)
            continue
        t, rss, r = run_timed([*py, "composite", str(stack), "--out", str(out), "--z-ref-um", f"{case.z_ref:g}",
                               "--quiet"])
        row = {"case": case.name, "what": case.what, "frames": len(case.orig), "import (s)": t_imp,
               "time (s)": t, "peak RSS (MB)": rss}
        if r.returncode:
            row["status"] = "composite failed: " + r.stderr.strip().splitlines()[-1][:200]
            results.append(row)
            print(row, flush=True)
            continue
        from fieldcal.composite.io import read_composite_metadata

        meta = read_composite_metadata(out)
        row["model"] = meta.get("registration", {}).get("model")
        img = tifffile.imread(out)
        w, h = img.shape[1], img.shape[0]
        maps, model = registration_maps(stack, case.z_ref)
        key = ("jpg" if case.fmt == "jpg" and case.base == "half" else case.base)
        ref_name = refs[key]
        if case.name == ref_name:
            base_stack[case.name] = (stack, case)
            row["ambiguity (px)"] = "{:.2f} / {:.2f}".format(*model_ambiguity(stack))
            base_img[case.name] = to_compare(case, img)
        if ref_name in base_stack and case.name != ref_name:
            # the reference stack registered with the model chosen here: the real frames' own small roll or
            # shear, below the model check's tolerance there, is not counted as this case's error
            if (ref_name, model) not in base_maps:
                bstack, bcase = base_stack[ref_name]
                bmaps, _ = registration_maps(bstack, bcase.z_ref, model)
                base_maps[(ref_name, model)] = [bmaps[bcase.orig.index(o)] for o in range(10)]
            bm = base_maps[(ref_name, model)]
            rms, mx = registration_error(case, maps, bm, (w, h))
            row["reg RMS (px)"], row["reg max (px)"] = rms, mx
            cmp = to_compare(case, img)
            ref_img = base_img[ref_name]
            row["sharpness ratio"] = msl(cmp) / msl(ref_img)
            row["PSNR vs unperturbed (dB)"] = psnr(cmp, ref_img)
            row["halo width (px)"], row["far diff (DN)"] = halo_width(cmp, ref_img, dist[case.base])
            ok = rms <= 0.5 and row["sharpness ratio"] >= 0.97
            row["status"] = "pass" if ok else "NOT MET"
        else:
            row["status"] = "reference"
        results.append(row)
        print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items() if k != "what"}, flush=True)
        if case.base == "full" and case is not orig_case:
            for p in (src, stack):
                shutil.rmtree(p, ignore_errors=True)
    bad = [] if a.no_bad else bad_inputs([area_half(crop(f)) for f in full], work, py)
    for b in bad:
        print(b, flush=True)
    (work / "results.json").write_text(json.dumps({"results": results, "bad": bad, "load": load}, indent=1,
                                                  default=str))
    report(results, bad, load, a.write)
    if not a.keep:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
