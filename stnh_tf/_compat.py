"""Old module paths of the flat package, kept importable for one release.

``stnh_tf.training.config`` and the other modules that moved into subpackages
(``docs/layout.md``) are served as aliases of their new modules, with a ``DeprecationWarning``
naming the new path, so ``import stnh_tf.layers`` and ``from stnh_tf.data.pairs import ...`` written
against earlier versions keep working. Hand-written because Python has no module alias; remove it
in the next release.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

# Old module path -> new module path.
MOVED = {}


class _MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports an old path of :data:`MOVED` as the very module object of its new path."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        new = MOVED[spec.name]
        warnings.warn(f"{spec.name} moved to {new}; the old path is removed in the next release.",
                      DeprecationWarning, stacklevel=3)
        module = importlib.import_module(new)
        self._spec = module.__spec__
        return module

    def exec_module(self, module):
        module.__spec__ = self._spec  # the import system set the alias' spec; keep the real one


def install(moved: dict) -> None:
    """Serve every old path of ``moved`` (old -> new module path) as its new module."""
    MOVED.update(moved)
    if not any(isinstance(f, _MovedModuleFinder) for f in sys.meta_path):
        sys.meta_path.append(_MovedModuleFinder())


def delegate(package: str, module: str):
    """A module ``__getattr__`` for ``package`` that replaced the module of the same old name:
    its submodules come first, then the public names of ``module`` (what the old module held), so
    ``from stnh_tf import training; training.train(cfg)`` keeps working."""

    def __getattr__(name):
        if name.startswith("__"):
            raise AttributeError(name)
        if importlib.util.find_spec(f"{package}.{name}") is not None:
            return importlib.import_module(f"{package}.{name}")
        try:
            return getattr(importlib.import_module(module), name)
        except AttributeError:
            raise AttributeError(f"module {package!r} has no attribute {name!r}") from None

    return __getattr__
