"""What a browser may send: a scene key, a sentence and numbers, each bounded; nothing else (no
paths, no code). Unknown fields are refused, not ignored."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

MAX_SENTENCE_CHARS = 300
MAX_BODY_BYTES = 4096  # a run request is a few hundred bytes
MAX_SEED = 2**31 - 1


class RunRequest(BaseModel):
    """One run: ``scene`` a key of :class:`~ctgpp.serve.scenes.SceneSets`; ``sentence`` what the
    traffic should do (empty: no query, the guards alone); ``policy`` one of the server's policies;
    ``guards`` the realism guards on or off; ``llm`` whether the sentence goes to the language model
    configured on the server; ``compare`` whether the same episode is also simulated unguided;
    ``exports`` the scenario files to write as well (``ctgpp simulate --export``)."""

    model_config = ConfigDict(extra="forbid", str_strip_whitespace=True)

    scene: str = Field(min_length=3, max_length=170, pattern=r"^[A-Za-z0-9_.:-]+$")
    sentence: str = Field(default="", max_length=MAX_SENTENCE_CHARS)
    seed: int = Field(default=0, ge=0, le=MAX_SEED)
    duration_s: float = Field(default=10.0, gt=0, le=20)
    policy: str = Field(default="ctgpp", max_length=40, pattern=r"^[A-Za-z0-9_+-]+$")
    guards: bool = True
    llm: bool = False
    compare: bool = True
    exports: list[Literal["scenarionet", "commonroad"]] = Field(default_factory=list, max_length=2)
