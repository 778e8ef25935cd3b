"""Language interface (DESIGN.md, Language interface): a sentence becomes a checked guidance loss.

- :mod:`~ctgpp.language.client`: :class:`LLMClient` for any OpenAI-compatible chat endpoint.
- :mod:`~ctgpp.language.prompt`: the prompt from the template files; :mod:`~ctgpp.language.extract`:
  the program in a reply.
- :mod:`~ctgpp.language.sandbox` (rules in :mod:`~ctgpp.language.sandbox_rules`, allow lists in
  :mod:`~ctgpp.language.vocabulary`): generated code is parsed and allow-listed before it runs.
- :mod:`~ctgpp.language.checks` (worker process :mod:`~ctgpp.language.worker`): shape, finiteness,
  gradients, time and memory limits on a real scene batch.
- :mod:`~ctgpp.language.generate`: prompt -> reply -> sandbox -> checks, with repair rounds and the
  cache of :mod:`~ctgpp.language.cache`.

Submodules are imported explicitly (``from ctgpp.language.generate import generate_loss``): importing
this package loads nothing else.
"""
