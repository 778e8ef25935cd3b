"""Generated code is untrusted: the syntax-tree allow lists before it runs (:mod:`.program`; the walk
over statements in :mod:`.statements`, over expressions in :mod:`.expressions`, node readings in
:mod:`.nodes`, the lists in :mod:`.vocabulary`), and the worker process that runs it under time and
memory limits (:mod:`.checks` on the parent side; :mod:`.worker`, :mod:`.session`, :mod:`.trial` inside)."""
