"""The layout holds: layers import only downwards, no import circle, the detector loads no
workflow machinery, and every package folder is installed (docs/ARCHITECTURE.md)."""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Layer of each part, from the bottom up; a module may import its own layer and those below.
LAYERS = {
    "streetcd": 0,  # the package itself: its public face is loaded lazily, by name
    "streetcd.errors": 0,
    "streetcd.types": 0,
    "streetcd.classes": 0,
    "streetcd.config": 0,
    "streetcd.geometry": 1,
    "streetcd.detect": 2,
    "streetcd.io": 3,
    "streetcd.store": 4,
    "streetcd.run": 5,
    "streetcd.synth": 5,
    "streetcd.eval": 6,
    "streetcd.cli": 7,
    "streetcd.report": 7,  # the review page: beside the CLI, which calls it
    "streetcd_flows": 7,
}
# streetcd/__init__.py re-exports the public face lazily (by name, on first access).


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[0] == "flows":
        parts[0] = "streetcd_flows"
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def modules() -> dict[str, Path]:
    files = [*(ROOT / "streetcd").rglob("*.py"), *(ROOT / "flows").rglob("*.py")]
    return {module_name(p): p for p in files}


def imports(path: Path, known: dict[str, Path]) -> set[str]:
    """The project modules ``path`` imports anywhere in it (in functions too)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*up, base] if base else up)
            targets = [
                f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names
            ]
        else:
            continue
        out |= {t for t in targets if t in known and t != name}
    return out


def layer(module: str) -> int:
    for prefix, rank in sorted(LAYERS.items(), key=lambda kv: -len(kv[0])):
        if module == prefix or module.startswith(prefix + "."):
            return rank
    raise AssertionError(f"{module} is in no layer: add it to LAYERS and docs/ARCHITECTURE.md")


GRAPH = {m: imports(p, modules()) for m, p in modules().items()}


def test_every_module_imports_only_its_own_layer_and_those_below():
    upward = [
        f"{m} ({layer(m)}) imports {t} ({layer(t)})"
        for m, targets in sorted(GRAPH.items())
        if m != "streetcd"
        for t in sorted(targets)
        if layer(t) > layer(m)
    ]
    assert not upward, "\n".join(upward)


def test_there_is_no_import_circle():
    seen: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(m: str, path: list[str]) -> None:
        seen[m] = 1
        for t in sorted(GRAPH[m]):
            if seen.get(t) == 1:
                raise AssertionError("import circle: " + " -> ".join([*path, m, t]))
            if t not in seen:
                visit(t, [*path, m])
        seen[m] = 2

    for m in sorted(GRAPH):
        if m not in seen:
            visit(m, [])


def test_the_flow_is_the_only_code_that_imports_prefect():
    users = []
    for m, path in modules().items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            if any(n == "prefect" or n.startswith("prefect.") for n in names):
                users.append(m)
    assert users and all(m.startswith("streetcd_flows") for m in users), users


def test_the_detector_and_cli_help_load_no_workflow_machinery():
    """`import streetcd.detect` (and the detector's chain) loads neither prefect, distributed
    nor zarr; nor does `import streetcd`, whose public face is loaded on first use."""
    code = (
        "import sys, streetcd, streetcd.detect, streetcd.detect.chain, streetcd.detect.cache\n"
        "heavy = ('prefect', 'distributed', 'zarr', 'dask')\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_the_public_face_is_there_and_lazy():
    import streetcd

    assert {"detect_view", "Config", "TileStore", "ChangeIndex", "errors"} <= set(streetcd.__all__)
    for name in streetcd.__all__:
        assert getattr(streetcd, name) is not None
    with pytest.raises(AttributeError, match="no_such_name"):
        _ = streetcd.no_such_name  # type: ignore[attr-defined]


def test_every_package_folder_is_installed():
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    listed = set(config["tool"]["setuptools"]["packages"])
    folders = {
        module_name(p.parent / "__init__.py")
        for p in [*(ROOT / "streetcd").rglob("__init__.py"), ROOT / "flows" / "__init__.py"]
    }
    assert folders == listed
