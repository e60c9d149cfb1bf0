"""fieldcal against align_image_stack + enfuse and focus-stack on honest variants of a real stack (issue 15).

fieldcal will be judged on real stacks it has not seen: other cameras, 3-60 frames, other resolutions, coarser or
finer focus steps, far-to-near order, exposure changes, handheld motion, noise, other file types. This benchmark
makes such stacks from the real circuit board (``../shared/data/real-stacks/pcb-depthmap/``, 10 JPEG frames,
2048x1536; ``--stack DIR`` or ``$FIELDCAL_SHARED``) by honest transforms only -- subsets, reorderings, area
downscales, crops, a known exposure change in linear light, known small camera motions, added noise, re-encodings
-- and for each runs, on the same frames:

* ``fieldcal import FRAMES --out STACK --z 0 50 --pixel-pitch-um P`` (P = 1.12 um times the downscale) and
  ``fieldcal composite STACK --out O.tiff --z-ref-um 0`` (no profile), each in its own process, in an empty
  working folder and with its own TMPDIR, both checked empty afterwards (nothing written outside ``--out``);
* ``align_image_stack -m -a`` + ``enfuse --hard-mask`` with the contrast weight only, as
  :mod:`bench_real_stack` does;
* focus-stack's merge (:mod:`focus_stack_ref`) on fieldcal's own registered frames.

Figures (grey, a border of 96/2048 of the width left out: align_image_stack's black borders):

* mean squared Laplacian and Tenengrad (:mod:`bench_real_stack`): both reward noise and ringing as much as detail;
* **band 0.05-0.4**: the mean power of the grey image between 0.05 and 0.4 cycles/px (Hann window), i.e. the
  variance of a band-passed copy: detail a viewer sees, with the top of the spectrum, where JPEG and sensor noise
  live, left out (so noise does not win); and the 0.4-0.71 power apart (noise, ringing, aliasing);
* ringing at depth edges: how far each composite leaves the range its own frames record at each place
  (:func:`bench_real_stack.overshoot`; fieldcal and focus-stack against fieldcal's registered frames, enfuse
  against align_image_stack's), RMS DN and the share of pixels > 2 DN outside;
* for the exposure, handheld and noise variants, the PSNR of each tool's composite against the same tool's
  composite of the unchanged frames (an exposure step, a ghost or a seam shows as a loss).

``--variants a,b`` runs some variants only; ``--keep DIR --reuse`` takes the composites an earlier ``--keep DIR``
run left there (figures only); ``--write`` puts the table into docs/benchmarks.md (section
``bench_real_variants_s14``) and the crops into ``docs/img/real-variants-s14-*.png``; ``--keep DIR`` keeps the
frames, stacks and composites. Bad inputs (mixed sizes; a frame swapped for another size after import) must end
in a clear error (exit 2, no traceback).
"""

from __future__ import annotations

import argparse
import json
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
from _common import REPO, write_docs_section  # noqa: E402
from bench_real_stack import DEFAULT_STACK, grey, onto, overshoot, save_palette_png, depth_edges  # noqa: E402
from focus_stack_ref import focus_stack  # noqa: E402

PITCH_UM = 1.12
SECTION = "real_variants_s14"


def checkout_env(**extra) -> dict:
    """The environment of a ``python -m fieldcal`` child: this checkout's package first (the children run in other
    working folders, where a relative PYTHONPATH would find an installed copy instead)."""
    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    return dict(os.environ, PYTHONPATH=path, **extra)


# ---------------------------------------------------------------- figures (border scaled with the image)
def border(img: np.ndarray) -> int:
    return max(8, int(round(img.shape[1] * 96 / 2048)))


def inner(a: np.ndarray, b: int) -> np.ndarray:
    return a[b:-b, b:-b]


def grey8(img: np.ndarray) -> np.ndarray:
    return grey(img)


def msl(img) -> float:
    lap = cv2.Laplacian(grey8(img), cv2.CV_32F, ksize=3)
    return float(np.mean(inner(lap, border(img)).astype(np.float64) ** 2))


def tenengrad(img) -> float:
    g = grey8(img)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    return float(np.mean(inner(gx * gx + gy * gy, border(img)).astype(np.float64)))


def band_powers(img, bands=((0.05, 0.4), (0.4, 0.71))) -> list[float]:
    """Mean power per pixel (Parseval: the variance of a band-passed copy) in each radial band (cycles/px)."""
    g = inner(grey8(img), border(img)).astype(np.float64)
    g -= g.mean()
    win = np.outer(np.hanning(g.shape[0]), np.hanning(g.shape[1]))
    g *= win / np.sqrt(np.mean(win ** 2))
    p = np.abs(np.fft.rfft2(g)) ** 2 / g.size ** 2
    p[:, 1:-1] *= 2.0  # rfft's half plane: the other half's power
    fy, fx = np.fft.fftfreq(g.shape[0])[:, None], np.fft.rfftfreq(g.shape[1])[None, :]
    r = np.sqrt(fx * fx + fy * fy)
    return [float(p[(r >= a) & (r < b)].sum()) for a, b in bands]


def psnr(a, b) -> float:
    ga, gb = grey8(a), grey8(b)
    if ga.shape != gb.shape:
        return float("nan")
    bd = border(a)
    d = inner(ga - gb, bd).astype(np.float64)
    return float(10 * np.log10(255.0 ** 2 / max(np.mean(d * d), 1e-12)))


# ---------------------------------------------------------------- variants
def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(v: np.ndarray) -> np.ndarray:
    v = np.clip(v, 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)


def exposure(img: np.ndarray, ev: float) -> np.ndarray:
    """A global exposure change of ``ev`` stops applied in linear light to sRGB-encoded 8-bit pixels (clipped)."""
    lin = srgb_to_linear(img.astype(np.float64) / 255.0) * 2.0 ** ev
    return np.clip(np.rint(linear_to_srgb(lin) * 255.0), 0, 255).astype(np.uint8)


def handheld(frames: list[np.ndarray], seed: int = 14) -> list[np.ndarray]:
    """Frames 1.. moved as a hand-held camera would: shifts up to +-3 px, roll up to +-0.2 deg (random), and
    focus breathing, a magnification ramp of 0.5 % over the stack (about the centre); frame 0 (the reference)
    unchanged. Lanczos-4, edges reflected."""
    rng = np.random.default_rng(seed)
    h, w = frames[0].shape[:2]
    out = [frames[0]]
    n = len(frames)
    for k in range(1, n):
        scale = 1.0 + 0.005 * k / (n - 1)
        ang = rng.uniform(-0.2, 0.2)
        m = cv2.getRotationMatrix2D((w / 2 - 0.5, h / 2 - 0.5), ang, scale)
        m[:, 2] += rng.uniform(-3, 3, 2)
        out.append(cv2.warpAffine(frames[k], m, (w, h), flags=cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REFLECT_101))
    return out


def noisy(img: np.ndarray, rng) -> np.ndarray:
    """Sensor-like noise on 8-bit sRGB: shot noise growing with the signal and a read-noise floor,
    sigma = sqrt(2^2 + I/8) DN (2-6 DN), independent per pixel and channel."""
    f = img.astype(np.float64)
    f += rng.standard_normal(f.shape) * np.sqrt(4.0 + f / 8.0)
    return np.clip(np.rint(f), 0, 255).astype(np.uint8)


def area(img: np.ndarray, f: int) -> np.ndarray:
    return cv2.resize(img, (img.shape[1] // f, img.shape[0] // f), interpolation=cv2.INTER_AREA)


VARIANTS = {
    # name: (description, pitch factor)
    "all10": "the 10 JPEG frames as they are",
    "first5": "frames 0-4 (JPEG)",
    "last5": "frames 5-9 (JPEG)",
    "every2": "frames 0, 2, 4, 6, 8 (JPEG): twice the focus step",
    "three": "frames 2, 5, 8 (JPEG): three frames, three times the step",
    "reversed": "the 10 JPEGs named far-to-near (z ascending away from the camera's first frame)",
    "reversed_near": "as reversed, composited with --z-ref-um 450: the near frame's geometry, as all10",
    "png": "the 10 frames decoded and written as 8-bit PNG",
    "tiff16": "the 10 frames decoded and written as 16-bit RGB TIFF (x 257)",
    "half": "1/2 area downscale (1024x768, PNG): a smaller sensor",
    "quarter": "1/4 area downscale (512x384, PNG)",
    "crop": "the central 1024x768 of each frame (PNG)",
    "exposure": "frames 2, 6: +0.3 EV; 4, 8: -0.3 EV (linear light, clipped; PNG)",
    "handheld": "frames 1-9 shifted <= 3 px, rolled <= 0.2 deg, breathing 0.5 % (PNG)",
    "noise": "sensor-like noise sigma = sqrt(4 + I/8) DN added to every frame (PNG)",
    # coarse steps whose disc (~15-22 px per step) the 64-px patches barely resolve (bench_ring_s14): the Wiener
    # step with a rate read short rang beside depth edges, so these must fall back to choosing frames (or not ring)
    "every2_60": "frames 0, 2, 4, 6, 8 at 0.6 area downscale (PNG): ~15 px of disc per step",
    "every2_80": "frames 0, 2, 4, 6, 8 at 0.8 area downscale (PNG): ~20 px of disc per step",
}
#: the coarse-step variants' downscale
SCALED_EVERY2 = {"every2_60": 0.6, "every2_80": 0.8}
#: variants compared with another one's composite (same frames before the change)
BASE = {"reversed_near": "all10", "exposure": "png", "handheld": "png", "noise": "png", "tiff16": "png"}


def build(name: str, jpegs: list[Path], dest: Path) -> tuple[list[Path], float]:
    """Write variant ``name``'s frames into ``dest``; their paths in stack order and the pixel pitch (um)."""
    dest.mkdir(parents=True)
    sub = {"all10": range(10), "first5": range(5), "last5": range(5, 10), "every2": range(0, 10, 2),
           "three": (2, 5, 8)}
    if name in sub:
        out = []
        for i in sub[name]:
            p = dest / jpegs[i].name
            p.symlink_to(jpegs[i])
            out.append(p)
        return out, PITCH_UM
    if name in ("reversed", "reversed_near"):
        out = []
        for j, p0 in enumerate(reversed(jpegs)):
            p = dest / f"rev_{j:03d}.JPG"
            p.symlink_to(p0)
            out.append(p)
        return out, PITCH_UM
    frames = [cv2.imread(str(p), cv2.IMREAD_COLOR) for p in jpegs]  # BGR
    pitch = PITCH_UM
    if name == "half":
        frames, pitch = [area(f, 2) for f in frames], 2 * PITCH_UM
    elif name == "quarter":
        frames, pitch = [area(f, 4) for f in frames], 4 * PITCH_UM
    elif name in SCALED_EVERY2:
        f_ = SCALED_EVERY2[name]
        frames = [cv2.resize(f, (round(f.shape[1] * f_), round(f.shape[0] * f_)), interpolation=cv2.INTER_AREA)
                  for f in frames[0:10:2]]
        pitch = PITCH_UM / f_
    elif name == "crop":
        h, w = frames[0].shape[:2]
        frames = [f[h // 4:h // 4 + h // 2, w // 4:w // 4 + w // 2] for f in frames]
    elif name == "exposure":
        ev = {2: 0.3, 6: 0.3, 4: -0.3, 8: -0.3}
        frames = [exposure(f, ev.get(k, 0.0)) if k in ev else f for k, f in enumerate(frames)]
    elif name == "handheld":
        frames = handheld(frames)
    elif name == "noise":
        rng = np.random.default_rng(15)
        frames = [noisy(f, rng) for f in frames]
    out = []
    for k, f in enumerate(frames):
        if name == "tiff16":
            p = dest / f"f_{k:03d}.tif"
            tifffile.imwrite(p, f[..., ::-1].astype(np.uint16) * 257, photometric="rgb")
        else:
            p = dest / f"f_{k:03d}.png"
            cv2.imwrite(str(p), f)
        out.append(p)
    return out, pitch


# ---------------------------------------------------------------- runs
def run(cmd: list[str], cwd: Path, env: dict) -> tuple[subprocess.CompletedProcess, float, float]:
    """A command in its own process: the result, wall and CPU (user + system of the child) seconds."""
    t0 = time.perf_counter()
    r0 = os.times()
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    r1 = os.times()
    cpu = (r1.children_user - r0.children_user) + (r1.children_system - r0.children_system)
    return r, time.perf_counter() - t0, cpu


def snapshot(d: Path) -> dict:
    return {str(p.relative_to(d)): (p.lstat().st_size, p.lstat().st_mtime_ns) for p in d.rglob("*")}


def read_rgb8(path: Path) -> np.ndarray:
    img = tifffile.imread(path)[..., :3]
    return (img.astype(np.float64) / 257.0 + 0.5).astype(np.uint8) if img.dtype == np.uint16 else img


#: the reference (--z-ref-um) when not 0
Z_REF_UM = {"reversed_near": 450.0}


def fieldcal_run(py, frames: list[Path], pitch: float, work: Path, z_ref_um: float = 0.0) -> dict:
    """import + composite in an empty cwd with their own TMPDIR; both must stay empty."""
    cwd, tmp = work / "cwd", work / "tmp"
    cwd.mkdir()
    tmp.mkdir()
    env = checkout_env(TMPDIR=str(tmp))
    src_before = snapshot(frames[0].parent)
    stack, out = work / "stack", work / "fieldcal.tiff"
    r, wi, ci = run([*py, "import", *map(str, frames), "--out", str(stack), "--z", "0", "50",
                     "--pixel-pitch-um", f"{pitch:g}", "--quiet"], cwd, env)
    if r.returncode:
        return {"error": f"import exit {r.returncode}: {r.stderr.strip()[-300:]}"}
    r, wc, cc = run([*py, "composite", str(stack), "--out", str(out), "--z-ref-um", f"{z_ref_um:g}", "--quiet"],
                    cwd, env)
    if r.returncode:
        return {"error": f"composite exit {r.returncode}: {r.stderr.strip()[-300:]}"}
    stray = [str(p) for p in (*cwd.iterdir(), *tmp.iterdir())]
    if snapshot(frames[0].parent) != src_before:
        stray.append("the frames' folder changed")
    return {"image": read_rgb8(out), "wall": wi + wc, "cpu": ci + cc, "stray": stray,
            "stderr": r.stderr.strip()}


def enfuse_run(frames: list[Path], work: Path) -> dict:
    t0 = time.perf_counter()
    r0 = os.times()
    prefix = work / "al_"
    r = subprocess.run(["align_image_stack", "-m", "-a", str(prefix), *map(str, frames)], capture_output=True,
                       text=True)
    if r.returncode:
        return {"error": f"align_image_stack exit {r.returncode}: {r.stderr.strip()[-200:]}"}
    aligned = sorted(work.glob("al_*.tif"))
    r = subprocess.run(["enfuse", "--exposure-weight=0", "--saturation-weight=0", "--contrast-weight=1",
                        "--hard-mask", f"--output={work / 'enfuse.tif'}", *map(str, aligned)], capture_output=True,
                       text=True)
    if r.returncode:
        return {"error": f"enfuse exit {r.returncode}: {r.stderr.strip()[-200:]}"}
    r1 = os.times()
    cpu = (r1.children_user - r0.children_user) + (r1.children_system - r0.children_system)
    return {"image": read_rgb8(work / "enfuse.tif"), "frames": [read_rgb8(p) for p in aligned],
            "wall": time.perf_counter() - t0, "cpu": cpu}


def registered(stack: Path, z_ref_um: float = 0.0) -> list[np.ndarray]:
    from fieldcal.composite.register import register_stack
    from fieldcal.formats.stack import Stack

    st = Stack.open(stack, verify=False)
    held, _ = register_stack(st, z_ref_um=z_ref_um, quiet=True)
    out = []
    for i in range(len(st.frames)):
        f = held.read(i)
        out.append(read_rgb8_arr(f))
    del held
    return out


def read_rgb8_arr(f: np.ndarray) -> np.ndarray:
    """A held (registered) frame on the 0-255 scale: 8-bit frames come back as float32 values, 16-bit ones as
    they are (0-65535)."""
    f = np.asarray(f)[..., :3]
    return f.astype(np.float32) / np.float32(257.0) if f.dtype == np.uint16 else f.astype(np.float32)


def figures(img: np.ndarray, frames: list[np.ndarray] | None) -> dict:
    b1, b2 = band_powers(img)
    d = {"msl": msl(img), "ten": tenengrad(img), "band": b1, "hi": b2}
    if frames is not None and frames[0].shape[:2] == img.shape[:2]:
        edges = depth_edges(frames)
        rms, share = overshoot_scaled(img, frames, edges)
        d.update(ring_rms=rms, ring_share=share)
    return d


def overshoot_scaled(img, frames, where):
    """:func:`bench_real_stack.overshoot` with this benchmark's border (its own is 96 px whatever the size)."""
    import bench_real_stack as brs

    old = brs.BORDER
    brs.BORDER = border(img)
    try:
        return overshoot(img, frames, where)
    finally:
        brs.BORDER = old


# ---------------------------------------------------------------- bad inputs
def said(stderr: str) -> str:
    """The error's first line and its fix, as one line."""
    lines = [v.strip() for v in stderr.strip().splitlines() if v.strip()]
    return " / ".join(lines[:1] + [v for v in lines[1:] if v.startswith("fix:")])[:220]


def bad_inputs(py, jpegs: list[Path], work: Path) -> list[dict]:
    rows = []
    shutil.rmtree(work, ignore_errors=True)  # an earlier run's (--keep)
    d = work / "bad_mixed"
    d.mkdir(parents=True)
    for k, p in enumerate(jpegs[:4]):
        img = cv2.imread(str(p))
        if k == 2:
            img = area(img, 2)
        cv2.imwrite(str(d / f"f{k}.png"), img)
    cwd = work / "bad_cwd"
    cwd.mkdir()
    r, _, _ = run([*py, "import", str(d), "--out", str(work / "bad_mixed_stack"), "--z", "0", "50",
                   "--pixel-pitch-um", "1.12", "--quiet"], cwd, checkout_env())
    rows.append({"case": "one frame of half the size (PNG)", "step": "import", "exit": r.returncode,
                 "clean": "Traceback" not in r.stderr, "message": said(r.stderr),
                 "wrote": (work / "bad_mixed_stack").exists()})
    # a frame swapped for one of another size after import
    d2 = work / "bad_swap"
    d2.mkdir()
    for k, p in enumerate(jpegs[:4]):
        cv2.imwrite(str(d2 / f"f{k}.png"), cv2.imread(str(p)))
    st = work / "bad_swap_stack"
    subprocess.run([*py, "import", str(d2), "--out", str(st), "--z", "0", "50", "--pixel-pitch-um", "1.12",
                    "--quiet"], check=True, env=checkout_env())
    f2 = sorted((st / "frames").iterdir())[2]
    cv2.imwrite(str(f2.with_suffix(".png")), area(cv2.imread(str(f2)), 2))
    r, _, _ = run([*py, "composite", str(st), "--out", str(work / "bad_swap.tiff"), "--z-ref-um", "0", "--quiet"],
                  cwd, checkout_env())
    rows.append({"case": "a frame replaced by one of half the size after import", "step": "composite",
                 "exit": r.returncode, "clean": "Traceback" not in r.stderr,
                 "message": said(r.stderr),
                 "wrote": (work / "bad_swap.tiff").exists()})
    # mixed file types
    d3 = work / "bad_types"
    d3.mkdir()
    for k, p in enumerate(jpegs[:4]):
        img = cv2.imread(str(p))
        cv2.imwrite(str(d3 / (f"f{k}.png" if k != 1 else f"f{k}.jpg")), img)
    r, _, _ = run([*py, "import", str(d3), "--out", str(work / "bad_types_stack"), "--z", "0", "50",
                   "--pixel-pitch-um", "1.12", "--quiet"], cwd, checkout_env())
    rows.append({"case": "PNG and JPEG frames mixed", "step": "import", "exit": r.returncode,
                 "clean": "Traceback" not in r.stderr,
                 "message": said(r.stderr),
                 "wrote": (work / "bad_types_stack").exists()})
    rows.append({"case": "(nothing written in the working folder)", "step": "", "exit": "",
                 "clean": not any(cwd.iterdir()), "message": "", "wrote": ""})
    return rows


# ---------------------------------------------------------------- crops
def crop_rows(name: str, res: dict, size: int, places) -> list[np.ndarray]:
    ours = res["fieldcal"]["image"]
    h, w = ours.shape[:2]
    enf = res.get("enfuse", {}).get("image")
    if enf is not None:
        try:
            enf = onto(enf, ours)
        except cv2.error:
            pass
    fs = res.get("focus_stack")
    rows = []
    for fx, fy in places:
        x, y = int(fx * w), int(fy * h)
        x, y = min(max(x, 0), w - size), min(max(y, 0), h - size)
        gap = np.full((size, 3, 3), 255, np.uint8)
        parts = []
        for img in (enf, fs, ours):
            parts += [img[y:y + size, x:x + size, :3] if img is not None else np.zeros((size, size, 3), np.uint8),
                      gap]
        rows.append(np.concatenate(parts[:-1], axis=1))
    return rows


def variant_row(name: str, res: dict, results: dict) -> dict:
    """The figures of one variant's composites (fieldcal, enfuse, focus-stack)."""
    row = {"variant": name, "what": VARIANTS[name], "frames": res["frames"]}
    for tool in ("fieldcal", "enfuse", "focus_stack"):
        img = res.get(tool)
        if isinstance(img, dict):
            if "error" in img:
                row[tool] = {"error": img["error"]}
                continue
            frames_for = res.get("regd") if tool == "fieldcal" else img.get("frames")
            img = img["image"]
        else:
            frames_for = res.get("regd")
        if img is None:
            continue
        row[tool] = figures(img, frames_for)
        base = BASE.get(name)
        if base in results:
            b = results[base].get(tool)
            b = b.get("image") if isinstance(b, dict) else b
            if b is not None:
                row[tool]["psnr_vs_" + base] = psnr(img, b)
    fc = res["fieldcal"]
    row["fieldcal_wall"], row["fieldcal_cpu"] = fc.get("wall"), fc.get("cpu")
    row["stray"] = fc.get("stray")
    row["enfuse_wall"], row["enfuse_cpu"] = res["enfuse"].get("wall"), res["enfuse"].get("cpu")
    row["load"] = res["load"]
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stack", type=Path, default=DEFAULT_STACK)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--no-focus-stack", action="store_true", help="leave focus-stack's merge out")
    ap.add_argument("--no-bad", action="store_true", help="leave the bad inputs out")
    ap.add_argument("--write", action="store_true")
    ap.add_argument("--keep", type=Path, help="keep frames, stacks and composites in this folder")
    ap.add_argument("--reuse", action="store_true", help="with --keep: take the composites an earlier run left there")
    ap.add_argument("--json", type=Path, help="write the figures to this JSON file too")
    a = ap.parse_args()
    if not a.stack.is_dir():
        sys.exit(f"{a.stack} not found: give --stack, or set FIELDCAL_SHARED to the folder holding data/")
    jpegs = sorted(a.stack.glob("*.JPG"))
    work = a.keep or Path(tempfile.mkdtemp())
    work.mkdir(parents=True, exist_ok=True)
    py = [sys.executable, "-m", "fieldcal"]
    names = [n for n in a.variants.split(",") if n]
    results: dict[str, dict] = {}
    table = []
    for name in names:
        vw = work / name
        if a.reuse and (vw / "fieldcal.tiff").exists() and (vw / "enfuse.tif").exists():
            # an earlier run's composites (--keep): figures only
            frames = sorted((vw / "frames").iterdir())
            res = {"frames": len(frames), "load": float("nan"),
                   "fieldcal": {"image": read_rgb8(vw / "fieldcal.tiff"),
                                **json.loads((vw / "times.json").read_text())},
                   "enfuse": {"image": read_rgb8(vw / "enfuse.tif"),
                              "frames": [read_rgb8(p) for p in sorted(vw.glob("al_*.tif"))],
                              **json.loads((vw / "times_enfuse.json").read_text())}}
            res["load"] = res["fieldcal"].pop("load", float("nan"))
        else:
            if vw.exists():
                shutil.rmtree(vw)
            frames, pitch = build(name, jpegs, vw / "frames")
            res = {"frames": len(frames), "load": os.getloadavg()[0]}
            res["fieldcal"] = fieldcal_run(py, frames, pitch, vw, Z_REF_UM.get(name, 0.0))
            res["enfuse"] = enfuse_run(frames, vw)
            for tool, fn in (("fieldcal", "times.json"), ("enfuse", "times_enfuse.json")):
                keep = {k: v for k, v in res[tool].items() if k in ("wall", "cpu", "stray", "error")}
                (vw / fn).write_text(json.dumps({**keep, "load": res["load"]}))
        if "image" in res["fieldcal"]:
            regd = registered(vw / "stack", Z_REF_UM.get(name, 0.0))
            res["regd"] = regd
            if not a.no_focus_stack:
                res["focus_stack"], _ = focus_stack(regd)
        results[name] = res
        table.append(variant_row(name, res, results))
        res.pop("regd", None)
        res["enfuse"].pop("frames", None)

        def said(d):
            return "ERR " + d["error"] if "error" in d else "%.1f s" % d["wall"]

        print(f"{name}: fieldcal {said(res['fieldcal'])}; enfuse {said(res['enfuse'])}", flush=True)
    lines = ["| variant | frames | msl: fieldcal / enfuse / focus-stack | Tenengrad | band 0.05-0.4 | power 0.4-0.71 | "
             "fieldcal / enfuse (msl, Ten., band) | ringing at depth edges RMS DN (> 2 DN): fieldcal / enfuse / "
             "focus-stack | PSNR vs unchanged (dB): fieldcal / enfuse / focus-stack | fieldcal wall / CPU (s) | "
             "enfuse wall / CPU (s) | load |",
             "|" + " --- |" * 12]

    def g(row, tool, key, fmt):
        v = row.get(tool, {})
        if "error" in v:
            return "ERR"
        v = v.get(key)
        return "—" if v is None else format(v, fmt)

    for row in table:
        tools = ("fieldcal", "enfuse", "focus_stack")
        ratio = []
        for k in ("msl", "ten", "band"):
            try:
                ratio.append(f"{row['fieldcal'][k] / row['enfuse'][k]:.3f}")
            except (KeyError, TypeError, ZeroDivisionError):
                ratio.append("—")
        ring = " / ".join(f"{g(row, t, 'ring_rms', '.2f')} ({g(row, t, 'ring_share', '.1%')})" for t in tools)
        base = BASE.get(row["variant"])
        ps = " / ".join(g(row, t, f"psnr_vs_{base}", ".1f") for t in tools) if base else "—"
        def num(v, fmt=".1f"):
            return "—" if v is None or not np.isfinite(v) else format(v, fmt)

        fw = f"{num(row['fieldcal_wall'])} / {num(row['fieldcal_cpu'])}"
        ew = f"{num(row['enfuse_wall'])} / {num(row['enfuse_cpu'])}"
        lines.append(f"| {row['variant']}: {row['what']} | {row['frames']} | "
                     + " | ".join(" / ".join(g(row, t, k, f) for t in tools)
                                  for k, f in (("msl", ".0f"), ("ten", ".0f"), ("band", ".1f"), ("hi", ".3f")))
                     + f" | {', '.join(ratio)} | {ring} | {ps} | {fw} | {ew} | {num(row['load'])} |")
    stray = [f"{r['variant']}: {r['stray']}" for r in table if r.get("stray")]
    errors = [f"{r['variant']}: {t}: {r[t]['error']}" for r in table for t in ("fieldcal", "enfuse", "focus_stack")
              if isinstance(r.get(t), dict) and "error" in r[t]]
    bad = [] if a.no_bad else bad_inputs(py, jpegs, work / "bad")
    out = lines[:]
    out += ["", "Errors: " + ("; ".join(errors) if errors else "none") + ". Files written outside `--out` (working "
            "folder, TMPDIR, the frames' folder): " + ("; ".join(stray) if stray else "none") + "."]
    if bad:
        out += ["", "| bad input | step | exit | clean (no traceback) | output written | message |",
                "| --- | --- | --- | --- | --- | --- |"]
        out += [f"| {b['case']} | {b['step']} | {b['exit']} | {b['clean']} | {b['wrote']} | {b['message']} |"
                for b in bad]
    print("\n".join(out))
    if a.json:
        a.json.write_text(json.dumps(table, indent=1, default=str))
    # crops: per variant one row (two places), enfuse | focus-stack | fieldcal
    places = ((0.576, 0.273), (0.303, 0.651))
    img_dir = REPO / "docs" / "img" if a.write else work
    per = -(-len(names) // 2)  # two figures, each under 300 KB
    groups = [names[i:i + per] for i in range(0, len(names), per)]
    crop_files = []
    for gi, grp in enumerate(groups):
        rows = []
        for name in grp:
            res = results[name]
            if "image" not in res["fieldcal"]:
                continue
            w = res["fieldcal"]["image"].shape[1]
            size = min(128, w // 4)
            for r in crop_rows(name, res, size, places[:1]):
                if r.shape[0] != 128:
                    r = cv2.resize(r, (r.shape[1] * 128 // r.shape[0], 128), interpolation=cv2.INTER_NEAREST)
                rows.append(r)
                rows.append(np.full((4, r.shape[1], 3), 255, np.uint8))
        if rows:
            wmax = max(r.shape[1] for r in rows)
            rows = [np.pad(r, ((0, 0), (0, wmax - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
            f = img_dir / f"real-variants-s14-{gi + 1}.png"
            save_palette_png(f, np.concatenate(rows, axis=0))
            crop_files.append(f)
            print(f"crops: {f} ({f.stat().st_size / 1024:.0f} KB): rows {', '.join(grp)}; enfuse | focus-stack | "
                  "fieldcal")
    if a.write:
        cmd = "python benchmarks/bench_real_variants.py --write"
        text = "\n".join([f"Command: `{cmd}` (machine shared; times are wall / CPU of user + system). Crops: "
                          + ", ".join(f"[img/{f.name}](img/{f.name})" for f in crop_files)
                          + " (one row per variant in the table's order, left to right enfuse brought onto "
                            "fieldcal's geometry, focus-stack's merge, fieldcal).", "", *out])
        write_docs_section(SECTION, text)
    if not a.keep:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
