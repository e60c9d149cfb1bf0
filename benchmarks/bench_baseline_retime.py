"""Re-time issue 15's own baseline on this machine: how fast is it against the machine that timed the issue?

Issue 15 timed the compositor of its day at 7.5 s on the 7-frame 2048x1536 circuit-board stack "converted to TIFF
by hand". That code is commit ef2b85d (the layout commit made right after the issue: the same algorithm). This
script checks it out into a temporary worktree, converts the first 7 frames of
``../shared/data/real-stacks/pcb-depthmap`` (or ``$FIELDCAL_SHARED/...``) to 8-bit RGB TIFF with a minimal
``stack.json`` (pixel pitch 1.12 µm, z 0, 50, ... µm), composites it with that commit in a child process and
prints wall time, CPU time (user + sys, ``os.wait4``), peak RSS and the output's mean squared Laplacian (the sharpness
measure of ``bench_real_stack.py``). The issue's machine: 7.5 s, mean squared Laplacian 989.

    python benchmarks/bench_baseline_retime.py
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

_SUB = Path("data") / "real-stacks" / "pcb-depthmap"
DEFAULT_STACK = (Path(os.environ["FIELDCAL_SHARED"]) / _SUB if os.environ.get("FIELDCAL_SHARED")
                 else REPO.parent / "shared" / _SUB)
BASELINE = "ef2b85d"


def tiff_stack(frames: list[Path], out: Path, step_um: float = 50.0) -> Path:
    """The frames as 8-bit RGB TIFFs with the minimal stack.json the baseline reads."""
    import cv2
    import tifffile
    (out / "frames").mkdir(parents=True)
    rows = []
    for i, f in enumerate(frames):
        name = f"frames/{i:04d}.tiff"
        tifffile.imwrite(out / name, cv2.imread(str(f))[:, :, ::-1], photometric="rgb")
        rows.append({"file": name, "z_um": i * step_um,
                     "sha256": hashlib.sha256((out / name).read_bytes()).hexdigest()})
    (out / "stack.json").write_text(json.dumps({"format": "fieldcal-stack/1", "pixel_pitch_um": 1.12,
                                                "channels": ["R", "G", "B"], "frames": rows}, indent=1))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stack", type=Path, default=DEFAULT_STACK, help="folder of the real JPEG frames")
    ap.add_argument("--frames", type=int, default=7)
    ap.add_argument("--commit", default=BASELINE)
    args = ap.parse_args()
    import tifffile
    from bench_real_stack import msl

    frames = sorted(p for p in args.stack.iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))[:args.frames]
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "-q", "--detach", str(tree), args.commit],
                       check=True)
        try:
            stack = tiff_stack(frames, Path(tmp) / "stack")
            out = Path(tmp) / "out.tiff"
            env = dict(os.environ, PYTHONPATH=str(tree))
            t0 = time.perf_counter()
            # from the temporary folder: `python -m` puts the working directory first on sys.path
            child = subprocess.Popen([sys.executable, "-m", "fieldcal", "composite", str(stack), "--out", str(out)],
                                     cwd=tmp, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            _, status, ru = os.wait4(child.pid, 0)
            wall = time.perf_counter() - t0
            if status != 0:
                raise SystemExit(f"the composite of {args.commit} exited with status {status}")
            print(f"{args.commit}: {len(frames)} frames, {wall:.2f} s wall, {ru.ru_utime + ru.ru_stime:.2f} s CPU, "
                  f"{ru.ru_maxrss / 1024:.0f} MiB peak, mean squared Laplacian {msl(tifffile.imread(out)):.0f} "
                  f"(issue 15's machine: 7.5 s, 989)")
        finally:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)], check=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
