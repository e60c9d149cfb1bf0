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
