"""One-file plugins: a package whose every module registers something when imported (the
estimators in control/estimators/, the task verbs in tecdard/verbs/)."""
from __future__ import annotations

import importlib
import pkgutil


def new_modules(package_path, package_name: str, seen: set[str]):
    """Import each module on `package_path` not imported yet (in name order; `_private` ones
    skipped), recording it in `seen`; yields the modules."""
    for info in sorted(pkgutil.iter_modules(package_path), key=lambda m: m.name):
        if info.name.startswith("_") or info.name in seen:
            continue
        module = importlib.import_module(f"{package_name}.{info.name}")
        seen.add(info.name)
        yield module
