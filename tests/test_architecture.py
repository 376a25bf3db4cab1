"""The shape of the package (docs/architecture.md): imports point down the layers, nobody imports another
module's private names, and no file or function grows past what a reader can hold."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "cylsfm"

#: The layers, lowest first. A module may import its own package and anything in a lower layer; never
#: a higher layer, never sideways into another package of its own layer.
LAYERS: list[set[str]] = [
    {"errors", "_version"},  # base: the error type and shape guard, the version (leaves)
    {"atomic", "runtime"},  # base: atomic writes, device choice and progress bars
    {"geometry"},
    {"nn", "losses"},
    {"data"},
    {"model"},
    {"train", "evaluate", "export"},
    {"predict", "odometry", "inference"},
    {"demo", "rounds"},  # rounds: training over the odometry of its own rides
    {"cli"},
    {"__init__"},  # the package root: the public names, importing from below
]
LEVEL = {name: level for level, names in enumerate(LAYERS) for name in names}

MAX_FILE_LINES = 500
MAX_FUNCTION_LINES = 80
#: Functions allowed to be longer, each with its reason.
LONG_FUNCTIONS: dict[str, str] = {}


def _modules() -> list[Path]:
    return sorted(p for p in SRC.rglob("*.py"))


def _top(path: Path, root: Path = SRC) -> str:
    """The top-level unit of a source file: ``geometry`` for ``geometry/pose.py``, ``cli`` for ``cli.py``."""
    rel = path.relative_to(root)
    return rel.parts[0].removesuffix(".py")


def _imports(path: Path, root: Path = SRC) -> list[tuple[str, list[str], int]]:
    """``(absolute module, imported names, line)`` of every ``cylsfm`` import in ``path``."""
    tree = ast.parse(path.read_text())
    rel = path.relative_to(root).with_suffix("")
    package = ["cylsfm", *rel.parts[:-1]]  # the package a relative import starts from
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if module.startswith("cylsfm"):
                out.append((module, [a.name for a in node.names], node.lineno))
        elif isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno) for a in node.names if a.name.startswith("cylsfm")]
    return out


def _unit(module: str) -> str | None:
    """The top-level unit a ``cylsfm`` module belongs to (the package root is ``__init__``)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def test_every_unit_has_a_layer() -> None:
    units = {_top(p) for p in _modules()} - {"__init__"}
    assert units <= set(LEVEL), f"add to LAYERS (and docs/architecture.md): {sorted(units - set(LEVEL))}"


def upward_imports(path: Path, root: Path = SRC) -> list[str]:
    """The imports of ``path`` that point up or sideways, as messages."""
    me = _top(path, root)
    if me == "__init__":  # the package's public surface re-exports from below
        return []
    bad = []
    for module, _names, line in _imports(path, root):
        other = _unit(module)
        if other is None or other == me:
            continue
        if LEVEL[other] >= LEVEL[me]:
            bad.append(
                f"{path.relative_to(root)}:{line} imports {module} ({other}, layer {LEVEL[other]}) from layer "
                f"{LEVEL[me]} ({me}): imports must point down"
            )
    return bad


def private_imports(path: Path, root: Path = SRC) -> list[str]:
    """The imports of another module's private names in ``path``, as messages."""
    bad = []
    for module, names, line in _imports(path, root):
        private = [n for n in names if n.startswith("_") and not n.startswith("__")]
        if private:
            bad.append(f"{path.relative_to(root)}:{line} imports private {private} from {module}")
    return bad


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(SRC)))
def test_imports_point_down(path: Path) -> None:
    assert not upward_imports(path)


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(SRC)))
def test_no_private_imports_across_modules(path: Path) -> None:
    assert not private_imports(path)


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(SRC)))
def test_files_and_functions_stay_short(path: Path) -> None:
    text = path.read_text()
    n = len(text.splitlines())
    assert n <= MAX_FILE_LINES, f"{path.relative_to(SRC)} has {n} lines (at most {MAX_FILE_LINES})"
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            length = node.end_lineno - node.lineno + 1  # type: ignore[operator]
            key = f"{path.relative_to(SRC)}:{node.name}"
            if key in LONG_FUNCTIONS:
                continue
            assert length <= MAX_FUNCTION_LINES, f"{key} has {length} lines (at most {MAX_FUNCTION_LINES})"


def test_the_checker_sees_a_violation(tmp_path: Path) -> None:
    """Negative control: an upward, a sideways and a private import are found in planted files."""
    (tmp_path / "geometry").mkdir()
    (tmp_path / "train").mkdir()
    up = tmp_path / "geometry" / "planted.py"
    up.write_text("from ..train.trainer import _Dist\nfrom . import pose\n")
    side = tmp_path / "train" / "planted.py"
    side.write_text("from cylsfm.evaluate.depth import evaluate_depth\nfrom ..data import splits\n")
    assert len(upward_imports(up, tmp_path)) == 1 and "train" in upward_imports(up, tmp_path)[0]
    assert len(private_imports(up, tmp_path)) == 1
    assert len(upward_imports(side, tmp_path)) == 1 and "evaluate" in upward_imports(side, tmp_path)[0]
