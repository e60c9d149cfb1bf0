"""Plots of a ``fieldcal-mtf/1`` result: MTF50 over the field per channel, through-focus MTF(fs) per edge track."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .esfr_focus import analyse_track
from .mtf import MtfResult


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _save(fig, path: Path) -> Path:
    from ..formats.atomic import save_figure

    try:  # the one atomic writer: unpredictable temporary name, never through a link, never over an input
        return save_figure(fig, path, dpi=110, bbox_inches="tight")
    finally:
        _plt().close(fig)


def _labels(res: MtfResult) -> list[str]:
    return sorted({e["plane"] or e["channel"] for e in res.edges}, key=lambda c: ("RGrGbBY".find(c[:2]), c))


def plot_mtf50_field(res: MtfResult, out: Path) -> Path:
    """MTF50 of each ok edge at its position, one panel per channel (plane); tangential edges as triangles,
    sagittal as circles. For a stack, each edge track's highest MTF50 (its best frame) is shown."""
    plt = _plt()
    best: dict[tuple, dict] = {}
    for e in res.edges:
        if not e["quality"]["ok"] or e["mtf50_cy_per_px"] is None:
            continue
        key = (e.get("track", e["edge"]), e["plane"] or e["channel"])
        if key not in best or e["mtf50_cy_per_px"] > best[key]["mtf50_cy_per_px"]:
            best[key] = e
    edges = list(best.values())
    stack = len({e["frame"] for e in res.edges}) > 1
    labels = _labels(res)
    n = max(1, len(labels))
    fig, axes = plt.subplots(1, n, figsize=(4.6 * n, 3.4), squeeze=False, sharey=True, constrained_layout=True)
    vals = [e["mtf50_cy_per_px"] for e in edges]
    vmin, vmax = (min(vals), max(vals)) if vals else (0, 0.5)
    sc = None
    for i, (ax, lab) in enumerate(zip(axes[0], labels)):
        for orient, marker in (("tangential", "^"), ("sagittal", "o")):
            sel = [e for e in edges if (e["plane"] or e["channel"]) == lab and e["orientation"] == orient]
            if sel:
                sc = ax.scatter([e["x_px"] for e in sel], [e["y_px"] for e in sel],
                                c=[e["mtf50_cy_per_px"] for e in sel],
                                marker=marker, s=24, vmin=vmin, vmax=vmax, cmap="viridis", label=orient)
        ax.set_title(("best-focus MTF50 " if stack else "MTF50 ") + lab)
        if i == 0:
            ax.invert_yaxis()
            ax.set_ylabel("y (px)")
        ax.set_aspect("equal")
        ax.set_xlabel("x (px)")
    if sc is not None:
        axes[0][0].legend(fontsize=7, loc="lower left", bbox_to_anchor=(0.0, 1.08), ncol=2, frameon=False)
        fig.colorbar(sc, ax=axes[0].tolist(), label="MTF50 (cycles/px)", shrink=0.8)
    return _save(fig, Path(out))


def plot_through_focus(res: MtfResult, out: Path, fs_cy_per_px: float = 0.25, q: float = 0.05,
                       max_tracks: int = 12) -> Path:
    """MTF(fs) against z for up to ``max_tracks`` edge tracks (spread over the field), per channel, with each
    track's best focus and tolerance interval."""
    plt = _plt()
    m = res.mtf_at(fs_cy_per_px)
    count: dict[int, int] = {}
    for e in res.edges:
        if e["quality"]["ok"]:
            count[e.get("track", 0)] = count.get(e.get("track", 0), 0) + 1
    longest = max(count.values(), default=0)
    tracks = sorted(t for t, n in count.items() if n >= 0.6 * longest)  # the edges seen through most of the scan
    if len(tracks) > max_tracks:  # spread the shown tracks over the field: every k-th by radius
        rad = {t: np.mean([np.hypot(e["x_px"], e["y_px"]) for e in res.edges if e.get("track", 0) == t])
               for t in tracks}
        tracks = sorted(tracks, key=rad.get)[:: max(1, len(tracks) // max_tracks)][:max_tracks]
    labels = _labels(res)
    fig, axes = plt.subplots(1, max(1, len(labels)), figsize=(4.4 * max(1, len(labels)), 3.4), squeeze=False,
                             sharey=True)
    for ax, lab in zip(axes[0], labels):
        for t in tracks:
            idx = [i for i, e in enumerate(res.edges) if e.get("track", 0) == t and (e["plane"] or e["channel"]) == lab
                   and e["z_um"] is not None]
            if len(idx) < 2:
                continue
            z = np.array([res.edges[i]["z_um"] for i in idx])
            v = m[idx]
            o = np.argsort(z)
            line, = ax.plot(z[o], v[o], ".-", lw=0.8, ms=3)
            tf = analyse_track(z, v, q)
            if tf.ok:
                ax.axvline(tf.z_best_um, color=line.get_color(), lw=0.5, ls=":")
                ax.plot([tf.z_best_um - tf.tol_left_um, tf.z_best_um + tf.tol_right_um], [(1 - q) * tf.peak_mtf] * 2,
                        color=line.get_color(), lw=2, alpha=0.6)
        ax.set_title(f"{lab}: MTF({fs_cy_per_px:g} cy/px) through focus")
        ax.set_xlabel("z (µm)")
        ax.set_ylabel("MTF")
    return _save(fig, Path(out))


#: The files :func:`write_plots` may write in its folder.
PLOT_FILES = ("mtf50_field.png", "through_focus.png")


def write_plots(res: MtfResult, out_dir, fs_cy_per_px: float = 0.25, q: float = 0.05) -> list[Path]:
    """All plots of ``res`` into ``out_dir``: mtf50_field.png, and through_focus.png for a stack."""
    out_dir = Path(out_dir)  # created by the atomic writer (a path through a file is a clear error)
    paths = [plot_mtf50_field(res, out_dir / "mtf50_field.png")]
    if len({e["frame"] for e in res.edges}) > 1:
        paths.append(plot_through_focus(res, out_dir / "through_focus.png", fs_cy_per_px, q))
    return paths
