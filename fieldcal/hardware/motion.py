"""Point-to-point motion with a trapezoidal velocity profile, and the run-up a constant-velocity sweep needs.

A servo controller (PI's C-863 among them) moves with a bounded acceleration ``a`` up to the commanded velocity
``v`` and decelerates as hard into the target: for a distance ``d``, the carriage is at constant velocity only
between ``v²/2a`` after the start and ``v²/2a`` before the target (a triangle when ``d < v²/a``). A focal
sweep must open its exposure only inside that plateau, so its move starts a *run-up* before the plan's range.
Units: µm, µm/s, µm/s², s (the stage's own units at its edge are converted by the backend).
"""

from __future__ import annotations

import math


def move_duration_s(distance_um: float, velocity_um_s: float, accel_um_s2: float) -> float:
    """Time a trapezoidal (or triangular) move of ``distance_um`` takes; ``accel = inf`` is constant velocity."""
    d, v, a = abs(float(distance_um)), float(velocity_um_s), float(accel_um_s2)
    if d == 0.0:
        return 0.0
    if not math.isfinite(a):
        return d / v
    if d >= v * v / a:  # reaches the plateau
        return d / v + v / a
    return 2.0 * math.sqrt(d / a)


def travelled_um(t_s: float, distance_um: float, velocity_um_s: float, accel_um_s2: float) -> float:
    """Distance (>= 0) covered ``t_s`` after the start of a move of ``|distance_um|`` (clamped to the move)."""
    d, v, a = abs(float(distance_um)), float(velocity_um_s), float(accel_um_s2)
    if t_s <= 0.0 or d == 0.0:
        return 0.0
    if not math.isfinite(a):
        return min(d, v * t_s)
    t_end = move_duration_s(d, v, a)
    if t_s >= t_end:
        return d
    vp = v if d >= v * v / a else math.sqrt(a * d)  # peak velocity (triangle when the plateau is not reached)
    t_acc = vp / a
    if t_s <= t_acc:
        return 0.5 * a * t_s * t_s
    t_dec = t_end - t_acc
    if t_s <= t_dec:
        return 0.5 * vp * t_acc + vp * (t_s - t_acc)
    r = t_end - t_s
    return d - 0.5 * a * r * r


def time_at_um(x_um: float, distance_um: float, velocity_um_s: float, accel_um_s2: float) -> float:
    """Inverse of :func:`travelled_um`: the time (s) at which ``x_um`` (0..|distance|) has been covered."""
    d, v, a = abs(float(distance_um)), float(velocity_um_s), float(accel_um_s2)
    x = min(max(float(x_um), 0.0), d)
    if not math.isfinite(a):
        return x / v
    vp = v if d >= v * v / a else math.sqrt(a * d)
    t_acc = vp / a
    x_acc = 0.5 * vp * t_acc
    t_end = move_duration_s(d, v, a)
    if x <= x_acc:
        return math.sqrt(2.0 * x / a)
    if x <= d - x_acc:
        return t_acc + (x - x_acc) / vp
    return t_end - math.sqrt(max(0.0, 2.0 * (d - x) / a))


def run_up_um(velocity_um_s: float, accel_um_s2: float, settle_ms: float = 0.0) -> float:
    """Distance before the exposure opens (and after it closes): ``v²/2a`` to reach (leave) the velocity, plus
    ``v · settle`` for the servo to settle onto it (the following error of a step in velocity)."""
    v, a = float(velocity_um_s), float(accel_um_s2)
    ramp = 0.0 if not math.isfinite(a) else v * v / (2.0 * a)
    return ramp + v * max(0.0, float(settle_ms)) / 1000.0
