"""The language-model path: a client for any OpenAI-compatible endpoint (:mod:`.client`), the prompt
from the template files (:mod:`.prompt`), the program in a reply (:mod:`.extract`), the loop of rounds
with repair and the cache (:mod:`.generate`, :mod:`.cache`), whether a program means what the query
means (:mod:`.meaning`), and the accepted program steering sampling from its worker (:mod:`.remote`)."""
