"""The benchmark's taxonomy as data: the dimensions tasks belong to, read from `kind: taxonomy` specs.

Scoring, reports, progress, suites and data collection all ask the taxonomy instead of naming dimensions: which
are scored and in what order, their labels, which are training-only (a suite may not list their tasks), which
are evaluation-only (`dojo collect` refuses them), and which compare two settings (RoboDojo's Generalization:
standard against random, episodes split between them). The built-in taxonomy is RoboDojo's; a pack adds its own
dimensions after the built-in ones with a taxonomy spec of its own.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from dojo.compiler.spec_library import Spec, SpecLibrary


@dataclass(frozen=True)
class Dimension:
    id: str
    label: str
    description: str = ""
    scored: bool = True
    evaluation_only: bool = False
    compare_settings: tuple[str, ...] = ()


@dataclass(frozen=True)
class Taxonomy:
    """Dimensions in report order."""

    dimensions: tuple[Dimension, ...]

    @classmethod
    def from_specs(cls, specs: list[Spec] | list[dict[str, Any]]) -> Taxonomy:
        dims: dict[str, Dimension] = {}
        for spec in specs:
            data = spec if isinstance(spec, dict) else spec.data
            for d in data["dimensions"]:
                dims.setdefault(d["id"], Dimension(d["id"], d["label"], d.get("description", ""),
                                                   d.get("scored", True), d.get("evaluation_only", False),
                                                   tuple(d.get("compare_settings", ()))))
        return cls(tuple(dims.values()))

    @property
    def ids(self) -> tuple[str, ...]:
        return tuple(d.id for d in self.dimensions)

    @property
    def scored(self) -> tuple[str, ...]:
        """The dimensions that count towards the overall score, in report order."""
        return tuple(d.id for d in self.dimensions if d.scored)

    @property
    def training_only(self) -> tuple[str, ...]:
        return tuple(d.id for d in self.dimensions if not d.scored)

    @property
    def evaluation_only(self) -> tuple[str, ...]:
        return tuple(d.id for d in self.dimensions if d.evaluation_only)

    def get(self, dimension: str) -> Dimension:
        for d in self.dimensions:
            if d.id == dimension:
                return d
        raise KeyError(f"unknown dimension {dimension!r}; one of {', '.join(self.ids)}")

    def label(self, dimension: str) -> str:
        return self.get(dimension).label if dimension in self.ids else dimension

    def compare_settings(self, dimension: str) -> tuple[str, ...]:
        """The two settings a dimension compares (standard, random), or () for one that does not."""
        return self.get(dimension).compare_settings if dimension in self.ids else ()


def taxonomy_of(library: SpecLibrary) -> Taxonomy:
    """The taxonomy of a loaded library: the built-in dimensions, then those packs add."""
    return Taxonomy.from_specs(library.of_kind("taxonomy"))


@lru_cache(maxsize=1)
def builtin_taxonomy() -> Taxonomy:
    """RoboDojo's own taxonomy (for readers of results that carry no library: reports over stores)."""
    from dojo.compiler.spec_library import SpecLibrary

    return taxonomy_of(SpecLibrary.load())
