"""Sweep plans: eq. 3 and the paper's sweep numbers, per-pixel windows against the surfaces, device masks and
their limits, CFA, the sidecar file, and the integrated PSF / Wiener trade against closed forms."""

import math

import numpy as np
import pytest

from fieldcal.errors import ParameterError, SpecError
from fieldcal.optics.sweep import integrated_psf_radial
from fieldcal.simulate.lens import LensSpec
from fieldcal.plan import Scene
from fieldcal.plan import ipsf as ip
from fieldcal.plan import masks as mk
from fieldcal.plan.planfile import read_plan, validate_plan
from fieldcal.plan.scene import full_grid
from fieldcal.plan.surfaces import sensor_focus_um
from fieldcal.plan.sweep_plan import SweepRequest, plan_sweep, write_sweep_plan
from fieldcal.plan.synthetic import SyntheticProfile
from fieldcal.simulate.truth import TruthProfile


def test_paper_sweep_numbers():
    # V.B: sections of 2α = 24 µm, 16 ms each, 13 sections, 208 ms, stage at 1.5 mm/s -> D = (13 - 1) * 24 = 288 µm
    assert ip.sweep_total_time_ms(288.0, 12.0, 16.0) == pytest.approx(208.0)
    prof = SyntheticProfile(65, 49, a_um=-288.0)
    plan = plan_sweep(prof, SweepRequest(alpha_um=12.0, pixel_exposure_ms=16.0, device="lcos"))
    assert plan.range_um == pytest.approx(288.0)
    assert plan.total_time_ms == pytest.approx(208.0)
    assert plan.velocity_um_per_ms == pytest.approx(1.5)  # 1.5 µm/ms = 1.5 mm/s
    assert plan.n_slots == 13 and plan.device.slot_ms == 16.0  # one sweep per circular section, as in the paper
    assert plan.to_dict()["device"]["wall_time_ms"] == pytest.approx(2 * 208.0)  # complement after each slot


@pytest.mark.parametrize("direction", ["+z", "-z"])
def test_windows_open_and_close_alpha_either_side_of_best_focus(models_dir, direction):
    prof = TruthProfile(LensSpec.load(models_dir / "doublet-mono.json"), 80, 60)
    plan = plan_sweep(prof, SweepRequest(alpha_um=20.0, pixel_exposure_ms=10.0, direction=direction))
    # each sensor pixel's best focus at the scene point it images (the lens breathes; tests/test_plan_geometry.py
    # checks it against the truth's maps)
    z = mk.focus_and_band(prof, plan.field, plan.planes, None)[0][0].astype(np.float64)
    sgn = 1.0 if direction == "+z" else -1.0
    stage = lambda t: plan.start_um + sgn * plan.velocity_um_per_ms * t  # noqa: E731
    t0 = plan.window_start_ms[0].astype(np.float64)
    t1 = plan.window_stop_ms[0].astype(np.float64)
    np.testing.assert_allclose(stage(t0), z - sgn * 20.0, atol=1e-3)
    np.testing.assert_allclose(stage(t1), z + sgn * 20.0, atol=1e-3)
    assert t0.min() == pytest.approx(0.0, abs=1e-4) and t1.max() == pytest.approx(plan.total_time_ms, abs=1e-3)
    assert plan.total_time_ms == pytest.approx((plan.range_um / 40.0 + 1) * 10.0)


def test_lcos_masks_honour_hold_limit_and_give_each_pixel_its_exposure(tmp_path):
    prof = SyntheticProfile(41, 33, a_um=-150.0)
    plan = plan_sweep(prof, SweepRequest(alpha_um=10.0, pixel_exposure_ms=32.0, device="lcos", max_hold_ms=20.0))
    assert plan.device.slot_ms == 16.0 and plan.device.slot_ms <= 20.0  # 32 ms split into two 16 ms slots
    doc = write_sweep_plan(plan, tmp_path / "sw.json")
    arr = mk.load_npz(tmp_path / doc["masks"]["file"])
    n, p, h, w = arr["mask_shape"]
    masks = mk.unpack(arr["mask_bits"], int(w))
    assert masks.shape == (n, p, h, w) == (plan.n_slots, 1, 33, 41)
    assert np.all(masks.sum(axis=0) == 2)  # exactly t_s / slot_ms slots per pixel
    # each open slot's stage range lies within α + half a slot of the pixel's best focus
    edges = np.asarray(plan.slot_z_edges_um())
    x, y = full_grid(plan.field.roi)
    z = prof.best_focus_um(x, y, "G")
    slack = plan.velocity_um_per_ms * plan.device.slot_ms / 2 + 1e-6
    for k in range(n):
        on = masks[k, 0]
        if on.any():
            assert np.all(edges[k] >= z[on] - 10.0 - slack) and np.all(edges[k + 1] <= z[on] + 10.0 + slack)
    import hashlib
    assert hashlib.sha256((tmp_path / "sw.masks.npz").read_bytes()).hexdigest() == doc["masks"]["sha256"]
    assert read_plan(tmp_path / "sw.json")["kind"] == "sweep"
    with pytest.raises(ParameterError) as e:
        plan_sweep(prof, SweepRequest(alpha_um=10.0, pixel_exposure_ms=16.0, device="lcos", slot_ms=25.0))
    assert e.value.field == "slot_ms"


def test_cfa_aware_windows_follow_each_sites_colour(models_dir):
    prof = TruthProfile(LensSpec.load(models_dir / "singlet-colour.json"), 64, 48)
    plan = plan_sweep(prof, SweepRequest(alpha_um=20.0, pixel_exposure_ms=16.0, device="lcos", cfa="RGGB"))
    assert plan.planes == ["CFA:RGGB"]
    t0 = plan.window_start_ms[0]
    x, y = full_grid(plan.field.roi)
    zmin = plan.field.z_min_um
    for (r, c), ch in {(0, 0): "R", (0, 1): "G", (1, 0): "G", (1, 1): "B"}.items():
        # each site's own colour's focus at the point it images (exact fixed point; the plan interpolates it)
        z = sensor_focus_um(prof, x[0], y[:, 0], ch)[r::2, c::2]
        np.testing.assert_allclose(t0[r::2, c::2], (z - zmin) / plan.velocity_um_per_ms,
                                   atol=0.05 / plan.velocity_um_per_ms)
    # R focuses ~260 µm behind B: on axis, R opens much later than its B neighbour
    assert t0[24, 32] - t0[25, 33] > 200.0 / plan.velocity_um_per_ms
    with pytest.raises(ParameterError) as e:  # an LCoS cannot follow three surfaces without a mosaic
        plan_sweep(prof, SweepRequest(device="lcos", cfa=None))
    assert e.value.field == "channels"
    one = plan_sweep(prof, SweepRequest(device="lcos", scene=Scene(channels=("G",))))
    assert one.planes == ["G"]


def test_pixel_device_registers(tmp_path):
    prof = SyntheticProfile(33, 25, a_um=-80.0, channels=("R", "G"), offsets_um={"R": 15.0})
    plan = plan_sweep(prof, SweepRequest(alpha_um=5.0, pixel_exposure_ms=4.0, device="pixel", clock_us=10.0))
    arr = plan.mask_arrays()
    assert set(arr) >= {"start_tick", "stop_tick", "window_start_ms", "window_stop_ms"}
    assert np.all(arr["stop_tick"].astype(np.int64) - arr["start_tick"] == 400)  # 4 ms at 10 µs
    np.testing.assert_allclose(arr["start_tick"] * 0.01, plan.window_start_ms, atol=0.0051)
    assert plan.planes == ["R", "G"] and plan.range_um == pytest.approx(95.0)
    with pytest.raises(ParameterError):
        plan_sweep(prof, SweepRequest(alpha_um=5.0, pixel_exposure_ms=4.0, clock_us=1e-6))  # 32-bit overflow


@pytest.mark.parametrize("kw,field", [({"alpha_um": 0.0}, "alpha_um"), ({"alpha_um": float("nan")}, "alpha_um"),
                                      ({"pixel_exposure_ms": -1.0}, "pixel_exposure_ms"),
                                      ({"device": "dmd"}, "device"), ({"cfa": "RGBW"}, "cfa"),
                                      ({"scene": Scene(roi=(0, 0, 0, 0))}, "roi")])
def test_invalid_sweep_parameters(kw, field):
    with pytest.raises(ParameterError) as e:
        plan_sweep(SyntheticProfile(17, 17), SweepRequest(**kw))
    assert e.value.field == field


def test_plan_file_rejects_inconsistent_or_orphaned_sweeps(tmp_path):
    prof = SyntheticProfile(17, 17, a_um=-40.0)
    doc = write_sweep_plan(plan_sweep(prof, SweepRequest()), tmp_path / "a.json")
    bad = dict(doc, total_time_ms=doc["total_time_ms"] * 2)
    with pytest.raises(SpecError) as e:
        validate_plan(bad)
    assert e.value.field == "total_time_ms"
    with pytest.raises(SpecError) as e:
        validate_plan(dict(doc, masks=dict(doc["masks"], file="/etc/x.npz")))
    assert e.value.field == "masks.file"
    (tmp_path / "a.masks.npz").unlink()
    with pytest.raises(SpecError) as e:
        read_plan(tmp_path / "a.json")
    assert "missing" in str(e.value)


# ----------------------------------------------------------------------------- integrated PSF and Wiener
def test_ipsf_is_normalised_and_widens_with_alpha():
    prof = SyntheticProfile(17, 17, f_number=4.0)
    r = np.linspace(0.0, 60.0, 1201)
    e = []
    for a in (0.0, 20.0, 40.0):
        psf = integrated_psf_radial(prof, r, a, "G", n_f=1024)
        e.append(np.trapezoid(2 * np.pi * r * psf, r))
        if a == 0.0:
            peak0 = psf[0]
        else:
            assert psf[0] < peak0
    assert all(abs(v - 1.0) < 0.03 for v in e[1:])  # integrates to 1 (in-focus Airy tail converges slowly)


def test_wiener_noise_gain_closed_form_and_trade():
    assert ip.wiener_noise_gain(np.ones(100), 0.25) == pytest.approx(1 / 1.25)
    h = np.array([1.0, 0.5])
    assert ip.wiener_noise_gain(h, 0.01) == pytest.approx(math.sqrt(((1 / 1.01) ** 2 + (0.5 / 0.26) ** 2) / 2))
    prof = SyntheticProfile(17, 17, f_number=2.0, pixel_pitch_um=2.0)
    rows = ip.alpha_trade(prof, 332.0, 16.0, [5, 10, 20, 40, 80], "G", 80.0, nsr=0.01)
    T = [r["total_time_ms"] for r in rows]
    g = [r["noise_gain"] for r in rows]
    assert all(a > b for a, b in zip(T, T[1:]))          # longer α: shorter sweep ...
    assert all(a < b for a, b in zip(g[:4], g[1:4]))     # ... but more noise after deconvolution,
    assert max(g) <= 1 / (2 * math.sqrt(0.01)) + 1e-9     # bounded by 1/(2 sqrt K): where H < sqrt K Wiener
    m = [r["restored_mtf_at_fs"] for r in rows]           # stops restoring and the result stays blurred
    assert all(a > b for a, b in zip(m, m[1:]))
    # restoring the in-focus MTF up to fs always costs more noise as α grows; at α -> 0 it costs nothing
    gf = [r["noise_gain_to_in_focus"] for r in rows]
    assert all(a < b for a, b in zip(gf, gf[1:]))
    assert ip.alpha_trade(prof, 332.0, 16.0, [1e-6], "G", 80.0)[0]["noise_gain_to_in_focus"] == pytest.approx(1.0)
    assert rows[2]["total_time_ms"] == pytest.approx((332 / 40 + 1) * 16)


class _BandProfile(SyntheticProfile):
    """A synthetic lens whose credible half-width grows over the field: u = u0 + u1 rho (µm)."""

    def __init__(self, u0, u1, **kw):
        super().__init__(**kw)
        self.u0, self.u1 = u0, u1

    def best_focus_interval_um(self, x, y, channel, level=0.9):
        z = self.best_focus_um(x, y, channel)
        u = self.u0 + self.u1 * self.rho(x, y)
        return z - u, z + u


@pytest.mark.parametrize("direction", ["+z", "-z"])
def test_confidence_widens_each_window_by_its_band_in_z(direction):
    alpha, ts = 10.0, 16.0
    prof = _BandProfile(2.0, 6.0, width_px=48, height_px=32, a_um=-120.0)
    plain = plan_sweep(prof, SweepRequest(alpha_um=alpha, pixel_exposure_ms=ts, direction=direction))
    wide = plan_sweep(prof, SweepRequest(alpha_um=alpha, pixel_exposure_ms=ts, direction=direction, confidence=0.9))
    x, y = full_grid(wide.field.roi)
    z = prof.best_focus_um(x, y, "G")
    u = 2.0 + 6.0 * prof.rho(x, y)
    sgn = 1.0 if direction == "+z" else -1.0
    v = wide.velocity_um_per_ms
    assert v == pytest.approx(plain.velocity_um_per_ms)  # the stage moves as fast; the windows get longer
    stage = lambda t: wide.start_um + sgn * v * t  # noqa: E731
    t0, t1 = (a[0].astype(np.float64) for a in (wide.window_start_ms, wide.window_stop_ms))
    # each pixel opens α + u before its MAP focus and closes α + u after it
    np.testing.assert_allclose(stage(t0), z - sgn * (alpha + u), atol=2e-3)
    np.testing.assert_allclose(stage(t1), z + sgn * (alpha + u), atol=2e-3)
    # in z the window is wider by exactly 2u, so its exposure grows by t_s u / α
    np.testing.assert_allclose((t1 - t0) - ts, ts * u / alpha, atol=2e-4)
    np.testing.assert_allclose(plain.window_stop_ms[0] - plain.window_start_ms[0], ts, atol=1e-4)
    # the sweep reaches α beyond every band: D = max(z + u) - min(z - u) over the pixels (z + u peaks off axis)
    assert wide.range_um == pytest.approx(float(np.max(z + u) - np.min(z - u)), abs=1e-3)
    assert wide.range_um > plain.range_um + 8.0 + 2.0 - 1e-3
    assert wide.total_time_ms == pytest.approx((wide.range_um / (2 * alpha) + 1) * ts)
    # any true surface inside the band is swept ±α while its pixel is open
    for s in (-1.0, 0.0, 1.0):
        zt = z + s * u
        lo, hi = np.minimum(stage(t0), stage(t1)), np.maximum(stage(t0), stage(t1))
        assert np.all(lo <= zt - alpha + 2e-3) and np.all(hi >= zt + alpha - 2e-3)
    assert wide.to_dict()["band_widening"]["half_width_um"]["max"] == pytest.approx(8.0, abs=0.05)


def test_confidence_windows_reach_the_device_files(tmp_path):
    prof = _BandProfile(3.0, 0.0, width_px=40, height_px=24, a_um=-80.0)
    plan = plan_sweep(prof, SweepRequest(alpha_um=10.0, pixel_exposure_ms=10.0, confidence=0.9, clock_us=10.0))
    doc = write_sweep_plan(plan, tmp_path / "sw.json")
    validate_plan(doc, tmp_path / "sw.json")
    arr = mk.load_npz(tmp_path / doc["masks"]["file"])
    ticks = (arr["stop_tick"] - arr["start_tick"]).astype(np.float64) * float(arr["clock_ms"])
    np.testing.assert_allclose(ticks, 10.0 * (1 + 3.0 / 10.0), atol=0.011)  # t_s (1 + u/α), clock-rounded
    with pytest.raises(ParameterError) as e:
        plan_sweep(prof, SweepRequest(alpha_um=10.0, pixel_exposure_ms=10.0, confidence=1.5))
    assert e.value.field == "confidence"
