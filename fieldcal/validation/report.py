"""The validation report: PNG plots, ``index.html``, ``report.md`` and ``summary.json`` of a
:class:`fieldcal.validation.run.ValidationResult`.

Every file is written atomically (temporary name + rename); ``summary.json`` is written last, so a folder with a
``summary.json`` holds a complete report.
"""

from __future__ import annotations

import html
import io
from pathlib import Path

import numpy as np

from fieldcal.formats import documents
from fieldcal.formats.atomic import atomic_write_bytes, atomic_write_text

_COLOURS = {"R": "tab:red", "G": "tab:green", "B": "tab:blue", "Y": "0.2"}


def _plt():
    import matplotlib
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    return plt


def _save(fig, path: Path) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    _plt().close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path.name


def _display(img: np.ndarray, black: float, white: float) -> np.ndarray:
    """Linear DN to a display image in [0, 1] (gamma 1/2.2), grey for one channel."""
    v = (np.asarray(img, dtype=np.float32) - black) / max(white - black, 1e-12)
    v = np.clip(v, 0.0, 1.0) ** (1 / 2.2)
    return v[..., 0] if v.shape[-1] == 1 else v[..., :3]


# ------------------------------------------------------------------------------------------------- plots
def plot_surfaces(result, out: Path) -> str:
    """Per channel: MAP − true best focus (µm) over the field, and where the truth lies outside the band."""
    plt = _plt()
    X, Y = result.maps["surface_grid"]
    chans = list(result.surface)
    tol = result.setup["true_tolerance_um"]
    fig, axes = plt.subplots(2, len(chans), figsize=(4.2 * len(chans), 5.4), squeeze=False, layout="constrained")
    ext = (X.min(), X.max(), Y.max(), Y.min())
    for j, c in enumerate(chans):
        err, inside = result.maps["surface"][c]
        lim = max(float(np.max(np.abs(err))), 0.25 * tol[c], 1e-3)
        im = axes[0, j].imshow(err, extent=ext, cmap="RdBu_r", vmin=-lim, vmax=lim)
        m = result.surface[c]
        axes[0, j].set_title(f"{c}: MAP − truth (µm)\nRMS {m['rms_um']:.2f}, max {m['max_um']:.2f}, δ {tol[c]:.1f}",
                             fontsize=9)
        fig.colorbar(im, ax=axes[0, j], shrink=0.8)
        axes[1, j].imshow(inside, extent=ext, cmap="RdYlGn", vmin=0, vmax=1, interpolation="nearest")
        axes[1, j].set_title(f"{c}: truth inside the 90 % band (green)\ncoverage {m['band_coverage']:.1%}, "
                             f"mean half-width {m['band_halfwidth_um']:.2f} µm", fontsize=9)
        for ax in axes[:, j]:
            ax.set_xlabel("x (px)")
            ax.set_ylabel("y (px)")
    return _save(fig, out / "surfaces.png")


def plot_geometry(result, out: Path) -> str:
    """Magnification and shift vs z, profile (solid) against truth (dashed), and the corner registration error."""
    plt = _plt()
    p, t = result.maps["profile"], result.maps["truth_profile"]
    z0, z1 = result.geometry["z_range_um"]
    z = np.linspace(z0, z1, 65)
    w, h = t.image_size_px
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6), layout="constrained")
    for c in t.channels:
        col = _COLOURS.get(c, None)
        axes[0].plot(z, 1e6 * (np.asarray(p.magnification(z, c)) - 1), color=col, label=f"{c} profile")
        axes[0].plot(z, 1e6 * (np.asarray(t.magnification(z, c)) - 1), color=col, ls="--", label=f"{c} truth")
        sp, st = p.shift_px(z, c), t.shift_px(z, c)
        axes[1].plot(z, sp[0], color=col, label=f"{c} dx profile")
        axes[1].plot(z, st[0], color=col, ls="--")
        axes[1].plot(z, sp[1], color=col, ls="-.", label=f"{c} dy profile")
        axes[1].plot(z, st[1], color=col, ls=":")
        from fieldcal.validation.run import _positions
        pts = np.array([[0.0, 0.0], [w - 1.0, h - 1.0]])
        d = _positions(p, z, c, pts) - _positions(t, z, c, pts)
        axes[2].plot(z, np.max(np.hypot(d[..., 0], d[..., 1]), axis=1), color=col, label=c)
    axes[0].set_ylabel("m(z) − 1 (ppm)")
    axes[1].set_ylabel("shift (px); dashed/dotted: truth")
    axes[2].set_ylabel("corner registration error (px)")
    axes[2].axhline(result.config["thresholds"]["registration_px_max"], color="k", lw=0.8, ls=":")
    for ax in axes:
        ax.set_xlabel("z (µm)")
        ax.legend(fontsize=7)
    return _save(fig, out / "geometry.png")


def plot_plan(result, out: Path) -> str:
    """Per channel: histogram of the true best focus with the planned frames ±δ, and the margin map."""
    plt = _plt()
    t = result.maps["truth_profile"]
    frames = result.maps["plan_frames_um"]
    tol = result.setup["true_tolerance_um"]
    chans = list(t.channels)
    w, h = t.image_size_px
    X, Y = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    fig, axes = plt.subplots(2, len(chans), figsize=(4.2 * len(chans), 5.6), squeeze=False, layout="constrained")
    for j, c in enumerate(chans):
        zt = np.asarray(t.best_focus_um(X, Y, c))
        ax = axes[0, j]
        for zf in frames:
            ax.axvspan(zf - tol[c], zf + tol[c], color="C2", alpha=0.15, lw=0)
            ax.axvline(zf, color="C3", lw=0.8)
        ax.hist(zt.ravel(), bins=100, color="0.4")
        ax.set_yticks([])
        ax.set_xlabel("true best focus (µm); red: frames, green: ±δ")
        ax.set_title(f"{c}: {len(frames)} frames, coverage {result.plan['coverage'][c]['coverage']:.1%}", fontsize=9)
        mg = result.maps["plan_margin"][c]
        lim = max(float(np.max(np.abs(mg))), 1e-3)
        im = axes[1, j].imshow(mg, cmap="RdYlGn", vmin=-lim, vmax=lim)
        axes[1, j].set_title(f"{c}: margin δ − |z_frame − z_true| (µm), min {mg.min():.2f}", fontsize=9)
        fig.colorbar(im, ax=axes[1, j], shrink=0.8)
    fig.suptitle(f"plan from the {result.config['profile']} profile: "
                 f"{result.plan['n_frames']} frames (optimum for the true surfaces: {result.plan['n_optimal_true']})")
    return _save(fig, out / "plan.png")


def plot_composite(result, out: Path) -> str:
    """Truth, one-shot, composite and oracle: full frames, a corner crop, and absolute error maps."""
    plt = _plt()
    im = result.maps["images"]
    cm = result.composite
    black, white = cm["black_level"], cm["white_level"]
    names = [("truth", "truth (all in focus)"), ("one_shot", "one shot at on-axis focus"),
             ("composite", "composite (true profile)" if result.config["profile"] == "truth" else "composite"),
             ("oracle", "oracle (true surfaces)")]
    h, w = im["truth"].shape[:2]
    cy, cx = slice(0, max(16, h // 3)), slice(0, max(16, w // 3))
    fig, axes = plt.subplots(3, 4, figsize=(15, 9), layout="constrained")
    grey = im["truth"].shape[-1] == 1
    err_lim = 0.25 * (white - black)
    for j, (k, label) in enumerate(names):
        disp = _display(im[k], black, white)
        axes[0, j].imshow(disp, cmap="gray" if grey else None, vmin=0, vmax=1)
        ttl = label if k == "truth" else f"{label}\nPSNR {cm[k]['psnr_db']:.2f} dB, corner MTF {cm[k]['mtf_rel_corners_mean']:.2f}"
        axes[0, j].set_title(ttl, fontsize=9)
        axes[1, j].imshow(disp[cy, cx], cmap="gray" if grey else None, vmin=0, vmax=1, interpolation="nearest")
        axes[1, j].set_title("top-left corner", fontsize=8)
        if k == "truth":
            axes[2, j].axis("off")
            continue
        e = np.abs(im[k].astype(np.float64) - im["truth"].astype(np.float64)).mean(axis=-1)
        axes[2, j].imshow(e, cmap="magma", vmin=0, vmax=err_lim)
        axes[2, j].set_title("|error| (DN, channel mean)", fontsize=8)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    return _save(fig, out / "composite.png")


# ------------------------------------------------------------------------------------------------ pages
def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def checks_markdown(result) -> list[str]:
    lines = ["| check | value | limit | result | what |", "| --- | --- | --- | --- | --- |"]
    for c in result.checks:
        lines.append(f"| {c.name} | {_fmt(float(c.value))} | {c.op} {_fmt(float(c.limit))} | "
                     f"{'pass' if c.passed else '**FAIL**'} | {c.what} |")
    return lines


def metrics_markdown(result) -> list[str]:
    s, g, p, cm = result.setup, result.geometry, result.plan, result.composite
    lines = [f"Lens `{result.lens}` at {s['size_px'][0]}x{s['size_px'][1]} px ({s['pixel_pitch_um']:.2f} µm pixels, "
             f"Nyquist {s['nyquist_cyc_per_mm']:.1f} cycles/mm), fs = {s['fs_cyc_per_mm']:g} cycles/mm, q = {s['q']:g}; "
             f"focus range D = {s['D_um']:.1f} µm; true tolerance δ = "
             + ", ".join(f"{c} {v:.2f}" for c, v in s["true_tolerance_um"].items()) + " µm.", ""]
    if s.get("chart"):
        ch = s["chart"]
        lines += [f"Chart stack: {ch['n_frames']} frames, {ch['z_first_um']:.1f} … {ch['z_last_um']:.1f} µm, "
                  f"step {ch['step_um']:.2f} µm; profile: {result.config['profile']}, effort {result.config['effort']}.", ""]
    lines += ["| channel | surface RMS (µm) | max (µm) | bias (µm) | 90 % band coverage | band half-width (µm) | "
              "mag slope error (ppm/µm) | registration error (px) |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for c, m in result.surface.items():
        gc = g["channels"][c]
        lines.append(f"| {c} | {m['rms_um']:.3f} | {m['max_um']:.3f} | {m['bias_um']:+.3f} | {m['band_coverage']:.3f} | "
                     f"{m['band_halfwidth_um']:.3f} | {gc['mag_slope_ppm_per_um']['error']:+.4f} | "
                     f"{gc['registration_error_px']:.3f} |")
    lines += ["", f"Plan: {p['n_frames']} frames (optimum for the true surfaces {p['n_optimal_true']}), confidence "
              f"{p['confidence']}, coverage {p['coverage_min']:.4f}, smallest margin {p['min_margin_um']:.3f} µm.", "",
              "| image | PSNR (dB) | corner PSNR (dB) | corner MTF at fs (rel. to truth, mean / worst) |",
              "| --- | --- | --- | --- |"]
    for k in ("one_shot", "composite", "oracle"):
        m = cm[k]
        lines.append(f"| {k.replace('_', '-')} | {m['psnr_db']:.2f} | {m['psnr_corners_db']:.2f} | "
                     f"{m['mtf_rel_corners_mean']:.3f} / {m['mtf_rel_corners_min']:.3f} |")
    lines += ["", f"Scene `{cm['scene']}`, one shot at z = {cm['z_one_shot_um']:.1f} µm, {cm['border_px']} px border "
              "excluded. Timings (s): " + ", ".join(f"{k} {v:.2f}" for k, v in result.timings_s.items()) + "."]
    return lines


def _md_table_to_html(lines: list[str]) -> str:
    rows = [ln.strip("|").split("|") for ln in lines if ln.startswith("|") and not ln.startswith("| ---")]
    out = ["<table>"]
    for i, r in enumerate(rows):
        tag = "th" if i == 0 else "td"
        cells = []
        for cell in r:
            txt = cell.strip()
            cls = ' class="fail"' if "FAIL" in txt else (' class="pass"' if txt == "pass" else "")
            cells.append(f"<{tag}{cls}>{html.escape(txt.replace('**', ''))}</{tag}>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def _html(result, figures: list[str]) -> str:
    verdict = "PASS" if result.passed else "FAIL"
    met = metrics_markdown(result)
    parts, table = [], []
    for ln in met:
        if ln.startswith("|"):
            table.append(ln)
            continue
        if table:
            parts.append(_md_table_to_html(table))
            table = []
        if ln:
            parts.append(f"<p>{html.escape(ln)}</p>")
    if table:
        parts.append(_md_table_to_html(table))
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in result.notes)
    figs = "\n".join(f'<figure><img src="{f}" alt="{f}"><figcaption>{f}</figcaption></figure>' for f in figures)
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>fieldcal validation: {html.escape(result.lens)}</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto}} table{{border-collapse:collapse;margin:1em 0}}
td,th{{border:1px solid #ccc;padding:3px 8px;font-size:90%}} .pass{{background:#d9f2d9}} .fail{{background:#f7c6c6}}
img{{max-width:100%}} h1 span{{padding:0 .3em}}</style></head><body>
<h1>fieldcal validate: {html.escape(result.lens)} <span class="{verdict.lower()}">{verdict}</span></h1>
<h2>Checks</h2>
{_md_table_to_html(checks_markdown(result))}
<h2>Metrics</h2>
{''.join(parts)}
{'<h2>Notes</h2><ul>' + notes + '</ul>' if notes else ''}
<h2>Figures</h2>
{figs}
<p>Summary data: <a href="summary.json">summary.json</a>. Method and thresholds: docs/validation.md.</p>
</body></html>
"""


def write_report(result, out_dir: str | Path, plots: bool = True) -> list[Path]:
    """Write the report of ``result`` into ``out_dir``; returns the files written (summary.json last)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figures = []
    if plots:
        figures = [plot_surfaces(result, out), plot_geometry(result, out), plot_plan(result, out),
                   plot_composite(result, out)]
    md = [f"# fieldcal validate: {result.lens} — {'PASS' if result.passed else 'FAIL'}", "", "## Checks", "",
          *checks_markdown(result), "", "## Metrics", "", *metrics_markdown(result), ""]
    if result.notes:
        md += ["## Notes", "", *[f"- {n}" for n in result.notes], ""]
    md += [f"![{f}]({f})" for f in figures]
    atomic_write_text(out / "report.md", "\n".join(md) + "\n")
    atomic_write_text(out / "index.html", _html(result, figures))
    summary = result.to_dict()
    summary["files"] = [*figures, "report.md", "index.html"]
    documents.write(out / "summary.json", summary, "validation", indent=1)
    return [out / f for f in summary["files"]] + [out / "summary.json"]
