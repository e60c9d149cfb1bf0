"""`fieldcal plan stack|sweep` end to end on small images: files, pictures, and clear errors without tracebacks."""

import json

import numpy as np
import pytest

from fieldcal.cli import main
from fieldcal.plan.planfile import masks_path, read_plan


def test_plan_stack_cli_writes_plan_and_pictures(tmp_path, triplet_path, capsys):
    out = tmp_path / "stack.json"
    rc = main(["plan", "stack", str(triplet_path), "--fs", "80", "--q", "0.05", "--size", "160x90",
               "--channels", "G,R", "--direction=-z", "--out", str(out), "--plots", str(tmp_path / "pl")])
    assert rc == 0
    doc = read_plan(out)
    assert doc["kind"] == "stack" and doc["parameters"]["channels"] == ["G", "R"]
    zs = [f["z_um"] for f in doc["frames"]]
    assert zs == sorted(zs, reverse=True) and doc["n_frames"] == len(zs)
    assert "design study" in doc["profile"]["source"]
    assert doc["total_exposure_ms"] == pytest.approx(20.0 * len(zs))
    png = (tmp_path / "pl" / "stack-plan.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert f"{len(zs)} frames" in capsys.readouterr().out


def test_plan_sweep_cli_writes_plan_masks_and_pictures(tmp_path, models_dir):
    out = tmp_path / "sweep.json"
    rc = main(["plan", "sweep", str(models_dir / "singlet-colour.json"), "--alpha-um", "20",
               "--pixel-exposure-ms", "16", "--device", "lcos", "--cfa", "RGGB", "--size", "96x72",
               "--out", str(out), "--plots", str(tmp_path / "pl")])
    assert rc == 0
    doc = read_plan(out)
    assert doc["total_time_ms"] == pytest.approx((doc["range_um"] / 40 + 1) * 16)
    arr = np.load(masks_path(out, doc))
    assert arr["mask_bits"].shape[0] == doc["device"]["n_slots"]
    for name in ("sweep-masks.png", "sweep-windows.png", "alpha-trade.png"):
        assert (tmp_path / "pl" / name).read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("args,needle", [
    (["--fs", "80", "--q", "1.5"], "field '--q'"),
    (["--fs", "nan", "--q", "0.05"], "field '--fs'"),
    (["--fs", "-3", "--q", "0.05"], "field '--fs'"),
    (["--fs", "80", "--q", "0.05", "--roi", "0,0,0,10"], "field '--roi'"),
    (["--fs", "80", "--q", "0.05", "--roi", "a,b"], "field '--roi'"),
    (["--fs", "80", "--q", "0.05", "--channels", "X"], "field '--channels'"),
])
def test_bad_parameters_exit_nonzero_with_a_message_and_no_file(tmp_path, triplet_path, capsys, args, needle):
    out = tmp_path / "p.json"
    rc = main(["plan", "stack", str(triplet_path), "--size", "64x36", "--out", str(out)] + args)
    err = capsys.readouterr().err
    assert rc == 2 and needle in err and "fix:" in err and "Traceback" not in err
    assert not out.exists()


def test_bad_profile_files(tmp_path, capsys):
    p = tmp_path / "x.json"
    p.write_text("{not json")
    assert main(["plan", "stack", str(p), "--fs", "80", "--q", "0.05", "--out", str(tmp_path / "o.json")]) == 2
    assert "not valid JSON" in capsys.readouterr().err
    assert main(["plan", "sweep", str(tmp_path / "none.json"), "--alpha-um", "20", "--pixel-exposure-ms", "16",
                 "--out", str(tmp_path / "o.json")]) == 2
    assert "not found" in capsys.readouterr().err
    p.write_text(json.dumps({"format": "fieldcal-lens/1"}))
    assert main(["plan", "stack", str(p), "--fs", "80", "--q", "0.05", "--out", str(tmp_path / "o.json")]) == 2


def test_help_has_examples(capsys):
    for kind in ("stack", "sweep"):
        with pytest.raises(SystemExit):
            main(["plan", kind, "--help"])
        assert "example:" in capsys.readouterr().out
