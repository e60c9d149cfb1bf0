"""Reading a message stream without running it: its travel, the checks against a stage, time and disk.

These functions take the same stream the runner executes, so the dry run and the pre-motion checks see
exactly the moves that will be made.
"""

from __future__ import annotations

from typing import Iterable

from ..errors import ParameterError
from .messages import (Checkpoint, CloseExposure, Expose, Message, Move, OpenExposure, Save, Settle, SweepMove,
                       to_dict)


def extent_um(stream: Iterable[Message]) -> tuple[float, float]:
    """``(lo, hi)`` of every position the stream may command (moves, sweep ends, rewind back-offs)."""
    zs: list[float] = []
    for m in stream:
        if isinstance(m, Move):
            zs.append(m.z_um)
        elif isinstance(m, Checkpoint):
            zs.append(m.back_off_um)
        elif isinstance(m, SweepMove):
            zs += [m.z_start_um, m.z_stop_um]
        elif isinstance(m, (OpenExposure, CloseExposure)) and m.at_um is not None:
            zs.append(m.at_um)
    if not zs:
        raise ParameterError("the stream has no moves", field="stream", fix="give a plan with at least one frame")
    return float(min(zs)), float(max(zs))


def max_velocity_um_s(stream: Iterable[Message]) -> float | None:
    """The fastest constant-velocity move the stream asks for (None without sweeps)."""
    v = [m.velocity_um_s for m in stream if isinstance(m, SweepMove)]
    return max(v) if v else None


def needs_exposure_during_motion(stream: Iterable[Message]) -> bool:
    return any(isinstance(m, (OpenExposure, CloseExposure)) for m in stream)


def check_against_stage(stream: list[Message], *, limits_um: tuple[float, float],
                        velocity_limit_um_s: float | None = None) -> None:
    """Refuse (before anything moves) a stream that leaves the stage's travel or exceeds its velocity."""
    lo, hi = limits_um
    m_lo, m_hi = extent_um(stream)
    if m_lo < lo or m_hi > hi:
        raise ParameterError(f"the plan needs the stage at {m_lo:g}..{m_hi:g} um (approach moves included) but its "
                             f"travel is {lo:g}..{hi:g} um; nothing was moved", field="z_um",
                             fix="shift or shorten the plan, or move the stage's zero (e.g. gcs:...,zero_mm=...)")
    v = max_velocity_um_s(stream)
    if v is not None and velocity_limit_um_s is not None and v > velocity_limit_um_s:
        raise ParameterError(f"the plan sweeps at {v:g} um/s but the stage allows {velocity_limit_um_s:g} um/s; "
                             "nothing was moved", field="velocity_um_s",
                             fix="plan a slower sweep (longer pixel exposure or smaller range)")


def estimate(stream: Iterable[Message], *, velocity_um_s: float, readout_ms: float = 30.0,
             default_exposure_ms: float | None = None, frame_bytes: int = 0) -> dict:
    """Time (s), number of moves and frames, and disk (bytes) the stream needs, walking it in order."""
    if not (velocity_um_s > 0):
        raise ParameterError(f"stage velocity {velocity_um_s} um/s must be > 0", field="velocity_um_s",
                             fix="check the stage's velocity setting")
    t_ms, here, n_moves, n_frames = 0.0, None, 0, 0
    for m in stream:
        if isinstance(m, Move):
            t_ms += 0.0 if here is None else abs(m.z_um - here) / velocity_um_s * 1000.0
            here, n_moves = m.z_um, n_moves + 1
        elif isinstance(m, SweepMove):
            t_ms += abs(m.z_stop_um - m.z_start_um) / m.velocity_um_s * 1000.0
            here, n_moves = m.z_stop_um, n_moves + 1
            continue
        elif isinstance(m, OpenExposure) and m.at_um is not None:
            continue  # spans the SweepMove already counted
        elif isinstance(m, Settle):
            t_ms += m.ms
        elif isinstance(m, (Expose, OpenExposure)):
            t_ms += (m.exposure_ms if m.exposure_ms is not None else (default_exposure_ms or 0.0)) + readout_ms
        elif isinstance(m, Save):
            n_frames += 1
    return {"n_frames": n_frames, "n_moves": n_moves, "time_s": round(t_ms / 1000.0, 3),
            "disk_bytes": int(frame_bytes) * n_frames}


def as_json(stream: Iterable[Message]) -> list[dict]:
    """The stream as a list of ``{"msg": name, field: value}`` (what ``--dry-run`` prints)."""
    return [to_dict(m) for m in stream]


__all__ = ["extent_um", "max_velocity_um_s", "needs_exposure_during_motion", "check_against_stage", "estimate",
           "as_json"]
