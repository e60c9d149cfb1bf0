"""Property-based fuzzing of the format layer: every load either succeeds or raises FieldcalError, never another
exception.

Two generators: documents drawn from the shipped schemas themselves (hypothesis-jsonschema; valid per schema, so
they exercise the semantic checks and the code behind the readers), and valid documents written by fieldcal with
one field replaced by a hostile value (wrong types, huge and non-finite numbers, deep nesting, traversal paths).
"""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fieldcal.errors import FieldcalError
from fieldcal.formats import documents

hjs = pytest.importorskip("hypothesis_jsonschema")

L = Path(__file__).parent / "data" / "legacy"
_HEALTH = [HealthCheck.too_slow, HealthCheck.function_scoped_fixture, HealthCheck.filter_too_much,
           HealthCheck.data_too_large]
SETTINGS = settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=_HEALTH)
# drawing from a schema is slow (hypothesis-jsonschema resolves it per example): fewer, still varied
SCHEMA_SETTINGS = settings(max_examples=10, deadline=None, derandomize=True, suppress_health_check=_HEALTH)


def _stack(path: Path):
    from fieldcal.formats.stack import Stack
    Stack.open(path.parent)


def _plan(path: Path):
    from fieldcal.capture.plan import CapturePlan
    from fieldcal.plan.planfile import read_plan
    try:
        read_plan(path)
    finally:
        try:
            CapturePlan.from_file(path)
        except FieldcalError:
            pass


def _lens(path: Path):
    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.truth import TruthProfile
    spec = LensSpec.load(path)
    TruthProfile(spec)  # what loading a spec as a plan's lens model does next


def _profile(path: Path):
    from fieldcal.profile.lens_profile import load_profile_or_truth
    load_profile_or_truth(path)


def _truth(path: Path):
    from fieldcal.simulate.truth import load_truth
    load_truth(path.parent)


def _journal(path: Path):
    from fieldcal.capture.folder import read_journal
    read_journal(path)


def _composite_meta(path: Path):
    documents.validate(documents.read_json(path), "composite", path)


READERS = {"stack": ("stack.json", _stack), "plan": ("plan.json", _plan), "lens": ("lens.json", _lens),
           "profile": ("lens.json", _profile), "truth": ("truth.json", _truth),
           "capture-journal": ("capture.journal", _journal), "composite": ("meta.json", _composite_meta)}


def load_or_refuse(kind: str, text: str, folder: Path) -> None:
    """Write ``text`` as the kind's file in a fresh folder and read it: success or FieldcalError only."""
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    for f in L.glob("*.npz"):
        shutil.copy(f, folder / f.name)
    name, reader = READERS[kind]
    path = folder / name
    path.write_text(text, encoding="utf-8")
    try:
        reader(path)
    except FieldcalError as e:
        assert path.name in str(e) or e.path is None or Path(e.path).name != "", str(e)


# ----------------------------------------------------------------------------------------- from the schemas
def _generator_schema(kind: str) -> dict:
    """The schema, with the plan's if/then branches flattened into one schema per kind (same constraints;
    hypothesis-jsonschema is an order of magnitude slower on if/then)."""
    if kind == "stack":  # without the cfa -> channels rule: documents breaking it are refused, as they should be
        return {k: v for k, v in documents.schema(kind).items() if k not in ("if", "then")}
    if not kind.startswith("plan/"):
        return documents.schema(kind)
    else:
        s = copy.deepcopy(documents.schema("plan"))
        value = kind.split("/")[1]
        branch = next(b["then"] for b in s.pop("allOf") if b["if"]["properties"]["kind"]["const"] == value)
        s["properties"].update(branch["properties"])
        s["properties"]["kind"] = {"const": value}
        s["required"] = [*s["required"], *branch["required"]]
    return s


@pytest.mark.parametrize("kind", ["stack", "plan/stack", "plan/sweep", "lens", "capture-journal", "composite"])
def test_documents_generated_from_the_schema_load_or_are_refused(kind, tmp_path):
    schema = _generator_schema(kind)
    kind = kind.split("/")[0]

    @SCHEMA_SETTINGS
    @given(doc=hjs.from_schema(schema))
    def run(doc):
        if kind not in ("capture-journal", "stack"):  # the generator and the validator agree
            documents.validate(doc, kind)
        load_or_refuse(kind, json.dumps(doc), tmp_path / "f")
    run()


# ----------------------------------------------------------------------------------------- mutated documents
HOSTILE_LITERALS = ["1" + "0" * 400, "-" + "9" * 5000, "NaN", "Infinity", "-Infinity", "1e999", "-1e400",
                    "[" * 100 + "]" * 100, '"../../etc/passwd"', '"/etc/passwd"', '""', '"abc"', "true", "null",
                    "-5", "0", "1e300", "[]", "{}", '[1]', '{"format": "fieldcal-stack/1"}', "1e-320", "4.5",
                    '"' + "x" * 10000 + '"']
json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False)
                           | st.text(max_size=20),
                           lambda inner: st.lists(inner, max_size=3)
                           | st.dictionaries(st.text(max_size=5), inner, max_size=3),
                           max_leaves=8)


def _paths(v, prefix=()):
    yield prefix
    if isinstance(v, dict):
        for k, x in v.items():
            yield from _paths(x, (*prefix, k))
    elif isinstance(v, list):
        for i, x in enumerate(v[:4]):  # the first few items of long lists are enough
            yield from _paths(x, (*prefix, i))


def _replace(doc, path, literal):
    """The document's text with the value at ``path`` replaced by a raw JSON literal (or deleted: None)."""
    marker = "__FUZZ_MARKER__"
    if not path:
        return literal if literal is not None else "{}"
    node = doc
    for k in path[:-1]:
        node = node[k]
    if literal is None:
        del node[path[-1]]
        return json.dumps(doc)
    node[path[-1]] = marker
    return json.dumps(doc).replace(f'"{marker}"', literal, 1)


SOURCES = {"stack": L / "stack" / "stack.json", "plan": L / "plan-stack.json", "lens": L / "lens-spec.json",
           "profile": L / "lens.json", "truth": L / "stack" / "truth.json"}


@pytest.mark.parametrize("kind", sorted(SOURCES))
def test_one_hostile_field_is_refused_or_harmless(kind, tmp_path):
    base = json.loads(SOURCES[kind].read_text())
    paths = list(_paths(base))

    @SETTINGS
    @given(path=st.sampled_from(paths),
           literal=st.one_of(st.sampled_from(HOSTILE_LITERALS), json_values.map(json.dumps), st.none()))
    def run(path, literal):
        doc = json.loads(json.dumps(base))
        if literal is None and not path:
            literal = "[]"
        text = _replace(doc, path, literal)
        folder = tmp_path / "f"
        load_or_refuse(kind, text, folder)
        if kind in ("stack", "truth"):  # frames and truth.tiff must be beside stack.json: rerun in a full copy
            shutil.rmtree(folder)
            shutil.copytree(L / "stack", folder)
            (folder / SOURCES[kind].name).write_text(text)
            try:
                READERS[kind][1](folder / SOURCES[kind].name)
            except FieldcalError:
                pass
    run()


def test_journal_lines_fuzzed(tmp_path):
    lines = (L / "capture" / "capture.journal").read_text().splitlines()

    @SETTINGS
    @given(n=st.integers(0, len(lines) - 1), data=st.data())
    def run(n, data):
        doc = json.loads(lines[n])
        path = data.draw(st.sampled_from(list(_paths(doc))))
        literal = data.draw(st.one_of(st.sampled_from(HOSTILE_LITERALS), json_values.map(json.dumps)))
        new = list(lines)
        new[n] = _replace(doc, path, literal).replace("\n", " ")
        load_or_refuse("capture-journal", "\n".join(new) + "\n", tmp_path / "f")
    run()
