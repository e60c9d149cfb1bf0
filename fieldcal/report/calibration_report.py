"""`fieldcal report`: PNG plots and one HTML page for a lens profile.

Every figure is drawn from the profile's public API (best_focus_um, best_focus_interval_um, magnification,
shift_px, focus_tolerance_um) plus the data it carries (tile table, geometry measurements, model-selection
table), so the report shows exactly what a deployed profile will answer. Any
:class:`fieldcal.optics.LensModel` can be drawn (a lens spec's truth, for design studies); the parts that
come from a calibration (tiles, measurements, uncertainty budget, model selection) need a
:class:`fieldcal.profile.LensProfile` and are left out otherwise.
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from fieldcal.formats.atomic import atomic_write_text, save_figure
from fieldcal.optics import LensModel
from fieldcal.profile.lens_profile import LensProfile

#: Every file a report writes into its folder (checked before any work; index.html is written last).
REPORT_FILES = ("surfaces.png", "bands.png", "residuals.png", "geometry.png", "tolerance.png", "index.html")

_COLOURS = {"R": "tab:red", "G": "tab:green", "B": "tab:blue", "Y": "0.2"}


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _save(fig, path: Path) -> str:
    try:  # rendered in memory, then the one atomic write (never through a link at the final name)
        save_figure(fig, path, dpi=110, bbox_inches="tight")
    finally:
        _plt().close(fig)
    return path.name


def _grid(profile, n: int = 96):
    w, h = profile.image_size_px
    nx = n
    ny = max(8, int(round(n * h / w)))
    xs = np.linspace(0, w - 1, nx)
    ys = np.linspace(0, h - 1, ny)
    return np.meshgrid(xs, ys)


def plot_surfaces(profile, out: Path) -> str:
    """Best-focus surface per channel (map, µm) on a shared colour scale."""
    plt = _plt()
    X, Y = _grid(profile)
    zs = {c: profile.best_focus_um(X, Y, c) for c in profile.channels}
    lo = min(float(z.min()) for z in zs.values())
    hi = max(float(z.max()) for z in zs.values())
    n = len(zs)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.2), squeeze=False)
    w, h = profile.image_size_px
    for ax, (c, z) in zip(axes[0], zs.items()):
        im = ax.imshow(z, extent=(0, w, h, 0), vmin=lo, vmax=hi, cmap="viridis")
        cs = ax.contour(X, Y, z, levels=8, colors="w", linewidths=0.6, negative_linestyles="solid")
        ax.clabel(cs, fontsize=6, fmt="%.0f")
        ax.set_title(f"best focus {c} (µm)")
        ax.set_xlabel("x (px)")
    axes[0][0].set_ylabel("y (px)")
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.85, label="z (µm)")
    return _save(fig, out / "surfaces.png")


def _radial_samples(profile, n: int = 200):
    w, h = profile.image_size_px
    cx, cy = profile.optical_centre_px()
    # along the diagonal towards the farthest corner
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], dtype=float)
    far = corners[np.argmax(np.hypot(corners[:, 0] - cx, corners[:, 1] - cy))]
    t = np.linspace(0.0, 1.0, n)
    x = cx + t * (far[0] - cx)
    y = cy + t * (far[1] - cy)
    r_mm = np.hypot(x - cx, y - cy) * profile.pixel_pitch_um / 1000.0
    return x, y, r_mm


def plot_bands(profile, out: Path, level: float = 0.9) -> str:
    """MAP surface and its credible band along the radius to the farthest corner."""
    plt = _plt()
    x, y, r_mm = _radial_samples(profile)
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for c in profile.channels:
        z = profile.best_focus_um(x, y, c)
        lo, hi = profile.best_focus_interval_um(x, y, c, level=level)
        col = _COLOURS.get(c, None)
        ax.plot(r_mm, z, color=col, label=f"{c} MAP")
        ax.fill_between(r_mm, lo, hi, color=col, alpha=0.25, label=f"{c} {int(level * 100)}% band")
    ax.set_xlabel("image height along the diagonal (mm)")
    ax.set_ylabel("best focus z (µm)")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    # the band is narrow next to the range: an inset of its width
    ax2 = ax.inset_axes([0.08, 0.08, 0.35, 0.3])
    for c in profile.channels:
        lo, hi = profile.best_focus_interval_um(x, y, c, level=level)
        ax2.plot(r_mm, hi - lo, color=_COLOURS.get(c))
    ax2.set_title("band width (µm)", fontsize=7)
    ax2.tick_params(labelsize=6)
    return _save(fig, out / "bands.png")


def plot_residuals(profile: LensModel, out: Path) -> str | None:
    """Per-tile residuals (measured − MAP) and the rejected tiles with their reasons (a calibrated profile)."""
    tiles = profile.tiles if isinstance(profile, LensProfile) else None
    if tiles is None or len(tiles.get("x_px", [])) == 0:
        return None
    plt = _plt()
    chans = list(profile.channels)
    fig, axes = plt.subplots(1, len(chans) + 1, figsize=(4.2 * (len(chans) + 1), 3.4), squeeze=False)
    w, h = profile.image_size_px
    status = np.asarray(tiles["status"]).astype(str)
    ch = np.asarray(tiles["channel"]).astype(str)
    x = np.asarray(tiles["x_px"], float)
    y = np.asarray(tiles["y_px"], float)
    z = np.asarray(tiles["z_best_um"], float)
    ok = status == "ok"
    vmax = 1e-9
    res = {}
    for c in chans:
        m = ok & (ch == c)
        if m.any():
            res[c] = (m, z[m] - profile.best_focus_um(x[m], y[m], c))
            vmax = max(vmax, float(np.nanpercentile(np.abs(res[c][1]), 98)))
    for ax, c in zip(axes[0], chans):
        if c in res:
            m, r = res[c]
            sc = ax.scatter(x[m], y[m], c=r, cmap="coolwarm", vmin=-vmax, vmax=vmax, s=14)
            ax.set_title(f"{c}: residual (µm), RMS {np.sqrt(np.mean(r ** 2)):.2f}")
            fig.colorbar(sc, ax=ax, shrink=0.8)
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_aspect("equal")
    ax = axes[0][-1]
    reasons = sorted(set(status[~ok]))
    cmap = plt.get_cmap("tab10")
    for i, r in enumerate(reasons):
        m = status == r
        ax.scatter(x[m], y[m], s=14, color=cmap(i % 10), label=f"{r} ({m.sum()})")
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_aspect("equal")
    ax.set_title(f"rejected tiles: {(~ok).sum()} of {len(ok)}")
    if reasons:
        ax.legend(fontsize=6, loc="lower right")
    return _save(fig, out / "residuals.png")


def plot_geometry(profile, out: Path) -> str:
    """Magnification and shift vs z: the fitted model and the per-frame measurements."""
    plt = _plt()
    if isinstance(profile, LensProfile):
        meas, zr = profile.geometry_measurements or {}, profile.z_range_um
    else:
        meas, zr = {}, (profile.z_ref_um - 100.0, profile.z_ref_um + 100.0)
    z = np.linspace(zr[0], zr[1], 200)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for c in profile.channels:
        col = _COLOURS.get(c)
        axes[0].plot(z, (np.asarray(profile.magnification(z, c)) - 1.0) * 1e3, color=col, label=f"{c} fit")
        dx, dy = profile.shift_px(z, c)
        axes[1].plot(z, dx, color=col, label=f"{c} dx fit")
        axes[1].plot(z, dy, color=col, ls="--", label=f"{c} dy fit")
        if meas:
            mch = np.asarray(meas.get("channel", []), str) == c
            mz = np.asarray(meas.get("z_um", []), float)[mch]
            if mz.size:
                axes[0].plot(mz, (np.asarray(meas["magnification"], float)[mch] - 1.0) * 1e3, "o", ms=3, color=col)
                axes[1].plot(mz, np.asarray(meas["shift_x_px"], float)[mch], "o", ms=3, color=col)
                axes[1].plot(mz, np.asarray(meas["shift_y_px"], float)[mch], "s", ms=3, color=col, mfc="none")
    axes[0].set_ylabel("magnification − 1 (×10⁻³)")
    axes[1].set_ylabel("shift (px)")
    for ax in axes:
        ax.set_xlabel("z (µm)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    return _save(fig, out / "geometry.png")


def plot_tolerance(profile, out: Path, fs: float, q: float) -> str:
    """Depth-of-focus tolerance δ(x, y) at (fs, q) per channel."""
    plt = _plt()
    X, Y = _grid(profile, 64)
    n = len(profile.channels)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.2), squeeze=False)
    w, h = profile.image_size_px
    for ax, c in zip(axes[0], profile.channels):
        t = np.asarray(profile.focus_tolerance_um(X, Y, c, fs, q), float) * np.ones_like(X)
        im = ax.imshow(t, extent=(0, w, h, 0), cmap="magma")
        ax.set_title(f"{c}: tolerance ±δ (µm) at {fs:g} cy/mm, q={q:g}")
        fig.colorbar(im, ax=ax, shrink=0.8)
    return _save(fig, out / "tolerance.png")


def _table(rows: list[dict]) -> str:
    if not rows:
        return "<p>(none)</p>"
    keys = list(rows[0].keys())
    head = "".join(f"<th>{html.escape(str(k))}</th>" for k in keys)
    body = []
    for r in rows:
        cells = []
        for k in keys:
            v = r.get(k, "")
            if isinstance(v, float):
                v = f"{v:.4g}"
            cells.append(f"<td>{html.escape(str(v))}</td>")
        style = ' class="chosen"' if r.get("chosen") else ""
        body.append(f"<tr{style}>{''.join(cells)}</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def uncertainty_budget(profile: LensProfile, level: float = 0.9) -> list[dict]:
    """Per channel: the band's half-width at the optical centre and at a corner, and the terms that make it.

    The band (``best_focus_interval_um``) is the posterior of the surface (model average, correlated
    discrepancy, misfit and common-mode terms: docs/fitting.md) plus the fixed and breathing systematics in
    quadrature; this lists the parts a lab would check before trusting it.
    """
    cal = profile.calibration or {}
    surf = profile.surfaces
    post = (surf.diagnostics or {}).get("posterior", {}) or {}
    rec = cal.get("systematic") or {}
    common = rec.get("common_mode_sd_um") or {}
    breathing = cal.get("breathing_systematic_sd_um") or {}
    cx, cy = (float(v) for v in profile.optical_centre_px())
    rows = []
    for c in profile.channels:
        lo, hi = profile.best_focus_interval_um(np.array([cx, 0.0]), np.array([cy, 0.0]), c, level=level)
        hw = 0.5 * (np.asarray(hi) - np.asarray(lo))
        rows.append({"channel": c, f"{level:.0%} half-width at centre (µm)": round(float(hw[0]), 3),
                     f"{level:.0%} half-width at corner (µm)": round(float(hw[1]), 3),
                     "breathing systematic sd (µm)": round(float(breathing.get(c, 0.0)), 3),
                     "common-mode sd (µm)": round(float(common.get(c, 0.0)), 3),
                     "stage sd (µm)": round(float((getattr(surf, "stage_sd_um", None) or {}).get(c, 0.0)), 3),
                     "band scale (held-out check)": round(float(getattr(surf, "band_scale", 1.0)), 2),
                     "misfit F": None if rec.get("misfit_F") is None else round(float(rec["misfit_F"]), 2),
                     "error scale": round(float((surf.diagnostics or {}).get("error_scale", float("nan"))), 2),
                     "posterior": post.get("method", "?") + ("" if post.get("converged", True) else " (NOT converged)"),
                     "effective sample size": post.get("effective_sample_size")})
    return rows


def self_check_summary(profile) -> tuple[str, str | None]:
    """One line on the profile's self-check (docs/fitting.md "Self-checked coverage") and its warning.

    Profiles from session 11 on state the band's estimated truth coverage (``estimates`` says what ``coverage`` is)
    and warn on the held-out evidence; older ones state the held-out tiles' coverage and warn outside 0.8-0.97
    (None when in range, or when an old profile has no self-check)."""
    from fieldcal.fit.selfcheck import TILE_ESTIMATES, WARN_RANGE

    surfaces = getattr(profile, "surfaces", None)  # a LensProfile, or anything shaped like one (tests)
    if surfaces is None or not hasattr(surfaces, "band_scale"):
        return "", None  # a simulated lens's truth: nothing was calibrated
    sc = ((profile.diagnostics or {}).get("surface") or {}).get("self_check")
    if not sc:
        return "no self-check in this profile (written before it existed): recalibrate to get one", None
    cov = sc.get("coverage")
    if sc.get("status") != "ok" or cov is None or not np.isfinite(cov):
        return f"self-check not run: {sc.get('status')}", None
    tiles = (f"{100 * sc.get('tile_coverage', cov):.0f} % of {sc.get('n_tiles')} left-out tiles ({sc.get('n_blocks')} "
             f"spatial blocks, each predicted from the others) fell inside their predicted "
             f"{100 * sc.get('level', 0.9):.0f} % band (before the band scale: "
             f"{100 * sc.get('coverage_unscaled', float('nan')):.0f} %; band scale {sc.get('band_scale', 1.0):.2f})")
    if sc.get("estimates", TILE_ESTIMATES) != TILE_ESTIMATES and sc.get("coverage_range"):
        lo_c, hi_c = sc["coverage_range"]
        k5, k95 = sc.get("kappa_90") or (float("nan"), float("nan"))
        dev = sc.get("coverage_abs_dev")
        # whether the held-out tiles' kappa entered the estimate, or the band was taken as built (no evidence)
        used = ("" if sc.get("kappa_evidence") is None else
                ": evidence, used" if sc["kappa_evidence"] else ": no evidence against the band, taken as built")
        line = (f"expected truth coverage of the {100 * sc.get('level', 0.9):.0f} % band {100 * cov:.0f} % of the "
                f"field (one lens: {100 * lo_c:.0f}-{100 * hi_c:.0f} %, 5-95 %"
                + (f", on average {100 * dev:.0f} points from the expectation" if dev is not None else "")
                + f"; {100 * sc.get('field_wide_share', 0.0):.0f} % of the band's variance is one draw for the field); "
                f"errors between tiles {k5:.2f}-{k95:.2f} x the band's (90 %{used}); " + tiles)
        return line, sc.get("warning")
    lo, hi = WARN_RANGE
    warn = None
    if not (lo <= cov <= hi):
        warn = sc.get("warning") or (f"self-checked coverage {cov:.2f} is outside {lo}-{hi}: the credible bands "
                                     "may not hold for this lens")
    return tiles, warn


def write_report(profile: LensModel, out_dir: str | Path, *, fs: float | None = None,
                 q: float | None = None) -> Path:
    """Write PNG plots and ``index.html`` for a profile into ``out_dir``; returns the HTML path.

    Each file is written atomically (:func:`fieldcal.formats.atomic.write_bytes`), ``index.html`` last; the
    command checks the folder first (:data:`REPORT_FILES`, ``--overwrite``).
    """
    out = Path(out_dir)
    calibrated = profile if isinstance(profile, LensProfile) else None
    cal = calibrated.calibration if calibrated is not None else {}
    fs = float(fs if fs is not None else cal.get("fs_cyc_per_mm", 80.0))
    q = float(q if q is not None else cal.get("q", 0.05))
    figs = [("Best-focus surfaces", plot_surfaces(profile, out)),
            ("Credible band along the radius", plot_bands(profile, out)),
            ("Per-tile residuals and rejected tiles", plot_residuals(profile, out)),
            ("Magnification and shift vs z", plot_geometry(profile, out)),
            ("Tolerance map", plot_tolerance(profile, out, fs, q))]
    sel = calibrated.model_selection if calibrated is not None else []
    diag = calibrated.diagnostics if calibrated is not None else {}
    prov = calibrated.provenance if calibrated is not None else {"source": profile.source_path}
    parts = [f"<h1>Lens profile report</h1><p>channels {', '.join(profile.channels)}; image "
             f"{profile.image_size_px[0]}×{profile.image_size_px[1]} px at {profile.pixel_pitch_um:g} µm; "
             f"z_ref = {profile.z_ref_um:g} µm</p>"]
    for title, name in figs:
        if name:
            parts.append(f"<h2>{html.escape(title)}</h2><img src='{html.escape(name)}'>")
    if calibrated is not None:
        parts.append("<h2>Uncertainty budget</h2><p>The 90 % band and what it is made of (docs/fitting.md "
                     "'Systematic').</p>" + _table(uncertainty_budget(calibrated)))
        line, warn = self_check_summary(calibrated)
        if line:
            parts.append("<h2>Self-checked coverage</h2><p>" + html.escape(line) + "</p>"
                         + (f"<p style='color:#b00'><b>warning:</b> {html.escape(warn)}</p>" if warn else ""))
        parts.append("<h2>Model selection</h2>" + _table(sel))
    parts.append("<h2>Diagnostics</h2><pre>" + html.escape(json.dumps(diag, indent=2, default=str)) + "</pre>")
    parts.append("<h2>Provenance</h2><pre>" + html.escape(json.dumps(prov, indent=2, default=str)) + "</pre>")
    page = ("<!doctype html><html><head><meta charset='utf-8'><title>fieldcal report</title><style>"
            "body{font-family:sans-serif;max-width:1100px;margin:auto}img{max-width:100%}"
            "table{border-collapse:collapse;font-size:12px}td,th{border:1px solid #ccc;padding:2px 6px}"
            "tr.chosen{background:#dfd}</style></head><body>" + "".join(parts) + "</body></html>")
    path = out / "index.html"
    atomic_write_text(path, page)
    return path
