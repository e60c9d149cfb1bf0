"""Record what the current code reads from the legacy files (run once, before the format layer changed)."""
import json, sys
from pathlib import Path
import numpy as np
L = Path(sys.argv[1])
from fieldcal.profile.lens_profile import LensProfile, load_profile_or_truth
from fieldcal.plan.planfile import read_plan
from fieldcal.simulate.lens import LensSpec
from fieldcal.formats.stack import Stack
from fieldcal.capture.folder import read_journal
from fieldcal.capture.plan import CapturePlan

x = [0.0, 60.0, 128.0, 255.0]; y = [0.0, 30.0, 72.0, 143.0]
p = LensProfile.load(L / "lens.json")
exp = {"profile": {
    "z_ref_um": p.z_ref_um, "image": p.image, "optics": p.optics, "channels": list(p.channels),
    "best_focus_um": {c: p.best_focus_um(x, y, c).tolist() for c in p.channels},
    "interval_um": {c: [a.tolist() for a in p.best_focus_interval_um(x, y, c, 0.9)] for c in p.channels},
    "magnification": {c: p.magnification([-300.0, 0.0, 40.0], c).tolist() for c in p.channels},
    "shift_px": [np.asarray(a).tolist() for a in p.shift_px([-300.0, 0.0, 40.0])],
    "tolerance_um": p.focus_tolerance_um(x, y, "G", 15.0, 0.05).tolist(),
    "n_samples": int(np.asarray(p.surfaces.samples).shape[0]) if p.surfaces.samples is not None else 0,
    "tiles_keys": sorted(p.tiles or {}),
}}
for name in ("lens-spec.json", "lens-spec-triplet.json"):
    s = LensSpec.load(L / name)
    t, info = load_profile_or_truth(L / name, (64, 48))
    exp[name] = {"to_dict": s.to_dict(), "truth_best_focus_um": {c: t.best_focus_um([0.0, 31.5, 63.0], [0.0, 23.5, 47.0], c).tolist() for c in t.channels},
                 "info": info}
for name in ("plan-stack.json", "plan-sweep.json", "plan-sweep-pixel.json"):
    exp[name] = read_plan(L / name)
cp = CapturePlan.from_file(L / "plan-stack.json")
exp["capture_plan"] = {"z_um": cp.z_um.tolist(), "approach": cp.approach, "exposure_ms": [f.exposure_ms for f in cp.frames],
                       "fingerprint": cp.fingerprint()}
for name in ("stack", "capture"):
    st = Stack.open(L / name)
    exp[name] = {"z_um": st.z_um.tolist(), "pixel_pitch_um": st.pixel_pitch_um, "channels": list(st.channels),
                 "shape": list(st.shape), "levels": [st.black_level, st.white_level], "meta": st.meta}
h, e = read_journal(L / "capture" / "capture.journal")
exp["journal"] = {"header": h, "entries": e}
exp["truth"] = json.loads((L / "stack" / "truth.json").read_text())
exp["targets"] = json.loads((L / "targets.json").read_text())
(L / "expected.json").write_text(json.dumps(exp, indent=1, allow_nan=False) + "\n")
print("ok", len(json.dumps(exp)))
