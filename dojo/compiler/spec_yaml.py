"""Reading spec YAML as plain data, remembering where every node came from.

Spec files are untrusted input (third-party task packs), so this reader is deliberately narrower than YAML:
- only the YAML core schema's tags (str, int, float, bool, null, map, seq, and merge keys): a custom tag such as
  `!include` or `!!python/object/apply` is an error, never a constructor call;
- one document per file, at most `MAX_SPEC_BYTES`, UTF-8;
- anchors and aliases are allowed (they only repeat data) but their expansion is bounded, so a "billion laughs"
  file cannot exhaust memory, and a recursive alias is an error;
- duplicate keys and non-string keys are errors (PyYAML would silently keep the last one);
- keys that Hydra/OmegaConf would treat as code (`_target_`, `_partial_`, ...) and `${...}` interpolations, which
  OmegaConf resolvers could evaluate, are rejected wherever they appear.
Every value's (line, column) and every key's position are recorded by JSON path for error messages.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from dojo.compiler.spec_errors import JsonPath, SpecProblem

MAX_SPEC_BYTES = 1 << 20
MAX_EXPANDED_NODES = 50_000
MAX_DEPTH = 64

_CORE = "tag:yaml.org,2002:"
ALLOWED_TAGS = {_CORE + t for t in ("str", "int", "float", "bool", "null", "map", "seq", "merge", "timestamp")}
CODE_KEYS = {"_target_", "_partial_", "_recursive_", "_convert_", "_args_"}
_INTERPOLATION = re.compile(r"\$\{")


@dataclass
class Located:
    """A parsed document and the source positions of its nodes (1-based line and column)."""

    data: Any
    value_locs: dict[JsonPath, tuple[int, int]] = field(default_factory=dict)
    key_locs: dict[JsonPath, tuple[int, int]] = field(default_factory=dict)

    def locate(self, path: JsonPath, *, key: bool = False) -> tuple[int, int]:
        """Position of the node at `path` (of its key when `key`), falling back to the nearest located parent."""
        table = self.key_locs if key else self.value_locs
        probe = tuple(path)
        while probe:
            if probe in table:
                return table[probe]
            if key and probe in self.value_locs:
                return self.value_locs[probe]
            probe = probe[:-1]
        return self.value_locs.get((), (1, 1))


_Base = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml's parser when present: the same nodes, 5x faster


class SpecLoader(_Base):  # type: ignore[misc,valid-type]
    """SafeLoader with YAML 1.2 booleans: only true/false are booleans, so `on:`, `off:`, `yes:` and `no:` stay
    strings (`on` is a predicate name, and a spec author never means a colour called `no` to be False)."""


SpecLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != _CORE + "bool"]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
SpecLoader.add_implicit_resolver(
    _CORE + "bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)


class _Problems(Exception):
    """Internal: stops conversion when the document cannot be read further."""


class _Converter:
    def __init__(self, file: str):
        self.file = file
        self.problems: list[SpecProblem] = []
        self.located = Located(None)
        self.expanded = 0
        self._constructor = SpecLoader("")

    def problem(self, node: Node, path: JsonPath, message: str, *, safety: bool = False) -> None:
        mark = node.start_mark
        self.problems.append(SpecProblem(self.file, mark.line + 1, mark.column + 1, path, message, safety))

    def convert(self, node: Node, path: JsonPath, active: tuple[int, ...]) -> Any:
        self.expanded += 1
        if self.expanded > MAX_EXPANDED_NODES:
            self.problem(node, path, f"document expands to more than {MAX_EXPANDED_NODES} nodes "
                                     "(aliases repeat too much data)", safety=True)
            raise _Problems
        if len(path) > MAX_DEPTH:
            self.problem(node, path, f"nesting deeper than {MAX_DEPTH} levels", safety=True)
            raise _Problems
        if id(node) in active:
            self.problem(node, path, "recursive alias: a node contains itself", safety=True)
            raise _Problems
        self.located.value_locs.setdefault(path, (node.start_mark.line + 1, node.start_mark.column + 1))
        if node.tag not in ALLOWED_TAGS:
            self.problem(node, path, f"tag '{node.tag}' is not allowed: specs are plain data "
                                     "(no custom YAML tags, no includes, no code)", safety=True)
            return None
        if isinstance(node, ScalarNode):
            return self.scalar(node, path)
        active = active + (id(node),)
        if isinstance(node, SequenceNode):
            return [self.convert(child, path + (i,), active) for i, child in enumerate(node.value)]
        assert isinstance(node, MappingNode)
        return self.mapping(node, path, active)

    def scalar(self, node: ScalarNode, path: JsonPath) -> Any:
        value = self._constructor.construct_object(node, deep=True)
        if node.tag == _CORE + "timestamp":
            value = node.value  # dates stay text: the schemas never ask for a datetime object
        if isinstance(value, str) and _INTERPOLATION.search(value):
            self.problem(node, path, "'${...}' interpolation is not allowed in specs: "
                                     "resolvers could run code; write the value itself", safety=True)
        return value

    def mapping(self, node: MappingNode, path: JsonPath, active: tuple[int, ...]) -> dict:
        out: dict[str, Any] = {}
        explicit: set[str] = set()
        merges: list[Node] = []
        for key_node, value_node in node.value:
            if key_node.tag == _CORE + "merge":
                merges.append(value_node)  # after the explicit keys, so that their positions win
                continue
            if not isinstance(key_node, ScalarNode) or key_node.tag != _CORE + "str":
                self.problem(key_node, path, f"keys must be plain strings, got {key_node.value!r}")
                continue
            key = key_node.value
            if key in explicit:
                self.problem(key_node, path + (key,), f"duplicate key '{key}'")
                continue
            explicit.add(key)
            if key in CODE_KEYS:
                self.problem(key_node, path + (key,), f"'{key}' is not allowed: specs are data and cannot "
                                                      "name code to import or call", safety=True)
            if _INTERPOLATION.search(key):
                self.problem(key_node, path + (key,), "'${...}' interpolation is not allowed in specs", safety=True)
            self.located.key_locs[path + (key,)] = (key_node.start_mark.line + 1, key_node.start_mark.column + 1)
            out[key] = self.convert(value_node, path + (key,), active)
        for merge in merges:
            for key, value in self.merge_sources(merge, path, active).items():
                out.setdefault(key, value)
        return out

    def merge_sources(self, node: Node, path: JsonPath, active: tuple[int, ...]) -> dict:
        """YAML merge keys (`<<: *base`) copy mappings: harmless, and handy for variants of one object."""
        sources = node.value if isinstance(node, SequenceNode) else [node]
        merged: dict[str, Any] = {}
        for source in reversed(sources):
            if not isinstance(source, MappingNode):
                self.problem(source, path, "'<<' merges only mappings")
                continue
            value = self.convert(source, path, active)
            if isinstance(value, dict):
                merged.update(value)
        return merged


def read_spec_yaml(path: Path, display: str) -> tuple[Located | None, list[SpecProblem]]:
    """Parse one spec file into plain data with positions, or return the problems that prevent it."""
    try:
        size = path.stat().st_size
        if size > MAX_SPEC_BYTES:
            return None, [SpecProblem(display, 1, 1, (), f"file is {size} bytes; specs may be at most "
                                                         f"{MAX_SPEC_BYTES} bytes", safety=True)]
        raw = path.read_bytes()
    except OSError as err:
        return None, [SpecProblem(display, 1, 1, (), f"cannot read file: {err.strerror or err}")]
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        line = raw[: err.start].count(b"\n") + 1
        return None, [SpecProblem(display, line, 1, (), "file is not valid UTF-8")]
    try:
        nodes = list(yaml.compose_all(text, Loader=SpecLoader))
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        line, col = (mark.line + 1, mark.column + 1) if mark else (1, 1)
        reason = err.problem or err.context or "invalid YAML"
        return None, [SpecProblem(display, line, col, (), f"invalid YAML: {reason}")]
    except yaml.YAMLError as err:
        return None, [SpecProblem(display, 1, 1, (), f"invalid YAML: {err}")]
    if len(nodes) != 1:
        where = nodes[1].start_mark.line + 1 if len(nodes) > 1 else 1
        message = "file holds no document" if not nodes else "a spec file holds exactly one YAML document"
        return None, [SpecProblem(display, where, 1, (), message)]
    converter = _Converter(display)
    try:
        converter.located.data = converter.convert(nodes[0], (), ())
    except _Problems:
        return None, converter.problems
    if converter.problems:
        return None, converter.problems
    return converter.located, []
