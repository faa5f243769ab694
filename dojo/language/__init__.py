"""The words of the task language, one module per word: its schema, its reference roles, how it compiles
against a scene, and how it is evaluated (import as ``dojo.language``).

A task spec is data; what its words *mean* lives here and nowhere else. The compiler reads each word's schema
fragment (the task schema's predicate part is filled from this registry) and the backends evaluate the nodes
its compile step produces, so adding a word to the language is adding one module.
"""
