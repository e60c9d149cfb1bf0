"""`fieldcal mtf`, `fieldcal.measure_mtf`, the fieldcal-mtf/1 file, and detection on the project's own charts."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

import fieldcal
from fieldcal.charts.targets import slanted_edge_image, slanted_edge_spec
from fieldcal.cli import main
from fieldcal.errors import SpecError
from fieldcal.measure.esfr_synth import analytic_mtf50
from fieldcal.measure.mtf import FORMAT, MtfResult


def _match(spec, res, tol_px):
    """For each edge of the chart spec, the detections within tol_px of its midpoint and parallel to it."""
    det = [e for e in res.edges if e["channel"] == res.edges[0]["channel"]]
    hits = 0
    for edge in spec.edges():
        mx, my = edge["mid_px"]
        ok = [e for e in det if math.hypot(e["x_px"] - mx, e["y_px"] - my) <= tol_px and
              abs((e["angle_deg"] - edge["direction_deg"] + 90) % 180 - 90) <= 1.5]
        hits += bool(ok)
    return hits


@pytest.mark.parametrize("size,cells", [((1920, 1080), 4), ((640, 360), None)])
def test_detection_on_the_slanted_edge_chart(size, cells):
    spec = slanted_edge_spec(*size, cells_short=cells)
    img = cv2.GaussianBlur(slanted_edge_image(spec), (0, 0), 1.0)
    res = fieldcal.measure_mtf(img)
    n = len(spec.edges())
    assert _match(spec, res, 0.2 * spec.side_px) >= 0.95 * n
    ok = [e for e in res.edges if e["quality"]["ok"]]
    assert len(ok) >= 0.9 * n
    # the chart squares are box-filtered (pixel aperture) then blurred by sigma 1: that is the closed form
    ref = analytic_mtf50(sigma_px=1.0, normal_deg=5.0)
    assert np.median([e["mtf50_cy_per_px"] for e in ok]) == pytest.approx(ref, rel=0.02)


def test_simulated_slanted_edge_stack(tmp_path):
    """`fieldcal simulate ... --scene slanted-edge`, then `fieldcal mtf` on the stack: edges in every frame,
    linked into tracks, and plots."""
    stack = tmp_path / "stk"
    assert main(["simulate", "models/triplet-uncorrected.json", str(stack), "--z", "-40", "40", "20",
                 "--size", "480x270", "--scene", "slanted-edge", "--quiet"]) == 0
    out = tmp_path / "mtf.json"
    plots = tmp_path / "plots"
    assert main(["mtf", str(stack), "--out", str(out), "--plots", str(plots), "--quiet"]) == 0
    doc = json.loads(out.read_text())
    assert doc["format"] == FORMAT
    frames = {e["frame"] for e in doc["edges"]}
    assert frames == set(range(5))
    spec = slanted_edge_spec(480, 270)
    per_frame = [sum(1 for e in doc["edges"] if e["frame"] == f and e["channel"] == "G") for f in frames]
    assert min(per_frame) >= 0.85 * len(spec.edges())  # 147-160 of 160 over this scan
    tracks = {}
    for e in doc["edges"]:
        if e["channel"] == "G":
            tracks.setdefault(e["track"], set()).add(e["frame"])
    assert sum(1 for f in tracks.values() if len(f) == 5) >= 0.8 * len(spec.edges())
    assert {p.name for p in plots.iterdir()} == {"mtf50_field.png", "through_focus.png"}


def test_document_round_trip_and_fields(tmp_path):
    img = cv2.GaussianBlur(slanted_edge_image(slanted_edge_spec(320, 180, cells_short=2)), (0, 0), 0.8)
    rgb = np.stack([img] * 3, axis=2)
    res = fieldcal.measure_mtf(rgb, centre_px=(159.5, 89.5))
    p = res.save(tmp_path / "m.json")
    back = MtfResult.load(p)
    assert np.array_equal(back.frequencies_cy_per_px, res.frequencies_cy_per_px)
    assert len(back.edges) == len(res.edges) > 0
    e = back.edges[0]
    for key in ("frame", "z_um", "channel", "x_px", "y_px", "angle_deg", "orientation", "mtf", "mtf50_cy_per_px",
                "quality", "track"):
        assert key in e
    assert len(e["mtf"]) == back.frequencies_cy_per_px.size
    assert {"ok", "reason", "contrast", "snr", "clipped_fraction", "slant_deg", "rows"} <= set(e["quality"])
    assert {x["channel"] for x in back.edges} == {"R", "G", "B"}
    assert back.provenance["centre_px"] == [159.5, 89.5]


def test_bad_files_name_the_problem(tmp_path, capsys):
    bad = tmp_path / "x.json"
    bad.write_text(json.dumps({"format": "something/1"}))
    with pytest.raises(SpecError, match="format"):
        MtfResult.load(bad)
    assert main(["mtf", str(tmp_path / "missing.png"), "--out", str(tmp_path / "o.json")]) == 2
    assert "missing.png" in capsys.readouterr().err
    (tmp_path / "notastack").mkdir()
    assert main(["mtf", str(tmp_path / "notastack"), "--out", str(tmp_path / "o.json")]) == 2  # no stack.json
    assert "stack.json" in capsys.readouterr().err


def test_single_image_file(tmp_path):
    img = cv2.GaussianBlur(slanted_edge_image(slanted_edge_spec(320, 180, cells_short=2)), (0, 0), 0.8)
    path = tmp_path / "chart.png"
    cv2.imwrite(str(path), np.round(img * 255).astype(np.uint8))
    out = tmp_path / "m.json"
    assert main(["mtf", str(path), "--out", str(out), "--centre", "159.5,89.5", "--quiet"]) == 0
    doc = json.loads(out.read_text())
    assert {e["channel"] for e in doc["edges"]} == {"Y"}
    assert sum(e["quality"]["ok"] for e in doc["edges"]) >= 0.9 * len(slanted_edge_spec(320, 180, cells_short=2)
                                                                        .edges())


def test_texture_chart_gives_no_trusted_edges():
    """The dead-leaves texture has no straight slanted edges: whatever the detector proposes is flagged, so a
    caller can tell a texture chart from an edge chart."""
    from fieldcal.charts.targets import chart_image
    res = fieldcal.measure_mtf(chart_image("texture", 640, 360))
    assert sum(e["quality"]["ok"] for e in res.edges) == 0


def test_raw_mosaic_stack_planes_and_tracks():
    """An RGGB ArrayStack: four planes per edge, frequencies in sensor cycles/px, one track per edge."""
    from fieldcal.measure.esfr_synth import render_edge
    from fieldcal.formats.frames import ArrayStack
    z = np.array([-10.0, 0.0, 10.0])
    frames = [render_edge(96, 96, normal_deg=-7.0, sigma_px=0.6, defocus_d_px=0.1 * abs(zi)) for zi in z]
    stack = ArrayStack(frames, z, ("R", "G", "B"), pixel_pitch_um=2.0, cfa="RGGB")
    res = fieldcal.measure_mtf(stack)
    assert {e["plane"] for e in res.edges} == {"R", "Gr", "Gb", "B"}
    assert len({e["track"] for e in res.edges}) == 1
    sharp = [e for e in res.edges if e["z_um"] == 0.0]
    ref = analytic_mtf50(sigma_px=0.6, normal_deg=7.0)
    for e in sharp:
        assert e["mtf50_cy_per_px"] == pytest.approx(ref, rel=0.03)
