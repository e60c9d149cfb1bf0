"""Hostile documents: every one ends in a FieldcalError naming the file and the field (and on the command line in
exit code 2 with that message and no traceback), never in another exception.

Each case starts from a valid document written by fieldcal (tests/data/legacy), changes one thing, and is read
both through the Python reader and through a command that reads that kind of file first.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import pytest

from fieldcal.cli import main
from fieldcal.errors import FieldcalError

L = Path(__file__).parent / "data" / "legacy"
MODELS = Path(__file__).resolve().parents[1] / "models"
RAW = "__RAW_LITERAL__"  # replaced by a raw JSON literal (a number or NaN that json.dumps cannot write)
DEEP = "[" * 100_000 + "]" * 100_000


@dataclass(frozen=True)
class Case:
    name: str
    base: str                 # stack | profile | plan | sweep | lens | journal | truth
    edit: Callable[[Any], Any] | None = None   # edits the parsed document (returns None: edited in place)
    raw: str | None = None    # the literal written where the edit put RAW
    text: str | None = None   # the whole file, replacing the document
    field: str | None = None  # expected "field '<field>" prefix in the message (None: file-level)
    line: int | None = None   # journal: which line the edit applies to


def at(path: str, value: Any) -> Callable:
    """Set the value at a dotted path (``frames.0.z_um``); value ``DELETE`` removes the key."""
    def edit(d):
        *head, last = path.split(".")
        node = d
        for k in head:
            node = node[int(k)] if isinstance(node, list) else node[k]
        key = int(last) if isinstance(node, list) else last
        if value is DELETE:
            del node[key]
        else:
            node[key] = value
    return edit


DELETE = object()
BIG = "1" + "0" * 400          # 10**400: OverflowError as a float
HUGE = "9" * 5000              # beyond Python's int-string conversion limit
SHA = "a" * 64


CASES = [
    # ------------------------------------------------------------------ stack.json
    Case("stack z 10**400", "stack", at("frames.0.z_um", RAW), BIG, field="frames[0].z_um"),
    Case("stack z 5000 digits", "stack", at("frames.1.z_um", RAW), HUGE, field="frames[1].z_um"),
    Case("stack z -10**400", "stack", at("frames.2.z_um", RAW), "-" + BIG, field="frames[2].z_um"),
    Case("stack pitch 10**400", "stack", at("pixel_pitch_um", RAW), BIG, field="pixel_pitch_um"),
    Case("stack pitch 5000 digits", "stack", at("pixel_pitch_um", RAW), HUGE, field="pixel_pitch_um"),
    Case("stack z NaN", "stack", at("frames.1.z_um", RAW), "NaN", field="frames[1].z_um"),
    Case("stack pitch Infinity", "stack", at("pixel_pitch_um", RAW), "Infinity", field="pixel_pitch_um"),
    Case("stack z -Infinity", "stack", at("frames.0.z_um", RAW), "-Infinity", field="frames[0].z_um"),
    Case("stack z 1e999", "stack", at("frames.0.z_um", RAW), "1e999", field="frames[0].z_um"),
    Case("stack z 1e300 out of range", "stack", at("frames.0.z_um", 1e300), field="frames[0].z_um"),
    Case("stack deep nesting", "stack", at("lens", RAW), DEEP),
    Case("stack z string", "stack", at("frames.0.z_um", "abc"), field="frames[0].z_um"),
    Case("stack z bool", "stack", at("frames.0.z_um", True), field="frames[0].z_um"),
    Case("stack z null", "stack", at("frames.0.z_um", None), field="frames[0].z_um"),
    Case("stack frames missing", "stack", at("frames", DELETE), field="frames"),
    Case("stack frames not a list", "stack", at("frames", {"a": 1}), field="frames"),
    Case("stack frames empty", "stack", at("frames", []), field="frames"),
    Case("stack pitch missing", "stack", at("pixel_pitch_um", DELETE), field="pixel_pitch_um"),
    Case("stack pitch negative", "stack", at("pixel_pitch_um", -5), field="pixel_pitch_um"),
    Case("stack pitch zero", "stack", at("pixel_pitch_um", 0), field="pixel_pitch_um"),
    Case("stack channels empty", "stack", at("channels", []), field="channels"),
    Case("stack channels repeated", "stack", at("channels", ["R", "R", "B"]), field="channels"),
    Case("stack bit_depth 64", "stack", at("bit_depth", 64), field="bit_depth"),
    Case("stack bit_depth 12.5", "stack", at("bit_depth", 12.5), field="bit_depth"),
    Case("stack frame without file", "stack", at("frames.1.file", DELETE), field="frames[1].file"),
    Case("stack frame file empty", "stack", at("frames.1.file", ""), field="frames[1].file"),
    Case("stack frame file traversal", "stack", at("frames.0.file", "../../etc/passwd"), field="frames[0].file"),
    Case("stack frame file NUL", "stack", at("frames.0.file", "frames/a\u0000b.tiff"), field="frames[0].file"),
    Case("stack frame file blank", "stack", at("frames.0.file", "   "), field="frames[0].file"),
    Case("stack frame file absolute", "stack", at("frames.0.file", "/etc/passwd"), field="frames[0].file"),
    Case("stack frame sha256 not hex", "stack", at("frames.0.sha256", "xyz"), field="frames[0].sha256"),
    Case("stack newer format", "stack", at("format", "fieldcal-stack/2"), field="format"),
    Case("stack format missing", "stack", at("format", DELETE), field="format"),
    Case("stack root is a list", "stack", text="[]"),
    Case("stack repeated key", "stack", text='{"format": "fieldcal-stack/1", "format": "fieldcal-stack/1"}',
         field="format"),
    Case("stack cfa unknown", "stack", at("cfa", "XYZW"), field="cfa"),
    Case("stack frame exposure negative", "stack", at("frames.0.exposure_ms", -1), field="frames[0].exposure_ms"),
    Case("stack white below black", "stack", at("white_level", 10), field="white_level"),
    Case("stack z repeated", "stack", at("frames.1.z_um", -40.0), field="frames[1].z_um"),
    Case("stack truncated JSON", "stack", text='{"format": "fieldcal-stack/1", "frames": ['),
    Case("stack not UTF-8", "stack", text="\udcff"),
    # ------------------------------------------------------------------ profile
    Case("profile sidecar ../../etc/passwd", "profile", at("sidecar.file", "../../etc/passwd"), field="sidecar.file"),
    Case("profile sidecar empty", "profile", at("sidecar.file", ""), field="sidecar.file"),
    Case("profile sidecar absolute", "profile", at("sidecar.file", "/etc/passwd"), field="sidecar.file"),
    Case("profile sidecar ..", "profile", at("sidecar.file", ".."), field="sidecar.file"),
    Case("profile sidecar missing file", "profile", at("sidecar.file", "other.npz"), field="sidecar.file"),
    Case("profile sidecar sha256 not hex", "profile", at("sidecar.sha256", "nothex"), field="sidecar.sha256"),
    Case("profile sidecar sha256 differs", "profile", at("sidecar.sha256", SHA), field="sidecar.sha256"),
    Case("profile z_ref abc", "profile", at("z_ref_um", "abc"), field="z_ref_um"),
    Case("profile z_ref 10**400", "profile", at("z_ref_um", RAW), BIG, field="z_ref_um"),
    Case("profile z_ref 5000 digits", "profile", at("z_ref_um", RAW), HUGE, field="z_ref_um"),
    Case("profile width -5", "profile", at("image.width_px", -5), field="image.width_px"),
    Case("profile width 2.5", "profile", at("image.width_px", 2.5), field="image.width_px"),
    Case("profile height 10**400", "profile", at("image.height_px", RAW), BIG, field="image.height_px"),
    Case("profile pitch NaN", "profile", at("image.pixel_pitch_um", RAW), "NaN", field="image.pixel_pitch_um"),
    Case("profile channels string", "profile", at("image.channels", "RGB"), field="image.channels"),
    Case("profile newer format", "profile", at("format", "fieldcal-profile/2"), field="format"),
    Case("profile other format", "profile", at("format", "somebody-else/1"), field="format"),
    Case("profile surfaces missing", "profile", at("surfaces", DELETE), field="surfaces"),
    Case("profile theta string", "profile", at("surfaces.theta_map.0", "x"), field="surfaces.theta_map[0]"),
    Case("profile geometry block missing key", "profile", at("geometry.magnification", DELETE),
         field="geometry.magnification"),
    Case("profile geometry z_scale 0", "profile", at("geometry.z_scale_um", 0), field="geometry.z_scale_um"),
    Case("profile tolerance empty object", "profile", at("tolerance", {}), field="tolerance"),
    Case("profile f_number negative", "profile", at("optics.f_number", -2), field="optics.f_number"),
    Case("profile q above 1", "profile", at("calibration.q", 1.5), field="calibration.q"),
    Case("profile deep diagnostics", "profile", at("diagnostics", RAW), DEEP),
    Case("profile root is a string", "profile", text='"lens"'),
    # ------------------------------------------------------------------ stack plan
    Case("plan z 10**400", "plan", at("frames.2.z_um", RAW), BIG, field="frames[2].z_um"),
    Case("plan z 5000 digits", "plan", at("frames.0.z_um", RAW), HUGE, field="frames[0].z_um"),
    Case("plan z NaN", "plan", at("frames.0.z_um", RAW), "NaN", field="frames[0].z_um"),
    Case("plan z string", "plan", at("frames.0.z_um", "1"), field="frames[0].z_um"),
    Case("plan frames empty", "plan", at("frames", []), field="frames"),
    Case("plan frames missing", "plan", at("frames", DELETE), field="frames"),
    Case("plan kind unknown", "plan", at("kind", "foo"), field="kind"),
    Case("plan exposure zero", "plan", at("frames.1.exposure_ms", 0), field="frames[1].exposure_ms"),
    Case("plan band one value", "plan", at("frames.0.bands.G", [1]), field="frames[0].bands.G"),
    Case("plan band reversed", "plan", at("frames.0.bands.G", [5.0, -5.0]), field="frames[0].bands.G"),
    Case("plan direction unknown", "plan", at("direction", "up"), field="direction"),
    Case("plan newer format", "plan", at("format", "fieldcal-plan/9"), field="format"),
    Case("plan frames out of order", "plan", at("frames.0.z_um", 1000.0), field="frames"),
    Case("plan deep nesting", "plan", at("profile", RAW), DEEP),
    # ------------------------------------------------------------------ sweep plan
    Case("sweep masks traversal", "sweep", at("masks.file", "../../x.npz"), field="masks.file"),
    Case("sweep masks absolute", "sweep", at("masks.file", "/etc/passwd"), field="masks.file"),
    Case("sweep masks missing", "sweep", at("masks", DELETE), field="masks"),
    Case("sweep velocity 1e999", "sweep", at("velocity_um_per_ms", RAW), "1e999", field="velocity_um_per_ms"),
    Case("sweep alpha negative", "sweep", at("alpha_um", -1), field="alpha_um"),
    Case("sweep velocity inconsistent", "sweep", at("velocity_um_per_ms", 7.0), field="velocity_um_per_ms"),
    # ------------------------------------------------------------------ lens spec
    Case("lens focal length 10**400", "lens", at("focal_length_mm", RAW), BIG, field="focal_length_mm"),
    Case("lens curvature 5000 digits", "lens", at("channels.0.curvature_um.0", RAW), HUGE,
         field="channels[0].curvature_um[0]"),
    Case("lens curvature NaN", "lens", at("channels.1.curvature_um.0", RAW), "NaN",
         field="channels[1].curvature_um[0]"),
    Case("lens f_number zero", "lens", at("f_number", 0), field="f_number"),
    Case("lens width -5", "lens", at("sensor.width_px", -5), field="sensor.width_px"),
    Case("lens width string", "lens", at("sensor.width_px", "640"), field="sensor.width_px"),
    Case("lens channels empty", "lens", at("channels", []), field="channels"),
    Case("lens channel without name", "lens", at("channels.0.name", DELETE), field="channels[0].name"),
    Case("lens bit depth 13", "lens", at("sensor.bit_depth", 13), field="sensor.bit_depth"),
    Case("lens exit pupil 0", "lens", at("exit_pupil_mm", 0), field="exit_pupil_mm"),
    Case("lens illumination 2", "lens", at("relative_illumination_edge", 2), field="relative_illumination_edge"),
    Case("lens sensor missing", "lens", at("sensor", DELETE), field="sensor"),
    Case("lens decentre one value", "lens", at("decentre_mm", [1.0]), field="decentre_mm"),
    Case("lens channel names repeated", "lens", at("channels.1.name", "R"), field="channels"),
    Case("lens cfa on a mono sensor", "lens",
         lambda d: [at("sensor.cfa", "RGGB")(d), at("channels", [{"name": "Y"}])(d)],
         field="sensor.cfa"),
    Case("lens newer format", "lens", at("format", "fieldcal-lens/3"), field="format"),
    # ------------------------------------------------------------------ capture journal (JSON lines)
    Case("journal header []", "journal", text="[]", line=0),
    Case("journal header wrong format", "journal", at("journal", "other/1"), line=0, field="line 1.journal"),
    Case("journal header n_frames 10**400", "journal", at("n_frames", RAW), BIG, line=0, field="line 1.n_frames"),
    Case("journal entry without file", "journal", at("entry.file", DELETE), line=1, field="line 2.entry.file"),
    Case("journal entry file outside", "journal", at("entry.file", "../../etc/passwd"), line=1,
         field="line 2.entry.file"),
    Case("journal entry i negative", "journal", at("i", -1), line=2, field="line 3.i"),
    Case("journal entry not JSON", "journal", text="{not json", line=2, field="line 3"),
    Case("journal entry NaN z", "journal", at("entry.z_um", RAW), "NaN", line=1, field="line 2.entry.z_um"),
    # ------------------------------------------------------------------ truth.json
    Case("truth lens f_number string", "truth", at("lens.f_number", "x"), field="lens.f_number"),
    Case("truth size one value", "truth", at("size_px", [32]), field="size_px"),
    Case("truth z 10**400", "truth", at("z_um.0", RAW), BIG, field="z_um[0]"),
]

FILES = {"stack": "stack.json", "profile": "lens.json", "plan": "plan-stack.json", "sweep": "plan-sweep.json",
         "lens": "lens-spec.json", "journal": "capture.journal", "truth": "truth.json"}


def _dump(doc, raw):
    text = json.dumps(doc, indent=1)
    if raw is not None:
        assert f'"{RAW}"' in text
        text = text.replace(f'"{RAW}"', raw)
    return text


def make(case: Case, tmp: Path) -> Path:
    """Copy the legacy files the case needs into ``tmp`` and write the hostile document; returns its path."""
    if case.base in ("stack", "truth"):
        shutil.copytree(L / "stack", tmp / "S")
        target = tmp / "S" / FILES[case.base]
    elif case.base == "journal":
        shutil.copytree(L / "capture", tmp / "S")
        target = tmp / "S" / FILES[case.base]
    else:
        for f in L.iterdir():
            if f.is_file():
                shutil.copy(f, tmp / f.name)
        target = tmp / FILES[case.base]
    if case.base == "journal":
        lines = target.read_text().splitlines()
        if case.text is not None:
            lines[case.line] = case.text
        else:
            d = json.loads(lines[case.line])
            case.edit(d)
            lines[case.line] = json.dumps(d).replace(f'"{RAW}"', case.raw) if case.raw else json.dumps(d)
        target.write_text("\n".join(lines) + "\n")
        return target
    if case.text is not None:
        target.write_bytes(case.text.encode("utf-8", "surrogateescape"))
        return target
    doc = json.loads(target.read_text())
    case.edit(doc)
    target.write_text(_dump(doc, case.raw))
    return target


def read_python(case: Case, target: Path) -> None:
    """The Python reader(s) of that kind of file."""
    from fieldcal.capture.folder import read_journal
    from fieldcal.capture.plan import CapturePlan
    from fieldcal.formats.stack import Stack
    from fieldcal.plan.planfile import read_plan
    from fieldcal.profile.lens_profile import LensProfile, load_profile_or_truth
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.truth import load_truth
    if case.base == "stack":
        Stack.open(target.parent)
    elif case.base == "profile":
        for reader in (LensProfile.load, load_profile_or_truth):
            with pytest.raises(FieldcalError):
                reader(target)
        LensProfile.load(target)
    elif case.base == "plan":
        with pytest.raises(FieldcalError):
            CapturePlan.from_file(target)
        read_plan(target)
    elif case.base == "sweep":
        read_plan(target)
    elif case.base == "lens":
        LensSpec.load(target)
    elif case.base == "journal":
        read_journal(target)
    elif case.base == "truth":
        with pytest.raises(FieldcalError):
            load_profile_or_truth(target)
        load_truth(target.parent)


def cli_args(case: Case, target: Path, tmp: Path) -> list[str]:
    """A command that reads that kind of file before doing any work."""
    cam = f"sim:{MODELS / 'triplet-uncorrected.json'},size=32x24"
    if case.base == "stack":
        return ["calibrate", str(target.parent), "--out", str(tmp / "out.json"), "-q"]
    if case.base in ("profile", "truth"):
        return ["plan", "stack", str(target), "--fs", "5", "--q", "0.05", "--out", str(tmp / "out-plan.json")]
    if case.base == "plan":
        return ["capture", "--plan", str(target), "--camera", cam, "--out", str(tmp / "D"), "--dry-run"]
    if case.base == "sweep":
        return ["composite", str(L / "stack"), "--profile", str(MODELS / "singlet-colour.json"), "--plan",
                str(target), "--out", str(tmp / "out.tiff")]
    if case.base == "lens":
        return ["simulate", str(target), str(tmp / "SIM"), "--z", "0", "10", "10", "--size", "32x24", "--quiet"]
    if case.base == "journal":
        return ["capture", "--z", "-100", "100", "100", "--camera", cam, "--out", str(target.parent)]
    raise AssertionError(case.base)


def check_message(msg: str, case: Case, target: Path) -> None:
    assert target.name in msg, f"file not named:\n{msg}"
    if case.field is not None:
        assert f"field '{case.field}" in msg, f"field {case.field!r} not named:\n{msg}"
    assert "fix:" in msg, f"no fix:\n{msg}"


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_reader_refuses_with_file_field_and_fix(case, tmp_path):
    target = make(case, tmp_path)
    with pytest.raises(FieldcalError) as ei:
        read_python(case, target)
    check_message(str(ei.value), case, target)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_cli_exits_2_without_traceback(case, tmp_path, capsys):
    target = make(case, tmp_path)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    rc = main(cli_args(case, target, tmp_path))
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err
    check_message(err, case, target)
    if case.base != "journal":  # (capture may hold a lock file in its folder)
        assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing written


def test_at_least_sixty_cases():
    assert len(CASES) >= 60
    assert {c.base for c in CASES} == set(FILES)


# ----------------------------------------------------------------------------------------- the parser itself
def test_depth_limit_is_exact_and_ignores_brackets_in_strings():
    from fieldcal.formats import documents
    ok = "[" * documents.MAX_DEPTH + "]" * documents.MAX_DEPTH
    assert documents.loads(ok) is not None
    with pytest.raises(FieldcalError, match="levels deep"):
        documents.loads("[" + ok + "]", "x.json")
    assert documents.loads(json.dumps({"s": "[" * 1000 + '\\"{' * 100})) == {"s": "[" * 1000 + '\\"{' * 100}


def test_number_limits_are_the_float_range():
    from fieldcal.formats import documents
    assert documents.loads(str(10 ** 308)) == 10 ** 308           # 309 digits, a float can hold it
    for text in (str(2 * 10 ** 308), "1e309", "-1e309", "9" * 401):
        with pytest.raises(FieldcalError, match="too large|overflows"):
            documents.loads(text, "x.json")
    assert documents.loads("1e-400") == 0.0                        # underflow is harmless


def test_bom_is_accepted_and_size_is_limited(tmp_path, monkeypatch):
    from fieldcal.formats import documents
    p = tmp_path / "d.json"
    p.write_bytes(b"\xef\xbb\xbf" + b'{"a": 1}')
    assert documents.read_json(p) == {"a": 1}
    monkeypatch.setattr(documents, "MAX_DOCUMENT_BYTES", 4)
    with pytest.raises(FieldcalError, match="larger than") as ei:
        documents.read_json(p)
    assert "d.json" in str(ei.value)


def test_write_validates_first_and_writes_nothing_when_invalid(tmp_path):
    from fieldcal.formats import documents
    doc = json.loads((L / "plan-stack.json").read_text())
    doc["frames"][0]["z_um"] = float("nan")
    with pytest.raises(FieldcalError, match="JSON"):
        documents.write(tmp_path / "p.json", doc, "plan")
    doc["frames"][0]["z_um"] = "abc"
    with pytest.raises(FieldcalError, match=r"frames\[0\]\.z_um"):
        documents.write(tmp_path / "p.json", doc, "plan")
    assert list(tmp_path.iterdir()) == []
    doc["frames"][0]["z_um"] = -300.0
    documents.write(tmp_path / "p.json", doc, "plan")
    assert documents.read(tmp_path / "p.json", "plan") == doc


@pytest.mark.parametrize("text, needle", [(DEEP, "levels deep"),
                                          ('{"surfaces": [{"radius": ' + BIG + "}]}", "surfaces[0].radius"),
                                          ('{"surfaces": NaN}', "surfaces")])
def test_prescription_json_is_parsed_safely(tmp_path, capsys, text, needle):
    """The ray-trace prescription is not a fieldcal-*/N document but is JSON from the user: same safe parser."""
    from fieldcal.raytrace.prescription import load_prescription
    p = tmp_path / "lens.json"
    p.write_text(text)
    with pytest.raises(FieldcalError) as ei:
        load_prescription(p)
    assert "lens.json" in str(ei.value) and needle in str(ei.value)


def test_capture_refuses_a_deeply_nested_stack_json_in_out(tmp_path, capsys):
    """A folder without a journal is adopted only if its stack.json is an empty stack: a hostile one is refused."""
    out = tmp_path / "X"
    out.mkdir()
    (out / "stack.json").write_text(DEEP)
    cam = f"sim:{MODELS / 'triplet-uncorrected.json'},size=32x24"
    rc = main(["capture", "--z", "-100", "100", "100", "--camera", cam, "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err and "capture folder" in err
    assert (out / "stack.json").read_text() == DEEP


def test_links_out_of_the_folder_are_refused(tmp_path):
    """A sidecar or mask file that is a symbolic link (to a file outside the document's folder) is refused."""
    from fieldcal.plan.planfile import read_plan
    from fieldcal.profile.lens_profile import LensProfile
    outside = tmp_path / "outside"
    outside.mkdir()
    here = tmp_path / "here"
    here.mkdir()
    for f in L.iterdir():
        if f.is_file():
            shutil.copy(f, outside / f.name)
            shutil.copy(f, here / f.name)
    (here / "lens.samples.npz").unlink()
    (here / "lens.samples.npz").symlink_to(outside / "lens.samples.npz")
    with pytest.raises(FieldcalError, match="sidecar") as ei:
        LensProfile.load(here / "lens.json")
    assert "field 'sidecar.file'" in str(ei.value)
    (here / "plan-sweep.masks.npz").unlink()
    (here / "plan-sweep.masks.npz").symlink_to(outside / "plan-sweep.masks.npz")
    with pytest.raises(FieldcalError) as ei:
        read_plan(here / "plan-sweep.json")
    assert "field 'masks.file'" in str(ei.value) and "outside" in str(ei.value)
