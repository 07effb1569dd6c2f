"""The shape of the code: the layering of the five packages, no import cycle, benchmarks without
`sys.path` edits, one Gaussian-set type and one render function.

Imports are read with `ast` from the source files (module-level and function-level alike), so the
checks see the lazy imports the CLI and the services use too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import networkx as nx

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("calibration", "rig", "reconstruction", "simulation", "deploy")
# What each package may import besides itself (calibration is the bottom; deploy may use all).
MAY_IMPORT = {
    "calibration": set(),
    "rig": {"calibration"},
    "reconstruction": {"calibration"},
    "simulation": {"calibration", "reconstruction"},
    "deploy": {"calibration", "rig", "reconstruction", "simulation"},
}


def _modules() -> dict[str, Path]:
    """Dotted module name -> source file, for every module of the five packages."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            parts = path.relative_to(REPO).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


MODULES = _modules()


def _imported(name: str, path: Path, tree: ast.AST) -> set[str]:
    """The project modules `tree` (the source of module `name` at `path`) imports, anywhere in it."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            # `from pkg import mod` imports the module pkg.mod; `from mod import name` imports mod.
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names]
        else:
            continue
        for target in targets:
            while target and target not in MODULES:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


GRAPH = {name: _imported(name, path, ast.parse(path.read_text(), str(path))) for name, path in MODULES.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles: strongly connected components of more than one module, each sorted."""
    g = nx.DiGraph([(a, b) for a, targets in graph.items() for b in targets])
    return sorted(sorted(c) for c in nx.strongly_connected_components(g) if len(c) > 1)


def test_the_import_walker_sees_lazy_and_relative_imports():
    assert "rig.camera" in GRAPH["rig.acquisition"]  # module level
    assert "reconstruction.twin" in GRAPH["deploy.steps"]  # inside a function
    relative = ast.parse("from .camera import CameraError\nfrom . import oak\nfrom ..calibration import so3\n")
    assert _imported("rig.assembly", MODULES["rig.assembly"], relative) == {"rig.camera", "rig.oak", "calibration.so3"}
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycle_between_modules():
    assert _cycles(GRAPH) == []


def test_no_package_imports_a_package_above_it():
    upward = sorted(
        f"{name} imports {target}"
        for name, targets in GRAPH.items()
        for target in targets
        if (src := name.split(".")[0]) != (dst := target.split(".")[0]) and dst not in MAY_IMPORT[src]
    )
    assert upward == []


def test_benchmarks_do_not_edit_sys_path():
    edits = [
        f"{p.relative_to(REPO)}:{i}"
        for p in sorted((REPO / "benchmarks").rglob("*.py"))
        for i, line in enumerate(p.read_text().splitlines(), start=1)
        if "sys.path" in line
    ]
    assert edits == []


GAUSSIAN_FIELDS = ({"means"}, {"quats"}, {"log_scales", "scales"}, {"opacity_logits", "opacities"}, {"sh"})
RENDER_NAMES = {"render", "render_rgba", "twin_rgba"}
# Training loops rasterize their own parameters while they learn (and read the rasterizer's
# screen-space gradients to densify), so they call `rasterize` directly; nothing else may.
TRAINING_MODULES = {"reconstruction.train", "reconstruction.baselines"}


def _class_fields(cls: ast.ClassDef) -> set[str]:
    """Names a class declares (annotated class attributes) or sets on self in its methods."""
    names = {n.target.id for n in cls.body if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name)}
    for node in ast.walk(cls):
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
        names |= {t.attr for t in targets if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id == "self"}
    return names


def _calls(node: ast.AST, name: str) -> bool:
    return any(isinstance(n, ast.Call) and name in (getattr(n.func, "id", None), getattr(n.func, "attr", None)) for n in ast.walk(node))


def test_one_gaussian_set_type_and_one_render_function():
    types, renders, rasterizing = [], [], []
    for name, path in MODULES.items():
        if name.startswith("reconstruction.render"):  # the rasterizer itself
            continue
        for node in ast.parse(path.read_text(), str(path)).body:
            if isinstance(node, ast.ClassDef) and all(_class_fields(node) & f for f in GAUSSIAN_FIELDS):
                types.append(f"{name}.{node.name}")
            if isinstance(node, ast.FunctionDef) and node.name in RENDER_NAMES and name.split(".")[0] in ("reconstruction", "simulation"):
                renders.append(f"{name}.{node.name}")
            training = name in TRAINING_MODULES  # the training loops' own losses render their batches
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and not training and _calls(node, "rasterize"):
                rasterizing.append(f"{name}.{node.name}")
    assert types == ["reconstruction.gaussians.Gaussians"]
    assert renders == ["reconstruction.gaussians.render"]
    assert rasterizing == ["reconstruction.gaussians.render"]
