"""The predicate registry: every predicate word of the task language (the built-in ones are the modules of
`dojo.language.predicates`, one word each).

A `PredicateWord` carries everything about one word:
- `schema`: the JSON Schema of its argument. The task schema's `$defs/predicate/properties` is this registry's
  `schema_properties()` (`specs/schemas/task.schema.json` holds the built-in words' copy for readers, and a test
  keeps the two equal); the validator overlays the registry, so a word registered at run time is accepted too.
- reference roles, read off the schema: an argument position typed `objref` names an object, `predicate` is a
  child predicate, `quantifier` names a group and a child in which `_` is bound (`references`). The compiler's
  reference checks need no per-word code.
- `compile(ctx, arg, ref, bound)`: the word against a plan's scene, returning a hashable node (a frozen
  dataclass). `ctx` is the program compiler (`frame`, `annotated_frame`, `atoms_of`, `joint`, `press`,
  `is_region`, `group_members`, `order_slots`, and `node` for child predicates); `ref` resolves `_` to `bound`.
- `evaluate(ev, node)`: the node's value bool[N] on one batch, for the node type the word produces (`None` for
  words that compile into other words' nodes, such as `stacked`). `ev` offers `xp`, `frame`, `touching`,
  `state`, `params`, `memory`, `press_count`, `step`, `record_first` and `eval` for children.

Registering a word that exists already is an error (`dojo.language.registry`), so a module cannot silently change
a built-in word.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from dojo.language import facts
from dojo.language.registry import Registry

Array = Any
OBJREF = "#/$defs/objref"
PREDICATE = "#/$defs/predicate"
QUANTIFIER = "#/$defs/quantifier"


@dataclass(frozen=True)
class PredicateWord:
    """One predicate word (see the module docstring)."""

    name: str
    schema: dict[str, Any]
    compile: Callable[[Any, Any, Callable[[str], str], str | None], Any]
    node: type | None = None
    evaluate: Callable[[Any, Any], Array] | None = None


_WORDS: Registry[PredicateWord] = Registry("predicate")
_EVALUATORS: dict[type, Callable[[Any, Any], Array]] = {}


def register(word: PredicateWord) -> PredicateWord:
    """Add a word to the language (its schema is accepted by the validator from now on)."""
    if (word.node is None) != (word.evaluate is None):
        raise ValueError(f"predicate {word.name!r}: give both a node type and its evaluate, or neither")
    _WORDS.add(word.name, word)
    if word.node is not None:
        _EVALUATORS[word.node] = word.evaluate
    return word


def unregister(name: str) -> None:
    """Remove a word (tests that add a word take it out again)."""
    word = _WORDS.remove(name)
    if word.node is not None:
        _EVALUATORS.pop(word.node, None)


def version() -> int:
    """Changes whenever the vocabulary does: caches of validators built from it key on this."""
    return _WORDS.version


def word(name: str) -> PredicateWord | None:
    return _WORDS.get(name)


def names() -> list[str]:
    return sorted(_WORDS.entries())


def evaluator(node_type: type) -> Callable[[Any, Any], Array] | None:
    return _EVALUATORS.get(node_type)


def node_types() -> list[type]:
    """Every node type the registered words produce (plans store compiled programs by these names)."""
    return list(_EVALUATORS)


def schema_properties() -> dict[str, dict[str, Any]]:
    """`$defs/predicate/properties` of the task schema: every word's argument schema, in registration order."""
    return {name: w.schema for name, w in _WORDS.entries().items()}


def references(name: str, arg: Any, path: tuple, quantified: bool) -> Iterator[tuple[tuple, str, str, bool]]:
    """(path, name, role, inside a quantifier) for every name the predicate `{name: arg}` uses, children included.

    Roles are `object` and `group`; they are read off the word's schema, so a new word needs no code here.
    """
    w = _WORDS.get(name)
    if w is not None:
        yield from _walk(w.schema, arg, path + (name,), quantified)


def _walk(schema: dict, value: Any, path: tuple, quantified: bool) -> Iterator[tuple[tuple, str, str, bool]]:
    ref = schema.get("$ref")
    if ref == OBJREF:
        if isinstance(value, str):
            yield path, value, "object", quantified
    elif ref == PREDICATE:
        if isinstance(value, dict) and len(value) == 1:
            (child, child_arg), = value.items()
            yield from references(child, child_arg, path, quantified)
    elif ref == facts.FACT:
        yield from _walk(facts.SCHEMA, value, path, quantified)
    elif "oneOf" in schema:
        for alternative in schema["oneOf"]:
            yield from _walk(alternative, value, path, quantified)
    elif ref == QUANTIFIER:
        if isinstance(value, dict):
            if isinstance(value.get("group"), str):
                yield path + ("group",), value["group"], "group", quantified
            yield from _walk({"$ref": PREDICATE}, value.get("holds"), path + ("holds",), True)
    elif isinstance(value, list):
        prefix = schema.get("prefixItems", [])
        items = schema.get("items")
        for i, item in enumerate(value):
            sub = prefix[i] if i < len(prefix) else items
            if isinstance(sub, dict):
                yield from _walk(sub, item, path + (i,), quantified)
    elif isinstance(value, dict):
        for key, sub in schema.get("properties", {}).items():
            if key in value:
                yield from _walk(sub, value[key], path + (key,), quantified)


def render(pred: Any) -> str:
    """A predicate as text, `{on: [a, b]}` as `on(a, b)`: children in place, keyword arguments as `key=value`.
    Names an episode's success terms and writes task cards."""
    if isinstance(pred, dict) and len(pred) == 1 and next(iter(pred)) in _WORDS.entries():
        (name, arg), = pred.items()
        return f"{name}({_render_arg(arg)})"
    return _render_arg(pred)


def _render_arg(arg: Any) -> str:
    if facts.is_fact(arg):
        return ".".join(map(str, arg["attribute"]))
    if isinstance(arg, list):
        return ", ".join(render(a) for a in arg)
    if isinstance(arg, dict):
        return ", ".join(f"{k}={render(v)}" for k, v in arg.items())
    return str(arg)


def objref_list(description: str, min_items: int, max_items: int | None = None) -> dict[str, Any]:
    """Schema of an argument that is a list of object references."""
    schema: dict[str, Any] = {"description": description, "type": "array", "items": {"$ref": OBJREF},
                              "minItems": min_items}
    if max_items is not None:
        schema["maxItems"] = max_items
    return schema


def ref_and_number(description: str) -> dict[str, Any]:
    """Schema of an `[objref, number]` argument."""
    return {"description": description, "type": "array", "prefixItems": [{"$ref": OBJREF}, {"type": "number"}],
            "items": False, "minItems": 2}
