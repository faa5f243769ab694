"""A compiled predicate program as JSON, so that a plan carries its program resolved once, at `dojo compile`.

The compiler resolves every name of a task's success program against the plan's scene (`compile_program`) and
stores the result in the plan (`Plan.compiled_program`): a predicate that does not resolve fails at compile time,
located in the spec, and a backend loads the program without resolving anything again. The encoding is generic
over the node types of `dojo.language.predicates` (each node a frozen dataclass, written with its class name), so
a new word needs nothing here. Floats are written with Python's shortest round-trip repr: a loaded program is
bit-identical to the one compiled.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from dojo.language import predicates as words

from dojo.backends.predicate_state import StateIndex
from dojo.backends.program_types import CompiledProgram, Press, ProgramLayout

FORMAT = 1
_NODE = "node"


def _node_types() -> dict[str, type]:
    types = {t.__name__: t for t in words.node_types()}
    types[Press.__name__] = Press
    return types


def _encode(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {_NODE: type(value).__name__,
                **{f.name: _encode(getattr(value, f.name)) for f in dataclasses.fields(value)}}
    if isinstance(value, (tuple, list)):
        return [_encode(v) for v in value]
    return value


def _decode(value: Any, types: dict[str, type]) -> Any:
    """Lists become tuples (nodes must stay hashable) and maps with a node name become that node."""
    if isinstance(value, list):
        return tuple(_decode(v, types) for v in value)
    if isinstance(value, dict) and _NODE in value:
        name = value[_NODE]
        if name not in types:
            raise ValueError(f"the plan's program uses predicate node {name!r}, which no registered word defines")
        return types[name](**{k: _decode(v, types) for k, v in value.items() if k != _NODE})
    return value


def program_to_json(program: CompiledProgram) -> dict[str, Any]:
    """The compiled program as plain JSON data."""
    layout = {f.name: _encode(getattr(program.layout, f.name)) for f in dataclasses.fields(program.layout)}
    index = {f.name: _encode(getattr(program.index, f.name)) for f in dataclasses.fields(program.index)}
    params = {k: {"shape": list(v.shape), "dtype": v.dtype.str, "data": v.ravel().tolist()}
              for k, v in program.params.items()}
    return {"format": FORMAT, "layout": layout, "index": index, "params": params}


def program_from_json(data: dict[str, Any]) -> CompiledProgram:
    """The compiled program a plan carries."""
    if data.get("format") != FORMAT:
        raise ValueError(f"compiled program format {data.get('format')!r}, this version reads {FORMAT}")
    types = _node_types()
    layout = ProgramLayout(**{k: _decode(v, types) for k, v in data["layout"].items()})
    index = StateIndex(**{k: _decode(v, types) for k, v in data["index"].items()})
    params = {k: np.asarray(v["data"], dtype=np.dtype(v["dtype"])).reshape(v["shape"])
              for k, v in data["params"].items()}
    return CompiledProgram(layout, index, params)
