"""The offline query compiler: a sentence becomes a composition of the rules library, with no model
and no network (:mod:`.compile`; the query families in :mod:`.families`, the lexicon in
:mod:`.patterns`, whom a clause is about in :mod:`.subjects`)."""
