"""A real 3-D focus stack: fieldcal against align_image_stack + enfuse, sharpness and crops side by side.

Uses ``../shared/data/real-stacks/pcb-depthmap/`` beside the checkout (or ``--stack DIR``, or
``$FIELDCAL_SHARED/data/real-stacks/pcb-depthmap``: 10 JPEG frames of a circuit board shot through focus). The
frames are imported with ``fieldcal import`` (the pitch is not in their EXIF; 1.12 µm is given, z is a uniform
step: only the order matters for depth from focus), composited without a profile in the geometry of the first
frame (align_image_stack's reference), and compared with ``align_image_stack -m -a`` + ``enfuse --hard-mask``
(contrast weight only) on the same JPEGs when those tools are installed (``apt-get install enfuse hugin-tools``),
on all frames and on the first 7; and with focus-stack's merge (:mod:`focus_stack_ref`, a re-implementation from
its sources: it cannot be built here) on fieldcal's own registered frames, with its wavelet merge's grey before
the colour reassignment as a row of its own.

Sharpness is the mean squared Laplacian (OpenCV ``Laplacian``, ksize 3, on grey 0-255) with a 96 px border left
out: align_image_stack's frames carry black borders up to ~40 px wide, whose edges would otherwise count as
detail. Also Tenengrad, the pixel noise (Immerkaer, robust: texture in the composite's flat majority raises it
too), the power in radial frequency bands, and the finest octave's energy against the most the composite's own
registered frames hold at each place. Prints the tables and writes crops to the temporary folder (enfuse's
output resampled onto fieldcal's geometry by an affine ECC fit first: align_image_stack's ``-m`` output frame is
not exactly the first frame's); ``--write`` puts the tables into docs/benchmarks.md and the crops into
``docs/img/real-pcb-crops.png``.

Speed: ``fieldcal composite`` in its own process, wall and CPU time (user + system, all threads) and peak RSS,
on all frames and on the first 7 (issue 15: a 7-frame 2048x1536 stack, registration included, in 5 s on 2
cores, 1 GB); a figure 2x slower than the stored table's is flagged (benchmarks/_common.py).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import tifffile

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import flag_slowdowns, slowdown_note  # noqa: E402
from focus_stack_ref import focus_stack  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
# ../shared beside the checkout, or FIELDCAL_SHARED (the folder holding data/), or --stack
_SUB = Path("data") / "real-stacks" / "pcb-depthmap"
DEFAULT_STACK = (Path(os.environ["FIELDCAL_SHARED"]) / _SUB if os.environ.get("FIELDCAL_SHARED")
                 else REPO.parent / "shared" / _SUB)
BORDER = 96


def grey(img: np.ndarray) -> np.ndarray:
    """Grey 0-255 float32 of an RGB image (8 or 16 bit)."""
    img = np.asarray(img)
    a = img[..., :3].astype(np.float32)
    if img.dtype == np.uint16:
        a /= np.float32(257.0)
    return cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)


def msl(img: np.ndarray) -> float:
    """Mean squared Laplacian (ksize 3): weighted towards the highest, diagonal frequencies."""
    lap = cv2.Laplacian(grey(img), cv2.CV_32F, ksize=3)[BORDER:-BORDER, BORDER:-BORDER]
    return float(np.mean(lap.astype(np.float64) ** 2))


def tenengrad(img: np.ndarray) -> float:
    """Mean squared Sobel gradient (Tenengrad): edge contrast, less weight on single-pixel noise than msl."""
    g = grey(img)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    return float(np.mean((gx * gx + gy * gy)[BORDER:-BORDER, BORDER:-BORDER].astype(np.float64)))


def noise_dn(img: np.ndarray) -> float:
    """Pixel noise (grey DN) by Immerkaer's operator with a robust median: the flat majority of the image."""
    from fieldcal.composite.sweep import estimate_noise_sigma

    return estimate_noise_sigma(grey(img)[BORDER:-BORDER, BORDER:-BORDER])


#: radial frequency bands (cycles/px) of the spectrum table; above 0.5 only diagonal frequencies remain
BANDS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.71)


def band_power(img: np.ndarray) -> list[float]:
    """Mean power spectrum (Hann window, grey) in each radial band of :data:`BANDS`."""
    g = grey(img)[BORDER:-BORDER, BORDER:-BORDER].astype(np.float64)
    g -= g.mean()
    g *= np.outer(np.hanning(g.shape[0]), np.hanning(g.shape[1]))
    p = np.abs(np.fft.rfft2(g)) ** 2 / g.size
    fy, fx = np.fft.fftfreq(g.shape[0])[:, None], np.fft.rfftfreq(g.shape[1])[None, :]
    r = np.sqrt(fx * fx + fy * fy)
    return [float(p[(r >= a) & (r < b)].mean()) for a, b in zip(BANDS[:-1], BANDS[1:])]


def finest_octave_energy(g: np.ndarray, box_px: int = 9) -> np.ndarray:
    """Local energy (box mean over ``box_px``) of the finest Laplacian-pyramid octave of a grey image."""
    up = cv2.pyrUp(cv2.pyrDown(g), dstsize=(g.shape[1], g.shape[0]))
    d = g - up
    return cv2.blur(d * d, (box_px, box_px))


def frame_detail_share(img: np.ndarray, frames: list[np.ndarray]) -> tuple[float, float]:
    """A composite's finest-octave energy against the most any of its own (registered) frames holds at each
    place (the per-pixel maximum of their local energies: what choosing frames can reach), and the share of its
    energy above that bound (detail no frame recorded: switching steps, ringing, noise)."""
    e = finest_octave_energy(grey(img))
    bound = np.zeros_like(e)
    for f in frames:
        np.maximum(bound, finest_octave_energy(grey(f)), out=bound)
    sl = (slice(BORDER, -BORDER), slice(BORDER, -BORDER))
    total = max(float(e[sl].sum()), 1e-30)
    return total / max(float(bound[sl].sum()), 1e-30), float(np.maximum(e - bound, 0.0)[sl].sum()) / total


def onto(img: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``img`` (8-bit RGB) resampled onto ``ref``'s geometry by an affine ECC fit of their grey half-size copies:
    align_image_stack's output frame (``-m`` fits the field of view) is not exactly the first frame's, so crops
    at the same coordinates would show different places."""
    a, b = (cv2.resize(grey(v), None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA) for v in (ref, img))
    m = np.eye(2, 3, dtype=np.float32)
    _, m = cv2.findTransformECC(a, b, m, cv2.MOTION_AFFINE,
                                (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6), None, 5)
    m[:, 2] *= 2.0
    return cv2.warpAffine(img, m, (ref.shape[1], ref.shape[0]), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)


def flat_noise(img: np.ndarray, frames: list[np.ndarray], share: float = 0.3) -> tuple[float, float]:
    """Pixel noise (grey DN, as :func:`noise_dn`) where no frame has texture (the ``share`` of pixels with the
    least finest-octave energy in the frame holding the most there), of a composite and of its frames (their
    median, rounded to the composite's 8 bits when it has them) at the same pixels: whether compositing added
    noise, with texture kept out of both figures."""
    bound, covered = None, None
    for f in frames:
        g = grey(f)
        e = finest_octave_energy(g)
        bound = e if bound is None else np.maximum(bound, e)
        c = cv2.erode((g > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # not align_image_stack's black
        covered = c if covered is None else covered & c
    sl = (slice(BORDER, -BORDER), slice(BORDER, -BORDER))
    bound, covered = bound[sl], covered[sl]
    flat = covered & (bound <= np.quantile(bound[covered], share))
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)

    def sigma(a: np.ndarray) -> float:  # Immerkaer's operator, robust, over the flat pixels only
        r = cv2.filter2D(grey(a), -1, k, borderType=cv2.BORDER_REFLECT)[sl]
        return float(np.median(np.abs(r[flat])) / 0.6745 / 6.0)

    def as_written(f: np.ndarray) -> np.ndarray:  # rounding to 8 bits adds 0.29 DN rms to a composite, so to its frames
        return np.clip(np.rint(f), 0, 255).astype(np.uint8) if img.dtype == np.uint8 else f

    return sigma(img), float(np.median([sigma(as_written(f)) for f in frames]))


def depth_edges(frames: list[np.ndarray], window_px: int = 31, jump_frames: int = 2) -> np.ndarray:
    """Pixels near a depth edge, from the frames alone: the sharpest frame per pixel (finest-octave energy over
    ``window_px``, median-filtered), and where it changes by ``jump_frames`` or more within 9 px. The band is as
    wide as the window: it holds the edge's own pixels and those a halo or ringing would reach."""
    e = np.stack([cv2.blur(finest_octave_energy(grey(f)), (window_px, window_px)) for f in frames])
    k = cv2.medianBlur(np.argmax(e, axis=0).astype(np.uint8), 5)
    box = np.ones((9, 9), np.uint8)
    return (cv2.dilate(k, box).astype(int) - cv2.erode(k, box).astype(int)) >= jump_frames


def overshoot(img: np.ndarray, frames: list[np.ndarray], where: np.ndarray) -> tuple[float, float]:
    """Ringing: how far the composite's grey leaves the range every frame records at that place (each frame's
    3 x 3 minimum and maximum, the least and most over the frames), RMS (DN) and the share of pixels more than
    2 DN outside, over ``where``. Choosing and blending frames stays inside; a deconvolution's overshoot, a
    sharpening halo or amplified noise leaves it. (A blurred object's spill onto the background stays inside:
    the crops show that.)"""
    box = np.ones((3, 3), np.uint8)
    lo = hi = None
    for f in frames:
        g = grey(f)
        a, b = cv2.erode(g, box), cv2.dilate(g, box)
        lo = a if lo is None else np.minimum(lo, a)
        hi = b if hi is None else np.maximum(hi, b)
    g = grey(img)
    out = np.maximum(np.maximum(g - hi, lo - g), 0.0)
    sl = (slice(BORDER, -BORDER), slice(BORDER, -BORDER))
    m = where[sl]
    o = out[sl][m]
    return float(np.sqrt(np.mean(o.astype(np.float64) ** 2))) if o.size else float("nan"), \
        float(np.mean(o > 2.0)) if o.size else float("nan")


def save_palette_png(path: Path, rgb: np.ndarray) -> None:
    """An 8-bit RGB figure as a 256-colour PNG (median cut, no dither): the real frames' sensor and JPEG noise makes a
    lossless one of these crops ~1 MB; the palette moves a pixel by ~2 DN on average (measured on the s11 crops:
    mean 1.8, 99th percentile 11) and keeps the figure under 0.5 MB."""
    from PIL import Image

    Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8)).quantize(
        256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(path, optimize=True)


def time_composite(py, stack: Path, out: Path, n: int, extra=()) -> dict:
    """Wall, CPU (user + system of the child) and peak RSS of one ``fieldcal composite`` process."""
    load = os.getloadavg()[0]
    code = ("import resource, subprocess, sys, time; t = time.perf_counter(); "
            "subprocess.run(sys.argv[1:], check=True); w = time.perf_counter() - t; "
            "u = resource.getrusage(resource.RUSAGE_CHILDREN); "
            "print(w, u.ru_utime + u.ru_stime, u.ru_maxrss / 1024)")
    r = subprocess.run([sys.executable, "-c", code, *py, "composite", str(stack), "--out", str(out), "--z-ref-um",
                        "0", "--quiet", *extra], check=True, capture_output=True, text=True)
    wall, cpu, rss = (float(v) for v in r.stdout.split()[-3:])
    return {"run": " ".join(["fieldcal composite", *extra]), "frames": n, "wall (s)": f"{wall:.2f}", "CPU (s)": f"{cpu:.2f}",
            "peak RSS (MB)": f"{rss:.0f}", "load at start": f"{load:.1f}"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stack", type=Path, default=DEFAULT_STACK,
                    help="folder of the JPEG frames (default ../shared/data/real-stacks/pcb-depthmap beside the "
                         "checkout, or $FIELDCAL_SHARED/data/real-stacks/pcb-depthmap)")
    ap.add_argument("--write", action="store_true",
                    help="put the table into docs/benchmarks.md and the crops into docs/img/real-pcb-crops.png")
    ap.add_argument("--tag", default="", help="write into the section bench_real_stack:TAG and the crops into "
                                              "docs/img/real-pcb-crops-TAG.png (default: the untagged ones)")
    a = ap.parse_args()
    STACK = a.stack
    if not STACK.is_dir():
        sys.exit(f"{STACK} not found: give --stack, or set FIELDCAL_SHARED to the folder holding data/")
    work = Path(tempfile.mkdtemp())
    py = [sys.executable, "-m", "fieldcal"]
    jpegs = sorted(STACK.glob("*.JPG"))
    timing = []
    for n in (len(jpegs), 7):
        src = work / f"jpg{n}"
        src.mkdir()
        for p in jpegs[:n]:
            (src / p.name).symlink_to(p)
        subprocess.run([*py, "import", str(src), "--out", str(work / f"pcb{n}"), "--z", "0", "50",
                        "--pixel-pitch-um", "1.12", "--quiet"], check=True)
        timing.append(time_composite(py, work / f"pcb{n}", work / f"fieldcal{n}.tiff", n))
        # the frames chosen per pixel, not combined by the measured defocus's Wiener filter
        timing.append(time_composite(py, work / f"pcb{n}", work / f"none{n}.tiff", n, ("--defocus", "none")))
    t_fc = timing[0]["wall (s)"]
    single = [cv2.imread(str(p))[..., ::-1] for p in jpegs]
    sharpest = int(np.argmax([msl(f) for f in single]))
    # fieldcal's own registered frames (the geometry of its output), to bound what detail its frames hold
    from fieldcal.composite.register import register_stack
    from fieldcal.formats.stack import Stack

    rows = {f"a single frame (the sharpest by msl, {jpegs[sharpest].name})": (single[sharpest], None)}
    ours = enf = fs_ref = none = None
    edges = None
    t_enf = None
    have_enfuse = bool(shutil.which("enfuse") and shutil.which("align_image_stack"))
    for n in (len(jpegs), 7):
        img = tifffile.imread(work / f"fieldcal{n}.tiff")
        held, _ = register_stack(Stack.open(work / f"pcb{n}", verify=False), z_ref_um=0.0, quiet=True)
        regd = [held.read(i) for i in range(n)]
        rows[f"fieldcal, {n} frames"] = (img, regd)
        rows[f"fieldcal --defocus none, {n} frames"] = (tifffile.imread(work / f"none{n}.tiff"), regd)
        if edges is None:
            edges = depth_edges(regd)
            none = rows[f"fieldcal --defocus none, {n} frames"][0]
        del held
        # focus-stack's merge on the same registered frames (benchmarks/focus_stack_ref.py), and its wavelet
        # merge's grey before the colour reassignment
        fs_img, fs_info = focus_stack(regd)
        rows[f"focus-stack (reference re-implementation), {n} frames"] = (fs_img, regd)
        rows[f"focus-stack's wavelet merge before colour reassignment (grey), {n} frames"] = (
            np.repeat(fs_info["grey"][..., None], 3, axis=2), regd)
        if ours is None:
            ours, fs_ref = img, fs_img
        if have_enfuse:
            t0 = time.perf_counter()
            subprocess.run(["align_image_stack", "-m", "-a", str(work / f"al{n}_"), *map(str, jpegs[:n])],
                           check=True, capture_output=True)
            subprocess.run(["enfuse", "--exposure-weight=0", "--saturation-weight=0", "--contrast-weight=1",
                            "--hard-mask", f"--output={work / f'enfuse{n}.tif'}",
                            *map(str, sorted(work.glob(f"al{n}_*.tif")))], check=True, capture_output=True)
            if t_enf is None:
                t_enf = time.perf_counter() - t0
            e = tifffile.imread(work / f"enfuse{n}.tif")[..., :3]
            rows[f"align_image_stack + enfuse --hard-mask, {n} frames"] = (
                e, [tifffile.imread(p)[..., :3] for p in sorted(work.glob(f"al{n}_*.tif"))])
            if enf is None:
                enf = e
    lines = ["| composite | mean squared Laplacian | Tenengrad | noise (grey DN) | noise where no frame has texture: "
             "composite / its frames at its bit depth (DN) | finest octave: energy / most its frames hold at each place | of it "
             "beyond every frame | outside the frames' range at depth edges: RMS DN / > 2 DN | elsewhere |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for k, (img, frames) in rows.items():
        share = ("", "") if frames is None else tuple(f"{100 * v:.1f} %" for v in frame_detail_share(img, frames))
        flat = "" if frames is None else "{:.3f} / {:.3f}".format(*flat_noise(img, frames))
        ring = ("", "") if frames is None or frames[0].shape[:2] != edges.shape else tuple(
            "{:.2f} / {:.2f} %".format(a, 100 * b) for a, b in (overshoot(img, frames, edges),
                                                                 overshoot(img, frames, ~edges)))
        lines.append(f"| {k} | {msl(img):.0f} | {tenengrad(img):.0f} | {noise_dn(img):.3f} | {flat} | {share[0]} | "
                     f"{share[1]} | {ring[0]} | {ring[1]} |")
    lines += ["", "| composite | " + " | ".join(f"{a:g}-{b:g}" for a, b in zip(BANDS[:-1], BANDS[1:])) + " |",
              "|" + " --- |" * len(BANDS)]
    for k, (img, _) in rows.items():
        lines.append(f"| {k} | " + " | ".join(f"{v:.3g}" for v in band_power(img)) + " |")
    lines.append("")
    head = ["run", "frames", "wall (s)", "CPU (s)", "peak RSS (MB)", "load at start"]
    lines += ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    lines += ["| " + " | ".join(str(r[k]) for k in head) + " |" for r in timing]
    if t_enf is not None:
        lines.append(f"| align_image_stack + enfuse | {len(jpegs)} | {t_enf:.1f} | | | |")
    lines += ["", "Wall and CPU time (user + system, all threads) of `fieldcal composite STACK --out OUT "
                  "--z-ref-um 0` in its own process, registration included, 2048x1536 JPEG frames, first N "
                  "frames; peak RSS of that process. The machine is shared: the load average is the 1-minute one."]
    flags = flag_slowdowns("real_stack", "\n".join(lines), ("run", "frames"), ("wall (s)", "CPU (s)"))
    if flags:
        lines += ["", slowdown_note(flags)]
    print(f"fieldcal composite (registration included): {t_fc} s")
    print("\n".join(lines))
    # crops side by side (same geometry: the first frame's), at 1x (a page shows a wider figure scaled down, and
    # zooming in does the 2x): depth edges of the switch against the
    # board and its pads, the silkscreen, fine dust on the switch body
    h, w = ours.shape[:2]
    if enf is not None:
        enf = onto(enf if enf.dtype == np.uint8 else (enf / 257).astype(np.uint8), ours)
    crops = []
    size = 192
    # ... and the left edge, where frames magnified less than the reference hold no pixels (no streaks)
    for (fx, fy) in ((0.576, 0.273), (0.303, 0.651), (0.703, 0.313), (0.508, 0.417), (0.0, 0.45)):
        x, y = int(fx * w), int(fy * h)
        gap = np.full((size, 4, 3), 255, np.uint8)
        row = [fs_ref[y:y + size, x:x + size], gap, none[y:y + size, x:x + size, :3], gap,
               ours[y:y + size, x:x + size, :3]]
        if enf is not None:
            row = [enf[y:y + size, x:x + size], gap] + row
        crops.append(np.concatenate(row, axis=1))
    # the docs' figure only with --write; otherwise beside the run, kept for a look
    name = f"real-pcb-crops-{a.tag}.png" if a.tag else "real-pcb-crops.png"
    out = (REPO / "docs" / "img" if a.write else Path(tempfile.gettempdir())) / name
    save_palette_png(out, np.concatenate(crops, axis=0))
    print(f"crops ({'enfuse | ' if enf is not None else ''}focus-stack reference | fieldcal --defocus none | fieldcal, five regions, 1x, 256 colours): {out}")
    if a.write:
        doc = REPO / "docs" / "benchmarks.md"
        text = doc.read_text(encoding="utf-8")
        tag = f":{a.tag}" if a.tag else ""
        b, e = f"<!-- bench_real_stack{tag}:begin -->", f"<!-- bench_real_stack{tag}:end -->"
        cmd = "python benchmarks/bench_real_stack.py" + (f" --tag {a.tag}" if a.tag else "") + " --write"
        block = "\n".join([b, f"Real circuit-board stack (`{cmd}`; crops: "
                              f"[img/{name}](img/{name}), left to right enfuse (10 frames, brought onto fieldcal's "
                              "geometry), the focus-stack reference on fieldcal's registered frames, fieldcal "
                              "`--defocus none` and fieldcal (10 frames); the last row is the left edge). Depth "
                              "edges: where the sharpest frame (finest-octave energy over 31 px) changes by 2 frames "
                              "or more within 9 px of fieldcal's registered frames:", "",
                           *lines, e])
        if b in text:
            text = text[:text.index(b)] + block + text[text.index(e) + len(e):]
        else:
            base_end = "<!-- bench_real_stack:end -->"
            if base_end in text:
                i = text.index(base_end) + len(base_end)
                text = text[:i] + "\n\n" + block + text[i:]
            else:
                text = text.rstrip() + "\n\n## A real stack with depth\n\n" + block + "\n"
        doc.write_text(text, encoding="utf-8")
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
