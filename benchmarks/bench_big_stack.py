"""Stacks bigger and longer than the circuit board: time, memory and registration (issue 15).

Published focus-stacking sets are often 20-60 frames of 12-24 MP, JPEG or 16-bit TIFF, sometimes ordered
far-to-near, with a few % of breathing and frames nearly identical to their neighbours. The only real stack we
have is the circuit board (``../shared/data/real-stacks/pcb-depthmap/``, 10 JPEG frames 2048x1536), so the big
stacks are made from its real frames by KNOWN maps, in a work folder (default a new one under /tmp), and each goes
through ``fieldcal import`` + ``fieldcal composite STACK --out OUT --z-ref-um 0`` as a user runs them:

* ``7 x 2 MP``, ``10 x 2 MP``: the original JPEG frames (issue 15's speed target is the first 7);
* ``10 x 12 MP``: the 10 frames upsampled to 4000x3000 (JPEG q95);
* ``30 x 12 MP TIFF``: 4000x3000 16-bit RGB TIFF, each frame 3 times, every copy shifted by a random sub-pixel
  amount (±0.5 px) and scaled by ±0.1 % (known);
* ``30 x 12 MP reversed``: the same maps as JPEG q95, the files named far-to-near;
* ``60 x 24 MP breathing``: 6000x4000 JPEG q95, each frame 6 times (the copies are nearly identical), 3 % total
  magnification change linear in z about the centre, plus random sub-pixel shifts.

Frame ``k`` of a case is original frame ``orig[k]`` moved by ``A_k`` (original px -> written px; bicubic,
OpenCV ``INTER_CUBIC``), where ``A_k`` = the perturbation after ``U``, a centred upsampling by a factor a little
larger than the output needs, so that no frame shows the repeated edge pixels a warp puts where a frame ends. The
reference frame (z = 0, ``--z-ref-um 0``) is a middle copy of original frame 5, moved by ``U`` alone.

**Figures** (:mod:`bench_real_robustness` defines the comparisons, reused here):

* wall and CPU time (user + system of the child) and peak RSS of each ``fieldcal composite`` process
  (``/usr/bin/time -v``), and of ``fieldcal import``;
* registration RMS and max (px of the case's frames): fieldcal's map of each frame (``choose_model``, the code
  ``composite`` runs) against ``A_k M_o A_ref^-1``, ``M_o`` fieldcal's map of original frame ``o`` on the 10
  original frames cropped to the part the reference frame shows, in the same z direction, with the same model
  (the scene's own motion between frames is in ``M_o``; :func:`originals_over_view` says why the view matters);
* sharpness: the mean squared Laplacian of the composite, area-downsampled by the upsampling factor, over that of
  the 10-frame original composite moved by ``U`` and downsampled the same way; PSNR of the two (dB, grey).

``--write`` puts the table in docs/benchmarks.md (section ``big_stack``); ``--cases`` runs some cases only
(comma-separated names); ``--keep DIR`` keeps the work folder (the 60 x 24 MP case writes ~0.6 GB of JPEG, its
composite a temporary file of registered frames of 8.6 GB beside it, see docs/compositing.md).
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
from _common import md_table, write_docs_section  # noqa: E402
from bench_real_robustness import Case, registration_error, registration_maps, similarity  # noqa: E402
from bench_real_stack import DEFAULT_STACK, grey, msl  # noqa: E402

Z_STEP_UM = 50.0
PITCH_UM = 1.12
REF = 5  # original frame of the reference (the middle of 10)
SEED = 1515
BORDER = 96


@dataclass
class BigCase(Case):
    """A case made lazily (frames warped while written): ``size`` (W, H), ``up`` the upsampling factor."""

    size: tuple = (2048, 1536)
    up: float = 1.0
    reverse_names: bool = False
    originals: bool = False
    n_orig: int = 10
    extra: dict = field(default_factory=dict)


def upsampling(size, margin: float) -> np.ndarray:
    """Centred map of 2048x1536 px onto ``size`` px, scaled ``margin`` beyond covering it (no repeated edges)."""
    w, h = size
    u = max(w / 2048, h / 1536) * (1.0 + margin)
    c_in = np.array([(2048 - 1) / 2, (1536 - 1) / 2])
    c_out = np.array([(w - 1) / 2, (h - 1) / 2])
    m = np.eye(3)
    m[0, 0] = m[1, 1] = u
    m[:2, 2] = c_out - u * c_in
    return m


def make_case(name: str) -> BigCase:
    rng = np.random.default_rng(SEED)
    if name in ("7 x 2 MP", "10 x 2 MP"):
        n = int(name.split()[0])
        c = BigCase(name, f"the first {n} original JPEG frames", originals=True, n_orig=n, fmt="jpg",
                    pitch_um=PITCH_UM, kref=min(REF, n - 1))
        c.orig, c.A = list(range(n)), [np.eye(3)] * n
        c.z = (-Z_STEP_UM * c.kref, Z_STEP_UM)
        return c
    if name == "10 x 12 MP":
        size, reps, fmt, breath, jitter = (4000, 3000), 1, "jpg", 0.0, 0.0
        what = "the 10 frames upsampled to 4000x3000 (JPEG q95)"
    elif name in ("30 x 12 MP TIFF", "30 x 12 MP reversed"):
        size, reps, breath, jitter = (4000, 3000), 3, 0.0, 0.5
        fmt = "tiff16" if "TIFF" in name else "jpg"
        what = ("4000x3000 16-bit TIFF" if fmt == "tiff16" else "4000x3000 JPEG q95, files named far-to-near") + \
            ", each frame 3 times, shifted ±0.5 px and scaled ±0.1 % at random"
    elif name == "60 x 24 MP breathing":
        size, reps, fmt, breath, jitter = (6000, 4000), 6, "jpg", 0.03, 0.5
        what = "6000x4000 JPEG q95, each frame 6 times, 3 % magnification over the stack, shifts ±0.5 px at random"
    else:
        raise SystemExit(f"unknown case {name!r}")
    n = 10 * reps
    kref_content = reps * REF + reps // 2  # a middle copy of original frame REF, in focus order
    kref = n - 1 - kref_content if "reversed" in name else kref_content  # its file index
    up = upsampling(size, 0.5 * breath + 0.004)
    w, h = size
    centre = ((w - 1) / 2, (h - 1) / 2)
    c = BigCase(name, what, fmt=fmt, pitch_um=PITCH_UM / up[0, 0], kref=kref, size=size, up=float(up[0, 0]),
                reverse_names="reversed" in name)
    step = Z_STEP_UM / reps
    c.z = (-step * kref, step)
    # reversed: the files are named far-to-near and --z gives z ascending over the names, so file j holds frame
    # n - 1 - j of the focus order; the lists are kept in file order, and the reference (z = 0, file kref) is
    # the unperturbed frame
    for k in range(n):
        if k == kref_content:
            a = up
        else:
            s = 1.0 + breath * (k - kref_content) / (n - 1)
            s += rng.uniform(-0.001, 0.001) if jitter and not breath else 0.0
            t = rng.uniform(-jitter, jitter, 2) if jitter else (0.0, 0.0)
            a = similarity(s, shift=t, centre=centre) @ up
        c.orig.append(k // reps)
        c.A.append(a)
    if c.reverse_names:
        c.orig, c.A = c.orig[::-1], c.A[::-1]
    return c


CASES = ["7 x 2 MP", "10 x 2 MP", "10 x 12 MP", "30 x 12 MP TIFF", "30 x 12 MP reversed", "60 x 24 MP breathing"]


def write_frames(case: BigCase, full: list[np.ndarray], jpegs: list[Path], folder: Path) -> None:
    folder.mkdir(parents=True)
    n = len(case.orig)
    if case.originals:
        for p in jpegs[:case.n_orig]:
            (folder / p.name).symlink_to(p)
        return
    for k in range(n):
        img = cv2.warpAffine(full[case.orig[k]], case.A[k][:2], case.size, flags=cv2.INTER_CUBIC,
                             borderMode=cv2.BORDER_REPLICATE)
        name = folder / f"frame_{k:03d}"  # file order (reversed cases: their lists are in file order already)
        if case.fmt == "tiff16":
            # 8-bit frames to 16 bits with the sub-DN values of a bicubic warp done again in float
            img = cv2.warpAffine(full[case.orig[k]].astype(np.float32) * 257.0, case.A[k][:2], case.size,
                                 flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
            img = np.clip(np.rint(img), 0, 65535).astype(np.uint16)
            tifffile.imwrite(name.with_suffix(".tif"), img[..., ::-1], photometric="rgb")
        else:
            cv2.imwrite(str(name.with_suffix(".jpg")), img, [cv2.IMWRITE_JPEG_QUALITY, 95])


def originals_over_view(case: BigCase, jpegs: list[Path], work: Path, model: str) -> list[np.ndarray]:
    """fieldcal's maps (reference px -> frame px, original px, indexed by original frame) of the 10 original frames
    cropped to the part of them the case's reference frame shows, registered with ``model`` in the case's z
    direction (reversed cases: far-to-near). A scene with depth breathes differently at different depths, so the
    best global map moves with what a frame shows: the 6000x4000 (3:2) frames show 78 % of the 4:3 originals'
    height, and against maps fitted over the whole originals they read 3.7 px RMS off, 0.39 px against maps over
    the same view."""
    a_ref_inv = np.linalg.inv(case.A[case.ref_index])
    w, h = case.size
    x0, y0, _ = a_ref_inv @ [0.0, 0.0, 1.0]
    x1, y1, _ = a_ref_inv @ [w - 1.0, h - 1.0, 1.0]
    cx0, cy0 = max(0, int(np.ceil(x0))), max(0, int(np.ceil(y0)))
    cx1, cy1 = min(2047, int(np.floor(x1))), min(1535, int(np.floor(y1)))
    tag = f"{cx0}_{cy0}_{cx1}_{cy1}_{int(case.reverse_names)}"
    src, stack = work / f"originals_{tag}", work / f"originals_{tag}_stack"
    for p in (src, stack):
        shutil.rmtree(p, ignore_errors=True)
    src.mkdir(parents=True)
    order = list(range(len(jpegs)))[::-1] if case.reverse_names else list(range(len(jpegs)))
    for j, o in enumerate(order):
        cv2.imwrite(str(src / f"f{j:02d}.png"), cv2.imread(str(jpegs[o]))[cy0:cy1 + 1, cx0:cx1 + 1])
    n = len(jpegs)
    first = order.index(REF)  # original REF at z = 0
    subprocess.run([sys.executable, "-m", "fieldcal", "import", str(src), "--out", str(stack), "--z",
                    f"{-Z_STEP_UM * first:g}", f"{Z_STEP_UM:g}", "--pixel-pitch-um", f"{PITCH_UM}", "--quiet"],
                   check=True, capture_output=True)
    maps, _ = registration_maps(stack, 0.0, model)
    by_orig = [None] * n
    for j, o in enumerate(order):
        by_orig[o] = maps[j]
    crop = np.array([[1.0, 0, cx0], [0, 1.0, cy0], [0, 0, 1.0]])  # crop px -> original px
    return [crop @ m @ np.linalg.inv(crop) for m in by_orig]


def run_timed(cmd: list[str]) -> tuple[dict, subprocess.CompletedProcess]:
    """Wall (s), CPU (user + system, s) and peak RSS (MB) of a command, by ``/usr/bin/time -v``."""
    r = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True)
    out = {"wall": float("nan"), "cpu": 0.0, "rss": float("nan")}
    for line in r.stderr.splitlines():
        line = line.strip()
        if line.startswith("Elapsed (wall clock)"):
            parts = line.rsplit(" ", 1)[-1].split(":")
            out["wall"] = sum(float(p) * 60 ** i for i, p in enumerate(reversed(parts)))
        elif line.startswith(("User time", "System time")):
            out["cpu"] += float(line.rsplit(" ", 1)[-1])
        elif line.startswith("Maximum resident set size"):
            out["rss"] = float(line.rsplit(" ", 1)[-1]) / 1024.0
    return out, r


def to_compare(case: BigCase, img: np.ndarray, ref: np.ndarray | None = None) -> np.ndarray:
    """The composite area-downsampled by the case's upsampling factor (8-bit scale); with ``ref`` (the 2048 px
    original composite), that composite moved by the case's reference map and downsampled the same way."""
    if ref is not None:
        a = cv2.warpAffine(ref.astype(np.float32), case.A[case.ref_index][:2], case.size, flags=cv2.INTER_CUBIC,
                           borderMode=cv2.BORDER_REPLICATE)
    else:
        a = img.astype(np.float32) / (257.0 if img.dtype == np.uint16 else 1.0)
    if case.up == 1.0:
        return a
    w, h = case.size
    return cv2.resize(a, (round(w / case.up), round(h / case.up)), interpolation=cv2.INTER_AREA)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    sl = (slice(BORDER, -BORDER), slice(BORDER, -BORDER))
    e = float(np.mean((grey(a)[sl] - grey(b)[sl]) ** 2))
    return 10 * np.log10(255.0 ** 2 / max(e, 1e-12))


def report(rows: list[dict], write: bool) -> None:
    for r in rows:  # CPU time, not wall: the wall clock of a shared machine says more about the load
        if r.get("cpu (s)") and r.get("size"):
            w, h = (int(v) for v in r["size"].split("x"))
            r["cpu per MP"] = r["cpu (s)"] / (r["frames"] * w * h / 1e6)
    cols = [("case", "case", ""), ("frames", "frames", "d"), ("size (px)", "size", ""), ("format", "fmt", ""),
            ("import (s)", "import (s)", ".1f"), ("composite wall (s)", "wall (s)", ".1f"),
            ("CPU (s)", "cpu (s)", ".1f"), ("peak RSS (MiB)", "rss (MB)", ".0f"),
            ("CPU s per frame-MP", "cpu per MP", ".3f"), ("model", "model", ""),
            ("registration RMS (px)", "reg RMS (px)", ".3f"), ("max (px)", "reg max (px)", ".3f"),
            ("sharpness / original", "sharpness ratio", ".3f"), ("PSNR vs original (dB)", "psnr", ".1f"),
            ("load at start", "load", ".1f"), ("result", "status", "")]
    text = "\n".join(md_table(rows, cols) + [
        "", "Command: `python benchmarks/bench_big_stack.py --write` (its docstring defines every figure). The machine "
            "has 2 cores shared by several engineers: the load is the 1-minute average when the composite started."])
    print(text)
    if write:
        write_docs_section("big_stack", text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stack", type=Path, default=DEFAULT_STACK)
    ap.add_argument("--cases", help="comma-separated case names (default all): " + ", ".join(CASES))
    ap.add_argument("--keep", type=Path, help="work folder to keep (default a temporary one, removed)")
    ap.add_argument("--write", action="store_true", help="put the table into docs/benchmarks.md")
    ap.add_argument("--merge", nargs="+", type=Path, metavar="RESULTS_JSON",
                    help="make the table from earlier runs' results.json (later files win)")
    a = ap.parse_args()
    if a.merge:
        rows = {}
        for p in a.merge:
            rows.update({r["case"]: r for r in json.loads(p.read_text())})
        report([rows[c] for c in CASES if c in rows], a.write)
        return
    jpegs = sorted(a.stack.glob("*.JPG"))
    if len(jpegs) != 10:
        sys.exit(f"{a.stack}: expected the 10 pcb JPEG frames")
    full = [cv2.imread(str(p)) for p in jpegs]  # BGR, as cv2 writes
    work = a.keep or Path(tempfile.mkdtemp(prefix="bigstack-"))
    work.mkdir(parents=True, exist_ok=True)
    os.environ.update({"PYTHONPATH": str(Path(__file__).resolve().parents[1]), "FIELDCAL_PROGRESS": "0"})
    py = [sys.executable, "-m", "fieldcal"]
    wanted = CASES if not a.cases else [s.strip() for s in a.cases.split(",")]
    todo = [c for c in CASES if c in wanted or c == "10 x 2 MP"]  # the original composite is the reference
    rows, base = [], {}
    try:
        for name in todo:
            case = make_case(name)
            src = work / re.sub(r"\W+", "_", name)
            stack, out = src.with_name(src.name + "_stack"), src.with_name(src.name + ".tiff")
            for p in (src, stack, out):
                shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
            write_frames(case, full, jpegs, src)
            imp, r = run_timed([*py, "import", str(src), "--out", str(stack), "--z", f"{case.z[0]:g}",
                                f"{case.z[1]:g}", "--pixel-pitch-um", f"{case.pitch_um:.4f}", "--quiet"])
            w, h = case.size
            row = {"case": name, "frames": len(case.orig), "size": f"{w}x{h}",
                   "fmt": {"jpg": "JPEG", "tiff16": "TIFF 16"}[case.fmt], "import (s)": imp["wall"]}
            if r.returncode:
                row["status"] = "import failed: " + r.stderr.strip().splitlines()[-1][:200]
                rows.append(row)
                print(row, flush=True)
                continue
            shutil.rmtree(src) if not case.originals else None  # import copied the frames
            load = os.getloadavg()[0]
            t, r = run_timed([*py, "composite", str(stack), "--out", str(out), "--z-ref-um", "0"])
            row.update({"wall (s)": t["wall"], "cpu (s)": t["cpu"], "rss (MB)": t["rss"], "load": load})
            if r.returncode:
                tail = r.stderr.strip().splitlines()
                row["status"] = (("TRACEBACK: " if "Traceback" in r.stderr else "refused: ")
                                 + (tail[-1][:200] if tail else ""))
                rows.append(row)
                print(row, flush=True)
                continue
            from fieldcal.composite.io import read_composite_metadata

            row["model"] = read_composite_metadata(out).get("registration", {}).get("model")
            img = tifffile.imread(out)
            if name == "10 x 2 MP":
                base["img"] = img
                base["stack"] = stack
            maps, model = registration_maps(stack, 0.0)
            if not case.originals:
                key = (model, case.reverse_names, case.size)
                if key not in base:
                    base[key] = originals_over_view(case, jpegs, work, model)
                row["reg RMS (px)"], row["reg max (px)"] = registration_error(case, maps, base[key], case.size)
                cmp, ref = to_compare(case, img), to_compare(case, None, base["img"])
                row["sharpness ratio"] = msl(cmp) / msl(ref)
                row["psnr"] = psnr(cmp, ref)
                row["status"] = "pass" if row["reg RMS (px)"] <= 0.5 and row["sharpness ratio"] >= 0.97 else "NOT MET"
            else:
                row["status"] = "reference" if name == "10 x 2 MP" else "speed target"
            out.unlink(missing_ok=True)
            if name != "10 x 2 MP":
                shutil.rmtree(stack, ignore_errors=True)
            rows.append(row)
            print(json.dumps(row), flush=True)
            (work / "results.json").write_text(json.dumps(rows, indent=1))
    finally:
        if a.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    report(rows, a.write)


if __name__ == "__main__":
    main()
