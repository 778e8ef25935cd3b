"""Language interface (DESIGN.md, Language interface): a sentence becomes a checked guidance loss.

- :mod:`~ctgpp.language.query`: the one entry point — the offline compiler's loss, or a language
  model's checked program, for a user's sentence.
- :mod:`~ctgpp.language.compiler`: the offline query compiler (no model, no network).
- :mod:`~ctgpp.language.llm`: the language-model path (client, prompt, reply, repair rounds, cache).
- :mod:`~ctgpp.language.sandbox`: generated code is allow-listed before it runs, and runs in a worker
  process under time and memory limits.
- :mod:`~ctgpp.language.satisfaction`: whether a rollout satisfies the query, checked independently.

Submodules are imported explicitly (``from ctgpp.language.llm.generate import generate_loss``):
importing this package loads nothing else.
"""
