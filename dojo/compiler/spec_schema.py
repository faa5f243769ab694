"""Validating spec data against the JSON Schemas in `specs/schemas/`, with errors a person can act on.

Two keywords of our own extend draft 2020-12:
- `x-relpath: true` checks a file path against the spec's package during validation: relative, no `..`, no
  symlink that leaves the package, the file exists. A path is data pointing at data; it must never reach the rest
  of the disk.
- `x-ref: <kind>` marks a reference to another spec (by id or by query); after validation a walk of the data beside
  its schema collects them with their paths so that the library can resolve them.
Errors are rewritten from jsonschema's wording into `file:line:col: $.path: message` problems, pointing at the
offending key for unknown keys and suggesting the closest valid key or value.
"""

from __future__ import annotations

import contextvars
import json
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path, PurePosixPath
from typing import Any, Iterator

import jsonschema
from jsonschema import ValidationError
from referencing import Registry, Resource

from dojo.language import predicates as predicate_words
from dojo.language import skills as skill_words

from dojo.compiler.spec_errors import JsonPath, SpecProblem, did_you_mean
from dojo.compiler.spec_yaml import Located

SPEC_KINDS = ("asset", "robot", "suite", "task", "taxonomy")
SCHEMA_BASE = "https://robodojo.dev/schemas/"


@dataclass
class RefUse:
    """A marked value found in a spec: where it is, the marker's value (for `x-ref` the kind referred to), and the
    value itself (an id or query, or a file path)."""

    path: JsonPath
    kind: str
    value: str | dict


@dataclass
class _Context:
    spec_dir: Path
    package_root: Path


_CONTEXT: contextvars.ContextVar[_Context] = contextvars.ContextVar("spec_context")


def schema_dir() -> Path:
    """The folder of the built-in schemas (inside the installed package, editable or wheel)."""
    return Path(str(resources.files("dojo.specs") / "schemas"))


def load_schemas() -> dict[str, dict]:
    """All schemas by file stem (`task`, `common`, ...), the task language's words filled in from their registry."""
    return _load_schemas(_vocabulary_version())


def _vocabulary_version() -> tuple[int, int]:
    return predicate_words.version(), skill_words.version()


@lru_cache(maxsize=2)
def _load_schemas(vocabulary_version: tuple[int, int]) -> dict[str, dict]:
    out = {}
    for path in sorted(schema_dir().glob("*.schema.json")):
        out[path.name.removesuffix(".schema.json")] = json.loads(path.read_text(encoding="utf-8"))
    # The file lists the built-in words for readers; the registries are the truth (a test keeps them equal).
    out["task"]["$defs"]["predicate"]["properties"] = predicate_words.schema_properties()
    out["task"]["$defs"]["skill"]["properties"]["skill"] = skill_words.schema_property()
    return out


def _relpath_keyword(validator: Any, enabled: Any, instance: Any, schema: dict) -> Iterator[ValidationError]:
    if not enabled or not isinstance(instance, str):
        return
    ctx = _CONTEXT.get(None)
    if ctx is None:  # data that did not come from a file (a schema example): there is no package to check against
        return
    problem = relpath_problem(instance, ctx.spec_dir, ctx.package_root)
    if problem:
        message, escapes = problem
        yield _PathEscape(message) if escapes else ValidationError(message)


class _PathEscape(ValidationError):
    """A file path that would read outside the spec's package: a safety problem, not a typo."""


def relpath_problem(value: str, spec_dir: Path, package_root: Path) -> tuple[str, bool] | None:
    """Why `value` is not an acceptable file path for a spec in `spec_dir`, and whether it reaches outside the
    package (a safety problem); None if it is fine."""
    pure = PurePosixPath(value)
    if "\\" in value or pure.is_absolute() or (len(value) > 1 and value[1] == ":"):
        return f"'{value}' is an absolute path: file paths in specs are relative to the spec file", True
    if ".." in pure.parts:
        return f"'{value}' contains '..': file paths in specs may not leave the spec's package", True
    target = spec_dir / pure
    try:
        resolved = target.resolve(strict=True)
    except (OSError, RuntimeError):
        return f"file '{value}' does not exist (looked in {spec_dir})", False
    root = package_root.resolve()
    if resolved != root and root not in resolved.parents:
        return f"'{value}' resolves outside the spec's package (a symlink to {resolved}): not allowed", True
    if not resolved.is_file():
        return f"'{value}' is not a file", False
    return None


@lru_cache(maxsize=1)
def _validator_class() -> type:
    base = jsonschema.Draft202012Validator
    return jsonschema.validators.extend(base, {"x-relpath": _relpath_keyword})


def validator_for(kind: str) -> Any:
    """A reusable validator for one spec kind, with every built-in schema resolvable by `$ref`."""
    return _validator_for(kind, _vocabulary_version())


@lru_cache(maxsize=None)
def _validator_for(kind: str, vocabulary_version: tuple[int, int]) -> Any:
    schemas = _load_schemas(vocabulary_version)
    resources_ = [(SCHEMA_BASE + f"{name}.schema.json", Resource.from_contents(s)) for name, s in schemas.items()]
    registry = Registry().with_resources(resources_)
    return _validator_class()(schemas[kind], registry=registry)


def validate_spec_data(kind: str, located: Located, display: str, spec_dir: Path,
                       package_root: Path) -> tuple[list[SpecProblem], list[RefUse]]:
    """Validate one parsed spec; return all problems and the references it makes."""
    ctx = _Context(spec_dir, package_root)
    token = _CONTEXT.set(ctx)
    try:
        errors = list(validator_for(kind).iter_errors(located.data))
    finally:
        _CONTEXT.reset(token)
    problems = [p for error in errors for p in _problems_from(error, located, display)]
    problems = sorted(_merge_typos(problems), key=lambda p: (p.line, p.column, p.message))
    refs = collect_marked(kind, located.data, "x-ref") if not problems else []
    return problems, refs


def collect_marked(kind: str, data: Any, keyword: str) -> list[RefUse]:
    """Walk the data beside its schema to find every value whose schema carries `keyword` (`x-ref` for
    references, `x-relpath` for file paths), with its JSON path and the keyword's value.

    Done after validation because jsonschema's keyword callbacks are not told where in the instance they are.
    Only called on valid data, so the walk can follow the schema without re-checking it.
    """
    schemas = load_schemas()
    out: list[RefUse] = []

    def deref(schema: dict, doc: dict) -> tuple[dict, dict]:
        while "$ref" in schema and keyword not in schema:
            target, _, pointer = schema["$ref"].partition("#")
            if target:
                doc = schemas[target.removesuffix(".schema.json")]
            node: Any = doc
            for part in [p for p in pointer.split("/") if p]:
                node = node[part]
            schema = node
        return schema, doc

    def declared_type(schema: dict, doc: dict) -> Any:
        while "type" not in schema and "$ref" in schema:
            schema, doc = deref({"$ref": schema["$ref"]}, doc)
        return schema.get("type")

    def walk(schema: dict, doc: dict, value: Any, path: JsonPath) -> None:
        schema, doc = deref(schema, doc)
        if keyword in schema:
            out.append(RefUse(path, schema[keyword], value))
            return
        for branch in schema.get("allOf", []):
            walk(branch, doc, value, path)
        for key in ("anyOf", "oneOf"):
            for branch in schema.get(key, []):
                expected = declared_type(branch, doc)
                if _type_name(value) == expected or (expected == "integer" and isinstance(value, int)):
                    walk(branch, doc, value, path)
                    break
        if isinstance(value, dict):
            props = schema.get("properties", {})
            extra = schema.get("additionalProperties")
            for key, child in value.items():
                if key in props:
                    walk(props[key], doc, child, path + (key,))
                elif isinstance(extra, dict):
                    walk(extra, doc, child, path + (key,))
        elif isinstance(value, list):
            items = schema.get("items")
            if isinstance(items, dict):
                for i, child in enumerate(value):
                    walk(items, doc, child, path + (i,))

    walk(schemas[kind], schemas[kind], data, ())
    return out


def _merge_typos(problems: list[SpecProblem]) -> list[SpecProblem]:
    """A misspelt required key is one mistake, not two: drop "missing required field 'x'" where an unknown key
    of the same object already suggests 'x'."""
    suggested = {(p.path[:-1], p.message.rsplit("'", 2)[-2]) for p in problems
                 if p.message.startswith("unknown key") and "did you mean" in p.message}
    return [p for p in problems
            if not (p.message.startswith("missing required field") and (p.path, p.message.split("'")[1]) in suggested)]


def _type_name(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, (int, float)):
        return "number"
    return {str: "string", list: "array", dict: "object"}.get(type(value), type(value).__name__)


def _as_list(value: Any) -> list:
    return value if isinstance(value, list) else [value]


def _short(value: Any) -> str:
    text = json.dumps(value, default=str)
    return text if len(text) <= 60 else text[:57] + "..."


def _pick_branch_error(error: ValidationError) -> ValidationError:
    """For oneOf/anyOf, report the failure of the branch the author evidently meant (the one whose type matched)."""
    candidates = [e for e in error.context if e.validator != "type"] or list(error.context)
    if not candidates:
        return error
    deepest = max(len(e.absolute_path) for e in candidates)
    chosen = next(e for e in candidates if len(e.absolute_path) == deepest)
    return _pick_branch_error(chosen) if chosen.validator in ("oneOf", "anyOf") and chosen.context else chosen


def _problems_from(error: ValidationError, located: Located, display: str) -> list[SpecProblem]:
    path: JsonPath = tuple(error.absolute_path)
    if error.validator in ("oneOf", "anyOf") and error.context:
        if all(len(e.absolute_path) == len(path) and e.validator in ("type", "const", "enum") for e in error.context):
            options = [_short(e.validator_value) if e.validator == "const" else
                       " or ".join(_as_list(e.validator_value)) if e.validator == "type" else
                       " or ".join(map(_short, e.validator_value)) for e in error.context]
            line, col = located.locate(path)
            return [SpecProblem(display, line, col, path,
                                f"expected {' or '.join(options)}, got {_type_name(error.instance)} "
                                f"{_short(error.instance)}")]
        chosen = _pick_branch_error(error)
        if chosen is not error:
            return _problems_from(chosen, located, display)
    schema = error.schema if isinstance(error.schema, dict) else {}
    instance = error.instance

    def at(p: JsonPath, message: str, key: bool = False) -> SpecProblem:
        line, col = located.locate(p, key=key)
        return SpecProblem(display, line, col, p, message)

    v = error.validator
    if v == "additionalProperties" and isinstance(instance, dict):
        known = list(schema.get("properties", {}))
        extras = [k for k in instance if k not in known]
        return [at(path + (k,), f"unknown key '{k}'{did_you_mean(k, known)}", key=True) for k in extras]
    if v == "required" and isinstance(instance, dict):
        missing = [k for k in schema.get("required", []) if k not in instance]
        return [at(path, f"missing required field '{k}'") for k in missing]
    if v == "type":
        expected = error.validator_value
        expected = " or ".join(expected) if isinstance(expected, list) else expected
        return [at(path, f"expected {expected}, got {_type_name(instance)} {_short(instance)}")]
    if v == "enum":
        options = [str(o) for o in error.validator_value]
        hint = did_you_mean(str(instance), options)
        return [at(path, f"{_short(instance)} is not one of: {', '.join(options)}{hint}")]
    if v == "const":
        return [at(path, f"must be {_short(error.validator_value)}, got {_short(instance)}")]
    if v == "pattern" and schema.get("description"):
        return [at(path, f"{_short(instance)} does not match {error.validator_value!r}: {schema['description']}")]
    if v == "maxProperties" and error.validator_value == 1 and isinstance(instance, dict):
        return [at(path, f"expected exactly one key (the predicate's name), got {len(instance)}: "
                         f"{', '.join(instance)}")]
    if v in ("minItems", "maxItems") and isinstance(instance, list):
        bound = "at least" if v == "minItems" else "at most"
        return [at(path, f"expected {bound} {error.validator_value} items, got {len(instance)}")]
    if v == "x-relpath":
        line, col = located.locate(path)
        return [SpecProblem(display, line, col, path, error.message, isinstance(error, _PathEscape))]
    return [at(path, error.message)]
