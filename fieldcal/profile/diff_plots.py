"""Difference maps of ``fieldcal profile diff --plot DIR``: per family, A - B, its sd and the z-score (Agg)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from fieldcal.formats.atomic import atomic_write_bytes


def plot_file_name(family: str) -> str:
    """``G/tangential`` -> ``diff-G-tangential.png``."""
    return "diff-" + "".join(c if c.isalnum() or c in "-_" else "-" for c in family.replace("/", "-")) + ".png"


def plot_names(maps: dict) -> list[str]:
    return [plot_file_name(name) for name in maps["families"]]


def write_plots(maps: dict, out_dir: str | Path, a_name: str, b_name: str) -> list[Path]:
    """One PNG per surface/tolerance family in ``out_dir``; returns their paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ny, nx = maps["shape"]
    extent = (0.0, 1.0, 1.0, 0.0)   # fractions of the frame, y down as in the image
    paths = []
    for name, f in maps["families"].items():
        fig, axes = plt.subplots(1, 3, figsize=(13, 3.6), constrained_layout=True)
        d = np.asarray(f["diff"]).reshape(ny, nx)
        sd = np.asarray(f["sd"]).reshape(ny, nx)
        z = np.asarray(f["z"]).reshape(ny, nx)
        lim = float(np.nanmax(np.abs(d))) or 1.0
        zl = max(float(np.nanmax(np.abs(z))), float(f["critical_z"])) if np.isfinite(z).any() else 1.0
        for ax, img, title, cmap, vlim in (
                (axes[0], d, f"A - B ({f['unit']})", "RdBu_r", (-lim, lim)),
                (axes[1], sd, f"sd of A - B ({f['unit']})", "viridis", (0.0, float(np.nanmax(sd)) or 1.0)),
                (axes[2], z, f"z-score (critical ±{f['critical_z']:.2f})", "RdBu_r", (-zl, zl))):
            im = ax.imshow(img, extent=extent, cmap=cmap, vmin=vlim[0], vmax=vlim[1], interpolation="bilinear",
                           aspect=ny / nx)   # the frame's shape (rows follow its aspect ratio)
            ax.set_title(title)
            ax.set_xlabel("x (fraction of width)")
            fig.colorbar(im, ax=ax, shrink=0.85)
        axes[0].set_ylabel("y (fraction of height)")
        if np.isfinite(z).any():
            gx, gy = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny))
            hot = np.abs(z) > f["critical_z"]
            axes[2].plot(gx[hot], gy[hot], "kx", ms=5, label="significant")
            i = np.unravel_index(int(np.nanargmax(np.abs(z))), z.shape)
            axes[2].plot(gx[i], gy[i], "ko", mfc="none", ms=9, label="max |z|")
            axes[2].legend(loc="lower right", fontsize=7)
        fig.suptitle(f"{name} {f['kind']}: {a_name} - {b_name}")
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=90)
        plt.close(fig)
        p = out_dir / plot_file_name(name)
        atomic_write_bytes(p, buf.getvalue())
        paths.append(p)
    return paths
