"""The prompt for the language model, from the template files in ``ctgpp/language/templates``.

The user message is: the loss API (``api.md``: the paper's contract and its six helpers as
``../shared/docs/LLM-API.md`` states them, then ctgpp's own helpers, the sandbox's vocabulary and what
each behaviour of :mod:`ctgpp.behaviours` means),
the paired examples (``examples.md``: query -> loss class, the paper's two among them), then the
query (``query.md``). The system message (``system.md``) states the rules of the sandbox; ``repair.md``
sends a refusal back. Helper descriptions are generated from the helpers' signatures and docstrings,
so the prompt never drifts from the code. :data:`PROMPT_VERSION` hashes everything that goes into a
prompt except the query, and keys the cache of accepted programs.
"""

from __future__ import annotations

import hashlib
import inspect
import re
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources

from ctgpp.guidance import helpers
from ctgpp.language.sandbox.vocabulary import (
    FUNCTIONAL_FUNCTIONS,
    HELPER_NAMES,
    LINALG_FUNCTIONS,
    MATH_NAMES,
    SAFE_BUILTIN_NAMES,
    TORCH_FUNCTIONS,
    prebound_names,
)

__all__ = [
    "PROMPT_VERSION",
    "TEMPLATE_NAMES",
    "Example",
    "Message",
    "behaviour_descriptions",
    "build_messages",
    "examples",
    "helper_descriptions",
    "load_template",
    "repair_message",
]

Message = dict[str, str]
"""One chat message: ``{"role": "system" | "user" | "assistant", "content": text}``."""

TEMPLATE_NAMES = ("system.md", "api.md", "examples.md", "query.md", "repair.md")
DEFAULT_DT_S = 0.1
DEFAULT_FUTURE_STEPS = 52
_ROLE = re.compile(r":[a-z]+:`~?([^`]+)`")  # Sphinx roles such as :func:`get_turn_lane`


def load_template(name: str) -> str:
    """The text of one template file (package data of ``ctgpp.language``)."""
    if name not in TEMPLATE_NAMES:
        raise ValueError(f"unknown template {name!r}; templates: {', '.join(TEMPLATE_NAMES)}")
    return (resources.files("ctgpp.language") / "templates" / name).read_text(encoding="utf-8")


def _fill(template: str, **values: str) -> str:
    """Replace ``{{name}}`` markers (braces in code stay untouched)."""
    for key, value in values.items():
        template = template.replace("{{" + key + "}}", value)
    return template


def helper_descriptions(which: Sequence[str] | None = None) -> str:
    """One Markdown entry per helper of ``which`` (default: every helper): ``name(signature)`` and its
    docstring (roles stripped)."""
    names = prebound_names()
    entries = []
    for name in HELPER_NAMES if which is None else which:
        fn = names[name]
        signature = str(inspect.signature(fn)).replace("'", "")
        doc = _ROLE.sub(lambda m: m.group(1).split(".")[-1], inspect.getdoc(fn) or "")
        body = "\n".join("  " + line if line else "" for line in doc.splitlines())
        entries.append(f"- `{name}{signature}`\n{body}")
    return "\n".join(entries)


def _api_text() -> str:
    def listing(names: frozenset[str] | list[str]) -> str:
        return ", ".join(f"`{n}`" for n in sorted(names))

    return _fill(
        load_template("api.md"),
        dt_s=f"{DEFAULT_DT_S:g}",
        future_steps=str(DEFAULT_FUTURE_STEPS),
        torch_functions=listing(TORCH_FUNCTIONS - {"linalg"}),
        linalg_functions=listing(LINALG_FUNCTIONS),
        functional_functions=listing(FUNCTIONAL_FUNCTIONS),
        math_names=listing(MATH_NAMES),
        builtins=listing(SAFE_BUILTIN_NAMES),
        paper_helpers=helper_descriptions(helpers.__all__),
        more_helpers=helper_descriptions([n for n in HELPER_NAMES if n not in helpers.__all__]),
        behaviours=behaviour_descriptions(),
    )


def behaviour_descriptions() -> str:
    """One Markdown entry per behaviour of the vocabulary (:mod:`ctgpp.behaviours`): its name, what
    it means and the window it is judged on."""
    from ctgpp.behaviours import behaviours

    return "\n".join(f"- {name.replace('_', ' ')}: {b.summary} Judged on: {b.window}."
                      for name, b in behaviours().items())


@dataclass(frozen=True)
class Example:
    """One paired example of ``examples.md``: the query and its program."""

    query: str
    code: str


_EXAMPLE = re.compile(r"^### Query: (?P<query>.+?)\n+```python\n(?P<code>.*?)^```", re.M | re.S)


def examples() -> tuple[Example, ...]:
    """The paired examples of the prompt, in order."""
    text = load_template("examples.md")
    return tuple(Example(m["query"].strip(), m["code"]) for m in _EXAMPLE.finditer(text))


def _scene_line(num_vehicles: int | None) -> str:
    if num_vehicles is None:
        return ""
    return (f"The scene has {num_vehicles} vehicles, numbered 0 to {num_vehicles - 1} "
            f"(B = {num_vehicles}).\n\n")


def build_messages(query: str, num_vehicles: int | None = None) -> list[Message]:
    """The chat messages for ``query``: system rules, then API + helpers + examples + the query."""
    if not query.strip():
        raise ValueError("the query is empty")
    user = "\n\n".join([
        _api_text().rstrip(),
        load_template("examples.md").rstrip(),
        _fill(load_template("query.md"), scene=_scene_line(num_vehicles), query=query.strip()).rstrip(),
    ])
    return [{"role": "system", "content": load_template("system.md").rstrip()},
            {"role": "user", "content": user + "\n"}]


# What to change for each kind of refusal, found by a phrase of its message (the first match wins).
# A small model resends the same program when told only what failed.
REPAIR_HINTS: tuple[tuple[str, str], ...] = (
    ("gradient with respect to x is zero",
     "the cost must change when x changes. Compute it from the positions x[..., :2] (or speed "
     "x[..., 2], yaw x[..., 3]) with a smooth penalty that is positive for the trajectories the query "
     "does not want, e.g. torch.relu(gap - target_m) or gap ** 2, never a comparison such as "
     "(gap > target_m).float(), and no .detach(), .item(), argmin/argmax or rounding of x. Check that "
     "every vehicle index you use is below B."),
    ("does not depend differentiably on x",
     "return a tensor computed from x with torch operations (no .detach(), .item(), numpy, Python "
     "floats or torch.tensor(...) built from values of x)."),
    ("forward returned shape",
     "reduce over the time and feature dimensions only, e.g. cost.mean(dim=(-2, -1)) for x of shape "
     "(B, N, T, 6), and keep the vehicle and sample dimensions: (B, N)."),
    ("nan or inf", "avoid division by values that can be 0 (add a small epsilon), sqrt of 0 "
     "(use torch.sqrt(d2 + 1e-6)) and log of values that can be 0 or negative."),
    ("wrote into data_batch", "read data_batch only: compute new tensors (a = b * 2), never assign "
     "into its fields or call in-place methods (add_, clamp_, [...] = ...) on them."),
    ("grows between calls", "do not store x, results or lists on self or in globals inside forward: "
     "compute everything from x and data_batch on each call."),
    ("did not finish within its time limit", "vectorize: no Python loops over time steps, samples "
     "or vehicles; use tensor operations over whole dimensions."),
    ("out of bounds", "a vehicle index is not in the scene: vehicles are numbered 0 to B - 1 "
     "(x.shape[0] = B), and the query's numbers are those indices."),
    ("RuntimeError", "a tensor operation got shapes it cannot combine at that line. x is (B, N, T, 6): "
     "vehicles, samples, time steps, features (x, y, speed, yaw, acceleration, yaw rate); "
     "select_agent_ind(t, i) gives vehicle i's (N, T, ...). Index with slices that keep dimensions, "
     "use unsqueeze/reshape rather than expand, and combine tensors whose dimensions line up."),
    ("without arguments", "give every parameter of __init__ a default value, e.g. "
     "def __init__(self, target_ind=1, speed_mps=10.0)."),
    ("no Python program", "reply with the whole program in one ```python code block."),
    ("changed data_batch.memo", "never assign into what a helper returns: copy it first (lane * 1.0)."),
    ("reads the wrong vehicles", "use exactly the vehicle numbers of the query as indices of x."),
    ("no default value for its parameter", "give every parameter of __init__ the value the query "
     "states as its default, e.g. def __init__(self, acc_limit=2.0)."),
    ("no class deriving from GuidanceLoss", "define exactly one class MyLoss(GuidanceLoss) with "
     "forward(self, x, data_batch, agt_mask=None)."),
)


def repair_hint(error: str) -> str | None:
    """What to change for the refusal ``error`` (:data:`REPAIR_HINTS`), or None when the message
    already says it (the sandbox's refusals name what is allowed)."""
    for phrase, hint in REPAIR_HINTS:
        if phrase in error:
            return hint
    return None


def repair_message(error: str) -> Message:
    """The user message that sends a refusal (sandbox, checks or extraction) back to the model, with
    what to change where the kind of refusal is known."""
    hint = repair_hint(error)
    text = error if hint is None else f"{error}\n\nHow to fix it: {hint}"
    return {"role": "user", "content": _fill(load_template("repair.md"), error=text).rstrip()}


def _prompt_version() -> str:
    digest = hashlib.sha256()
    for name in TEMPLATE_NAMES:
        digest.update(name.encode() + b"\0" + load_template(name).encode() + b"\0")
    digest.update(_api_text().encode())  # the generated parts: helper docs, vocabulary
    return digest.hexdigest()[:16]


PROMPT_VERSION = _prompt_version()
"""16 hex digits of SHA-256 over the templates and the generated helper descriptions."""
