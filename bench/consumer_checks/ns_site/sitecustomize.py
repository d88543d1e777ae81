"""ONLY for `ns-train` in the nerfstudio scratch venv of `python -m bench.consumers`, on its
PYTHONPATH there: where the only torchvision installable is a CUDA build (its ops fail to
register on a CPU torch, so `import torchvision` raises), every `torchvision.*` module is a stub
whose functions and classes raise when used. ns-train then gets through its imports and its data
setup, and stops where a model first uses torchvision (nerfacto's LPIPS metric, whose weights it
would also download)."""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import sys
import types


class _Stub(types.ModuleType):
    def __getattr__(self, name: str) -> object:
        if name.startswith("__"):
            raise AttributeError(name)
        why = self.__dict__.get("_why", "")

        def unavailable(*_: object, **__: object) -> None:
            raise RuntimeError(f"{self.__name__}.{name}: torchvision is stubbed in this check ({why})")

        return unavailable


class _Finder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def __init__(self, why: str) -> None:
        self.why = why

    def find_spec(
        self, name: str, path: object = None, target: object = None
    ) -> importlib.machinery.ModuleSpec | None:
        if name == "torchvision" or name.startswith("torchvision."):
            return importlib.machinery.ModuleSpec(name, self, is_package=True)
        return None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        mod = _Stub(spec.name)
        mod._why = self.why  # type: ignore[attr-defined]
        mod.__path__ = []  # type: ignore[attr-defined]
        return mod

    def exec_module(self, module: types.ModuleType) -> None:
        return None


try:
    import torchvision  # noqa: F401
except RuntimeError as exc:
    for key in [k for k in sys.modules if k == "torchvision" or k.startswith("torchvision.")]:
        del sys.modules[key]
    sys.meta_path.insert(0, _Finder(str(exc)))
    print(
        f"(stubbed here only: torchvision, whose CUDA build fails on this CPU torch: {exc})", file=sys.stderr
    )
