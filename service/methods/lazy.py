"""Names imported at their first use: what keeps ``facesynth serve``'s start free of the
method modules (issue 23's cold start).

Each method's model module pulls in SciPy, the geometry kernels and its own dozen modules
(pdm, pose space, shape space, stress blend: ~0.4 s of imports together, measured with
``python -X importtime``), and a server needs at most the one kind it loads. The kind
registry (:mod:`service.methods.kinds`) therefore names its ``train``/``load`` functions as
``"module:attr"`` strings (:class:`LazyFunction`), and a method package's ``__init__``
re-exports its public names with :func:`lazy_exports` instead of importing them.

Examples
--------
>>> load = LazyFunction("service.methods.pdm.model:PdmModel.load")
>>> load.target
'service.methods.pdm.model:PdmModel.load'
"""

from __future__ import annotations

import importlib
import sys
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Callable, Mapping


def resolve(target: str) -> Any:
    """The object named ``"package.module:attr[.attr...]"``, its module imported now."""
    module, _, path = target.partition(":")
    value: Any = importlib.import_module(module)
    for name in path.split(".") if path else ():
        value = getattr(value, name)
    return value


@dataclass(frozen=True)
class LazyFunction:
    """A function named ``"module:attr"`` (attributes may be dotted: ``"m:Class.load"``),
    imported at its first call and called as itself from then on.

    Attributes
    ----------
    target : str   where the function is, e.g. ``"service.methods.pdm.model:train"``
    """

    target: str

    @cached_property
    def function(self) -> Callable[..., Any]:
        """The function itself (its module imported at the first read)."""
        return resolve(self.target)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.function(*args, **kwargs)


def lazy_exports(package: str, exports: Mapping[str, str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` (PEP 562) for ``package``'s ``__init__``: ``exports`` maps a
    public name to the submodule (relative to ``package``) that defines it, imported when
    the name is first read, and bound on the package from then on (as the eager import
    bound it: a function named as its own submodule, correspondence's ``correspond``, then
    replaces the submodule that its import bound there); any other name raises
    ``AttributeError`` (so ``from package import submodule`` still imports the submodule)."""

    def __getattr__(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        setattr(sys.modules[package], name, value)
        return value

    return __getattr__
