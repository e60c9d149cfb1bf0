"""Pictures of plans (PNG, matplotlib Agg): stack plan over the field, masks at instants, exposure windows, α trade."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import cover as cv
from . import masks as mk


def _plt():
    import matplotlib
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    return plt


def _save(fig, path: Path) -> Path:
    import io
    from fieldcal.formats.atomic import atomic_write_bytes
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())
    return path


def plot_stack_plan(profile, plan, path: str | Path, step_px: int | None = None) -> Path:
    """Per channel: which frame serves each pixel (nearest-frame rule), and the bands along z."""
    plt = _plt()
    chans = list(plan.field.channels)
    x0, y0, w, h = plan.field.roi
    step = step_px or max(1, int(max(w, h) / 200))
    gx, gy = np.meshgrid(np.arange(x0, x0 + w, step, dtype=np.float64), np.arange(y0, y0 + h, step, dtype=np.float64))
    order = plan.capture_order()
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)  # ascending index -> capture index
    fig, axes = plt.subplots(2, len(chans), figsize=(4.6 * len(chans), 5.6), squeeze=False,
                             gridspec_kw={"height_ratios": [2.2, 1]}, layout="constrained")
    for j, c in enumerate(chans):
        z = np.asarray(profile.best_focus_um(gx, gy, c)) + plan.field.refocus_um
        k = rank[cv.nearest_index(plan.frames_um, z)]
        ax = axes[0, j]
        im = ax.imshow(k, extent=(x0, x0 + w, y0 + h, y0), cmap="turbo", vmin=0, vmax=max(1, plan.n_frames - 1),
                       interpolation="nearest")
        ax.set_title(f"{c}: frame (capture index) per pixel", fontsize=9)
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
        fig.colorbar(im, ax=ax, shrink=0.8)
        ax2 = axes[1, j]
        ax2.hist(z.ravel(), bins=120, color="0.6")
        for zf in plan.frames_um:
            ax2.axvline(zf, color="C3", lw=0.6)
        ax2.set_xlabel("best focus z (µm); red: frames")
        ax2.set_yticks([])
    fig.suptitle(f"stack plan: {plan.n_frames} frames, q = {plan.q_used:.3f} at "
                 f"{plan.request.fs_cyc_per_mm:g} cycles/mm, direction {plan.request.direction}")
    out = _save(fig, Path(path))
    plt.close(fig)
    return out


def plot_masks(plan, path: str | Path, n_instants: int = 4) -> Path:
    """Which pixels integrate at a few instants of the sweep (first plane; on a Bayer sensor, its mosaic)."""
    plt = _plt()
    start = plan.window_start_ms[0]
    stop = plan.window_stop_ms[0]
    T = plan.total_time_ms
    ts = np.linspace(0.0, T, n_instants + 2)[1:-1]
    fig, axes = plt.subplots(1, n_instants, figsize=(3.6 * n_instants, 3.4), squeeze=False)
    for ax, t in zip(axes[0], ts):
        if plan.device.name == "lcos":
            k = min(int(t // plan.device.slot_ms), plan.n_slots - 1)
            tc = (k + 0.5) * plan.device.slot_ms
            m = mk.mask_at(start, start + np.float32(plan.request.pixel_exposure_ms), tc)
            ttl = f"slot {k} (t = {k * plan.device.slot_ms:.0f}–{(k + 1) * plan.device.slot_ms:.0f} ms)"
        else:
            m = mk.mask_at(start, stop, t)
            ttl = f"t = {t:.1f} ms"
        ax.imshow(m, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        ax.set_title(ttl, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"exposure masks ({plan.device.name}, plane {plan.planes[0]}): white = integrating")
    out = _save(fig, Path(path))
    plt.close(fig)
    return out


def plot_windows(plan, path: str | Path) -> Path:
    """Opening time of each pixel's exposure window (per plane)."""
    plt = _plt()
    P = len(plan.planes)
    fig, axes = plt.subplots(1, P, figsize=(4.4 * P, 3.6), squeeze=False)
    for p in range(P):
        ax = axes[0, p]
        im = ax.imshow(plan.window_start_ms[p], cmap="viridis", interpolation="nearest")
        ax.set_title(f"{plan.planes[p]}: window opens at (ms)", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(f"exposure windows: each pixel integrates {plan.request.pixel_exposure_ms:g} ms from the shown time; "
                 f"T = {plan.total_time_ms:.1f} ms", fontsize=10)
    out = _save(fig, Path(path))
    plt.close(fig)
    return out


def plot_alpha_trade(profile, plan, path: str | Path) -> Path:
    """Total time vs noise gain and MTF at fs for the α values of the plan's table, plus the IPSF MTFs."""
    from ..optics.sweep import integrated_otf
    plt = _plt()
    rows = plan.trade
    a = np.array([r["alpha_um"] for r in rows])
    fig, (ax1, ax3) = plt.subplots(1, 2, figsize=(11.5, 3.8), layout="constrained")
    ax1.plot(a, [r["total_time_ms"] for r in rows], "o-", color="C0")
    ax1.set_xlabel("α (µm)")
    ax1.set_ylabel("total time T (ms)", color="C0")
    ax2 = ax1.twinx()
    ax2.plot(a, [r["noise_gain"] for r in rows], "s-", color="C3", label="Wiener noise gain (NSR fixed)")
    ax2.plot(a, [r["noise_gain_to_in_focus"] for r in rows], "d-", color="C1",
             label="noise gain to restore in-focus MTF (|f| ≤ fs)")
    ax2.plot(a, [r["mtf_at_fs"] for r in rows], "^--", color="C2", label="IPSF MTF at fs")
    ax2.set_ylabel("noise gain / MTF")
    ax2.legend(loc="center right", fontsize=8)
    ax1.axvline(plan.request.alpha_um, color="0.5", lw=0.8)
    ax1.set_title(f"α trade: D = {plan.range_um:.0f} µm, t_s = {plan.request.pixel_exposure_ms:g} ms", fontsize=10)
    ch = plan.ipsf_summary["channel"]
    fc = 1.0 / (profile.wavelength_nm(ch) * 1e-6 * profile.f_number)
    f = np.linspace(0, min(fc, 1000.0 / (2 * profile.pixel_pitch_um) * 1.5), 300)
    for al in sorted({0.0, plan.request.alpha_um, 2 * plan.request.alpha_um}):
        ax3.plot(f, integrated_otf(profile, f, al, ch), label=f"α = {al:g} µm")
    ax3.axhline(0, color="0.7", lw=0.6)
    ax3.set_xlabel("f (cycles/mm)")
    ax3.set_ylabel(f"IPSF OTF ({ch})")
    ax3.set_title("MTF of the integrated PSF (eq. 2)", fontsize=10)
    ax3.legend(fontsize=8)
    out = _save(fig, Path(path))
    plt.close(fig)
    return out
