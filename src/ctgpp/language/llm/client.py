"""A client for any OpenAI-compatible chat endpoint (OpenAI, vLLM, Ollama, llama.cpp server).

Configuration comes from flags or the environment, never module globals: ``OPENAI_BASE_URL``,
``OPENAI_API_KEY``, ``CTGPP_LLM_MODEL``, ``CTGPP_LLM_TIMEOUT`` and ``CTGPP_LLM_MAX_TOKENS`` (flags
win). The defaults fit a small model on a CPU server as well as a hosted one: a request may take
minutes (the cold ~8.5k-token prompt is read at 50-100 tokens/s on two quiet cores, at ~12 under
load), and one that times out is
never sent again (the server would still be busy with it); only a refused connection, HTTP 429 and
5xx are retried. The ``openai`` package is an optional
dependency (``pip install 'ctgpp[llm]'``), imported only when a client is built. Failures become an
:class:`LLMError` that says what went wrong and where: unreachable, key refused, unknown model, ...
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from ctgpp.language.llm.prompt import Message

__all__ = ["DEFAULT_BASE_URL", "LLM_MODES", "LLMClient", "LLMConfig", "LLMError"]

DEFAULT_BASE_URL = "https://api.openai.com/v1"
PLACEHOLDER_KEY = "not-needed"  # local servers (vLLM, Ollama) accept any key; the client needs one
DEFAULT_TIMEOUT_S = 600.0  # per request: a cold prompt on a 2-core CPU server, then the program
DEFAULT_MAX_TOKENS = 1024  # a loss program is 30-60 lines; bounds a reply that rambles on
LLM_MODES = ("program", "structured", "auto")
"""What the model is asked for: a loss program (the paper's path), structured calls of the behaviour
registry (:mod:`ctgpp.language.llm.structured`), or structured calls only where the offline compiler
refuses the sentence (``auto``)."""
RETRY_WAIT_S = (1.0, 4.0)  # before the first and later retries of a refused connection, 429 or 5xx


class LLMError(RuntimeError):
    """The language model could not be used: unreachable, refused the key, unknown model, bad reply."""


@dataclass(frozen=True)
class LLMConfig:
    """Where and how to reach the model. timeout_s: per request, s (a request that times out is not
    repeated); max_retries: retries of a refused connection, HTTP 429 and 5xx; max_tokens: the most
    tokens of one reply (None: the server's limit); temperature None leaves the server default;
    mode: one of :data:`LLM_MODES`."""

    base_url: str
    model: str
    api_key: str = field(default=PLACEHOLDER_KEY, repr=False)
    timeout_s: float = DEFAULT_TIMEOUT_S
    max_retries: int = 2
    temperature: float | None = 0.0
    max_tokens: int | None = DEFAULT_MAX_TOKENS
    mode: str = "program"

    @classmethod
    def resolve(
        cls,
        base_url: str | None = None,
        model: str | None = None,
        api_key: str | None = None,
        timeout_s: float | None = None,
        max_retries: int | None = None,
        env: Mapping[str, str] | None = None,
        max_tokens: int | None = None,
        mode: str | None = None,
    ) -> LLMConfig | None:
        """The configuration from flags (arguments) over the environment, or None when no model is
        named anywhere (then the offline compiler is used). Raises :class:`LLMError` when a model
        is named for the OpenAI API but no key is given, or a timeout or token limit is not a
        positive number, or the mode (``--llm-mode``, env ``CTGPP_LLM_MODE``) is not one of
        :data:`LLM_MODES`."""
        env = os.environ if env is None else env
        model = model or env.get("CTGPP_LLM_MODEL") or None
        if model is None:
            return None
        timeout = _positive("--llm-timeout", timeout_s, env.get("CTGPP_LLM_TIMEOUT"), DEFAULT_TIMEOUT_S)
        tokens = _positive("--llm-max-tokens", max_tokens, env.get("CTGPP_LLM_MAX_TOKENS"),
                           DEFAULT_MAX_TOKENS)
        mode = mode or env.get("CTGPP_LLM_MODE") or "program"
        if mode not in LLM_MODES:
            raise LLMError(f"--llm-mode must be one of {', '.join(LLM_MODES)} (got {mode!r})")
        url = (base_url or env.get("OPENAI_BASE_URL") or DEFAULT_BASE_URL).rstrip("/")
        key = api_key or env.get("OPENAI_API_KEY") or None
        if key is None and url == DEFAULT_BASE_URL:
            raise LLMError(f"model {model!r} at {url} needs an API key: set OPENAI_API_KEY or pass "
                           "--llm-api-key (or point OPENAI_BASE_URL / --llm-base-url at a local server)")
        return cls(
            base_url=url,
            model=model,
            api_key=key or PLACEHOLDER_KEY,
            timeout_s=timeout,
            max_retries=2 if max_retries is None else int(max_retries),
            max_tokens=int(tokens),
            mode=mode,
        )


def _positive(flag: str, given: float | None, from_env: str | None, default: float) -> float:
    """A flag's value, else the environment's, else ``default``; LLMError unless positive and finite."""
    value: float | str = given if given is not None else from_env if from_env else default
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not (math.isfinite(number) and number > 0):
        raise LLMError(f"{flag} must be a positive number (got {value!r})")
    return number


def _openai() -> Any:
    try:
        import openai
    except ImportError:
        raise LLMError("the language-model interface needs the openai package: pip install 'ctgpp[llm]' "
                       "(or run without --llm-model to use the offline compiler)") from None
    return openai


class LLMClient:
    """Chat completions against ``config``'s endpoint through the ``openai`` package."""

    def __init__(self, config: LLMConfig) -> None:
        self.config = config
        openai = _openai()
        self._errors = openai
        self._client = openai.OpenAI(
            base_url=config.base_url,
            api_key=config.api_key,
            timeout=config.timeout_s,
            max_retries=0,  # retried here: never after a timeout
        )

    def complete(self, messages: Sequence[Message], request: Mapping[str, Any] | None = None) -> str:
        """The model's reply text to ``messages`` (``[{"role": ..., "content": ...}, ...]``);
        ``request``: more fields of the chat request (``response_format``, ``max_tokens``,
        ``extra_body`` for a server's own fields such as llama.cpp's ``cache_prompt``)."""
        for attempt in range(self.config.max_retries + 1):
            try:
                return self._complete_once(messages, request or {})
            except _Retryable as failure:
                if attempt == self.config.max_retries:
                    raise LLMError(str(failure)) from None
                time.sleep(RETRY_WAIT_S[min(attempt, len(RETRY_WAIT_S) - 1)])
        raise AssertionError("the loop returns or raises")

    def _complete_once(self, messages: Sequence[Message], request: Mapping[str, Any]) -> str:
        cfg, err = self.config, self._errors
        where = f"the language model at {cfg.base_url}"
        extra: dict[str, Any] = {} if cfg.temperature is None else {"temperature": cfg.temperature}
        if cfg.max_tokens is not None:
            extra["max_tokens"] = cfg.max_tokens
        extra |= request
        if cfg.max_tokens is not None and "max_tokens" in request:
            extra["max_tokens"] = min(int(request["max_tokens"]), cfg.max_tokens)
        try:
            response = self._client.chat.completions.create(
                model=cfg.model, messages=[dict(m) for m in messages], **extra
            )
        except err.APITimeoutError:
            raise LLMError(f"{where} did not answer within {cfg.timeout_s:g} s (not sent again: the "
                           "server may still be working on it; a small model on a CPU may need "
                           "--llm-timeout of several minutes)") from None
        except err.APIConnectionError as e:
            raise _Retryable(f"cannot reach {where}: {_cause(e)}") from None
        except err.AuthenticationError as e:
            raise LLMError(f"{where} refused the API key (HTTP 401): set OPENAI_API_KEY or --llm-api-key "
                           f"({_message(e)})") from None
        except err.PermissionDeniedError as e:
            raise LLMError(f"{where} denied access (HTTP 403): {_message(e)}") from None
        except err.RateLimitError as e:
            raise _Retryable(f"{where} is rate-limiting requests (HTTP 429): {_message(e)}") from None
        except err.InternalServerError as e:
            raise _Retryable(f"{where} answered HTTP {e.status_code}: {_message(e)}") from None
        except err.NotFoundError as e:
            raise LLMError(f"{where} has no model {cfg.model!r} or no chat endpoint (HTTP 404): "
                           f"{_message(e)}") from None
        except err.APIStatusError as e:
            raise LLMError(f"{where} answered HTTP {e.status_code}: {_message(e)}") from None
        except err.APIError as e:  # malformed responses and the like
            raise LLMError(f"{where} gave an unusable answer: {_message(e)}") from None
        except ValueError as e:  # a body that says it is JSON and is not
            raise LLMError(f"{where} answered with a body that is not JSON ({e}); is --llm-base-url the "
                           "server's OpenAI-compatible /v1 address?") from None
        if isinstance(response, str | bytes):  # the openai package hands back a body that is not JSON as is
            text = response.decode(errors="replace") if isinstance(response, bytes) else response
            raise LLMError(f"{where} answered with something that is not JSON ({len(text)} characters: "
                           f"{_snippet(text)}); is --llm-base-url the server's OpenAI-compatible /v1 "
                           "address?")
        choices = getattr(response, "choices", None)
        if choices is None:
            raise LLMError(f"{where} answered JSON that is not a chat completion (no 'choices'); is "
                           "--llm-base-url the server's OpenAI-compatible /v1 address?")
        content = choices[0].message.content if choices else None
        if not content or not content.strip():
            raise LLMError(f"{where} returned an empty reply for model {cfg.model!r}")
        return str(content)


class _Retryable(Exception):
    """A refused or dropped connection, HTTP 429 or 5xx: tried again; its message becomes the
    LLMError's when no retry is left."""


def _message(e: BaseException) -> str:
    text = str(getattr(e, "message", "") or e)
    return text if len(text) <= 300 else text[:297] + "..."


def _snippet(text: str, limit: int = 80) -> str:
    """The start of ``text`` on one line, quoted."""
    flat = " ".join(text.split())
    return repr(flat if len(flat) <= limit else flat[: limit - 3] + "...")


def _cause(e: BaseException) -> str:
    """The innermost cause of a connection error (e.g. 'Connection refused'), else the message."""
    inner: BaseException = e
    while inner.__cause__ is not None:
        inner = inner.__cause__
    return _message(inner) if inner is not e else _message(e)
