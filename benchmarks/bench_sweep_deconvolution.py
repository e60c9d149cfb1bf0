"""Sweep deconvolution: fieldcal's Wiener and Richardson-Lucy against scikit-image's ``restoration`` module.

The composite end-to-end test's simulated stack (the paper triplet on a 160 px sensor, tests/test_composite_e2e.py),
sweeps emulated at α = 8 and 16 µm, each method restoring the lens's in-focus image (skimage's results are then
blurred by the in-focus PSF, as fieldcal's are); PSNR against the simulator's all-in-focus truth. skimage gets the
same PSF kernel and mirror padding (its convolutions are zero-padded). Its ``wiener`` needs a hand-set balance:
the table lists several, the best chosen *with* the truth, which no user has. Writes ``results.md`` into --out.

    python benchmarks/bench_sweep_deconvolution.py --out /tmp/bench-deconv      # ~30 s
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import _common  # noqa: F401  (puts the repository on sys.path)

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "sweep_deconvolution"))
    args = ap.parse_args(argv)

    import cv2
    import numpy as np
    import tifffile
    from skimage import restoration

    from fieldcal.composite import deconvolve_sweep, emulate_sweep
    from fieldcal.composite.stack_profile import to_input_dtype
    from fieldcal.optics.sweep import sweep_psf_kernel
    from fieldcal.simulate import simulate_stack
    from fieldcal.simulate.scene import load_scene
    from fieldcal.simulate.truth import TruthProfile
    from tests.test_composite_e2e import SIZE, Z_UM, psnr, small_lens

    spec = small_lens(REPO / "models" / "triplet-uncorrected.json")
    scene = np.array(load_scene("chart", SIZE, SIZE, seed=2)[0], dtype=np.float32)
    scene[: SIZE // 2, SIZE // 2:] = 0.5
    root = Path(tempfile.mkdtemp(prefix="fieldcal-deconv-"))
    st = simulate_stack(spec, root / "stack", Z_UM, scene=scene, seed=1, progress=False)
    truth = tifffile.imread(root / "stack" / "truth.tiff")
    prof = TruthProfile(spec)
    white, black, pitch = st.white_level, st.black_level, prof.pixel_pitch_um

    def kernels(alpha, ch):
        size = 2 * int(np.ceil(1.5 * alpha / prof.f_number / pitch)) + 9  # as fieldcal's RL
        return (sweep_psf_kernel(prof, alpha, ch, pitch, size), sweep_psf_kernel(prof, 0.0, ch, pitch, 15), size)

    def skimage_channel(img, alpha, ch, how, arg):
        psf, focus, pad = kernels(alpha, ch)
        u = np.pad((img - black) / (white - black), pad, mode="symmetric")
        if how == "rl":
            est = restoration.richardson_lucy(np.clip(u, 0, None), psf, num_iter=arg, clip=False)
        elif how == "wiener":
            est = restoration.wiener(u, psf, arg, clip=False)
        else:
            est = restoration.unsupervised_wiener(u, psf, clip=False, rng=0)[0]
        est = cv2.filter2D(est[pad:-pad, pad:-pad].astype(np.float32), -1, focus.astype(np.float32),
                           borderType=cv2.BORDER_REFLECT)
        return est * (white - black) + black

    def skimage_image(img, alpha, how, arg=None):
        return np.stack([skimage_channel(img[..., c], alpha, ch, how, arg) for c, ch in enumerate(st.channels)], -1)

    def db(x):
        return psnr(to_input_dtype(np.asarray(x, np.float32), st.dtype, white), truth, white)

    lines = ["# Sweep deconvolution: fieldcal vs scikit-image (PSNR dB against the all-in-focus truth, time s)", "",
             "| method | α = 8 µm | α = 16 µm |", "| --- | --- | --- |"]
    rows: dict[str, list[str]] = {}
    for alpha in (8.0, 16.0):
        sw = emulate_sweep(st, prof, alpha, quiet=True).image
        cases = [("raw sweep (no deconvolution)", lambda: sw),
                 ("fieldcal Wiener (noise + power-law spectrum from the image)",
                  lambda: deconvolve_sweep(sw, prof, alpha, st.channels, black=black, white=white).image),
                 ("skimage unsupervised_wiener", lambda: skimage_image(sw, alpha, "uwiener"))]
        cases += [(f"skimage wiener, balance {b:g}", lambda b=b: skimage_image(sw, alpha, "wiener", b))
                  for b in (1e-4, 3e-4, 1e-3)]
        for n in (30, 100, 300):
            cases += [(f"fieldcal RL {n} it (starts from the observed image)",
                       lambda n=n: deconvolve_sweep(sw, prof, alpha, st.channels, black=black, white=white,
                                                    method="rl", rl_iterations=n).image),
                      (f"skimage richardson_lucy {n} it (starts from 0.5)",
                       lambda n=n: skimage_image(sw, alpha, "rl", n))]
        for name, fn in cases:
            t0 = time.perf_counter()
            out = fn()
            rows.setdefault(name, []).append(f"{db(out):.2f} ({time.perf_counter() - t0:.2f} s)")
    lines += [f"| {k} | {' | '.join(v)} |" for k, v in rows.items()]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
