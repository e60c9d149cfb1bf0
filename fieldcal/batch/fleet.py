"""The fleet report of a batch: how the units' best-focus surfaces and tolerances spread, and which units differ.

Every unit's profile is sampled on one grid of field positions given as fractions of the image width and
height (so units calibrated at other sizes compare point for point): its best-focus surface ``s_i``, the
surface's posterior sd ``σ_i`` and the focus tolerance at the batch's fs and q. Per channel the report gives
the fleet's mean surface and sd map, each unit's RMS and largest deviation from the fleet mean, the
tolerances' mean and sd, and a z-score per unit (:func:`compare_units`, docs/batch.md):

    z_i(x) = (s_i(x) − m_−i(x)) / sqrt(σ_i(x)² + τ²_−i(x) + (τ²_−i(x) + σ̄²_−i(x)) / (n − 1))

where ``m_−i`` is the mean of the *other* units, ``σ̄²_−i`` their mean squared uncertainty and ``τ²_−i`` the
unit-to-unit variance they show beyond it (``max(S²_−i − σ̄²_−i, 0)`` with ``S²`` their sample variance; 0 with
fewer than two others). A unit whose RMS of ``z`` over the field exceeds ``Z_LIMIT`` differs significantly
from the fleet in that channel. Leaving the unit out keeps an outlier from widening the spread that judges it.
:func:`compare_units` is the one place this test lives, so a better profile comparison can replace it.

:func:`fleet_document` builds the ``fieldcal-fleet/1`` JSON; :func:`write_fleet_report` writes it and the plot.
"""

from __future__ import annotations

import math
from datetime import datetime, timezone
from pathlib import Path
from typing import Sequence

import numpy as np

from fieldcal.formats import documents

FLEET_FORMAT = documents.format_id("fleet")
GRID = (25, 15)      # field positions across x and y; the surfaces are smooth, finer grids change nothing
Z_LIMIT = 3.0        # RMS z above this: the unit differs significantly from the fleet
REPORT_FILES = ("fleet.json", "fleet.png")


def field_points(width_px: int, height_px: int, grid: tuple[int, int] = GRID) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (ny x nx arrays) of the grid's field fractions, corners included."""
    nx, ny = grid
    x = np.linspace(0.0, width_px - 1.0, nx)
    y = np.linspace(0.0, height_px - 1.0, ny)
    return np.meshgrid(x, y)


def unit_maps(profile, grid: tuple[int, int] = GRID, fs_cyc_per_mm: float = 80.0, q: float = 0.05) -> dict:
    """A profile sampled on the fleet grid: per channel the surface, its sd and the tolerance (µm, ny x nx).

    The tolerance is ``None`` when the profile has no way to give one (no measured widths, no F-number).
    """
    from fieldcal.errors import FieldcalError

    w, h = (int(v) for v in profile.image_size_px)
    X, Y = field_points(w, h, grid)
    out = {"image_size_px": [w, h], "channels": {}}
    for c in profile.channels:
        try:
            tol = np.asarray(profile.focus_tolerance_um(X, Y, c, fs_cyc_per_mm, q), dtype=np.float64)
        except FieldcalError:
            tol = None
        out["channels"][c] = {"surface_um": np.asarray(profile.best_focus_um(X, Y, c), dtype=np.float64),
                              "sd_um": np.asarray(profile.best_focus_sd_um(X, Y, c), dtype=np.float64),
                              "tolerance_um": tol}
    return out


def compare_units(surfaces_um: np.ndarray, sd_um: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-out z-scores of each unit against the rest of the fleet (module docstring).

    Parameters
    ----------
    surfaces_um, sd_um : (n, ...) arrays
        Each unit's surface and its posterior sd at the same field points.

    Returns
    -------
    z_rms, z_max : (n,) arrays
        RMS and largest ``|z|`` over the field points per unit (NaN with fewer than two units).
    """
    s = np.asarray(surfaces_um, dtype=np.float64)
    v = np.asarray(sd_um, dtype=np.float64) ** 2
    n = s.shape[0]
    if n < 2:
        return np.full(n, np.nan), np.full(n, np.nan)
    z_rms, z_max = np.empty(n), np.empty(n)
    for i in range(n):
        others = np.delete(np.arange(n), i)
        so, vo = s[others], v[others]
        var_o = vo.mean(axis=0)
        tau2 = np.maximum(so.var(axis=0, ddof=1) - var_o, 0.0) if others.size >= 2 else np.zeros_like(var_o)
        var = v[i] + tau2 + (tau2 + var_o) / others.size
        z = (s[i] - so.mean(axis=0)) / np.sqrt(np.maximum(var, 1e-18))
        z_rms[i] = float(np.sqrt(np.mean(z ** 2)))
        z_max[i] = float(np.max(np.abs(z)))
    return z_rms, z_max


def _finite(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _grid_list(a: np.ndarray) -> list:
    return [[round(float(x), 4) for x in row] for row in a]


def fleet_statistics(maps: dict[str, dict], grid: tuple[int, int] = GRID, z_limit: float = Z_LIMIT) -> dict:
    """Per channel: mean surface, sd map, per-unit deviations and z-scores, tolerance spread (arrays kept).

    ``maps``: unit name -> :func:`unit_maps` of the units that finished. A channel is compared over the units
    that have it.
    """
    channels: list[str] = []
    for m in maps.values():
        channels += [c for c in m["channels"] if c not in channels]
    out = {}
    for c in channels:
        names = [n for n, m in maps.items() if c in m["channels"]]
        s = np.stack([maps[n]["channels"][c]["surface_um"] for n in names])
        sd = np.stack([maps[n]["channels"][c]["sd_um"] for n in names])
        mean = s.mean(axis=0)
        spread = s.std(axis=0, ddof=1) if len(names) > 1 else np.zeros_like(mean)
        dev = s - mean
        z_rms, z_max = compare_units(s, sd)
        tols = [maps[n]["channels"][c]["tolerance_um"] for n in names]
        have_tol = all(t is not None for t in tols)
        t = np.stack(tols) if have_tol else None
        per_unit = {}
        for k, n in enumerate(names):
            per_unit[n] = {"rms_deviation_um": float(np.sqrt(np.mean(dev[k] ** 2))),
                           "max_deviation_um": float(np.max(np.abs(dev[k]))),
                           "sd_mean_um": float(np.mean(sd[k])),
                           "z_rms": _finite(z_rms[k]), "z_max": _finite(z_max[k]),
                           "tolerance_mean_um": None if t is None else float(np.mean(t[k])),
                           "significant": bool(np.isfinite(z_rms[k]) and z_rms[k] > z_limit)}
        out[c] = {"units": names, "mean_surface_um": mean, "sd_surface_um": spread,
                  "sd_surface_rms_um": float(np.sqrt(np.mean(spread ** 2))),
                  "mean_tolerance_um": None if t is None else t.mean(axis=0),
                  "sd_tolerance_um": None if t is None else (t.std(axis=0, ddof=1) if len(names) > 1
                                                             else np.zeros_like(mean)),
                  "per_unit": per_unit}
    return out


def significant_units(stats: dict) -> list[dict]:
    """Units that differ significantly in any channel: name, channels, largest RMS z (by name order given)."""
    found: dict[str, dict] = {}
    for c, st in stats.items():
        for n, u in st["per_unit"].items():
            if u["significant"]:
                e = found.setdefault(n, {"unit": n, "channels": [], "z_rms_max": 0.0})
                e["channels"].append(c)
                e["z_rms_max"] = max(e["z_rms_max"], float(u["z_rms"]))
    return list(found.values())


def fleet_document(command: str, units: Sequence[dict], stats: dict | None = None, *,
                   grid: tuple[int, int] = GRID, fs_cyc_per_mm: float | None = None, q: float | None = None,
                   scheduler: str | None = None, workers: int | None = None,
                   z_limit: float = Z_LIMIT) -> dict:
    """The ``fieldcal-fleet/1`` document: the units (name, input, output, status, error) and the statistics."""
    from fieldcal import __version__

    fleet = None
    if stats:
        nx, ny = grid
        chans = {}
        for c, st in stats.items():
            chans[c] = {"units": st["units"], "mean_surface_um": _grid_list(st["mean_surface_um"]),
                        "sd_surface_um": _grid_list(st["sd_surface_um"]),
                        "sd_surface_rms_um": st["sd_surface_rms_um"],
                        "mean_tolerance_um": None if st["mean_tolerance_um"] is None
                        else _grid_list(st["mean_tolerance_um"]),
                        "sd_tolerance_um": None if st["sd_tolerance_um"] is None
                        else _grid_list(st["sd_tolerance_um"]),
                        "per_unit": st["per_unit"]}
        fleet = {"grid": {"nx": nx, "ny": ny, "x_frac": np.linspace(0, 1, nx).round(6).tolist(),
                          "y_frac": np.linspace(0, 1, ny).round(6).tolist()},
                 "fs_cyc_per_mm": fs_cyc_per_mm, "q": q,
                 "comparison": {"method": "leave-one-out z-score (docs/batch.md)", "z_limit": z_limit},
                 "channels": chans, "significant": significant_units(stats)}
    failed = [u for u in units if not u["ok"]]
    return {"format": FLEET_FORMAT, "tool": {"name": "fieldcal", "version": __version__},
            "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "command": command, "scheduler": scheduler, "workers": workers,
            "n_units": len(units), "n_failed": len(failed), "units": list(units), "fleet": fleet}


def write_fleet_report(doc: dict, stats: dict | None, out: str | Path, plot: bool = True) -> list[Path]:
    """Write ``OUT/fleet.json`` (validated against its schema) and, with statistics, ``OUT/fleet.png``."""
    out = Path(out)
    written = [documents.write(out / "fleet.json", doc, "fleet", indent=1)]
    if plot and stats:
        written.append(plot_fleet(stats, out / "fleet.png"))
    return written


def plot_fleet(stats: dict, path: str | Path) -> Path:
    """Per channel: the fleet's mean surface, its sd map, each unit's RMS deviation (significant units red)
    and each unit's mean tolerance."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fieldcal.formats.atomic import save_figure

    chans = list(stats)
    n_units = max(len(st["units"]) for st in stats.values())
    fig, axes = plt.subplots(len(chans), 4, figsize=(16, 3.2 * len(chans) + 0.4), squeeze=False,
                             gridspec_kw={"width_ratios": [1, 1, max(1.0, n_units / 12), max(1.0, n_units / 12)]})
    for r, c in enumerate(chans):
        st = stats[c]
        for ax, key, title in ((axes[r, 0], "mean_surface_um", "mean best focus (µm)"),
                               (axes[r, 1], "sd_surface_um", "sd across units (µm)")):
            im = ax.imshow(st[key], origin="upper", extent=(0, 1, 1, 0), aspect="auto", cmap="viridis")
            ax.set_title(f"{c}: {title}", fontsize=9)
            ax.set_xlabel("x / width")
            ax.set_ylabel("y / height")
            fig.colorbar(im, ax=ax, fraction=0.046)
        names = st["units"]
        pu = st["per_unit"]
        x = np.arange(len(names))
        colours = ["tab:red" if pu[n]["significant"] else "tab:blue" for n in names]
        axes[r, 2].bar(x, [pu[n]["rms_deviation_um"] for n in names], color=colours)
        axes[r, 2].set_title(f"{c}: RMS deviation from the fleet mean (µm; red: |z| RMS > limit)", fontsize=9)
        tol = [pu[n]["tolerance_mean_um"] for n in names]
        if all(t is not None for t in tol):
            axes[r, 3].bar(x, tol, color="tab:green")
        axes[r, 3].set_title(f"{c}: mean focus tolerance (µm)", fontsize=9)
        for ax in axes[r, 2:]:
            ax.set_xticks(x)
            ax.set_xticklabels(names, rotation=60, ha="right", fontsize=7)
    fig.tight_layout()
    try:
        return save_figure(fig, path, dpi=90)
    finally:
        plt.close(fig)
