"""Modules of the Python package (python/drivesim) that the tools here share with it, loaded by
path, so that the tools run without the package installed: one implementation of each."""

import importlib.util
import os

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "python", "drivesim")


def load(relative):
    """The module at `python/drivesim/RELATIVE` (e.g. "carracing/view.py"), loaded by path."""
    name = "drivesim_" + relative.replace("/", "_").removesuffix(".py")
    spec = importlib.util.spec_from_file_location(name, os.path.join(ROOT, relative))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
