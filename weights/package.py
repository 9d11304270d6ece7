"""Modules of the Python package (python/drivesim) that the tools here share with it, loaded by
path, so that the tools run without the package installed: one implementation of each."""

import importlib.util
import os
import sys
import types

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "python", "drivesim")
# The package's top-level modules are loaded as members of this stand-in for it, so that their
# relative imports (`from . import _checks`) find their neighbours in ROOT; its __init__.py,
# which needs the compiled extension, is never run.
PACKAGE = "drivesim_tools"


def _stand_in():
    if PACKAGE not in sys.modules:
        package = types.ModuleType(PACKAGE)
        package.__path__ = [ROOT]
        sys.modules[PACKAGE] = package


def load(relative):
    """The module at `python/drivesim/RELATIVE` (e.g. "carracing/view.py"), loaded by path."""
    stem = relative.removesuffix(".py")
    if "/" in stem:  # a subpackage's module: loaded on its own (it has no relative imports)
        name = "drivesim_" + stem.replace("/", "_")
    else:
        _stand_in()
        name = f"{PACKAGE}.{stem}"
    spec = importlib.util.spec_from_file_location(name, os.path.join(ROOT, relative))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
