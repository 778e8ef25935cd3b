"""Generated code is untrusted: the syntax-tree allow lists (:mod:`.program`, :mod:`.rules`,
:mod:`.vocabulary`) before it runs, and the worker process that runs it under time and memory limits
(:mod:`.checks` on the parent side; :mod:`.worker`, :mod:`.session`, :mod:`.trial` inside)."""
