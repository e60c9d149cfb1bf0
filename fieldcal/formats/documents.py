"""Every ``fieldcal-*/N`` JSON document is read and written here, and validated against its shipped schema.

One module, one route in and out (docs/formats.md):

* :func:`read` / :func:`loads` parse safely: a size limit, a nesting-depth pre-scan (Python's parser would
  hit ``RecursionError``), numbers checked as they are parsed (an integer of 400 digits or ``1e999`` would
  be ``OverflowError`` or infinity later; ``NaN``/``Infinity`` are not JSON), duplicate keys refused.
* :func:`validate` checks a document against its JSON Schema (draft 2020-12, ``fieldcal/formats/schemas/``)
  with the ``jsonschema`` library and turns the most relevant error into a :class:`~fieldcal.errors.FieldcalError`
  that names the file, the JSON path of the field (``frames[3].z_um``) and the fix.
* :func:`write` / :func:`dumps` validate what is written the same way (dumped, parsed back, validated), then
  write through :mod:`fieldcal.formats.atomic`.

What a schema cannot say (z sorted and distinct, a file inside the document's folder, two fields that must
agree) stays in the format's own module, in one place per format.
"""

from __future__ import annotations

import functools
import json
import math
import re
import sys
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from fieldcal.errors import FieldcalError, SpecError
from fieldcal.formats.atomic import atomic_write_text

#: Largest JSON document fieldcal reads (a 100 000-frame stack.json is ~30 MB).
MAX_DOCUMENT_BYTES = 256 * 2**20
#: Deepest nesting of objects/arrays: fieldcal writes at most ~8 levels; Python's parser recurses per level.
MAX_DEPTH = 64
#: Longest integer literal converted at all (10**308 has 309 digits; Python refuses int() past 4300).
MAX_INT_DIGITS = 400

SCHEMA_PACKAGE = "fieldcal.formats"
SCHEMA_DIR = "schemas"


@dataclass(frozen=True)
class DocumentKind:
    """A ``fieldcal-*/N`` document: its schema file, the key that carries the format, and the usual fix."""

    name: str
    schema_file: str
    format_key: str
    fix: str


KINDS: dict[str, DocumentKind] = {k.name: k for k in (
    DocumentKind("stack", "fieldcal-stack-1.schema.json", "format",
                 "see docs/stack-format.md for every key of stack.json"),
    DocumentKind("profile", "fieldcal-profile-1.schema.json", "format",
                 "regenerate the profile with `fieldcal calibrate` (docs/profile-format.md)"),
    DocumentKind("surface-fit", "fieldcal-surface-fit-1.schema.json", "format",
                 "regenerate the profile with `fieldcal calibrate`"),
    DocumentKind("geometry-fit", "fieldcal-geometry-fit-1.schema.json", "format",
                 "regenerate the profile with `fieldcal calibrate`"),
    DocumentKind("geometry-map", "fieldcal-geometry-map-1.schema.json", "format",
                 "regenerate the profile with `fieldcal calibrate`"),
    DocumentKind("distortion", "fieldcal-distortion-1.schema.json", "format",
                 "regenerate the profile with `fieldcal calibrate` on a ChArUco stack (docs/geometry.md)"),
    DocumentKind("tolerance-fit", "fieldcal-tolerance-fit-1.schema.json", "format",
                 "regenerate the profile with `fieldcal calibrate`"),
    DocumentKind("plan", "fieldcal-plan-1.schema.json", "format",
                 "make the plan again with `fieldcal plan stack|sweep` (docs/planning.md)"),
    DocumentKind("lens", "fieldcal-lens-1.schema.json", "format",
                 "see docs/lens-spec.md for every key of a lens spec"),
    DocumentKind("truth", "fieldcal-truth-1.schema.json", "format",
                 "simulate the stack again with `fieldcal simulate`"),
    DocumentKind("capture-journal", "fieldcal-capture-journal-1.schema.json", "journal",
                 "this folder's capture.journal was not written by fieldcal capture; use a new --out folder"),
    DocumentKind("composite", "fieldcal-composite-1.schema.json", "format",
                 "read a file written by `fieldcal composite`"),
    DocumentKind("targets", "fieldcal-targets-1.schema.json", "format",
                 "write the charts again with `fieldcal targets`"),
    DocumentKind("validation", "fieldcal-validation-1.schema.json", "format",
                 "run `fieldcal validate` again"),
    DocumentKind("mtf", "fieldcal-mtf-1.schema.json", "format", "re-run `fieldcal mtf` (docs/measurement.md)"),
    DocumentKind("masks", "fieldcal-masks-1.schema.json", "format",
                 "export the masks again with `fieldcal plan export-masks` (docs/planning.md)"),
    DocumentKind("fleet", "fieldcal-fleet-1.schema.json", "format",
                 "run `fieldcal batch calibrate` (or `fieldcal validate --lenses N`) again (docs/batch.md)"),
    DocumentKind("profile-diff", "fieldcal-profile-diff-1.schema.json", "format",
                 "compare the profiles again with `fieldcal profile diff A B --json` (docs/profiles.md)"),
)}


# ----------------------------------------------------------------------------------------------- schemas


@functools.cache
def schema(kind: str) -> dict:
    """The JSON Schema of a document kind (parsed once)."""
    k = _kind(kind)
    text = resources.files(SCHEMA_PACKAGE).joinpath(SCHEMA_DIR, k.schema_file).read_text(encoding="utf-8")
    return json.loads(text)


def schema_files() -> list[str]:
    """File names of every shipped schema."""
    return sorted(k.schema_file for k in KINDS.values())


def format_id(kind: str) -> str:
    """The ``fieldcal-*/N`` string of a kind, as its schema states it (the one definition)."""
    return schema(kind)["properties"][_kind(kind).format_key]["const"]


def _kind(kind: str) -> DocumentKind:
    try:
        return KINDS[kind]
    except KeyError:
        raise ValueError(f"unknown document kind {kind!r}; known: {', '.join(KINDS)}") from None


@functools.cache
def _registry():
    from referencing import Registry, Resource
    return Registry().with_resources(
        (schema(k)["$id"], Resource.from_contents(schema(k))) for k in KINDS)


@functools.cache
def _validator(kind: str, pointer: str = ""):
    from jsonschema import Draft202012Validator
    s = schema(kind)
    if pointer:
        s = {"$ref": s["$id"] + "#" + pointer}
    return Draft202012Validator(s, registry=_registry())


# ----------------------------------------------------------------------------------------------- parsing


class _Bad:
    """A value the parser refused (kept in place so its JSON path can be reported)."""

    __slots__ = ("what", "fix")

    def __init__(self, what: str, fix: str):
        self.what = what
        self.fix = fix


_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"', re.S)
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")


_EXPONENT_3 = re.compile(r"[eE][+-]?\d{3}")
#: a literal of 300 digits or more (or with a 3-digit exponent) may overflow a float or int(): such text is parsed
#: with the checking hooks. Digit runs are looked for in aligned blocks of this many characters (2 * 150 - 1 < 300).
_ALIGNED = 150


def _may_overflow(bare: str) -> bool:
    """Whether JSON text with its strings removed may hold a number the parser hooks would refuse: NaN/Infinity
    (no other N or I is left outside strings), a 3-digit exponent or a long run of digits. False means a plain
    float()/int() parse gives exactly what the hooks would (~0.7 s less for 5 M numbers; this test ~0.2 s)."""
    if "N" in bare or "I" in bare:
        return True
    # every e/E outside strings belongs to true/false unless some number has an exponent
    if bare.count("e") + bare.count("E") != bare.count("true") + bare.count("false") and \
            _EXPONENT_3.search(bare):
        return True
    b = np.frombuffer(bare.encode("ascii", "replace"), dtype=np.uint8)
    n = b.size // _ALIGNED * _ALIGNED
    # a run of 2 * _ALIGNED - 1 digits fills at least one aligned block of _ALIGNED: any all-digit block is "may"
    # (the tail past n is shorter than a block: a long run ending there fills the block before it)
    digit = (b[:n] >= 48) & (b[:n] <= 57)
    return bool(digit.reshape(-1, _ALIGNED).all(axis=1).any())


def _max_depth(text: str, bare: str | None = None) -> int:
    """Deepest nesting of [] and {} outside strings (vectorised: a deep document is long); ``bare`` is ``text``
    without its strings, when known."""
    brackets = _NOT_BRACKET.sub("", _STRING.sub("", text) if bare is None else bare)
    if not brackets:
        return 0
    b = np.frombuffer(brackets.encode("ascii"), dtype=np.uint8)
    step = np.where((b == ord("[")) | (b == ord("{")), 1, -1).astype(np.int64)
    return int(np.cumsum(step).max())


def _short(text: str, n: int = 24) -> str:
    return text if len(text) <= n else f"{text[:n // 2]}…{text[-6:]} ({len(text)} characters)"


_NUMBER_FIX = ("write a finite number of ordinary size (no stage position, pixel pitch or lens value is this "
               "large)")


class _Hooks:
    """Parser hooks that replace refused numbers and repeated keys by :class:`_Bad` markers."""

    def __init__(self):
        self.bad = False

    def _mark(self, what: str, fix: str = _NUMBER_FIX) -> _Bad:
        self.bad = True
        return _Bad(what, fix)

    def parse_int(self, s: str):
        digits = len(s.lstrip("-"))
        # int() of a 5000-digit literal hits Python's int-string limit; past ~309 digits it cannot be a float
        v = int(s) if digits <= MAX_INT_DIGITS else None
        if v is None or abs(v) > sys.float_info.max:
            return self._mark(f"is an integer of {digits} digits ({_short(s)}): too large for any quantity "
                              "fieldcal stores (at most 1.8e308)")
        return v

    def parse_float(self, s: str):
        v = float(s)
        if not math.isfinite(v):
            return self._mark(f"is {_short(s)}, which overflows a 64-bit float (largest 1.8e308)")
        return v

    def parse_constant(self, s: str):
        return self._mark(f"is {s}, which is not a JSON number (JSON has no NaN or Infinity)")

    def pairs(self, pairs: list[tuple[str, Any]]) -> dict:
        d = dict(pairs)
        if len(d) != len(pairs):
            seen: set[str] = set()
            for k, _ in pairs:
                if k in seen:
                    d[k] = self._mark("appears more than once in the same object (which value was meant?)",
                                      "keep one value per key")
                seen.add(k)
        return d


def _find_bad(v: Any, path: list) -> tuple[list, _Bad] | None:
    stack = [(v, path)]
    while stack:
        v, p = stack.pop()
        if isinstance(v, _Bad):
            return p, v
        if isinstance(v, dict):
            stack.extend((x, [*p, k]) for k, x in reversed(list(v.items())))
        elif isinstance(v, list):
            stack.extend((x, [*p, i]) for i, x in reversed(list(enumerate(v))))
    return None


def loads(text: str, path: str | Path | None = None, *, where: str = "", error: type[FieldcalError] = SpecError,
          fix: str = "repair the JSON syntax") -> Any:
    """Parse JSON text safely: every failure is ``error`` naming ``path``, the field and ``fix``."""
    if len(text) > MAX_DOCUMENT_BYTES:
        raise error(f"is {len(text)} characters long; fieldcal reads JSON documents up to "
                    f"{MAX_DOCUMENT_BYTES // 2**20} MiB", path=path, field=where or None,
                    fix="check that this is the right file")
    bare = _STRING.sub("", text)
    depth = _max_depth(text, bare)
    if depth > MAX_DEPTH:
        raise error(f"nests arrays/objects {depth} levels deep; fieldcal documents nest at most {MAX_DEPTH}",
                    path=path, field=where or None, fix="check that this is the right file; " + fix)
    try:
        hooks = _Hooks()
        if _may_overflow(bare):
            doc = json.loads(text, parse_int=hooks.parse_int, parse_float=hooks.parse_float,
                             parse_constant=hooks.parse_constant, object_pairs_hook=hooks.pairs)
        else:  # no number can overflow: the C parser's own float()/int() (NaN/Infinity cannot occur)
            doc = json.loads(text, object_pairs_hook=hooks.pairs)
    except json.JSONDecodeError as exc:
        raise error(f"is not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}", path=path,
                    field=where or None, fix=fix) from None
    except (RecursionError, ValueError, MemoryError) as exc:  # defence in depth behind the checks above
        raise error(f"cannot be parsed as JSON ({type(exc).__name__}: {_short(str(exc), 80)})", path=path,
                    field=where or None, fix=fix) from None
    bad = _find_bad(doc, []) if hooks.bad else None
    if bad is not None:
        p, b = bad
        raise error(b.what, path=path, field=json_path(p, where) or None, fix=b.fix)
    return doc


def read_json(path: str | Path, *, error: type[FieldcalError] = SpecError, not_found: str = "not found",
              not_found_fix: str = "check the path", fix: str = "repair the JSON syntax") -> Any:
    """Read and safely parse a JSON file (size-limited, UTF-8)."""
    path = Path(path)
    if not path.exists():
        raise error(not_found, path=path, fix=not_found_fix)
    if not path.is_file():
        raise error("is not a file", path=path, fix=not_found_fix)
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_DOCUMENT_BYTES + 1)
    except OSError as exc:
        raise error(f"cannot be read ({exc.strerror or exc})", path=path, fix="check the file's permissions") from None
    if len(data) > MAX_DOCUMENT_BYTES:
        raise error(f"is larger than {MAX_DOCUMENT_BYTES // 2**20} MiB; fieldcal's JSON documents are far smaller",
                    path=path, fix="check that this is the right file")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(f"is not UTF-8 text (byte {exc.start})", path=path, fix="write the file as UTF-8 JSON") from None
    return loads(text, path, error=error, fix=fix)


# ----------------------------------------------------------------------------------------------- validation


def json_path(parts: Iterable, where: str = "") -> str:
    """``["frames", 3, "z_um"]`` -> ``frames[3].z_um`` (prefixed by ``where``)."""
    out = where
    for p in parts:
        if isinstance(p, int):
            out += f"[{p}]"
        else:
            out += f".{p}" if out else str(p)
    return out


def _show(v: Any) -> str:
    if isinstance(v, (dict, list)):
        kind = "an object" if isinstance(v, dict) else "a list"
        text = json.dumps(v, default=str)
        return f"{kind} {text}" if len(text) <= 60 else f"{kind} of {len(v)} item(s)"
    text = json.dumps(v, default=str)
    return text if len(text) <= 60 else text[:40] + "…"


_TYPE_WORDS = {"object": "an object", "array": "a list", "string": "a string", "number": "a number",
               "integer": "an integer", "boolean": "true or false", "null": "null"}


def _what(e) -> tuple[str, str | None]:
    """(message, extra field suffix) for a jsonschema ValidationError."""
    v, val, inst = e.validator, e.validator_value, e.instance
    custom = e.schema.get("x-message") if isinstance(e.schema, dict) else None
    if v == "required":
        missing = next((k for k in val if isinstance(inst, dict) and k not in inst), val[0])
        return "is missing (required)", missing
    if custom:
        return f"{custom}, got {_show(inst)}", None
    if v == "type":
        types = val if isinstance(val, list) else [val]
        words = " or ".join(_TYPE_WORDS.get(t, t) for t in types)
        return f"must be {words}, got {_show(inst)}", None
    if v in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"):
        op = {"minimum": ">=", "maximum": "<=", "exclusiveMinimum": ">", "exclusiveMaximum": "<"}[v]
        return f"must be {op} {val:g}, got {_show(inst)}", None
    if v == "enum":
        return f"must be one of {', '.join(_show(x) for x in val)}; got {_show(inst)}", None
    if v == "const":
        return f"must be {_show(val)}, got {_show(inst)}", None
    if v == "minItems":
        return f"must hold at least {val} item(s), got {len(inst)}", None
    if v == "maxItems":
        return f"must hold at most {val} item(s), got {len(inst)}", None
    if v == "minLength":
        return "must not be empty" if val == 1 else f"must be at least {val} characters long", None
    if v == "maxLength":
        return f"must be at most {val} characters long, got {len(inst)}", None
    if v == "uniqueItems":
        return f"holds a repeated value ({_show(inst)}); values must be distinct", None
    if v == "pattern":
        return f"has an unexpected form: {_show(inst)}", None
    if v == "minProperties":
        return "must not be empty", None
    if v == "additionalProperties":
        extra = sorted(set(inst) - set(e.schema.get("properties", {})))
        return f"has unknown key(s) {extra}", None
    return e.message, None


def _fixes_along(e, kind: DocumentKind, pointer: str) -> list[str]:
    """Every ``x-fix`` on the way from the schema's root to the failing keyword (``$ref`` followed)."""
    root = schema(kind.name)
    resolver = _registry().resolver(root["$id"])
    node: Any = resolver.lookup(root["$id"] + "#" + pointer).contents if pointer else root
    fixes = []
    try:
        for step in e.absolute_schema_path:
            # jsonschema's path does not name the $ref it follows: follow it when the step is not a sibling
            while isinstance(node, dict) and "$ref" in node and step not in node:
                if isinstance(node.get("x-fix"), str):
                    fixes.append(node["x-fix"])
                resolved = resolver.lookup(node["$ref"])
                node, resolver = resolved.contents, resolved.resolver
            if isinstance(node, dict) and isinstance(node.get("x-fix"), str):
                fixes.append(node["x-fix"])
            node = node[step]
    except (KeyError, IndexError, TypeError, LookupError):
        pass
    if isinstance(node, dict) and isinstance(node.get("x-fix"), str):
        fixes.append(node["x-fix"])
    return fixes


def _fix_for(e, kind: DocumentKind, extra: str | None, pointer: str) -> str:
    s = e.schema if isinstance(e.schema, dict) else {}
    if extra is not None:
        sub = s.get("properties", {}).get(extra, {})
        own = sub.get("x-fix") if isinstance(sub, dict) else None
        return own or f'add "{extra}"; {kind.fix}'
    fixes = _fixes_along(e, kind, pointer)
    return fixes[-1] if fixes else kind.fix


def _format_error(doc: Any, kind: DocumentKind, path, where: str, error: type[FieldcalError]) -> None:
    """A clear message for a wrong or missing format string (before any schema detail)."""
    key = kind.format_key
    expected = format_id(kind.name)
    field = json_path([key], where)
    fix = f'set "{key}": "{expected}"'
    if not isinstance(doc, dict):
        raise error(f"must hold a JSON object, got {_show(doc)}", path=path, field=where or None, fix=kind.fix)
    if key not in doc:
        raise error(f"is missing: this is not a {expected} document", path=path, field=field,
                    fix=f"{fix} if it is one; {kind.fix}")
    fmt = doc[key]
    if fmt == expected:
        return
    family, version = expected.rsplit("/", 1)
    m = re.fullmatch(re.escape(family) + r"/(\d+)", fmt) if isinstance(fmt, str) else None
    if m and int(m.group(1)) > int(version):
        raise error(f"{fmt} is newer than this fieldcal understands ({expected})", path=path, field=field,
                    fix="upgrade fieldcal (pip install -U fieldcal)")
    raise error(f"unknown {kind.name} format {_show(fmt)}; this fieldcal reads only {expected!r}", path=path,
                field=field,
                fix=f"{fix}, or give a {expected} file")


# A fast test "is this instance valid?" compiled from the schema, for the keywords fieldcal's schemas use most
# (jsonschema spends ~10 us per value: a 46 000-record fieldcal-mtf/1 file of 4.6 M numbers took ~50 s). It only
# ever says "valid" or "not sure": on "not sure" (an invalid document, or a keyword it does not know) the full
# jsonschema validation runs, so every error message stays jsonschema's best match, word for word.
_ANNOTATIONS = frozenset({"$schema", "$id", "$comment", "title", "description", "x-message", "x-fix", "examples",
                          "default"})
_PY_TYPES = {"number": (int, float), "integer": (int,), "string": (str,), "object": (dict,), "array": (list,),
             "null": (type(None),), "boolean": (bool,)}
#: the types a parsed JSON document holds; anything else (a NumPy scalar, a tuple) is left to jsonschema
_PLAIN = frozenset({int, float, str, dict, list, bool, type(None)})
_BOUNDS = {"minimum": lambda v, b: v >= b, "maximum": lambda v, b: v <= b,
           "exclusiveMinimum": lambda v, b: v > b, "exclusiveMaximum": lambda v, b: v < b}


def _type_test(types: list[str]):
    """``value -> bool`` for a JSON Schema ``type`` (bool is no number; 2.0 is an integer, as in jsonschema)."""
    if any(t not in _PY_TYPES for t in types):
        return None
    exact = frozenset(c for t in types for c in _PY_TYPES[t])
    int_float = "integer" in types and "number" not in types

    def ok(v):
        c = type(v)
        return c in exact or (int_float and c is float and v.is_integer())
    ok.exact = exact  # the Python types that pass as they are (for whole lists at once)
    return ok


@functools.cache
def _compiled(kind: str, pointer: str = ""):
    """The fast test of a kind's schema, or None when it uses a keyword the test does not know."""
    s = schema(kind)
    if pointer:
        return None
    return _compile(s)


def _compile(s):
    if not isinstance(s, dict):
        return None
    keys = set(s) - _ANNOTATIONS
    known = {"type", "required", "properties", "items", "enum", "const", "minLength", "maxLength", "minItems",
             "maxItems", *_BOUNDS}
    if keys - known:
        return None
    tests = []
    type_ok = None
    if "type" in s:
        types = s["type"] if isinstance(s["type"], list) else [s["type"]]
        type_ok = _type_test(types)
        if type_ok is None:
            return None
        tests.append(type_ok)
    for key in ("enum", "const"):  # strings only (jsonschema's equality of 1, 1.0 and true is its own)
        if key in s:
            vals = s[key] if key == "enum" else [s[key]]
            if not all(isinstance(x, str) for x in vals):
                return None
            allowed = frozenset(vals)
            tests.append(lambda v, allowed=allowed: type(v) is str and v in allowed)
    for key, cmp in _BOUNDS.items():
        if key in s:
            b = s[key]
            tests.append(lambda v, b=b, cmp=cmp: cmp(v, b) if type(v) in (int, float) else type(v) in _PLAIN)
    if "minLength" in s or "maxLength" in s:
        lo, hi = s.get("minLength", 0), s.get("maxLength", math.inf)
        tests.append(lambda v: lo <= len(v) <= hi if type(v) is str else type(v) in _PLAIN)
    if "minItems" in s or "maxItems" in s:
        lo_n, hi_n = s.get("minItems", 0), s.get("maxItems", math.inf)
        tests.append(lambda v: lo_n <= len(v) <= hi_n if type(v) is list else type(v) in _PLAIN)
    if "required" in s:
        req = tuple(s["required"])
        tests.append(lambda v: all(k in v for k in req) if type(v) is dict else type(v) in _PLAIN)
    if "properties" in s:
        props = {}
        for k, sub in s["properties"].items():
            t = _compile(sub)
            if t is None:
                return None
            props[k] = t

        def props_ok(v):
            if type(v) is not dict:
                return type(v) in _PLAIN
            for k, t in props.items():
                if k in v and not t(v[k]):
                    return False
            return True
        tests.append(props_ok)
    if "items" in s:
        item = _compile(s["items"])
        if item is None:
            return None
        sub = s["items"]
        only_type = isinstance(sub, dict) and set(sub) - _ANNOTATIONS == {"type"}
        exact = _type_test(sub["type"] if isinstance(sub["type"], list) else [sub["type"]]).exact if only_type \
            else None

        def items_ok(v):
            if type(v) is not list:
                return type(v) in _PLAIN
            if exact is not None and set(map(type, v)) <= exact:  # a list of plain numbers: one pass in C
                return True
            return all(map(item, v))
        tests.append(items_ok)
    if len(tests) == 1:
        return tests[0]
    tests = tuple(tests)
    return lambda v: all(t(v) for t in tests)


def validate(doc: Any, kind: str, path: str | Path | None = None, *, where: str = "", pointer: str = "",
             error: type[FieldcalError] = SpecError) -> Any:
    """Validate ``doc`` against the schema of ``kind`` (or its sub-schema at ``pointer``, e.g.
    ``/$defs/frame``); raise ``error`` naming the file, the JSON path (prefixed by ``where``) and the fix.
    Returns ``doc``."""
    from jsonschema.exceptions import best_match

    k = _kind(kind)
    if not pointer:
        _format_error(doc, k, path, where, error)
    fast = _compiled(kind, pointer)
    if fast is not None and fast(doc):
        return doc
    e = best_match(_validator(kind, pointer).iter_errors(doc))
    if e is None:
        return doc
    what, extra = _what(e)
    parts = list(e.absolute_path) + ([extra] if extra is not None else [])
    raise error(what, path=path, field=json_path(parts, where) or None, fix=_fix_for(e, k, extra, pointer))


def read(path: str | Path, kind: str, *, error: type[FieldcalError] = SpecError,
         not_found: str | None = None, not_found_fix: str | None = None) -> dict:
    """Read, parse safely and validate a ``kind`` document from ``path``."""
    k = _kind(kind)
    doc = read_json(path, error=error, not_found=not_found or f"{format_id(kind)} file not found",
                    not_found_fix=not_found_fix or k.fix, fix="repair the JSON syntax; " + k.fix)
    return validate(doc, kind, path, error=error)


# ----------------------------------------------------------------------------------------------- writing


def _default(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    if isinstance(v, tuple):
        return list(v)
    raise TypeError(f"{type(v).__name__} {v!r} is not JSON serialisable")


def dumps(doc: Any, kind: str | None = None, path: str | Path | None = None, *, indent: int | None = 2,
          sort_keys: bool = False, error: type[FieldcalError] = SpecError) -> str:
    """Serialise ``doc`` (numpy values become plain JSON; NaN/Infinity refused) and, given ``kind``,
    validate what a reader will see. Returns the text (with a final newline when indented)."""
    try:
        text = json.dumps(doc, indent=indent, allow_nan=False, default=_default, sort_keys=sort_keys)
    except (TypeError, ValueError) as exc:
        raise error(f"cannot be stored as JSON ({exc})", path=path,
                    fix="pass only str, finite numbers, bools, None, lists and dicts") from None
    if kind is not None:
        validate(loads(text, path, error=error), kind, path, error=error)
    return text + ("\n" if indent is not None else "")


def write(path: str | Path, doc: Any, kind: str, *, indent: int | None = 2,
          error: type[FieldcalError] = SpecError) -> Path:
    """Validate and write a document atomically (temporary name, fsync, rename). Returns the path."""
    path = Path(path)
    atomic_write_text(path, dumps(doc, kind, path, indent=indent, error=error))
    return path
