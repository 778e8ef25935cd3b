"""The vocabulary generated loss code may use: allow lists of names, attributes and imports.

Everything here is an *allow* list: a ``torch`` function, a tensor method, a builtin or an import that
is not listed is refused by :func:`ctgpp.language.sandbox.program.check_source`. The lists are meant to be
just sufficient for losses in the paper's style (tensor math, the helpers, decaying weights, loops
over vehicles) and to contain nothing that reaches files, processes, the network, frames, code
objects or compiled extensions.
"""

from __future__ import annotations

import math
from types import MappingProxyType
from typing import Any, ClassVar, Optional

import torch
import torch.nn.functional as F  # noqa: N812  (the conventional name generated code uses)
from torch import Tensor

from ctgpp.guidance import helpers, lane_helpers
from ctgpp.guidance.base import GuidanceLoss

TORCH_FUNCTIONS = frozenset(
    """abs acos amax amin arange argmax argmin asin atan atan2 bool broadcast_to cat cdist ceil clamp
    clamp_max clamp_min clip cos cosh cumprod cumsum deg2rad diff einsum exp expm1 eye flatten float float32
    float64 floor fmod full full_like gather hypot inf isfinite linspace log log1p logical_and
    logical_not logical_or logsumexp long matmul max maximum mean min minimum norm ones ones_like
    permute pi pow prod rad2deg relu remainder reshape round sigmoid sign sin sinh softmax sort sqrt
    square squeeze stack std sum tan tanh tensor Tensor topk transpose unsqueeze var where zeros
    zeros_like linalg""".split()
)
"""``torch.<name>``: math on tensors, constructors, dtypes. ``linalg`` only as ``torch.linalg.<f>``."""

LINALG_FUNCTIONS = frozenset({"norm", "vector_norm"})
FUNCTIONAL_FUNCTIONS = frozenset(
    """relu softplus smooth_l1_loss huber_loss mse_loss l1_loss normalize leaky_relu elu gelu silu
    softmax log_softmax""".split()
)
MATH_NAMES = frozenset(
    """pi e tau inf exp log log2 log10 sqrt cos sin tan acos asin atan atan2 cosh sinh tanh hypot
    radians degrees floor ceil fabs copysign isfinite isinf isnan""".split()
)
"""``math.<name>`` (no ``factorial``/``comb``/``prod``: they can run for minutes on big integers)."""

MODULE_ATTRIBUTES: MappingProxyType[str, frozenset[str]] = MappingProxyType(
    {"torch": TORCH_FUNCTIONS, "math": MATH_NAMES, "F": FUNCTIONAL_FUNCTIONS,
     "torch.linalg": LINALG_FUNCTIONS}
)
"""Module name as written in the code -> the attributes it may be used with."""

TENSOR_ATTRIBUTES = frozenset(
    """abs all amax amin any argmax argmin atan2 bool clamp clamp_max clamp_min clip clone cos cumsum
    detach device diff dim dtype exp expand expand_as flatten flip float gather indices isfinite item
    log log1p long masked_fill max mean min ndim neg new_full new_ones new_tensor new_zeros norm numel
    permute pow prod relu repeat reshape roll shape sigmoid sign sin size softmax sort sqrt square
    squeeze std sum t tanh to topk transpose unsqueeze values view view_as T append forward""".split()
)
"""Attributes allowed on any value that is not a module or ``self``: tensor methods and properties,
``.values``/``.indices`` of ``max``/``min`` results, ``list.append`` and ``.forward`` of the program's
own helper losses. No ``numpy``, ``tolist``,
``data``, ``grad``, in-place methods (``add_``) or anything reaching frames and code objects."""

BATCH_ATTRIBUTES = frozenset(
    """pose speed extent num_vehicles num_obstacles obstacles_xy obstacles_yaw obstacles_extent
    obstacles_valid dt_s future_steps""".split()
)
"""Fields of :class:`~ctgpp.guidance.context.GuidanceBatch` loss code may read directly (tensors and
numbers; the scene, its numpy arrays and the lane memo stay behind the helpers)."""

HELPER_NAMES = tuple(helpers.__all__) + tuple(lane_helpers.__all__) + ("lane_offset",)

HELPER_MODULES: MappingProxyType[str, frozenset[str]] = MappingProxyType(
    {
        "ctgpp.guidance.helpers": frozenset(helpers.__all__),
        "ctgpp.guidance.lane_helpers": frozenset(lane_helpers.__all__) | {"lane_offset"},
        "ctgpp.guidance.base": frozenset({"GuidanceLoss"}),
        "ctgpp.guidance": frozenset({"GuidanceLoss"}),
        "torch": frozenset({"Tensor"}),
        "typing": frozenset({"Any", "Optional", "ClassVar"}),
        "__future__": frozenset({"annotations"}),
    }
)
"""``from MODULE import NAME`` statements allowed (they bind names that are pre-bound anyway)."""

PLAIN_IMPORTS: MappingProxyType[str, str | None] = MappingProxyType(
    {"torch": None, "math": None, "torch.nn.functional": "F"}
)
"""``import MODULE`` (alias None) or ``import MODULE as ALIAS`` allowed; no other aliases."""

SAFE_BUILTIN_NAMES = (
    "abs all any bool enumerate float int isinstance len list max min range reversed round sorted sum "
    "super tuple zip ValueError IndexError"
).split()

FORBIDDEN_CALLS = frozenset(
    """getattr setattr delattr hasattr eval exec compile open globals locals vars input breakpoint help
    dir type object memoryview id print exit quit classmethod staticmethod property format repr
    bytearray bytes iter next""".split()
)
"""Names refused with a specific message (they are absent from the namespace anyway)."""

MAX_INT_CONSTANT = 10**8
"""Integer constants (after folding ``a ** b``, ``a * b`` of literals) above this are refused."""


def prebound_names() -> dict[str, Any]:
    """The names generated code sees without importing: modules, helpers, the base class, typing."""
    names: dict[str, Any] = {"torch": torch, "math": math, "F": F, "Tensor": Tensor}
    names.update({"Any": Any, "Optional": Optional, "ClassVar": ClassVar, "GuidanceLoss": GuidanceLoss})
    for name in helpers.__all__:
        names[name] = getattr(helpers, name)
    for name in (*lane_helpers.__all__, "lane_offset"):
        names[name] = getattr(lane_helpers, name)
    return names


LIBRARY_IMPORT_ROOTS = frozenset({"torch", "numpy", "math"})


def _library_import(
    name: str, globals: Any = None, locals: Any = None, fromlist: Any = (), level: int = 0
) -> Any:
    """``__import__`` for C code of torch that imports its own modules while a generated function is
    the current frame (``torch.tensor`` does); anything outside torch/numpy/math is refused."""
    import builtins

    if level != 0 or name.split(".")[0] not in LIBRARY_IMPORT_ROOTS:
        raise ImportError(f"import of {name} is not allowed in generated code")
    return builtins.__import__(name, globals, locals, fromlist, level)


def safe_builtins() -> dict[str, Any]:
    """The ``__builtins__`` of generated code: the listed builtins, ``__build_class__`` (which the
    ``class`` statement needs) and an ``__import__`` limited to torch/numpy/math (which torch's C code
    needs); no generated code can name these two, since names starting with ``_`` are refused."""
    import builtins

    table: dict[str, Any] = {name: getattr(builtins, name) for name in SAFE_BUILTIN_NAMES}
    table["__build_class__"] = builtins.__build_class__
    table["__import__"] = _library_import
    return table
