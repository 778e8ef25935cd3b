"""Restricted unpickling of user scene files (DESIGN.md, Files and safety).

A pickle is a small program: every global it names is imported and may be called while loading, so
``pickle.load`` on a file from elsewhere runs whatever code the file asks for (``os.system``,
``builtins.eval``, ...). :func:`safe_load` resolves only an allow list of globals that rebuild plain
data: numpy arrays, dtypes and scalars, ``collections.defaultdict``/``OrderedDict`` (ScenarioNet's
``metadata.number_summary`` holds a ``defaultdict(int)``), ``_codecs.encode`` (how protocol 2 stores
bytes) and the builtin value types. Calling any of these with data arguments cannot reach the file
system, processes or the interpreter. Everything else raises :class:`UnsafePickleError` before
anything is called.
"""

from __future__ import annotations

import importlib
import io
import pickle
import struct
from pathlib import Path

# (module, name) pairs a scene pickle may reference. numpy 1.x writes ``numpy.core.*``, numpy 2.x
# ``numpy._core.*``; both are accepted and resolved against the installed numpy.
_NUMPY_GLOBALS = {
    ("multiarray", "_reconstruct"),
    ("multiarray", "scalar"),
    ("numeric", "_frombuffer"),  # arrays pickled with protocol 5
}
_ALLOWED = {
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("collections", "defaultdict"),
    ("collections", "OrderedDict"),
    ("_codecs", "encode"),  # protocol <= 2 writes bytes (array buffers) as encode(str, "latin1")
    *(
        ("builtins", name)
        for name in (
            "int",
            "float",
            "complex",
            "bool",
            "str",
            "bytes",
            "bytearray",
            "list",
            "tuple",
            "dict",
            "set",
            "frozenset",
        )
    ),
}

_PY2_NAMES = {"long": "int", "unicode": "str"}


class UnsafePickleError(ValueError):
    """A pickle references a global outside the allow list; nothing from it was executed."""


class CorruptPickleError(ValueError):
    """A file is not a complete pickle (truncated, damaged or another format)."""


# what unpickling damaged data raises (besides UnsafePickleError): truncation gives EOFError or
# UnpicklingError, damaged opcodes and arguments the others
_BROKEN = (
    pickle.UnpicklingError, EOFError, ValueError, TypeError, IndexError, KeyError, AttributeError,
    struct.error, MemoryError, OverflowError, UnicodeDecodeError,
)


def _numpy_core_module(submodule: str) -> str:
    """The installed numpy's module for ``numpy.core.<submodule>`` / ``numpy._core.<submodule>``."""
    try:
        importlib.import_module(f"numpy._core.{submodule}")
        return f"numpy._core.{submodule}"
    except ImportError:  # numpy < 2
        return f"numpy.core.{submodule}"


def is_allowed_global(module: str, name: str) -> bool:
    """Whether a pickle may reference ``module.name``."""
    if (module, name) in _ALLOWED:
        return True
    for prefix in ("numpy.core.", "numpy._core."):
        if module.startswith(prefix) and (module[len(prefix) :], name) in _NUMPY_GLOBALS:
            return True
    return False


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that resolves only allow-listed globals (see the module docstring)."""

    def __init__(self, file: io.BufferedIOBase, source_name: str) -> None:
        super().__init__(file)
        self._source_name = source_name

    def find_class(self, module: str, name: str) -> object:
        if module == "__builtin__":  # protocol <= 2 spells builtins the Python 2 way
            module, name = "builtins", _PY2_NAMES.get(name, name)
        if not is_allowed_global(module, name):
            raise UnsafePickleError(
                f"refusing to load {self._source_name}: it references {module}.{name}, which is not allowed"
            )
        for prefix in ("numpy.core.", "numpy._core."):
            if module.startswith(prefix):
                module = _numpy_core_module(module[len(prefix) :])
        return super().find_class(module, name)

    def persistent_load(self, pid: object) -> object:
        raise UnsafePickleError(f"refusing to load {self._source_name}: it uses persistent ids")


def safe_loads(data: bytes, source_name: str = "<bytes>") -> object:
    """Unpickle ``data`` with :class:`RestrictedUnpickler`. Raises :class:`UnsafePickleError`, and
    :class:`CorruptPickleError` naming ``source_name`` for data that is not a complete pickle."""
    try:
        return RestrictedUnpickler(io.BytesIO(data), source_name).load()
    except UnsafePickleError:
        raise
    except _BROKEN as err:
        reason = str(err) or type(err).__name__
        raise CorruptPickleError(
            f"{source_name} is not a readable pickle (truncated or damaged: {reason})"
        ) from None


def safe_load(path: Path | str) -> object:
    """Load a pickle file that may come from anywhere (a ScenarioNet scenario, say).

    Raises :class:`UnsafePickleError` when the file references a global that could run code.
    """
    path = Path(path)
    return safe_loads(path.read_bytes(), str(path))
