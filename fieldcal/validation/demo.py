"""The numbers behind ``fieldcal demo``: its settings for a lens, and the comparison of its composite with the truth.

The demo itself runs the CLI commands a user would type (it is a tour of the command line); what it decides
and measures is here, as Python: :func:`demo_settings` (fs, the chart's z range and step, the sweep's alpha)
and :func:`compare_with_truth` (PSNR of the composite and of one shot against the simulator's all-in-focus
image, and a picture of corner crops).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class DemoSettings:
    """What the demo asks of each stage for a lens at its render size.

    ``fs_cyc_per_mm`` is the paper's 80 cycles/mm where the render resolves it, else 40 % of Nyquist;
    ``tolerance_um`` the narrowest channel's focus tolerance at (fs, q); the chart stack spans the best-focus
    range ``focus_lo_um .. focus_hi_um`` plus four steps each side, on a grid through ``z_ref`` with
    ``step_um`` ~ half the tolerance; ``alpha_um`` (the sweep's half-range) ~ twice the tolerance.
    """

    fs_cyc_per_mm: float
    tolerance_um: float
    focus_lo_um: float
    focus_hi_um: float
    z_start_um: float
    z_stop_um: float
    step_um: float
    alpha_um: float


def demo_settings(spec, q: float) -> DemoSettings:
    """The demo's settings for a simulated lens (a ``LensSpec`` already at the render size)."""
    nyquist = 1000.0 / (2.0 * spec.sensor.pixel_pitch_um)
    fs = float(min(80.0, round(0.4 * nyquist)))
    tol = min(spec.focus_tolerance_um(fs, q, c) for c in spec.channel_names)
    lo, hi = spec.focus_range_um()
    step = max(1.0, round(tol / 2.0, 1))
    margin = 4 * step
    z0 = spec.z_ref_um - np.ceil((spec.z_ref_um - (lo - margin)) / step) * step
    z1 = spec.z_ref_um + np.ceil(((hi + margin) - spec.z_ref_um) / step) * step
    return DemoSettings(fs, float(tol), float(lo), float(hi), float(z0), float(z1), float(step),
                        float(max(2.0, round(2 * tol, 1))))


def compare_with_truth(spec, scene_dir: str | Path, composite_path: str | Path, seed: int,
                       crops_png: str | Path | None = None) -> dict:
    """PSNR of the composite and of a one-shot frame (the captured frame nearest the on-axis focus) against the
    simulator's all-in-focus image of the ``colour-leaves`` scene; optionally a PNG of corner/centre crops.

    Returns ``psnr_composite_db``, ``psnr_one_shot_db``, ``one_shot_z_um`` and ``n_frames``.
    """
    import tifffile

    from fieldcal.formats.stack import Stack
    from fieldcal.simulate import Renderer
    from fieldcal.simulate.scene import load_scene
    from fieldcal.simulate.truth import TruthProfile
    from fieldcal.validation.run import psnr_db

    stack = Stack.open(scene_dir)
    image, _ = load_scene("colour-leaves", spec.sensor.width_px, spec.sensor.height_px, seed=seed)
    truth = Renderer(spec, image, seed=seed).truth()
    comp = tifffile.imread(composite_path)
    cx, cy = spec.optical_centre_px()
    z_axis = float(np.mean([TruthProfile(spec).best_focus_um(cx, cy, c) for c in spec.channel_names]))
    one = int(np.argmin(np.abs(np.asarray(stack.z_um) - z_axis)))
    shot = stack.read(one)
    black, white = float(stack.black_level), float(stack.white_level)
    border = max(4, spec.sensor.width_px // 64)
    res = {"psnr_composite_db": psnr_db(comp, truth, black, white, border_px=border),
           "psnr_one_shot_db": psnr_db(shot, truth, black, white, border_px=border),
           "one_shot_z_um": float(stack.z_um[one]), "n_frames": len(stack)}
    if crops_png is not None:
        _crops(truth, shot, comp, black, white, Path(crops_png))
    return res


def _crops(truth, shot, comp, black, white, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h, w = truth.shape[:2]
    ch, cw = h // 4, w // 4
    fig, axes = plt.subplots(2, 3, figsize=(10, 5.6))
    for row, (y0, x0, name) in enumerate(((0, 0, "top-left corner"), (h // 2 - ch // 2, w // 2 - cw // 2, "centre"))):
        for col, (img, title) in enumerate(((shot, "one shot (on-axis focus)"), (comp, "fieldcal composite"),
                                            (truth, "truth"))):
            crop = (np.asarray(img[y0:y0 + ch, x0:x0 + cw], dtype=np.float32) - black) / (white - black)
            axes[row, col].imshow(np.clip(crop.squeeze(), 0, 1),
                                  cmap=None if crop.ndim == 3 and crop.shape[2] == 3 else "gray",
                                  interpolation="nearest")
            axes[row, col].set_title(f"{title}: {name}", fontsize=8)
            axes[row, col].axis("off")
    fig.tight_layout()
    from fieldcal.formats.atomic import save_figure

    save_figure(fig, path, dpi=110)
    plt.close(fig)
