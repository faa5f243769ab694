"""The schemas are the reference documentation: valid draft 2020-12, every property described, examples valid."""

from __future__ import annotations

from typing import Any, Iterator

import jsonschema
import pytest

from dojo.compiler.spec_schema import SPEC_KINDS, load_schemas, validator_for

SCHEMAS = load_schemas()


def properties(node: Any, path: str = "$") -> Iterator[tuple[str, dict]]:
    """Every property schema (at any depth, through $defs, items and combinators) with a readable path. `if`
    branches are conditions, not documentation, and are skipped."""
    if isinstance(node, dict):
        for name, sub in node.get("properties", {}).items():
            yield f"{path}.{name}", sub
        for key, value in node.items():
            if key in ("properties", "$defs") and isinstance(value, dict):
                for name, sub in value.items():
                    yield from properties(sub, f"{path}.{name}")
            elif key in ("items", "additionalProperties", "not", "then", "else") and isinstance(value, dict):
                yield from properties(value, f"{path}[{key}]")
            elif key in ("anyOf", "oneOf", "allOf", "prefixItems") and isinstance(value, list):
                for i, sub in enumerate(value):
                    yield from properties(sub, f"{path}[{key}{i}]")


@pytest.mark.parametrize("name", sorted(SCHEMAS))
def test_schema_is_valid_and_every_property_is_described(name: str) -> None:
    schema = SCHEMAS[name]
    jsonschema.Draft202012Validator.check_schema(schema)
    assert schema["$schema"].endswith("2020-12/schema")
    undocumented = [path for path, sub in properties(schema)
                    if isinstance(sub, dict) and "description" not in sub and "$ref" not in sub]
    assert undocumented == [], f"{name}: properties without a description: {undocumented}"


@pytest.mark.parametrize("kind", SPEC_KINDS)
def test_kind_version_and_examples(kind: str) -> None:
    schema = SCHEMAS[kind]
    assert schema["properties"]["kind"]["const"] == kind
    assert {"kind", "version", "id"} <= set(schema["required"])
    assert schema.get("examples"), f"{kind} schema has no example"
    for example in schema["examples"]:
        errors = [e.message for e in validator_for(kind).iter_errors(example)]
        assert errors == []
