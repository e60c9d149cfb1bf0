"""Compositing benchmark: quality against the all-in-focus truth, and speed/memory, vs align_image_stack + enfuse.

Quality: for each simulated lens (models/) and scene (dead-leaves texture, a photograph from scikit-image's
sample data) a stack is rendered at the frame positions a stack plan gives (fs = 80 cycles/mm, q = 0.05), and
composited by

* **oracle**: per pixel and channel the frame nearest the *true* surface (hard seams), true geometry;
* **profile**: fieldcal with the lens profile (the simulated lens's true surfaces and geometry);
* **profile (calibrated)**: with a profile fitted by ``fieldcal.calibrate`` to a chart stack (unless --no-calibrate);
* **dff / hybrid**: depth from focus with the profile's geometry / the profile refined by DFF;
* **dff, no profile**: depth from focus with breathing/shift measured from the stack (output at z_ref);
* **enfuse**: ``align_image_stack -m`` then ``enfuse --exposure-weight=0 --saturation-weight=0
  --contrast-weight=1 --hard-mask --gray-projector=l-star`` on the same frames (its output is mapped to the
  geometry of z_ref with the true lens geometry, which only helps it);

PSNR is over the image less a 2 % border. Side-by-side top-left corner crops go to docs/img/.
Sweep: the paper triplet's emulated sweep (alpha = 20 µm), Wiener and Richardson-Lucy, with noise gains.
Speed: ``fieldcal composite`` on N frames of W x H RGB 16-bit (synthetic content, timing does not depend on it),
wall time (best and median of --repeat runs), CPU time and peak RSS of the process and the load average (the
machine may be shared), optionally another source tree (--baseline-src: before/after in one run), and
align_image_stack + enfuse on the same stack (or on a smaller one, --ratio-size) in the same run.

    python benchmarks/bench_composite.py --quick                 # small images, a few minutes on 2 cores
    python benchmarks/bench_composite.py                          # 960x540 quality, 3840x2160x42 speed (the lead)
    python benchmarks/bench_composite.py --no-quality --ratio-size 1920x1080x42 \
        --baseline-src /tmp/before               # speed only: 4K, the ratio vs enfuse at 1080p, before/after
    python benchmarks/bench_composite_profile.py --work /tmp/bcp  # makes /tmp/bcp/lens.json (calibrated, 1080p)
    python benchmarks/bench_composite.py --no-quality --no-enfuse --speed-profile /tmp/bcp/lens.json \
        --work /tmp/bcs                          # issue 18: 42 x 4K RGB16 with a calibrated profile

A timing 2x slower than the stored table's (same row) is flagged on stderr and under the table.

Results go between ``<!-- bench_composite:start -->`` and ``<!-- bench_composite:end -->`` in
docs/benchmarks.md (the rest of the file is left alone) and to --work/results.json.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import flag_slowdowns, slowdown_note  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
START, END = "<!-- bench_composite:start -->", "<!-- bench_composite:end -->"
SPEED_START, SPEED_END = "<!-- bench_composite_speed:start -->", "<!-- bench_composite_speed:end -->"
ENFUSE_ARGS = ["--exposure-weight=0", "--saturation-weight=0", "--contrast-weight=1", "--hard-mask",
               "--gray-projector=l-star"]
INSTALL_HINT = "apt-get install hugin-tools enfuse   (Debian/Ubuntu: align_image_stack is in hugin-tools)"


# ------------------------------------------------------------------------------------------------ helpers
def have_enfuse() -> bool:
    return shutil.which("enfuse") is not None and shutil.which("align_image_stack") is not None


def psnr(img, truth, white, border=0.02) -> float:
    img = img if img.ndim == 3 else img[..., None]
    truth = truth if truth.ndim == 3 else truth[..., None]
    h, w = truth.shape[:2]
    by, bx = max(1, int(border * h)), max(1, int(border * w))
    d = img.astype(np.float64)[by:-by, bx:-bx] - truth.astype(np.float64)[by:-by, bx:-bx]
    return float(10 * np.log10(white ** 2 / max(np.mean(d * d), 1e-12)))


def photo_scene():
    from skimage import data
    return data.astronaut().astype(np.float32) / 255.0


def corner_crop_spec(spec, width: int, height: int):
    """The top-left ``width x height`` pixels of the lens's native sensor, at the native pitch: a real corner
    of the field (the optical centre moves off the small sensor via ``decentre_mm``)."""
    import dataclasses as dc
    s = spec.sensor
    dx = ((s.width_px - 1) / 2.0 - (width - 1) / 2.0) * s.pixel_pitch_um / 1000.0
    dy = ((s.height_px - 1) / 2.0 - (height - 1) / 2.0) * s.pixel_pitch_um / 1000.0
    return dc.replace(spec, name=spec.name + "-corner", sensor=dc.replace(s, width_px=width, height_px=height),
                      decentre_mm=(spec.decentre_mm[0] + dx, spec.decentre_mm[1] + dy))


def plan_positions(prof) -> np.ndarray:
    """Frame positions of a stack plan at fs = 80 cycles/mm, q = 0.05 (the planning module's optimum)."""
    from fieldcal.plan import StackRequest, plan_stack
    plan = plan_stack(prof, StackRequest(fs_cyc_per_mm=80.0, q=0.05))
    return np.array(sorted(f["z_um"] for f in plan.to_dict()["frames"]))


def timed(cmd, cwd=None, env=None) -> tuple[float, float, subprocess.CompletedProcess, float]:
    """Wall time (s), peak RSS (MB), the completed process and CPU time (user + system, s) of a command,
    via /usr/bin/time when present (else RSS and CPU are NaN)."""
    gnu_time = Path("/usr/bin/time")
    full = ([str(gnu_time), "-f", "__RSS_KB__ %M %U %S"] if gnu_time.exists() else []) + [str(c) for c in cmd]
    t0 = time.perf_counter()
    r = subprocess.run(full, capture_output=True, text=True, cwd=cwd, env=env)
    dt = time.perf_counter() - t0
    rss = cpu = float("nan")
    for line in r.stderr.splitlines():
        if line.startswith("__RSS_KB__"):
            _, kb, user, system = line.split()
            rss, cpu = float(kb) / 1024.0, float(user) + float(system)
    return dt, rss, r, cpu


def run_enfuse(stack, frames_sorted, work: Path) -> tuple[np.ndarray | None, float, float, str, float]:
    """align_image_stack + enfuse on the frames; returns (image or None, wall s, peak MB, note, CPU s)."""
    import tifffile
    work.mkdir(parents=True, exist_ok=True)
    files = [stack.frames[int(i)].path for i in frames_sorted]
    # align to the frame nearest z_ref (first in the list), then outwards in z order
    t1, m1, r, c1 = timed(["align_image_stack", "-m", "-a", work / "al_", "--use-given-order", *files])
    aligned = sorted(work.glob("al_*.tif"))
    note = ""
    if r.returncode != 0 or len(aligned) != len(files):
        note = "align_image_stack failed; enfuse on unaligned frames"
        aligned = files
    t2, m2, r2, c2 = timed(["enfuse", *ENFUSE_ARGS, "-o", work / "enfuse.tif", *aligned])
    if r2.returncode != 0:
        return None, t1 + t2, max(m1, m2), "enfuse failed: " + r2.stderr.strip()[-200:], c1 + c2
    img = tifffile.imread(work / "enfuse.tif")
    if img.ndim == 3 and img.shape[2] > len(stack.channels):
        img = img[..., :len(stack.channels)]  # drop enfuse's alpha
    if img.ndim == 2:
        img = img[..., None]
    return img, t1 + t2, max(m1, m2), note, c1 + c2


def to_zref(img, prof, z_um, channels, dtype, white):
    """Map an image in the geometry of the frame at z into the geometry of z_ref (true lens geometry)."""
    from fieldcal.composite import ArrayStack
    from fieldcal.composite.stack_profile import to_input_dtype
    from fieldcal.composite.warp import warp_frame_by_profile
    s = ArrayStack([img.astype(np.float32)], [float(z_um)], channels)
    h, w = img.shape[:2]
    return to_input_dtype(warp_frame_by_profile(s, 0, prof, w, h), dtype, white)


def save_crops(path: Path, panels: list[tuple[str, np.ndarray]], white: float, crop: int) -> None:
    """Top-left corner crops side by side, labelled, 8-bit PNG (display gamma 1/2.2)."""
    import cv2
    tiles = []
    for label, img in panels:
        c = img[:crop, :crop].astype(np.float32) / white
        c = np.clip(c, 0, 1) ** (1 / 2.2)
        c = (c * 255).astype(np.uint8)
        if c.shape[2] == 1:
            c = np.repeat(c, 3, axis=2)
        c = cv2.resize(c[..., ::-1], (2 * crop, 2 * crop), interpolation=cv2.INTER_NEAREST)
        c = np.ascontiguousarray(c)
        cv2.putText(c, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 255, 255), 1, cv2.LINE_AA)
        tiles.append(c)
        tiles.append(np.zeros((2 * crop, 4, 3), np.uint8))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(tiles[:-1], axis=1))


# ------------------------------------------------------------------------------------------------ quality
def quality(lens: str, scene_name: str, width: int, work: Path, enfuse: bool, calibrate: bool,
            img_dir: Path | None, corner: bool = False) -> dict:
    import tifffile
    from fieldcal.composite import composite_stack
    from fieldcal.composite.stack_profile import to_input_dtype
    from fieldcal.composite.stream import accumulate
    from fieldcal.composite.surface import profile_focus_map
    from fieldcal.composite.weights import BlendKernel
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate import simulate_stack
    from fieldcal.simulate.truth import TruthProfile

    spec0 = LensSpec.load(REPO / "models" / f"{lens}.json")
    height = round(width * spec0.sensor.height_px / spec0.sensor.width_px)
    if corner:
        spec = corner_crop_spec(spec0, width, height)
        z = plan_positions(TruthProfile(spec))
    else:
        spec = spec0.with_sensor_size(width, height)
        z = plan_positions(TruthProfile(spec0, width, height))
    prof = TruthProfile(spec)
    scene = "chart" if scene_name == "texture" else photo_scene()
    sdir = work / f"{lens}-{scene_name}-{width}{'-corner' if corner else ''}"
    st = simulate_stack(spec, sdir, z, scene=scene, seed=3, progress=False, overwrite=True)
    truth = tifffile.imread(sdir / "truth.tiff")
    truth = truth if truth.ndim == 3 else truth[..., None]
    white = st.white_level
    row = {"lens": lens + (" (corner, native pitch)" if corner else ""), "scene": scene_name,
           "size": [width, height], "frames": len(st)}
    panels = [("truth", truth)]
    zb = profile_focus_map(prof, width, height, st.channels)
    oracle = to_input_dtype(accumulate(st, zb, BlendKernel(np.sort(st.z_um), 0.0, min_band=0.0), prof,
                                       quiet=True), st.dtype, white)
    row["oracle"] = psnr(oracle, truth, white)
    panels.append(("oracle", oracle))
    best = max(range(len(st)), key=lambda i: psnr(st.read(i), truth, white))
    row["best single frame"] = psnr(st.read(best), truth, white)
    for label, method, p in (("profile", "profile", prof), ("dff", "dff", prof), ("hybrid", "hybrid", prof),
                             ("dff, no profile", "dff", None)):
        t0 = time.perf_counter()
        res = composite_stack(st, p, method, quiet=True, z_ref_um=spec.z_ref_um)
        row[label] = psnr(res.image, truth, white)
        row[label + " s"] = time.perf_counter() - t0
        if label in ("profile", "dff"):
            panels.append((label, res.image))
    if calibrate:
        try:
            row["profile (calibrated)"] = calibrated_psnr(spec, z, work, st, truth, white)
        except Exception as e:  # report, do not hide: the row says why
            row["profile (calibrated)"] = f"failed: {type(e).__name__}: {e}"[:160]
    if enfuse:
        order = np.argsort(np.abs(st.z_um - spec.z_ref_um))[:1].tolist()
        rest = [int(i) for i in np.argsort(st.z_um)[::-1] if int(i) not in order]
        # align_image_stack's RANSAC is not always repeatable (we saw 29.0 and 19.8 dB on one stack):
        # run it twice and keep the better, reporting both when they differ
        tries = []
        for rep in range(2):
            edir = work / f"enfuse-{lens}-{scene_name}{'-corner' if corner else ''}-{rep}"
            shutil.rmtree(edir, ignore_errors=True)
            img, t, _, note, _ = run_enfuse(st, order + rest, edir)
            if img is not None:
                img = to_zref(img, prof, float(st.z_um[order[0]]), st.channels, st.dtype, white)
                tries.append((psnr(img, truth, white), img, note))
            else:
                row["enfuse note"] = note
        if tries:
            best_try = max(tries, key=lambda x: x[0])
            row["enfuse"] = best_try[0]
            panels.append(("enfuse", best_try[1]))
            row["enfuse note"] = best_try[2]
            if abs(tries[0][0] - tries[-1][0]) > 0.05:
                row["enfuse note"] = (row["enfuse note"] + " " if row["enfuse note"] else "") + \
                    "two runs gave " + " and ".join(f"{t[0]:.2f}" for t in tries) + " dB (best kept)"
    panels.append((f"single z={st.z_um[best]:.0f}", st.read(best)))
    if img_dir is not None:
        name = f"composite-{lens}-{scene_name}{'-corner' if corner else ''}.png"
        save_crops(img_dir / name, panels, white, crop=min(96, width // 5))
        row["crops"] = f"img/{name}"
    return row


def calibrated_psnr(spec, z, work: Path, scene_stack, truth, white) -> float:
    """Calibrate from a chart stack of the same lens, then composite the scene stack with that profile."""
    from fieldcal.calibration.pipeline import calibrate
    from fieldcal.composite import composite_stack
    from fieldcal.simulate import simulate_stack
    lo, hi = spec.focus_range_um()
    zc = np.unique(np.round(np.concatenate([np.arange(lo - 20, hi + 20, 8.0), [spec.z_ref_um]]), 3))
    chart = simulate_stack(spec, work / f"chart-{spec.name}", zc, scene="chart", seed=11, progress=False,
                           overwrite=True)
    nyquist = 1000.0 / (2.0 * spec.sensor.pixel_pitch_um)
    prof = calibrate(chart, fs_cyc_per_mm=min(80.0, 0.5 * nyquist), effort="quick", z_ref_um=spec.z_ref_um,
                     quiet=True)
    return psnr(composite_stack(scene_stack, prof, "profile", quiet=True).image, truth, white)


# ------------------------------------------------------------------------------------------------- sweep
def sweep(width: int, work: Path) -> dict:
    import tifffile
    from fieldcal.composite import deconvolve_sweep, emulate_sweep
    from fieldcal.composite.stack_profile import to_input_dtype
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate import simulate_stack
    from fieldcal.simulate.truth import TruthProfile

    spec0 = LensSpec.load(REPO / "models" / "triplet-uncorrected.json")
    height = round(width * spec0.sensor.height_px / spec0.sensor.width_px)
    spec = corner_crop_spec(spec0, width, height)  # native pitch: the sweep blur is several pixels
    prof = TruthProfile(spec)
    lo, hi = spec.focus_range_um()
    z = np.arange(np.floor(lo) - 24, hi + 24, 4.0)  # dense: the paper emulates with ~4 um steps
    st = simulate_stack(spec, work / f"sweep-{width}", z, scene="chart", seed=5, progress=False, overwrite=True)
    truth = tifffile.imread(work / f"sweep-{width}" / "truth.tiff")
    out = {"size": [width, height], "frames": len(st), "rows": []}
    for alpha in (10.0, 20.0, 40.0):
        sw = emulate_sweep(st, prof, alpha, quiet=True)
        raw = psnr(to_input_dtype(sw.image, st.dtype, st.white_level), truth, st.white_level)
        t0 = time.perf_counter()
        wi = deconvolve_sweep(sw.image, prof, alpha, st.channels, black=st.black_level, white=st.white_level,
                              noise_sigma=sw.info["noise_sigma"])
        tw = time.perf_counter() - t0
        rl = deconvolve_sweep(sw.image, prof, alpha, st.channels, black=st.black_level, white=st.white_level,
                              method="rl", rl_iterations=30)
        out["rows"].append({
            "alpha_um": alpha, "sweep": raw,
            "wiener": psnr(to_input_dtype(wi.image, st.dtype, st.white_level), truth, st.white_level),
            "rl30": psnr(to_input_dtype(rl.image, st.dtype, st.white_level), truth, st.white_level),
            "noise_gain": float(np.mean([c["noise_gain"] for c in wi.info["channels"].values()])),
            "wiener_s": tw})
    return out


# ------------------------------------------------------------------------------------------------- speed
def make_speed_stack(path: Path, width: int, height: int, n: int) -> None:
    """N frames of smooth random texture, RGB uint16 with 12-bit values, z over the triplet's focus range."""
    import cv2
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.formats.stack import Stack, StackWriter
    if (path / "stack.json").exists():
        try:
            s = Stack.open(path)
            if len(s) == n and s.shape == (height, width):
                return
        except Exception:
            pass
    spec = LensSpec.load(REPO / "models" / "triplet-uncorrected.json")
    lo, hi = spec.focus_range_um()
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.random((height, width, 3), dtype=np.float32), (0, 0), 2.0)
    base = (base - base.min()) / (base.max() - base.min())
    w = StackWriter.create(path, pixel_pitch_um=spec.sensor.pixel_pitch_um * spec.sensor.width_px / width,
                           channels=["R", "G", "B"], overwrite=True, bit_depth=12)
    for k, z in enumerate(np.linspace(lo - 5, hi + 5, n)):
        noise = rng.normal(0, 0.01, (height, width, 1)).astype(np.float32)
        w.add_frame(np.clip((base + noise) * 4095, 0, 4095).astype(np.uint16), float(round(z, 3)))


def _fieldcal_runs(spath: Path, lens: Path, out: Path, repeat: int, src: Path | None = None) -> dict:
    """``fieldcal composite`` (profile method) ``repeat`` times: best and median wall, CPU, peak RSS, load."""
    import os
    env = dict(os.environ, FIELDCAL_PROGRESS="0")
    if src is not None:  # another fieldcal source tree (e.g. before a change), ahead of the installed one
        env["PYTHONPATH"] = os.pathsep.join([str(src), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    cmd = [sys.executable, "-m", "fieldcal", "composite", Path(spath).resolve(), "--profile", Path(lens).resolve(),
           "--quiet", "--overwrite", "--out", Path(out).resolve()]
    runs = []
    for _ in range(max(1, repeat)):
        load = os.getloadavg()[0]
        # run from the output folder: `python -m` puts the working directory first on sys.path, and from the
        # repository that would shadow --baseline-src with the checkout's own fieldcal
        t, rss, r, cpu = timed(cmd, env=env, cwd=Path(out).resolve().parent)
        if r.returncode != 0:
            return {"error": r.stderr.strip()[-300:]}
        runs.append({"wall_s": t, "cpu_s": cpu, "rss_mb": rss, "load_1min": load})
    walls = sorted(x["wall_s"] for x in runs)
    return {"runs": runs, "wall_best_s": walls[0], "wall_median_s": float(np.median(walls)),
            "cpu_best_s": min(x["cpu_s"] for x in runs), "rss_max_mb": max(x["rss_mb"] for x in runs),
            "load_1min": float(np.mean([x["load_1min"] for x in runs]))}


def profile_on_finer_grid(src: Path, dst: Path, factor: int) -> Path:
    """A calibrated ``fieldcal-profile/1`` moved onto a sensor grid ``factor`` times finer (same sensor area, pitch
    / factor): image size and pitch, and the shift coefficients (px) scale; the surfaces and their discrepancy
    are in normalised coordinates and stay. Lets the 4K speed run use a profile calibrated at 1920x1080 (a 4K
    chart stack takes long to simulate): the compositing work is the same as with a 4K calibration."""
    import json
    d = json.loads(Path(src).read_text(encoding="utf-8"))
    for block in (d["image"], d["surfaces"]["geometry"]):
        block["width_px"] *= factor
        block["height_px"] *= factor
        block["pixel_pitch_um"] /= factor
    for key in ("shift_x_px", "shift_y_px"):
        for fit in d["geometry"][key].values():
            fit["coef"] = [c * factor for c in fit["coef"]]
            fit["cov"] = [[c * factor * factor for c in row] for row in fit["cov"]]
    Path(dst).write_text(json.dumps(d), encoding="utf-8")
    side = d.get("sidecar")
    if side:  # the calibration samples, checked by sha256 when the profile loads
        shutil.copy(Path(src).parent / side["file"], Path(dst).parent / side["file"])
    return Path(dst)


def _speed_inputs(width: int, height: int, n: int, work: Path, profile: Path | None = None) -> tuple[Path, Path]:
    """The speed stack and its profile: the lens's truth, or ``profile`` (calibrated; resampled onto this size's
    grid when it was calibrated at a whole fraction of it)."""
    from fieldcal.simulate.lens import LensSpec
    spath = work / f"speed-{width}x{height}x{n}"
    make_speed_stack(spath, width, height, n)
    if profile is not None:
        from fieldcal.profile.lens_profile import LensProfile
        pw, ph = LensProfile.load(profile).image_size_px
        factor = width // pw
        if (pw * factor, ph * factor) != (width, height):
            raise SystemExit(f"--speed-profile is for {pw}x{ph} px; the speed stack is {width}x{height}")
        if factor == 1:
            return spath, Path(profile)
        return spath, profile_on_finer_grid(profile, work / f"speed-calibrated-{width}x{height}.json", factor)
    spec = LensSpec.load(REPO / "models" / "triplet-uncorrected.json").with_sensor_size(width, height)
    lens = work / f"speed-lens-{width}x{height}.json"
    spec.save(lens)
    return spath, lens


def speed(size: tuple[int, int, int], work: Path, enfuse: bool, ratio_size: tuple[int, int, int] | None = None,
          repeat: int = 3, baseline: Path | None = None, profile: Path | None = None) -> dict:
    """fieldcal's time on the speed stack (and a baseline source tree's, if given), and the ratio against
    align_image_stack + enfuse measured in the same run on ``ratio_size`` (default: the speed stack).
    ``profile``: a calibrated profile (see :func:`_speed_inputs`) instead of the lens's truth."""
    import os
    from fieldcal.formats.stack import Stack
    spath, lens = _speed_inputs(*size, work, profile)
    out = {"size": list(size[:2]), "frames": size[2], "cores": len(os.sched_getaffinity(0)),
           "profile": "calibrated" if profile is not None else "truth"}
    out["fieldcal"] = _fieldcal_runs(spath, lens, work / "speed-profile.tiff", repeat)
    if baseline is not None:
        out["baseline"] = _fieldcal_runs(spath, lens, work / "speed-baseline.tiff", repeat, src=baseline)
        out["baseline_src"] = str(baseline)
    if enfuse:
        rsize = ratio_size or size
        rpath, rlens = (spath, lens) if tuple(rsize) == tuple(size) else _speed_inputs(*rsize, work, profile)
        fc = out["fieldcal"] if rpath == spath else _fieldcal_runs(rpath, rlens, work / "ratio-profile.tiff", repeat)
        st = Stack.open(rpath)
        order = [int(i) for i in np.argsort(st.z_um)[::-1]]
        shutil.rmtree(work / "enfuse-speed", ignore_errors=True)
        load = os.getloadavg()[0]
        _, te, me, note, ce = run_enfuse(st, order, work / "enfuse-speed")
        out["ratio"] = {"size": list(rsize[:2]), "frames": rsize[2], "fieldcal": fc,
                        "enfuse": {"wall_s": te, "cpu_s": ce, "rss_mb": me, "load_1min": load, "note": note}}
        if "wall_best_s" in fc:
            out["ratio"]["speed-up wall"] = te / fc["wall_median_s"]
            out["ratio"]["speed-up cpu"] = ce / fc["cpu_best_s"] if fc["cpu_best_s"] > 0 else float("nan")
    return out


# -------------------------------------------------------------------------------------------------- docs
def fmt(v):
    if isinstance(v, float):
        return f"{v:.2f}"
    v = str(v)
    return "failed (see notes)" if v.startswith("failed") else v.replace("|", "/").replace("\n", " ")


def markdown(res: dict) -> str:
    q = res["quality"]
    cols = ["oracle", "profile", "profile (calibrated)", "dff", "hybrid", "dff, no profile", "enfuse",
            "best single frame"]
    cols = [c for c in cols if any(c in r for r in q)]
    lines = [START, "", f"### Compositing (`benchmarks/bench_composite.py{' --quick' if res['quick'] else ''}`)", "",
             "PSNR (dB) against the simulator's all-in-focus truth; frames at a stack plan's positions "
             "(fs = 80 cy/mm, q = 0.05). *oracle*: the frame nearest the true surface per pixel and channel. "
             "*profile*: fieldcal with the lens's true profile; *calibrated*: with `fieldcal.calibrate` on a chart "
             "stack. *enfuse*: `align_image_stack -m` + `enfuse " + " ".join(ENFUSE_ARGS) + "`.", "",
             "| lens | scene | size | frames | " + " | ".join(cols) + " |",
             "| --- | --- | --- | --- | " + " | ".join("---" for _ in cols) + " |"]
    for r in q:
        lines.append(f"| {r['lens']} | {r['scene']} | {r['size'][0]}x{r['size'][1]} | {r['frames']} | "
                     + " | ".join(fmt(r.get(c, "–")) for c in cols) + " |")
    notes = [f"{r['lens']}/{r['scene']}: {r['enfuse note']}" for r in q if r.get("enfuse note")]
    notes += [f"{r['lens']}/{r['scene']} calibrated profile: " + str(r["profile (calibrated)"]).split("\n")[0][8:]
              for r in q if str(r.get("profile (calibrated)", "")).startswith("failed")]
    if not res["enfuse"]:
        notes.append(f"enfuse/align_image_stack not installed: {INSTALL_HINT}")
    if notes:
        lines += ["", "Notes: " + "; ".join(notes)]
    lines += ["", "Corner crops (top-left, 2x nearest-neighbour): truth | oracle | profile | dff | enfuse | "
              "best single frame.", ""]
    lines += [f"![{r['lens']} {r['scene']}]({r['crops']})" for r in q if "crops" in r]
    sw = res.get("sweep")
    if sw:
        lines += ["", f"Focal sweep emulated from a {sw['frames']}-frame, 4 µm stack of the triplet "
                      f"(top-left {sw['size'][0]}x{sw['size'][1]} px of the 4K sensor at its native pitch), "
                      "deconvolved with the integrated PSF (noise from the stack's frames):", "",
                  "| α (µm) | sweep | Wiener | Richardson–Lucy (30 it.) | Wiener noise gain |",
                  "| --- | --- | --- | --- | --- |"]
        for r in sw["rows"]:
            lines.append(f"| {r['alpha_um']:g} | {r['sweep']:.2f} | {r['wiener']:.2f} | {r['rl30']:.2f} | "
                         f"{r['noise_gain']:.2f} |")
    lines += ["", speed_markdown(res), "", END]
    return "\n".join(lines)


def speed_markdown(res: dict) -> str:
    """The speed table between its own markers (a --no-quality run replaces only this part)."""
    sp = res.get("speed")
    if not sp:
        return ""
    w, h, n = sp["size"][0], sp["size"][1], sp["frames"]
    argv = res.get("argv", "")
    lines = [SPEED_START, "", f"#### Speed (`python benchmarks/bench_composite.py{' ' + argv if argv else ''}`)", "",
             "`fieldcal composite STACK --profile lens.json` (profile method, "
             + ("a calibrated profile (`--speed-profile`; made for a coarser grid, it is moved onto this one by "
                "`profile_on_finer_grid`)" if sp.get("profile") == "calibrated" else "the lens's truth profile")
             + f") on {n} frames of {w}x{h} RGB 16-bit "
             f"(uncompressed TIFF, 12-bit values), {sp['cores']} cores, {res.get('repeat', 1)} run(s) each: wall "
             "time of the whole process (imports, reading, compositing, writing the TIFF) best and median, CPU "
             "time (user + system) of the best run, peak RSS (`/usr/bin/time`), and the 1-minute load average "
             "when it started — the machine is shared, so wall time depends on the load; CPU time much less.", "",
             "| what | stack | wall best (s) | wall median (s) | CPU (s) | peak RSS (MB) | load at start |",
             "| --- | --- | --- | --- | --- | --- | --- |"]

    def row(label, size, r):
        if "error" in r:
            return f"| {label} | {size} | failed: {fmt(r['error'])[:80]} | | | | |"
        return (f"| {label} | {size} | {fmt(r['wall_best_s'])} | {fmt(r['wall_median_s'])} | "
                f"{fmt(r['cpu_best_s'])} | {fmt(r['rss_max_mb'])} | {r['load_1min']:.1f} |")

    size = f"{w}x{h}x{n}"
    if "baseline" in sp:
        lines.append(row(f"fieldcal before (`{sp['baseline_src']}`)", size, sp["baseline"]))
    label = "fieldcal, calibrated profile" if sp.get("profile") == "calibrated" else "fieldcal"
    lines.append(row(label, size, sp["fieldcal"]))
    ra = sp.get("ratio")
    if ra:
        rs = f"{ra['size'][0]}x{ra['size'][1]}x{ra['frames']}"
        if rs != size:
            lines.append(row(label, rs, ra["fieldcal"]))
        e = ra["enfuse"]
        lines.append(f"| align_image_stack + enfuse | {rs} | {fmt(e['wall_s'])} | – | {fmt(e['cpu_s'])} | "
                     f"{fmt(e['rss_mb'])} | {e['load_1min']:.1f} |")
        if "speed-up wall" in ra:
            lines += ["", f"On the same {rs} stack in the same run fieldcal is {ra['speed-up wall']:.1f}x faster "
                          f"than align_image_stack + enfuse in wall time (median) and {ra['speed-up cpu']:.1f}x in "
                          "CPU time." + (f" enfuse: {e['note']}." if e.get("note") else "")]
    lines += ["", SPEED_END]
    return "\n".join(lines)


def write_docs(doc: Path, section: str, speed_only: bool = False) -> None:
    """Replace our section of docs/benchmarks.md (or, for a speed-only run, only its speed table)."""
    from fieldcal.formats.atomic import atomic_write_text
    text = doc.read_text() if doc.exists() else "# Benchmarks\n"
    if speed_only and START in text and END in text:
        if SPEED_START in text and SPEED_END in text:
            a, b = text.index(SPEED_START), text.index(SPEED_END) + len(SPEED_END)
            text = text[:a] + section + text[b:]
        else:
            b = text.index(END)
            text = text[:b] + section + "\n\n" + text[b:]
    elif START in text and END in text:
        a, b = text.index(START), text.index(END) + len(END)
        text = text[:a] + section + text[b:]
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    atomic_write_text(doc, text)


def _shown_argv(argv: list[str]) -> str:
    """The command line for the docs, with local folders replaced by DIR."""
    out, hide = [], False
    for a in argv:
        if hide:
            out.append("DIR")
            hide = False
        elif a in ("--work", "--baseline-src", "--docs", "--speed-profile"):
            out.append(a)
            hide = True
        elif a.split("=")[0] in ("--work", "--baseline-src", "--docs", "--speed-profile"):
            out.append(a.split("=")[0] + "=DIR")
        else:
            out.append(a)
    return " ".join(out)


def main(argv=None) -> int:
    import os
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small images and a small speed stack (minutes)")
    ap.add_argument("--work", default=None, help="scratch folder for stacks (default: a temporary folder)")
    ap.add_argument("--width", type=int, default=None, help="quality image width (default 960, quick 384)")
    ap.add_argument("--speed-size", default=None, help="WxHxN of the speed stack (default 3840x2160x42, "
                                                       "quick 960x540x42)")
    ap.add_argument("--ratio-size", default=None, help="WxHxN of the stack for the ratio against enfuse, "
                                                       "measured in the same run (default: the speed stack; "
                                                       "enfuse takes ~20x longer than fieldcal)")
    ap.add_argument("--repeat", type=int, default=3, help="fieldcal runs per stack (best and median reported)")
    ap.add_argument("--baseline-src", default=None, metavar="DIR",
                    help="also time another fieldcal source tree on the speed stack, e.g. the code before a "
                         "change: git archive COMMIT fieldcal | tar -x -C DIR")
    ap.add_argument("--speed-profile", default=None, metavar="PROFILE",
                    help="time with this calibrated profile (e.g. bench_composite_profile.py's WORK/lens.json, "
                         "1920x1080; moved onto a 2x finer grid for a 3840x2160 stack) instead of the truth")
    ap.add_argument("--no-enfuse", action="store_true", help="skip align_image_stack + enfuse")
    ap.add_argument("--no-calibrate", action="store_true", help="skip the calibrated-profile row")
    ap.add_argument("--no-speed", action="store_true")
    ap.add_argument("--no-quality", action="store_true",
                    help="speed only (replaces only the speed table in docs/benchmarks.md)")
    ap.add_argument("--docs", default=str(REPO / "docs" / "benchmarks.md"))
    ap.add_argument("--no-docs", action="store_true", help="print only, do not touch docs/")
    args = ap.parse_args(argv)
    os.environ.setdefault("FIELDCAL_PROGRESS", "0")

    enfuse = not args.no_enfuse and have_enfuse()
    if not args.no_enfuse and not enfuse:
        print(f"align_image_stack/enfuse not found; install with: {INSTALL_HINT}", file=sys.stderr)
    width = args.width or (384 if args.quick else 960)
    ss = args.speed_size or ("960x540x42" if args.quick else "3840x2160x42")
    size = tuple(int(v) for v in ss.lower().split("x"))
    ratio = tuple(int(v) for v in args.ratio_size.lower().split("x")) if args.ratio_size else None
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="bench-composite-"))
    work.mkdir(parents=True, exist_ok=True)
    img_dir = None if args.no_docs else Path(args.docs).parent / "img"
    res = {"quick": args.quick, "enfuse": enfuse, "cores": os.cpu_count(), "quality": [], "repeat": args.repeat,
           "argv": _shown_argv(argv if argv is not None else sys.argv[1:])}
    cases = [("triplet-uncorrected", "texture", False), ("triplet-uncorrected", "photo", False),
             ("triplet-uncorrected", "texture", True), ("singlet-colour", "texture", False),
             ("doublet-mono", "photo", False)]
    for lens, scene, corner in ([] if args.no_quality else cases):
        t0 = time.perf_counter()
        row = quality(lens, scene, width, work, enfuse,
                      not args.no_calibrate and scene == "texture" and not corner, img_dir, corner)
        res["quality"].append(row)
        print(f"{lens}/{scene}: " + ", ".join(f"{k}={fmt(v)}" for k, v in row.items()
                                               if isinstance(v, float) and not k.endswith(" s"))
              + f"  ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    if not args.no_quality:
        res["sweep"] = sweep(width, work)
        print("sweep:", json.dumps(res["sweep"]["rows"]), file=sys.stderr)
    if not args.no_speed:
        res["speed"] = speed(size, work, enfuse, ratio, args.repeat,
                             Path(args.baseline_src) if args.baseline_src else None,
                             Path(args.speed_profile) if args.speed_profile else None)
        print("speed:", json.dumps(res["speed"]), file=sys.stderr)
    (work / "results.json").write_text(json.dumps(res, indent=2, default=str))
    section = speed_markdown(res) if args.no_quality else markdown(res)
    # a figure 2x slower than the table it replaces is flagged, here and under the table
    flags = flag_slowdowns("composite_speed", speed_markdown(res), ("what", "stack"),
                           ("wall best (s)", "wall median (s)", "CPU (s)"), path=Path(args.docs))
    if flags:
        section = section.replace(SPEED_END, slowdown_note(flags) + "\n\n" + SPEED_END)
    print(section)
    if not args.no_docs and section:
        write_docs(Path(args.docs), section, speed_only=args.no_quality)
    return 0


if __name__ == "__main__":
    sys.exit(main())
