"""The shipped schemas: valid draft 2020-12, one per fieldcal-*/N document, published unchanged in docs/, and the
only definition of each format string."""

import json
import re
from importlib import resources
from pathlib import Path

import pytest
from jsonschema import Draft202012Validator

from fieldcal.formats import documents

REPO = Path(__file__).resolve().parents[1]
SHIPPED = resources.files("fieldcal.formats").joinpath("schemas")


@pytest.mark.parametrize("kind", sorted(documents.KINDS))
def test_schema_is_valid_and_names_its_format(kind):
    s = documents.schema(kind)
    Draft202012Validator.check_schema(s)
    assert s["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    fmt = documents.format_id(kind)
    assert re.fullmatch(r"fieldcal-[a-z-]+/\d+", fmt)
    assert documents.KINDS[kind].schema_file == fmt.replace("/", "-") + ".schema.json"


def test_every_fieldcal_format_in_the_code_has_a_schema():
    """Every "fieldcal-…/N" string in the package is a document with a schema (the renderer's version tag is a
    version string inside truth.json, not a document)."""
    found = set()
    for py in (REPO / "fieldcal").rglob("*.py"):
        found |= set(re.findall(r'"(fieldcal-[a-z-]+/\d+)"', py.read_text(encoding="utf-8")))
    found.discard("fieldcal-render/1")
    assert found <= {documents.format_id(k) for k in documents.KINDS}


def test_format_constants_come_from_the_schemas():
    from fieldcal.capture.folder import JOURNAL_FORMAT
    from fieldcal.charts.targets import TARGETS_FORMAT
    from fieldcal.composite.io import COMPOSITE_FORMAT
    from fieldcal.fit.geometry import GEOMETRY_FIT_FORMAT
    from fieldcal.fit.geometry_map import GEOMETRY_MAP_FORMAT
    from fieldcal.fit.distortion import DISTORTION_FORMAT
    from fieldcal.fit.result import SURFACE_FIT_FORMAT
    from fieldcal.fit.tolerance import TOLERANCE_FIT_FORMAT
    from fieldcal.formats.stack import FORMAT
    from fieldcal.plan.planfile import PLAN_FORMAT
    from fieldcal.profile.lens_profile import PROFILE_FORMAT
    from fieldcal.simulate.lens import LENS_FORMAT
    from fieldcal.simulate.truth import TRUTH_FORMAT
    from fieldcal.measure.mtf import FORMAT as MTF_FORMAT
    from fieldcal.validation.run import VALIDATION_FORMAT
    from fieldcal.plan.device_masks import MASKS_FORMAT
    from fieldcal.batch.fleet import FLEET_FORMAT
    from fieldcal.profile.diff import DIFF_FORMAT
    got = {"profile-diff": DIFF_FORMAT, "mtf": MTF_FORMAT, "stack": FORMAT, "profile": PROFILE_FORMAT, "plan": PLAN_FORMAT, "lens": LENS_FORMAT,
           "truth": TRUTH_FORMAT, "capture-journal": JOURNAL_FORMAT, "composite": COMPOSITE_FORMAT,
           "targets": TARGETS_FORMAT, "validation": VALIDATION_FORMAT, "surface-fit": SURFACE_FIT_FORMAT,
           "geometry-fit": GEOMETRY_FIT_FORMAT, "tolerance-fit": TOLERANCE_FIT_FORMAT, "masks": MASKS_FORMAT,
           "geometry-map": GEOMETRY_MAP_FORMAT, "fleet": FLEET_FORMAT, "distortion": DISTORTION_FORMAT}
    assert got == {k: documents.format_id(k) for k in documents.KINDS}


def test_plan_format_is_defined_once():
    hits = [p for p in (REPO / "fieldcal").rglob("*.py") if '"fieldcal-plan/1"' in p.read_text(encoding="utf-8")]
    assert hits == []  # only the schema spells it; code uses documents.format_id("plan")


def test_docs_copies_equal_the_shipped_schemas():
    shipped = {p.name: p.read_bytes() for p in SHIPPED.iterdir() if p.name.endswith(".schema.json")}
    published = {p.name: p.read_bytes() for p in (REPO / "docs" / "schemas").glob("*.schema.json")}
    assert shipped == published, "copy fieldcal/formats/schemas/*.json to docs/schemas/"
    assert sorted(shipped) == documents.schema_files()
    text = (REPO / "docs" / "formats.md").read_text(encoding="utf-8")
    for name in shipped:
        assert f"(schemas/{name})" in text, f"docs/formats.md does not list {name}"


def test_schemas_are_package_data():
    pyproject = (REPO / "pyproject.toml").read_text(encoding="utf-8")
    assert '"formats/schemas/*.json"' in pyproject
    assert re.search(r'"jsonschema>=', pyproject)


@pytest.mark.parametrize("model", sorted((REPO / "models").glob("*.json")), ids=lambda p: p.name)
def test_shipped_lens_models_follow_the_schema(model):
    documents.read(model, "lens")


def test_writers_produce_valid_documents(tmp_path):
    """What fieldcal writes passes its own schema (write validates; this reads it back independently)."""
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.stackgen import simulate_stack
    spec = LensSpec.load(REPO / "models" / "singlet-colour.json")
    simulate_stack(spec, tmp_path / "S", [-20.0, 20.0], size=(32, 24), progress=False)
    for f, kind in (("stack.json", "stack"), ("truth.json", "truth")):
        doc = json.loads((tmp_path / "S" / f).read_text())
        assert not list(Draft202012Validator(documents.schema(kind), registry=documents._registry()).iter_errors(doc))


def _mtf_doc():
    edge = {"frame": 0, "z_um": 1.5, "channel": "G", "x_px": 10.0, "y_px": 20, "angle_deg": 5.0,
            "orientation": "tangential", "mtf": [1.0, 0.5, None], "mtf50_cy_per_px": 0.2, "quality": {"ok": True}}
    return {"format": documents.format_id("mtf"), "frequencies_cy_per_px": [0.0, 0.5, 1.0],
            "edges": [dict(edge), dict(edge, frame=None, z_um=None, mtf50_cy_per_px=None)], "provenance": {}}


@pytest.mark.parametrize("path, value", [
    (("edges", 1, "mtf", 2), True), (("edges", 1, "mtf", 0), "0.5"), (("edges", 0, "frame"), -1),
    (("edges", 0, "frame"), 1.5), (("edges", 0, "frame"), 2.0), (("edges", 0, "frame"), True),
    (("edges", 1, "orientation"), "radial"), (("edges", 1, "channel"), ""), (("edges", 0, "angle_deg"), 400),
    (("edges", 0, "x_px"), None), (("frequencies_cy_per_px", 1), 11), (("frequencies_cy_per_px",), [0.1]),
    (("edges", 0, "quality"), []), (("edges", 0, "mtf"), {}), (("edges", 0, "mtf", 1), 2.0**40),
])
def test_fast_validity_test_agrees_with_jsonschema(path, value):
    """The compiled fast test says "valid" exactly when jsonschema does on these documents (it may only ever say
    "not sure" more often), and an invalid document's message is jsonschema's."""
    fast = documents._compiled("mtf")
    assert fast is not None and fast(_mtf_doc())
    doc = _mtf_doc()
    node = doc
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    ok = not list(documents._validator("mtf").iter_errors(doc))
    assert fast(doc) == ok
    if not ok:
        with pytest.raises(documents.SpecError) as err:
            documents.validate(doc, "mtf", "m.json")
        assert "m.json" in str(err.value) and documents.json_path(path[:2]) in str(err.value)
    missing = _mtf_doc()
    del missing["edges"][1]["mtf"]
    assert not fast(missing)


@pytest.mark.parametrize("pad", range(0, 160, 7))
@pytest.mark.parametrize("digits", [299, 300, 309, 450])
def test_plain_parse_never_passes_an_overflowing_literal(pad, digits):
    """Text parsed without the checking hooks (no long literal in it) gives what the hooks give: a long integer
    anywhere in the text (at every alignment) is still refused with its own message."""
    text = '{"a": "' + "x" * pad + '", "v": [0.5, ' + "9" * digits + "]}"
    if digits > 308:
        with pytest.raises(documents.SpecError, match=f"integer of {digits} digits"):
            documents.loads(text)
    else:
        assert documents.loads(text)["v"][1] == int("9" * digits)
    for lit in ("1e999", "-1E+400", "NaN", "-Infinity"):
        with pytest.raises(documents.SpecError, match="overflows|not a JSON number"):
            documents.loads(text.replace("0.5", lit))
