"""The offline query compiler: a sentence becomes a composition of the rules library, with no model
and no network (:mod:`.compile`; what people write rewritten into its wording in :mod:`.normalise`,
the paraphrase benchmark in :mod:`.paraphrases`; where a query splits into clauses in
:mod:`.segments`, the query families in :mod:`.families` with their wording in :mod:`.phrases` and the
rules each becomes in :mod:`.handlers`, the lexicon in :mod:`.patterns`, whom a clause is about in
:mod:`.subjects`, what is refused in :mod:`.refusals`, the compiled parts and their code in
:mod:`.compiled`).

The public entry: :func:`compile_query` and what it returns or raises, importable from here."""

from ctgpp.language.compiler.compile import compile_query
from ctgpp.language.compiler.compiled import CompiledQuery, QueryPart, compose, render_code
from ctgpp.language.compiler.refusals import UnsupportedQuery, VehicleOutOfRange, phrasings, suggest
from ctgpp.language.compiler.subjects import QueryError

__all__ = [
    "CompiledQuery",
    "QueryError",
    "QueryPart",
    "UnsupportedQuery",
    "VehicleOutOfRange",
    "compile_query",
    "compose",
    "phrasings",
    "render_code",
    "suggest",
]
