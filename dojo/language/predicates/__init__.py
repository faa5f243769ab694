"""The predicate words of the task language, one module per word (see `dojo.language.predicate_registry` for what a
word carries). Importing this package registers the built-in words, in the order the task schema lists them, and
gives the registry's API: `register`, `word`, `names`, `schema_properties`, `references`, `render`, ...
"""

from dojo.language.predicate_registry import (  # noqa: F401  (the registry's API, re-exported)
    OBJREF,
    PREDICATE,
    PredicateWord,
    QUANTIFIER,
    evaluator,
    names,
    node_types,
    objref_list,
    ref_and_number,
    references,
    register,
    render,
    schema_properties,
    unregister,
    version,
    word,
)
from dojo.language.predicates import on, inside, stacked, upright, lifted, joint_bound, aligned, near, touched, pressed  # noqa: F401,E402
from dojo.language.predicates import ordered, connectives, quantifiers, at_start_of, same_order_as, sequence  # noqa: F401,E402
from dojo.language.predicates import struck, fraction_inside, tightened  # noqa: F401,E402
from dojo.language.predicates import plugged, turned  # noqa: F401,E402
