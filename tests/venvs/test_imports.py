"""Every third-party module a Python file imports is named by a requirement list of each
virtualenv that runs it: the scan that catches a missing install step before a fresh machine does.

`./test` makes one virtualenv per list in this folder (and the package's own from its wheel);
VENVS below says what each one runs, as `./test` runs it. From those files the scan follows every
import (plain, `from`, inside functions, `pytest.importorskip`) through the checkout's own modules
(the package's where the virtualenv has it installed), and checks that each third-party
module it reaches is provided by that virtualenv's requirements, unless the virtualenv is meant
to go without it (its tests skip themselves: `may_skip`).

    python -m pytest tests/venvs/test_imports.py     # stdlib only: any Python >= 3.10 with pytest
"""

import ast
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "python" / "drivesim"
# The checkout's other package, run from its folder (`weights/tool`, ./test): the PyTorch reference.
REFERENCE = "drivesim_reference"

# Each virtualenv ./test makes: its requirement lists (files; `pyproject:EXTRA` is the package's
# dependencies plus those extras (`pyproject:A,B`), what installing the wheel as `wheel[A,B]`
# brings), the files it
# runs (globs from the root), and the third-party modules whose absence there is intended.
VENVS = {
    "data": {
        "requirements": ["tests/venvs/data.txt"],
        "runs": ["tests/venvs/test_imports.py", "tests/test_layout.py"],
        "may_skip": set(),
    },
    "torch": {
        "requirements": ["tests/venvs/torch.txt", "pyproject:carracing,comma"],
        "runs": ["weights/tests/*.py", "weights/drivesim_reference/fixtures.py"],
        "may_skip": set(),
    },
    "package": {
        "requirements": ["pyproject:test", "tests/venvs/package.txt"],
        "runs": ["python/tests/*.py"],
        # drivesim.carracing.sb3 imports stable-baselines3 (and its PyTorch) only when it trains or scores.
        "may_skip": {"torch", "stable_baselines3"},
    },
    # The machine's python3 drives the play page in Chromium: the standard library alone.
    "host": {"requirements": [], "runs": ["tests/browser/*.py"], "may_skip": set()},
    # `weights/tool setup`'s weights/.venv, which runs every tool in weights/.
    "tool": {
        "requirements": ["weights/requirements.txt", "weights/requirements-data.txt", "pyproject:carracing,comma"],
        "runs": ["weights/drivesim_reference/*.py", "weights/tests/*.py"],
        "may_skip": set(),
    },
}

# Distributions (with an extra where it matters) whose modules are not their own name.
PROVIDES = {
    "pillow": {"PIL"},
    "gymnasium[box2d]": {"gymnasium", "Box2D", "pygame"},
    "box2d-py": {"Box2D"},
    "maturin": set(),
}
# Installed as the wheel under test, not from a requirement list.
WHEEL_MODULES = {"drivesim"}


def normalize(name):
    return re.sub(r"[-_.]+", "-", name).lower()


def modules_of(requirement):
    """The top-level modules a requirement line (`name[extras] >= x ; marker`) provides."""
    match = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(\[[^\]]*\])?", requirement)
    if not match:
        raise ValueError(f"not a requirement: {requirement!r}")
    name = normalize(match.group(1))
    modules = set(PROVIDES.get(name, {name.replace("-", "_")}))
    for extra in (match.group(2) or "[]")[1:-1].split(","):
        if extra.strip():
            modules |= PROVIDES.get(f"{name}[{extra.strip()}]", set())
    return modules


def read_requirements(path):
    """The modules a requirements file provides, following `-r` relative to the file."""
    modules = set()
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith(("-r ", "--requirement ")):
            modules |= read_requirements((path.parent / line.split(None, 1)[1]).resolve())
        elif line.startswith("-"):
            raise ValueError(f"{path}: option lines other than -r are not understood here: {line!r}")
        else:
            modules |= modules_of(line)
    return modules


def read_pyproject(extras):
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        pytest.skip("reading pyproject.toml needs Python >= 3.11 (tomllib)")
    project = tomllib.loads((ROOT / "python" / "pyproject.toml").read_text())["project"]
    modules = set()
    requirements = list(project["dependencies"])
    for extra in extras.split(","):
        requirements += project["optional-dependencies"][extra]
    for requirement in requirements:
        modules |= modules_of(requirement)
    return modules


def provided(venv):
    modules = set(WHEEL_MODULES) if any(r.startswith("pyproject:") for r in VENVS[venv]["requirements"]) else set()
    for source in VENVS[venv]["requirements"]:
        if source.startswith("pyproject:"):
            modules |= read_pyproject(source.split(":", 1)[1])
        else:
            modules |= read_requirements(ROOT / source)
    return modules


def imports_of(path):
    """(module, level) of every import in the file, `pytest.importorskip("m")` included."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, 0) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            found.append((node.module or "", node.level))
            if node.level and not node.module:  # `from . import a, b`
                found += [(alias.name, node.level) for alias in node.names]
            elif not node.level:  # `from package import module`: the names may be modules
                found += [(f"{node.module}.{alias.name}", 0) for alias in node.names]
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.args
              and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            owner = node.func.value.id if isinstance(node.func.value, ast.Name) else None
            if (owner, node.func.attr) == ("pytest", "importorskip"):
                found.append((node.args[0].value, 0))
    return found


def package_file(dotted):
    """python/drivesim's file for `drivesim.a.b`, or None (the compiled extension, a name in a module)."""
    parts = dotted.split(".")[1:]
    while parts:
        base = PACKAGE.joinpath(*parts)
        for candidate in (base.with_suffix(".py"), base / "__init__.py"):
            if candidate.is_file():
                return candidate
        parts.pop()  # `from drivesim.carracing import view`'s module is drivesim.carracing
    return PACKAGE / "__init__.py"


def third_party(venv):
    """{module: [the files that import it]} for every third-party module `venv` reaches."""
    package_installed = "drivesim" in provided(venv)
    stdlib = set(sys.stdlib_module_names)
    files = sorted({p for pattern in VENVS[venv]["runs"] for p in ROOT.glob(pattern)})
    assert files, f"{venv}: its runs match no file"
    seen, queue, reached = set(), list(files), {}
    while queue:
        path = queue.pop()
        if path in seen:
            continue
        seen.add(path)
        for module, level in imports_of(path):
            if level:  # relative: inside python/drivesim
                base = path.parent
                for _ in range(level - 1):
                    base = base.parent
                queue.append(package_file(".".join(("drivesim",) + base.relative_to(PACKAGE).parts
                                                   + ((module,) if module else ()))))
                continue
            top = module.split(".")[0]
            if top in stdlib or top == "__future__":
                continue
            if top == REFERENCE:  # weights/drivesim_reference: its module, or its __init__.py
                parts = module.split(".")[1:]
                target = ROOT.joinpath("weights", REFERENCE, *parts).with_suffix(".py") if parts else None
                queue.append(target if target and target.is_file() else ROOT / "weights" / REFERENCE / "__init__.py")
            elif (path.parent / f"{top}.py").is_file():  # a neighbour: a test's helper, conftest.py
                queue.append(path.parent / f"{top}.py")
            elif top == "drivesim" and package_installed:
                queue.append(package_file(module))
                reached.setdefault(top, []).append(path)
            else:
                reached.setdefault(top, []).append(path)
    return reached


@pytest.mark.parametrize("venv", sorted(VENVS))
def test_every_import_is_installed(venv):
    if sys.version_info < (3, 10):
        pytest.skip("needs sys.stdlib_module_names (Python >= 3.10)")
    have = provided(venv) | VENVS[venv]["may_skip"]
    missing = {m: sorted({str(p.relative_to(ROOT)) for p in paths})
               for m, paths in third_party(venv).items() if m not in have}
    assert not missing, (f"the {venv} virtualenv ({', '.join(VENVS[venv]['requirements'])}) lacks modules its "
                         f"files import: {missing}; name each in a requirement list (PROVIDES maps a distribution "
                         f"whose module has another name)")


def test_the_scan_sees_what_a_venv_lacks(tmp_path, monkeypatch):
    """The scan itself: a file importing an unlisted module through a neighbour is reported."""
    (tmp_path / "tool.py").write_text("import helper\n")
    (tmp_path / "helper.py").write_text("def f():\n    from gymnasium.envs.box2d import car_racing\n")
    (tmp_path / "needs.txt").write_text("numpy\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setitem(VENVS, "probe", {"requirements": ["needs.txt"], "runs": ["tool.py"], "may_skip": set()})
    assert set(third_party("probe")) == {"gymnasium"}
    with pytest.raises(AssertionError, match="gymnasium"):
        test_every_import_is_installed("probe")
    (tmp_path / "needs.txt").write_text("numpy\ngymnasium[box2d]\n")
    test_every_import_is_installed("probe")


def test_requirement_lines_name_their_modules():
    assert modules_of("gymnasium[box2d]>=1.0") == {"gymnasium", "Box2D", "pygame"}
    assert modules_of("pillow") == {"PIL"}
    assert modules_of("maturin>=1.9,<2") == set()
    assert modules_of("Safe_Tensors==0.8.0 ; python_version >= '3.9'") == {"safe_tensors"}
