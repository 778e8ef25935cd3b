"""The sandbox for generated loss code: hostile programs are refused with their reason, programs in the
paper's style are accepted and pass the checks on a real scene (scene-0103 at step 30)."""

from __future__ import annotations

import textwrap
from collections.abc import Iterator

import pytest
import torch

from ctgpp.guidance import GuidanceBatch, build_guidance_batch
from ctgpp.guidance.rules import SpeedLimit
from ctgpp.language.llm.prompt import examples
from ctgpp.language.sandbox.checks import LossChecker, LossCheckError
from ctgpp.language.sandbox.program import SandboxError, check_source, load_loss_class
from ctgpp.language.sandbox.vocabulary import HELPER_MODULES, safe_builtins
from tests.support.observations import logged_x, real_observation


def loss_program(body: str, head: str = "", init: str = "") -> str:
    """A well-formed loss class whose forward runs ``body`` (indented into the method)."""
    forward = textwrap.indent(textwrap.dedent(body).strip("\n"), " " * 8)
    init_block = ""
    if init:
        init_block = "    def __init__(self):\n        super().__init__()\n" + textwrap.indent(
            textwrap.dedent(init).strip("\n"), " " * 8) + "\n\n"
    return (f"import torch\n{textwrap.dedent(head)}\n\nclass Hostile(GuidanceLoss):\n{init_block}"
            f"    def forward(self, x, data_batch, agt_mask=None):\n{forward}\n")


RETURN = "\nreturn x.sum((2, 3))"

HOSTILE_SOURCE: dict[str, tuple[str, str]] = {
    # name: (program, expected reason)
    "import os": (loss_program(RETURN, head="import os"), "import os is not allowed"),
    "import subprocess": (loss_program(RETURN, head="import subprocess"), "import subprocess is not allowed"),
    "import sys": (loss_program(RETURN, head="import sys"), "import sys is not allowed"),
    "import builtins": (loss_program(RETURN, head="import builtins"), "import builtins is not allowed"),
    "import importlib": (loss_program(RETURN, head="import importlib"), "import importlib is not allowed"),
    "from os import system": (loss_program(RETURN, head="from os import system"), "import from os"),
    "import torch as t": (loss_program("t.load('w.pt')" + RETURN, head="import torch as t"),
                          "import torch as t is not allowed"),
    "from torch import load": (loss_program(RETURN, head="from torch import load"),
                               "from torch import load is not allowed"),
    "__import__": (loss_program("__import__('os').system('ls')" + RETURN), "names starting with '_'"),
    "__builtins__": (loss_program("__builtins__['eval']('1')" + RETURN), "names starting with '_'"),
    "subclasses walk": (loss_program("k = ().__class__.__bases__[0].__subclasses__()" + RETURN),
                        "attributes starting with '_' are not allowed (.__subclasses__)"),
    "x.__class__": (loss_program("k = x.__class__" + RETURN), "attributes starting with '_'"),
    "helper __globals__": (loss_program("g = select_agent_ind.__globals__" + RETURN),
                           "attributes starting with '_' are not allowed (.__globals__)"),
    "lambda dunder": (loss_program("f = lambda: x.__class__\nf()" + RETURN), "attributes starting with '_'"),
    "getattr string": (loss_program("k = getattr(x, '_' + '_class_' + '_')" + RETURN),
                       "getattr is not allowed"),
    "setattr": (loss_program("setattr(self, 'w', 1)" + RETURN), "setattr is not allowed"),
    "delattr": (loss_program("delattr(self, 'training')" + RETURN), "delattr is not allowed"),
    "eval": (loss_program("eval('1 + 1')" + RETURN), "eval is not allowed"),
    "exec": (loss_program("exec('import os')" + RETURN), "exec is not allowed"),
    "compile": (loss_program("c = compile('1', 'f', 'eval')" + RETURN), "compile is not allowed"),
    "open": (loss_program("open('/etc/passwd').read()" + RETURN), "open is not allowed"),
    "with open": (loss_program("with open('/etc/passwd') as fh:\n    pass" + RETURN), "with statements"),
    "globals()": (loss_program("g = globals()" + RETURN), "globals is not allowed"),
    "locals()": (loss_program("g = locals()" + RETURN), "locals is not allowed"),
    "vars()": (loss_program("g = vars()" + RETURN), "vars is not allowed"),
    "breakpoint": (loss_program("breakpoint()" + RETURN), "breakpoint is not allowed"),
    "type 3 args": (loss_program("K = type('K', (), {})" + RETURN), "type is not allowed"),
    "torch.load": (loss_program("w = torch.load('w.pt')" + RETURN), "torch.load is not on the allow list"),
    "torch.save": (loss_program("torch.save(x, 'x.pt')" + RETURN), "torch.save is not on the allow list"),
    "torch.hub.load": (loss_program("m = torch.hub.load('a/b', 'c')" + RETURN), "torch.hub is not on"),
    "torch.jit": (loss_program("f = torch.jit.script" + RETURN), "torch.jit is not on the allow list"),
    "torch.ops": (loss_program("f = torch.ops.aten.add" + RETURN), "torch.ops is not on the allow list"),
    "torch.utils.cpp_extension": (loss_program("torch.utils.cpp_extension.load_inline('m', '')" + RETURN),
                                  "torch.utils is not on the allow list"),
    "torch._C": (loss_program("c = torch._C" + RETURN), "attributes starting with '_' are not allowed (._C)"),
    "torch.classes": (loss_program("c = torch.classes" + RETURN), "torch.classes is not on the allow list"),
    "torch.from_file": (loss_program("t = torch.from_file('/etc/passwd')" + RETURN),
                        "torch.from_file is not"),
    "module as value": (loss_program("t = torch\nt.load('w.pt')" + RETURN), "may only be used as torch.<f"),
    "while True": (loss_program("while True:\n    pass" + RETURN), "while loops are not allowed"),
    "try around a loop": (loss_program("try:\n    k = 1\nexcept Exception:\n    pass" + RETURN),
                          "try/except is not allowed"),
    "huge allocation": (loss_program("z = torch.zeros(10**12)" + RETURN), "integer constant too large"),
    "power tower": (loss_program("z = 10**10**10" + RETURN), "integer constant too large"),
    "recursion bomb": (loss_program("return self.forward(x, data_batch)"), "recursion is not allowed"),
    "second class": (loss_program(RETURN) + "\n\nclass Other(GuidanceLoss):\n    pass\n",
                     "class Other has no forward"),
    "module-level side effect": ("x = torch.zeros(3)\n" + loss_program(RETURN), "module-level Assign"),
    "module-level call": (loss_program(RETURN) + "\nHostile()\n", "module-level Expr"),
    "format dunder string": (loss_program("s = '{0.__class__}'.format(x)" + RETURN),
                             "string constants may not contain '__'"),
    "format method": (loss_program("s = '{0.mro}'.format(x)" + RETURN), ".format is not on the allow list"),
    "generator frame walk": (loss_program("g = (i for i in range(2))\nf = g.gi_frame.f_back.f_globals"
                                          + RETURN),
                             ".gi_frame is not on the allow list"),
    "batch scene numpy": (loss_program("a = data_batch.scene.agents" + RETURN), ".scene is not on the allow"),
    "tensor numpy": (loss_program("a = x.numpy()" + RETURN), ".numpy is not on the allow list"),
    "assign to torch": (loss_program("torch.exp = torch.log" + RETURN), "assigning to torch.exp"),
    "self module method": (loss_program("self.load_state_dict({})" + RETURN),
                           "self.load_state_dict is never"),
    "metaclass": (loss_program(RETURN).replace("(GuidanceLoss)", "(GuidanceLoss, metaclass=M)"),
                  "class keywords"),
    "other base": (loss_program(RETURN).replace("(GuidanceLoss)", "(torch.nn.Module)"),
                   "must derive from GuidanceLoss only"),
    "decorator": (loss_program(RETURN).replace("    def forward", "    @staticmethod\n    def forward"),
                  "decorators are not allowed"),
    "global": (loss_program("global k" + RETURN), "global statements are not allowed"),
    "default with call": (loss_program(RETURN).replace("agt_mask=None", "agt_mask=torch.zeros(3)"),
                          "default values must be literal"),
    "loop over map": (loss_program("for k in map(abs, [1]):\n    pass" + RETURN), "for loops may only run"),
    "math.factorial": (loss_program("k = math.factorial(100000)" + RETURN), "math.factorial is not on"),
    "syntax error": (loss_program("return x.sum(("), "syntax error"),
    "call in an annotation": (loss_program(RETURN).replace("data_batch,", "data_batch: os.system('ls'),"),
                              "Call is not allowed in an annotation"),
    "required argument": (loss_program(RETURN).replace("    def forward", "    def __init__(self, k):\n"
                                                       "        super().__init__()\n\n    def forward"),
                          "give every parameter of __init__ a default value"),
    "dict of dunder keywords": (loss_program("k = max(**{'__class__': 1})" + RETURN),
                                "string constants may not contain '__'"),
}


@pytest.mark.parametrize("name", sorted(HOSTILE_SOURCE))
def test_hostile_program_is_refused(name: str) -> None:
    code, reason = HOSTILE_SOURCE[name]
    with pytest.raises(SandboxError) as refused:
        load_loss_class(code)
    assert reason in str(refused.value)
    assert str(refused.value).startswith(f"line {refused.value.lineno}: ")


def test_at_least_25_hostile_programs() -> None:
    assert len(HOSTILE_SOURCE) + len(HOSTILE_AT_RUN_TIME) >= 25


def test_restricted_builtins() -> None:
    table = safe_builtins()
    for name in ("open", "eval", "exec", "getattr", "globals", "compile", "type", "print", "input", "vars"):
        assert name not in table
    with pytest.raises(ImportError, match="import of os is not allowed"):
        table["__import__"]("os")


# ---- run time: accepted by the sandbox, refused by the checks in the worker process -------------

TIMED_OUT = "did not finish within the time limit of 2 s"
HOSTILE_AT_RUN_TIME: dict[str, tuple[str, str]] = {
    "allocation of 40 GB": (loss_program("z = torch.zeros(100000, 100000)" + RETURN),
                            "can't allocate memory"),
    "endless nested loops": (loss_program("k = 0\nfor i in range(10000000):\n    for j in range(10000000):\n"
                                          "        k = k + 1" + RETURN), TIMED_OUT),
    "list that grows while iterated": (loss_program("items = [1]\nfor k in items:\n    items.append(k)"
                                                    + RETURN), TIMED_OUT),
    "mutual recursion": (
        "import torch\n\ndef ping(n):\n    return pong(n + 1)\n\ndef pong(n):\n    return ping(n + 1)\n\n"
        "class Hostile(GuidanceLoss):\n    def forward(self, x, data_batch, agt_mask=None):\n"
        "        return ping(0) + x.sum((2, 3))\n", "RecursionError"),
    "wrong shape": (loss_program("return x.sum()"), "forward returned shape ()"),
    "nan cost": (loss_program("return x.sum((2, 3)) * float('nan')"), "non-finite values"),
    "detached cost": (loss_program("return x.detach().sum((2, 3))"), "does not depend differentiably"),
    "not a tensor": (loss_program("return 1.0"), "must return a torch tensor"),
    "constant cost": (loss_program("return x.sum((2, 3)) * 0.0"), "gradient with respect to x is zero"),
    "raises": (loss_program("raise ValueError('boom')"), "ValueError: boom (at line 6 of the program)"),
}


@pytest.fixture(scope="module")
def checker() -> Iterator[LossChecker]:
    with LossChecker() as worker:
        yield worker


@pytest.fixture(scope="module")
def batch() -> GuidanceBatch:
    return build_guidance_batch(real_observation())


@pytest.fixture(scope="module")
def x() -> torch.Tensor:
    return logged_x(real_observation())[0]


@pytest.mark.parametrize("name", sorted(HOSTILE_AT_RUN_TIME))
def test_refused_at_run_time(name: str, checker: LossChecker, batch: GuidanceBatch, x: torch.Tensor) -> None:
    code, reason = HOSTILE_AT_RUN_TIME[name]
    cls = load_loss_class(code)
    with pytest.raises(LossCheckError) as refused:
        checker.check(cls, batch, x, time_limit_s=2.0)
    assert reason in str(refused.value)


# ---- accepted: programs in the paper's style pass the sandbox and the checks --------------------

PAPER_STYLE = {
    "comprehension over vehicles, math decay": '''
import math

import torch


class NoFasterThanNow(GuidanceLoss):
    """Vehicles 0, 1 and 2 should not drive faster than they do now; near-term steps weigh more."""

    def __init__(self, vehicles=(0, 1, 2), tau_s=1.5):
        super().__init__()
        self.vehicles = list(vehicles)
        self.tau_s = tau_s

    def forward(self, x, data_batch, agt_mask=None):
        weights = torch.tensor([math.exp(-t * data_batch.dt_s / self.tau_s) for t in range(x.shape[2])])
        rows = [torch.relu(x[i, :, :, 2] - data_batch.speed[i]) for i in self.vehicles]
        per_vehicle = torch.stack([(r * weights).sum(-1) / weights.sum() for r in rows])  # (V, N)
        cost = torch.zeros(x.shape[0], x.shape[1])
        for k, i in enumerate(self.vehicles):
            cost[i] = per_vehicle[k]
        return cost
''',
    "module function, lambda, zip, sum": '''
import torch
from ctgpp.guidance.helpers import transform_coord_agents_to_world

WEIGHT = 2.0


def soft_min(values, temperature=1.0):
    return -temperature * torch.logsumexp(-values / temperature, dim=-1)


class MeetInPairs(GuidanceLoss):
    couples_agents = True

    def __init__(self, first=(0, 2), second=(1, 3)):
        super().__init__()
        self.pairs = list(zip(first, second))

    def forward(self, x, data_batch, agt_mask=None):
        pos, _ = transform_coord_agents_to_world(x[..., :2], x[..., 3:4], data_batch)
        dist = lambda a, b: torch.linalg.norm(pos[a] - pos[b], dim=-1)  # noqa: E731
        return WEIGHT * sum([soft_min(dist(a, b)) for a, b in self.pairs])
''',
}


@pytest.mark.parametrize("name", sorted(PAPER_STYLE))
def test_paper_style_program_is_accepted(name: str, checker: LossChecker, batch: GuidanceBatch,
                                         x: torch.Tensor) -> None:
    code = PAPER_STYLE[name]
    cls = load_loss_class(code)
    report = checker.check(cls, batch, x)
    assert report.output_shape in ((x.shape[0], x.shape[1]), (x.shape[1],)) and report.grad_abs_sum > 0
    assert cls._ctgpp_source == code
    cost = cls()(x, batch)  # also runs in this process, with the restricted builtins
    assert torch.isfinite(cost).all()


def test_prompt_examples_cover_the_paper_and_map_queries() -> None:
    queries = " | ".join(ex.query for ex in examples())
    for words in ("collide", "acceleration below", "left side", "distance", "slower than",
                  "follow their lanes", "reach", "change to the left lane",
                  "turn right at the next intersection"):
        assert words in queries
    assert len(examples()) >= 9


@pytest.mark.parametrize("index", range(len(examples())))
def test_prompt_example_passes_the_checks(index: int, checker: LossChecker, batch: GuidanceBatch,
                                          x: torch.Tensor) -> None:
    example = examples()[index]
    check_source(example.code)
    cls = load_loss_class(example.code)
    if "left lane" in example.query:  # scene-0103 has no lane to anyone's left: nothing to steer towards
        with pytest.raises(LossCheckError, match="zero for every probe"):
            checker.check(cls, batch, x)
        obs = real_observation("scene-0061")  # vehicle 2 has a lane to its left there
        batch, x = build_guidance_batch(obs), logged_x(obs)[0]
    report = checker.check(cls, batch, x)
    assert report.grad_abs_sum > 0


def test_library_class_is_checked_by_reference(checker: LossChecker, batch: GuidanceBatch,
                                               x: torch.Tensor) -> None:
    report = checker.check(SpeedLimit, batch, x * 3.0)
    assert report.output_shape == tuple(x.shape[:2])


def test_worker_survives_a_time_limit(checker: LossChecker, batch: GuidanceBatch, x: torch.Tensor) -> None:
    slow = load_loss_class(HOSTILE_AT_RUN_TIME["endless nested loops"][0])
    with pytest.raises(LossCheckError, match="did not finish"):
        checker.check(slow, batch, x, time_limit_s=1.0)
    assert checker.check(load_loss_class(PAPER_STYLE["module function, lambda, zip, sum"]), batch, x)


def test_an_import_of_a_helper_that_does_not_exist_lists_the_helpers_closest_first() -> None:
    """What the 1.5B model sent three rounds running: a helper that does not exist. The refusal names
    the module's helpers so that the next round can use one."""
    program = loss_program(RETURN, head="from ctgpp.guidance.helpers import get_right_lane")
    with pytest.raises(SandboxError) as refused:
        check_source(program)
    message = str(refused.value)
    assert "ctgpp.guidance.helpers has no helper get_right_lane" in message
    listed = message.split("the closest first: ")[1].split(". ")[0].split(", ")
    assert listed[0] == "get_right_lane_projection"
    assert set(listed) == set(HELPER_MODULES["ctgpp.guidance.helpers"])
    with pytest.raises(SandboxError, match="the helper modules: ctgpp.guidance, "):
        check_source(loss_program(RETURN, head="from ctgpp.guide import select_agent_ind"))


def test_an_import_from_the_wrong_helper_module_names_the_right_one() -> None:
    """What the 1.5B model sent in all six rounds of "vehicle 3 should take a left at the next
    intersection": a lane helper imported from ctgpp.guidance.helpers. The refusal says where it is."""
    program = loss_program(RETURN, head="from ctgpp.guidance.helpers import get_turn_lane_projection")
    with pytest.raises(SandboxError) as refused:
        check_source(program)
    assert ("it is in ctgpp.guidance.lane_helpers: write `from ctgpp.guidance.lane_helpers import "
            "get_turn_lane_projection`") in str(refused.value)
    right = "from ctgpp.guidance.lane_helpers import get_turn_lane_projection"
    assert check_source(loss_program(RETURN, head=right))
