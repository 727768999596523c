"""The package's shape: its layers (a lower one never imports a higher one), stage
modules as leaves (imported by their scripts only), the moved modules' old names."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[2] / "src" / "hwp_tes_systematics"


def imported_modules(path: Path) -> set[str]:
    """Absolute names of the package modules ``path`` imports (relative imports resolved)."""
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = parts[: len(parts) - node.level] if node.level else []
            module = ".".join(base + ([node.module] if node.module else []))
            names.add(module)
            names.update(f"{module}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return names


def test_no_module_imports_a_stage():
    offenders = []
    for path in PACKAGE.rglob("*.py"):
        for name in imported_modules(path):
            if name.startswith("hwp_tes_systematics.stages.") and name.count(".") >= 2:
                offenders.append(f"{path.relative_to(PACKAGE)} imports {name}")
    assert not offenders, "\n".join(offenders)


# The package's layers, lowest first: a module imports only from its own layer or lower
# ones. Subpackages and top-level modules are named by their first component.
LAYERS = (
    ("io", "paths", "seeding", "timing"),  # infrastructure
    ("instrument", "sky", "config"),  # the instrument and its inputs
    ("simulation",),  # TOD, filters, map-making, the map-domain path
    ("figures",),  # plotting helpers and the stages' figures (arrays in, PNG out)
    ("analysis", "diagnose"),  # maps -> requirement; recordings -> diagnosis
    ("stages", "cli", "__main__", "__init__"),  # the workflow's stages and the command line
)
SIBLINGS_APART = (("analysis", "diagnose"),)  # neither imports the other


def layer_of(module: str) -> tuple[int, str]:
    """(layer index, group) of an absolute package module name."""
    group = module.split(".")[1]
    for index, layer in enumerate(LAYERS):
        if group in layer:
            return index, group
    raise AssertionError(f"{module}: in no layer of tests/project/test_package_layout.py LAYERS")


def package_imports():
    """(importing module's group and layer, imported module's group and layer) pairs."""
    for path in PACKAGE.rglob("*.py"):
        me = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        for name in imported_modules(path):
            if name.startswith("hwp_tes_systematics.") and not name.endswith("__version__"):
                yield path.relative_to(PACKAGE), layer_of(me), layer_of(name), name


def test_no_layer_imports_a_higher_one():
    offenders = [
        f"{path} (layer {mine[0]}) imports {name} (layer {theirs[0]})"
        for path, mine, theirs, name in package_imports()
        if theirs[0] > mine[0]
    ]
    assert not offenders, "\n".join(offenders)


def test_analysis_and_diagnosis_stay_apart():
    offenders = [
        f"{path} imports {name}"
        for path, mine, theirs, name in package_imports()
        for pair in SIBLINGS_APART
        if mine[1] != theirs[1] and {mine[1], theirs[1]} == set(pair)
    ]
    assert not offenders, "\n".join(offenders)


def test_the_old_module_names_are_gone():
    """The modules that moved into subpackages after 0.1.0 lost their old names at 0.2.0:
    ``import hwp_tes_systematics.tod`` fails, ``hwp_tes_systematics.simulation.tod`` works."""
    import importlib

    import pytest

    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("hwp_tes_systematics.tod")
    assert importlib.import_module("hwp_tes_systematics.simulation.tod").PairSimulator


def test_the_tests_mirror_the_package_and_each_file_has_a_kind():
    """tests/<folder>/test_*.py: a folder per layer of the package (instrument, sky,
    simulation, analysis, diagnose), then workflow and project; no test file at the top;
    every file conftest.py names as physics, rule or workflow exists."""
    import conftest

    tests = PACKAGE.parents[1] / "tests"
    folders = {p.parent.name for p in tests.rglob("test_*.py")}
    layers = {"instrument", "sky", "simulation", "analysis", "diagnose"}
    assert layers <= {p.name for p in PACKAGE.iterdir() if p.is_dir()}
    assert folders == layers | {"workflow", "project"}
    assert not list(tests.glob("test_*.py"))
    names = {p.name for p in tests.rglob("test_*.py")}
    named = conftest.PHYSICS_FILES | conftest.RULE_FILES | conftest.WORKFLOW_FILES
    assert named <= names, sorted(named - names)
    assert conftest.kind_of_test(Path("test_rules_maps.py"), True) == "rule"
    assert conftest.kind_of_test(Path("test_cli.py"), False) == "unit"
    assert conftest.kind_of_test(Path("test_cli.py"), True) == "workflow"


DEVELOPMENT = PACKAGE.parents[1] / "docs" / "development.md"
MODULE_LINES, FUNCTION_LINES = 500, 100


def size_exceptions() -> dict[str, str]:
    """The manual's table of modules and functions that stay large: {where: why}."""
    text = DEVELOPMENT.read_text().split("### Sizes", 1)[1].split("\n## ", 1)[0]
    rows = [line.split("|") for line in text.splitlines() if line.startswith("| `")]
    return {row[1].strip().strip("`"): row[3].strip() for row in rows}


def test_modules_and_functions_stay_small_unless_the_manual_says_why():
    """A module over MODULE_LINES or a function over FUNCTION_LINES lines is listed, with
    a reason, in docs/development.md ("Sizes"); a listed one still exists and is large."""
    large = set()
    for path in PACKAGE.rglob("*.py"):
        where = path.relative_to(PACKAGE).as_posix()
        text = path.read_text()
        if text.count("\n") > MODULE_LINES:
            large.add(where)
        for node in ast.walk(ast.parse(text)):
            function = isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
            if function and node.end_lineno - node.lineno + 1 >= FUNCTION_LINES:
                large.add(f"{where}::{node.name}")
    listed = size_exceptions()
    assert all(listed.values()), "a listed size exception has no reason"
    assert large - set(listed) == set(), "large and not listed in docs/development.md"
    assert set(listed) - large == set(), "listed in docs/development.md but no longer large"


DIAGNOSIS_STEPS = ("nominal", "locate", "select", "explain", "bound", "report")


def test_a_diagnosis_step_imports_only_earlier_steps():
    """diagnose/<step>/ imports the ground floor, the catalog and earlier steps: never a
    later step, the pipeline, the segments or the test bed."""
    diagnose = "hwp_tes_systematics.diagnose"
    above = {"pipeline", "segments", "simulate", "testbed"}
    offenders = []
    for i, step in enumerate(DIAGNOSIS_STEPS):
        for path in (PACKAGE / "diagnose" / step).glob("*.py"):
            for name in imported_modules(path):
                if not name.startswith(diagnose + "."):
                    continue
                first = name[len(diagnose) + 1 :].split(".")[0]
                later = first in DIAGNOSIS_STEPS[i + 1 :]
                if later or first in above:
                    offenders.append(f"diagnose/{step}/{path.name} imports {name}")
    assert offenders == []
