"""A real 3-D focus stack: fieldcal against align_image_stack + enfuse, sharpness and crops side by side.

Uses ``../shared/data/real-stacks/pcb-depthmap/`` beside the checkout (or ``--stack DIR``, or
``$FIELDCAL_SHARED/data/real-stacks/pcb-depthmap``: 10 JPEG frames of a circuit board shot through focus). The
frames are imported with ``fieldcal import`` (the pitch is not in their EXIF; 1.12 µm is given, z is a uniform
step: only the order matters for depth from focus), composited without a profile in the geometry of the first
frame (align_image_stack's reference), and compared with ``align_image_stack -m -a`` + ``enfuse --hard-mask``
(contrast weight only) on the same JPEGs when those tools are installed (``apt-get install enfuse hugin-tools``).

Sharpness is the mean squared Laplacian (OpenCV ``Laplacian``, ksize 3, on grey 0-255) with a 96 px border left
out: align_image_stack's frames carry black borders up to ~40 px wide, whose edges would otherwise count as
detail. Prints the table and writes crops to the temporary folder; ``--write`` puts the table into
docs/benchmarks.md and the crops into ``docs/img/real-pcb-crops.png``.

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

REPO = Path(__file__).resolve().parents[1]
# ../shared beside the checkout, or FIELDCAL_SHARED (the folder holding data/), or --stack
_SUB = Path("data") / "real-stacks" / "pcb-depthmap"
DEFAULT_STACK = (Path(os.environ["FIELDCAL_SHARED"]) / _SUB if os.environ.get("FIELDCAL_SHARED")
                 else REPO.parent / "shared" / _SUB)
BORDER = 96


def msl(img: np.ndarray) -> float:
    a = np.asarray(img)[..., :3].astype(np.float32)
    if a.max() > 255.5:
        a = a / 257.0
    g = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)
    lap = cv2.Laplacian(g, cv2.CV_32F, ksize=3)[BORDER:-BORDER, BORDER:-BORDER]
    return float(np.mean(lap.astype(np.float64) ** 2))


def time_composite(py, stack: Path, out: Path, n: int) -> dict:
    """Wall, CPU (user + system of the child) and peak RSS of one ``fieldcal composite`` process."""
    load = os.getloadavg()[0]
    code = ("import resource, subprocess, sys, time; t = time.perf_counter(); "
            "subprocess.run(sys.argv[1:], check=True); w = time.perf_counter() - t; "
            "u = resource.getrusage(resource.RUSAGE_CHILDREN); "
            "print(w, u.ru_utime + u.ru_stime, u.ru_maxrss / 1024)")
    r = subprocess.run([sys.executable, "-c", code, *py, "composite", str(stack), "--out", str(out), "--z-ref-um",
                        "0", "--quiet"], check=True, capture_output=True, text=True)
    wall, cpu, rss = (float(v) for v in r.stdout.split()[-3:])
    return {"run": "fieldcal composite", "frames": n, "wall (s)": f"{wall:.2f}", "CPU (s)": f"{cpu:.2f}",
            "peak RSS (MB)": f"{rss:.0f}", "load at start": f"{load:.1f}"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stack", type=Path, default=DEFAULT_STACK,
                    help="folder of the JPEG frames (default ../shared/data/real-stacks/pcb-depthmap beside the "
                         "checkout, or $FIELDCAL_SHARED/data/real-stacks/pcb-depthmap)")
    ap.add_argument("--write", action="store_true",
                    help="put the table into docs/benchmarks.md and the crops into docs/img/real-pcb-crops.png")
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
    shutil.copy(work / f"fieldcal{len(jpegs)}.tiff", work / "fieldcal.tiff")
    t_fc = timing[0]["wall (s)"]
    ours = tifffile.imread(work / "fieldcal.tiff")
    rows = {"a single frame (the sharpest, by this measure)": max(
        msl(cv2.imread(str(p))[..., ::-1]) for p in sorted(STACK.glob("*.JPG"))), "fieldcal": msl(ours)}
    enf = None
    if shutil.which("enfuse") and shutil.which("align_image_stack"):
        t0 = time.perf_counter()
        subprocess.run(["align_image_stack", "-m", "-a", str(work / "al_"), *map(str, sorted(STACK.glob("*.JPG")))],
                       check=True, capture_output=True)
        subprocess.run(["enfuse", "--exposure-weight=0", "--saturation-weight=0", "--contrast-weight=1",
                        "--hard-mask", f"--output={work / 'enfuse.tif'}", *map(str, sorted(work.glob("al_*.tif")))],
                       check=True, capture_output=True)
        t_enf = time.perf_counter() - t0
        enf = tifffile.imread(work / "enfuse.tif")[..., :3]
        rows["align_image_stack + enfuse --hard-mask"] = msl(enf)
    lines = ["| composite | mean squared Laplacian (96 px border out) |", "| --- | --- |"]
    lines += [f"| {k} | {v:.0f} |" for k, v in rows.items()]
    lines.append("")
    head = ["run", "frames", "wall (s)", "CPU (s)", "peak RSS (MB)", "load at start"]
    lines += ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    lines += ["| " + " | ".join(str(r[k]) for k in head) + " |" for r in timing]
    if enf is not None:
        lines.append(f"| align_image_stack + enfuse | {len(jpegs)} | {t_enf:.1f} | | | |")
    lines += ["", "Wall and CPU time (user + system, all threads) of `fieldcal composite STACK --out OUT "
                  "--z-ref-um 0` in its own process, registration included, 2048x1536 JPEG frames, first N "
                  "frames; peak RSS of that process. The machine is shared: the load average is the 1-minute one."]
    flags = flag_slowdowns("real_stack", "\n".join(lines), ("run", "frames"), ("wall (s)", "CPU (s)"))
    if flags:
        lines += ["", slowdown_note(flags)]
    print(f"fieldcal composite (registration included): {t_fc} s")
    print("\n".join(lines))
    # crops side by side (same geometry: the first frame's)
    h, w = ours.shape[:2]
    crops = []
    for (y, x) in ((int(0.45 * h), int(0.45 * w)), (int(0.15 * h), int(0.65 * w)), (int(0.7 * h), int(0.15 * w))):
        row = [ours[y:y + 256, x:x + 256, :3]]
        if enf is not None:
            e = enf if enf.dtype == np.uint8 else (enf / 257).astype(np.uint8)
            row = [e[y:y + 256, x:x + 256]] + row
        crops.append(np.concatenate(row, axis=1))
    # the docs' figure only with --write; otherwise beside the run, kept for a look
    out = (REPO / "docs" / "img" if a.write else Path(tempfile.gettempdir())) / "real-pcb-crops.png"
    cv2.imwrite(str(out), np.concatenate(crops, axis=0)[..., ::-1])
    print(f"crops ({'enfuse | fieldcal' if enf is not None else 'fieldcal'}, three regions): {out}")
    if a.write:
        doc = REPO / "docs" / "benchmarks.md"
        text = doc.read_text(encoding="utf-8")
        b, e = "<!-- bench_real_stack:begin -->", "<!-- bench_real_stack:end -->"
        block = "\n".join([b, "Real circuit-board stack (`python benchmarks/bench_real_stack.py --write`; crops: "
                              "[img/real-pcb-crops.png](img/real-pcb-crops.png), left enfuse, right fieldcal):", "",
                           *lines, e])
        if b in text:
            text = text[:text.index(b)] + block + text[text.index(e) + len(e):]
        else:
            text = text.rstrip() + "\n\n## A real stack with depth\n\n" + block + "\n"
        doc.write_text(text, encoding="utf-8")
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
