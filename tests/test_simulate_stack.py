"""simulate_stack and `fieldcal simulate`: a valid stack + truth on disk, and clear errors for user mistakes."""

import json

import cv2
import numpy as np
import pytest

import fieldcal
from fieldcal.cli import main
from fieldcal.errors import ParameterError, StackError
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.scene import fit_to_sensor, load_scene
from fieldcal.simulate.stackgen import simulate_stack, z_grid


def test_z_grid_inclusive_stop():
    z = z_grid(-200, 200, 25)
    assert len(z) == 17 and z[0] == -200 and z[-1] == 200
    assert len(z_grid(-200, 190, 25)) == 16  # 190 is off the grid: stop at 175
    np.testing.assert_allclose(z_grid(0, 0.3, 0.1), [0, 0.1, 0.2, 0.3])
    with pytest.raises(ParameterError, match="step_um"):  # library errors name the API parameter
        z_grid(0, 10, 0)
    with pytest.raises(ParameterError, match="stop_um"):
        z_grid(10, 0, 1)


def test_cli_writes_17_frame_stack(tmp_path, triplet_path, capsys):
    out = tmp_path / "out"
    rc = main(["simulate", str(triplet_path), str(out), "--z", "-200", "200", "25", "--size", "96x54", "--quiet"])
    assert rc == 0
    stack = fieldcal.Stack.open(out)
    assert len(stack) == 17 and stack.shape == (54, 96) and list(stack.channels) == ["R", "G", "B"]
    np.testing.assert_allclose(stack.z_um, np.arange(-200, 201, 25))
    spec = LensSpec.load(triplet_path)
    assert stack.pixel_pitch_um == pytest.approx(spec.sensor.pixel_pitch_um * 40)  # same sensor area
    assert stack.meta["bit_depth"] == 12 and stack.meta["lens"] == "triplet-uncorrected"
    assert stack.meta["chart"] == "chart" and stack.white_level == 4095 and stack.black_level == 64
    frame = stack.read(8)
    assert frame.dtype == np.uint16 and frame.shape == (54, 96, 3) and frame.max() <= 4095
    truth = json.loads((out / "truth.json").read_text())
    assert truth["format"] == "fieldcal-truth/1" and truth["size_px"] == [96, 54] and len(truth["z_um"]) == 17
    assert LensSpec.from_dict(truth["lens"]).sensor.width_px == 96
    import tifffile
    t = tifffile.imread(out / "truth.tiff")
    assert t.shape == (54, 96, 3) and t.dtype == np.uint16
    # the truth is sharper than any frame: the texture's high-frequency energy peaks there
    hf = lambda a: float(np.var(cv2.Laplacian(a[..., 1].astype(np.float32), cv2.CV_32F)))
    assert hf(t) > max(hf(stack.read(i)) for i in range(17)) * 0.9


def test_stack_is_deterministic_and_frames_follow_renderer(tmp_path):
    spec = LensSpec.load(fieldcal_models() / "doublet-mono.json")
    a = simulate_stack(spec, tmp_path / "a", [-50, 0, 50], seed=3, size=(64, 48), progress=False)
    b = simulate_stack(spec, tmp_path / "b", [50, 0, -50], seed=3, size=(64, 48), progress=False)
    assert a.channels == b.channels
    for i, j in ((0, 2), (1, 1), (2, 0)):
        assert np.array_equal(a.read(i), b.read(j))
    assert a.read(0).shape == (48, 64, 1)


def fieldcal_models():
    from pathlib import Path
    return Path(__file__).resolve().parents[1] / "models"


def test_bayer_stack_records_cfa(tmp_path):
    spec = LensSpec.load(fieldcal_models() / "singlet-colour.json")
    d = json.loads(json.dumps(spec.to_dict()))  # as a file holds it
    d["sensor"]["cfa"] = "RGGB"
    spec = LensSpec.from_dict(d)
    st = simulate_stack(spec, tmp_path / "s", [0, 40], size=(64, 48), progress=False, scene="slanted-edge")
    assert st.cfa == "RGGB" and st.meta["cfa"] == "RGGB"
    assert st.read(0).shape[:2] == (48, 64)


def test_overwrite_rules(tmp_path, triplet_path):
    spec = LensSpec.load(triplet_path)
    out = tmp_path / "s"
    simulate_stack(spec, out, [0], size=(32, 18), progress=False)
    with pytest.raises(StackError, match="not empty"):
        simulate_stack(spec, out, [0], size=(32, 18), progress=False)
    st = simulate_stack(spec, out, [0, 10], size=(32, 18), progress=False, overwrite=True)
    assert len(st) == 2
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    with pytest.raises(StackError, match="will not delete"):
        simulate_stack(spec, other, [0], size=(32, 18), progress=False, overwrite=True)
    assert (other / "notes.txt").read_text() == "keep me"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no partial folders left


def test_interrupted_run_leaves_nothing(tmp_path, triplet_path, monkeypatch):
    from fieldcal.simulate import render
    spec = LensSpec.load(triplet_path)
    calls = {"n": 0}
    orig = render.Renderer.render

    def flaky(self, z, noise=True):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return orig(self, z, noise)

    monkeypatch.setattr(render.Renderer, "render", flaky)
    with pytest.raises(KeyboardInterrupt):
        simulate_stack(spec, tmp_path / "s", [0, 10, 20, 30], size=(32, 18), progress=False)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv,match", [
    (["--size", "12"], "--size"),
    (["--size", "4x4"], "--size"),
    (["--z", "10", "0", "5"], "STOP"),
    (["--z", "0", "10", "0"], "STEP"),
    (["--z", "0", "10", "-1"], "STEP"),
    (["--scene", "no-such-image.png"], "scene image not found"),
    (["--seed", "-1"], "seed"),
])
def test_cli_errors_are_clear(tmp_path, triplet_path, capsys, argv, match):
    base = {"--z": ["0", "50", "25"], "--size": ["32x18"]}
    args = ["simulate", str(triplet_path), str(tmp_path / "o"), "--quiet"]
    for k, v in base.items():
        if k not in argv:
            args += [k, *v]
    args += [a if a != "no-such-image.png" else str(tmp_path / a) for a in argv]
    rc = main(args)
    err = capsys.readouterr().err
    assert rc != 0 and match in err and "Traceback" not in err and "fix:" in err
    assert not (tmp_path / "o").exists()


def test_cli_bad_lens_and_existing_output(tmp_path, triplet_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert main(["simulate", str(bad), str(tmp_path / "o"), "--z", "0", "1", "1"]) != 0
    assert "bad.json" in capsys.readouterr().err
    out = tmp_path / "o2"
    out.mkdir()
    (out / "x").write_text("x")
    assert main(["simulate", str(triplet_path), str(out), "--z", "0", "1", "1", "--size", "32x18"]) != 0
    err = capsys.readouterr().err
    assert "--overwrite" in err and "Traceback" not in err


def test_unreadable_scene_file(tmp_path):
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image at all")
    with pytest.raises(ParameterError, match="cannot be read") as e:
        load_scene(junk, 32, 18)
    assert str(junk) in str(e.value)


def test_image_scene_resized_and_cropped(tmp_path):
    # a 200x100 RGB image with a red left half, to a 32x32 sensor: centre crop 100x100, INTER_AREA
    img = np.zeros((100, 200, 3), dtype=np.uint8)
    img[:, :100] = (0, 0, 255)  # BGR red on disk
    img[:, 100:] = (255, 0, 0)  # BGR blue
    p = tmp_path / "s.png"
    cv2.imwrite(str(p), img)
    a, name = load_scene(p, 32, 32)
    assert name == "s.png" and a.shape == (32, 32, 3)
    np.testing.assert_allclose(a[:, :15, 0], 1.0, atol=1e-6)  # R order, left half red
    np.testing.assert_allclose(a[:, 17:, 2], 1.0, atol=1e-6)
    b = fit_to_sensor(np.full((10, 10), 65535, dtype=np.uint16), 20, 20)
    np.testing.assert_allclose(b, 1.0, atol=1e-6)


def test_mono_lens_from_rgb_image_stack(tmp_path):
    img = np.zeros((60, 80, 3), dtype=np.uint8)
    img[..., 1] = 200
    p = tmp_path / "g.png"
    cv2.imwrite(str(p), img)
    spec = LensSpec.load(fieldcal_models() / "doublet-mono.json")
    st = simulate_stack(spec, tmp_path / "s", [0], scene=p, size=(40, 30), progress=False, noise=False)
    assert list(st.channels) == ["Y"] and st.meta["chart"] == "g.png"
    f = st.read(0)
    assert f.shape == (30, 40, 1)


def test_colour_leaves_scene_is_colour_and_textured():
    from fieldcal.simulate.scene import load_scene
    img, name = load_scene("colour-leaves", 160, 90, seed=2)
    assert name == "colour-leaves" and img.shape == (90, 160, 3) and img.dtype == np.float32
    assert 0.0 <= img.min() and img.max() <= 1.0
    # channels correlated (one luminance) but not identical (per-channel focus matters)
    r = np.corrcoef(img[..., 0].ravel(), img[..., 2].ravel())[0, 1]
    assert 0.5 < r < 0.99
    # edges at fine scale: strong pixel-to-pixel differences
    assert np.abs(np.diff(img[..., 1], axis=1)).mean() > 0.02
    again, _ = load_scene("colour-leaves", 160, 90, seed=2)
    np.testing.assert_array_equal(img, again)
