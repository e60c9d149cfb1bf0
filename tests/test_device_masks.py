"""Device mask files (fieldcal-masks/1): loaded back they equal the plan's windows exactly, for the LCoS slot
sequence (1-bit PNGs) and the pixel-wise sensor (16-bit start/stop TIFFs); the files are what they claim to be;
damaged, missing or mismatched files and unsafe outputs are refused with the field and the fix."""

import json

import numpy as np
import pytest
import tifffile

from fieldcal.cli import main
from fieldcal.errors import FieldcalError, OutputError, ParameterError, SpecError
from fieldcal.plan import Scene
from fieldcal.plan import device_masks as dm
from fieldcal.plan import masks as mk
from fieldcal.plan.sweep_plan import SweepRequest, plan_sweep, write_sweep_plan
from fieldcal.plan.synthetic import SyntheticProfile

RGB = dict(channels=("R", "G", "B"), offsets_um={"R": 12.0, "G": 0.0, "B": -9.0})


def _pixel_plan(**kw):
    prof = SyntheticProfile(64, 48, a_um=-200.0, **RGB)
    return plan_sweep(prof, SweepRequest(alpha_um=15.0, pixel_exposure_ms=12.0, device="pixel", clock_us=10.0, **kw))


def _lcos_plan():
    prof = SyntheticProfile(64, 48, a_um=-200.0, **RGB)
    return plan_sweep(prof, SweepRequest(alpha_um=15.0, pixel_exposure_ms=32.0, device="lcos", max_hold_ms=20.0,
                                         cfa="RGGB"))


def test_pixelwise_round_trip_is_exact_and_matches_the_windows(tmp_path):
    # an ROI leaves pixels that are never exposed: they must come back as start = stop = 0
    plan = _pixel_plan(scene=Scene(roi=(8, 4, 40, 30)))
    arrays = plan.mask_arrays()
    man = dm.export_device_masks(plan.to_dict(), arrays, tmp_path / "dev")
    back = dm.load_device_masks(tmp_path / "dev")
    assert back.manifest == man and man["device"] == "pixelwise" and man["planes"] == ["R", "G", "B"]
    for k in ("start_tick", "stop_tick"):
        assert back.arrays[k].dtype == np.uint32 and np.array_equal(back.arrays[k], arrays[k])
    # against the plan's float windows: the register is the window in clock ticks, rounded
    clk = plan.device.clock_ms
    ok = np.isfinite(plan.window_start_ms)
    assert ok.any() and (~ok).any()
    np.testing.assert_allclose(back.arrays["start_tick"][ok] * clk, plan.window_start_ms[ok], atol=clk / 2 + 1e-6)
    np.testing.assert_allclose(back.arrays["stop_tick"][ok] * clk, plan.window_stop_ms[ok], atol=clk / 2 + 1e-6)
    assert not back.arrays["start_tick"][~ok].any() and not back.arrays["stop_tick"][~ok].any()
    # each plane's map is its own channel's window (R focuses 21 µm later than B: later start on +z)
    assert (back.arrays["start_tick"][0][ok[0]] > back.arrays["start_tick"][2][ok[2]]).all()
    assert man["pixelwise"]["exposure_ticks"] == 1200


def test_pixelwise_files_are_compressed_16_bit_tiffs(tmp_path):
    plan = _pixel_plan()
    man = dm.export_device_masks(plan.to_dict(), plan.mask_arrays(), tmp_path / "dev")
    assert [f["name"] for f in man["files"]] == ["R-start.tif", "R-stop.tif", "G-start.tif", "G-stop.tif",
                                                 "B-start.tif", "B-stop.tif"]
    with tifffile.TiffFile(tmp_path / "dev" / "G-start.tif") as t:
        page = t.pages[0]
        assert page.dtype == np.uint16 and page.shape == (48, 64)
        assert page.compression == tifffile.COMPRESSION.ADOBE_DEFLATE
    raw = 6 * 64 * 48 * 2
    assert man["total_bytes"] < raw / 4
    assert man["total_bytes"] == sum(p.stat().st_size for p in (tmp_path / "dev").glob("*.tif"))


def test_lcos_round_trip_is_exact_and_masks_follow_each_bayer_site(tmp_path):
    plan = _lcos_plan()
    arrays = plan.mask_arrays()
    man = dm.export_device_masks(plan.to_dict(), arrays, tmp_path / "dev")
    back = dm.load_device_masks(tmp_path / "dev")
    assert man["device"] == "lcos" and man["planes"] == ["CFA:RGGB"] and man["cfa"] == "RGGB"
    assert man["lcos"]["n_slots"] == plan.n_slots and man["lcos"]["slot_ms"] == 16.0
    assert len(man["files"]) == plan.n_slots
    assert np.array_equal(back.arrays["mask_bits"], arrays["mask_bits"])
    assert np.array_equal(back.arrays["mask_shape"], arrays["mask_shape"])
    # independently of the sidecar: slot k is open where its centre lies in the pixel's window
    masks = mk.unpack(back.arrays["mask_bits"], 64)
    for k, want in enumerate(mk.slot_masks(plan.window_start_ms, 32.0, 16.0, plan.n_slots)):
        assert np.array_equal(masks[k], want)
    assert (masks.sum(axis=0) == 2).all()  # t_s / slot_ms slots for every pixel
    # R and B sites of one 2x2 cell open at different slots (their surfaces differ by 21 µm)
    first = masks[:, 0].argmax(axis=0)
    assert (first[0::2, 0::2] != first[1::2, 1::2]).any()


def test_lcos_files_are_1_bit_pngs(tmp_path):
    plan = _lcos_plan()
    dm.export_device_masks(plan.to_dict(), plan.mask_arrays(), tmp_path / "dev")
    data = (tmp_path / "dev" / "CFA-RGGB-slot-0000.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    assert int.from_bytes(data[16:20], "big") == 64 and int.from_bytes(data[20:24], "big") == 48
    assert data[24] == 1 and data[25] == 0  # bit depth 1, greyscale


def test_plan_file_to_device_folder_through_the_cli(tmp_path, capsys):
    plan = _pixel_plan()
    write_sweep_plan(plan, tmp_path / "sw.json")
    out = tmp_path / "dev"
    assert main(["plan", "export-masks", str(tmp_path / "sw.json"), "--out", str(out)]) == 0
    man = json.loads((out / "masks.json").read_text())
    assert man["format"] == "fieldcal-masks/1" and man["plan"]["file"] == "sw.json"
    back = dm.load_device_masks(out)
    assert np.array_equal(back.arrays["start_tick"], plan.mask_arrays()["start_tick"])
    # again: refused without --overwrite, replaced with it
    assert main(["plan", "export-masks", str(tmp_path / "sw.json"), "--out", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["plan", "export-masks", str(tmp_path / "sw.json"), "--out", str(out), "--overwrite"]) == 0
    # the wrong format for the plan's device
    assert main(["plan", "export-masks", str(tmp_path / "sw.json"), "--out", str(tmp_path / "x"),
                 "--format", "lcos"]) == 2
    assert "--format pixelwise" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_export_refuses_a_changed_sidecar(tmp_path):
    plan = _pixel_plan()
    doc = write_sweep_plan(plan, tmp_path / "sw.json")
    npz = tmp_path / doc["masks"]["file"]
    mk.write_npz(npz, {**plan.mask_arrays(), "start_tick": plan.mask_arrays()["start_tick"] + 1})
    with pytest.raises(SpecError, match="sha256"):
        dm.export_plan_file(tmp_path / "sw.json", tmp_path / "dev")


def test_damaged_or_missing_files_are_refused(tmp_path):
    plan = _lcos_plan()
    dm.export_device_masks(plan.to_dict(), plan.mask_arrays(), tmp_path / "dev")
    f = tmp_path / "dev" / "CFA-RGGB-slot-0003.png"
    data = bytearray(f.read_bytes())
    data[-20] ^= 0xFF
    f.write_bytes(bytes(data))
    with pytest.raises(SpecError, match="sha256") as e:
        dm.load_device_masks(tmp_path / "dev")
    assert "slot-0003" in str(e.value)
    f.unlink()
    with pytest.raises(SpecError, match="missing"):
        dm.load_device_masks(tmp_path / "dev")
    (tmp_path / "dev" / "masks.json").unlink()
    with pytest.raises(SpecError, match="masks.json"):
        dm.load_device_masks(tmp_path / "dev")


def test_manifest_is_checked_against_its_schema(tmp_path):
    plan = _pixel_plan()
    dm.export_device_masks(plan.to_dict(), plan.mask_arrays(), tmp_path / "dev")
    m = tmp_path / "dev" / "masks.json"
    doc = json.loads(m.read_text())
    doc["files"][0]["name"] = "../escape.tif"
    m.write_text(json.dumps(doc))
    with pytest.raises(SpecError) as e:
        dm.load_device_masks(tmp_path / "dev")
    assert "files[0].name" in str(e.value)


def test_sweeps_too_long_for_16_bit_registers_are_refused_with_a_clock_that_fits(tmp_path):
    plan = plan_sweep(SyntheticProfile(64, 48, a_um=-200.0, **RGB),
                      SweepRequest(alpha_um=15.0, pixel_exposure_ms=12.0, device="pixel", clock_us=0.5))
    top = int(plan.mask_arrays()["stop_tick"].max())
    assert top > dm.MAX_TICK_16
    with pytest.raises(ParameterError) as e:
        dm.export_device_masks(plan.to_dict(), plan.mask_arrays(), tmp_path / "dev")
    assert e.value.field == "clock_us"
    assert not (tmp_path / "dev").exists()
    fix_us = float(str(e.value.fix).split("--clock-us ")[1])
    assert top * 0.5 / fix_us <= dm.MAX_TICK_16  # the suggested clock fits the same sweep


def test_outputs_are_guarded(tmp_path):
    plan = _pixel_plan()
    other = tmp_path / "notes"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    with pytest.raises(OutputError, match="holds no masks.json"):
        dm.export_device_masks(plan.to_dict(), plan.mask_arrays(), other, overwrite=True)
    assert (other / "keep.txt").read_text() == "mine"
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="not a folder"):
        dm.export_device_masks(plan.to_dict(), plan.mask_arrays(), tmp_path / "file")
    # no partial folder is left beside the output after a refusal
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "notes"]


def test_stack_plans_have_no_masks(tmp_path):
    with pytest.raises(FieldcalError, match="sweep"):
        dm.export_format({"kind": "stack"}, None)
