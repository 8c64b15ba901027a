"""The import direction of docs/architecture.md, checked on the code (every `import`, also inside functions).

    cli -> stages -> libraries (model, render, fit, evaluate, ingest, io, body, synth, export, viewer, splat) -> base (geometry, project, ...)

A lower layer never imports a higher one; the core model never imports io/, cli/ or project.py; a stage never
imports another stage's module (the chains, demo and reproduce, excepted); the CLI imports no library.
"""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "avatarctl"
LIBRARIES = {"model", "render", "fit", "evaluate", "ingest", "io", "body", "synth", "export", "viewer", "splat"}
BASE = {"geometry", "project", "atomic", "lock", "errors", "device", "frames", "allocator", "safe_pickle", "dist",
        "__init__"}
LAYER = {"__main__": 4, "cli": 3, "stages": 2, **{lib: 1 for lib in LIBRARIES}, **{b: 0 for b in BASE}}
CHAINS = {"avatarctl.stages.demo", "avatarctl.stages.reproduce"}  # stages that run other stages
CLI_MAY_IMPORT = {"cli", "stages", "project", "errors", "allocator", "__init__"}


def _room(module: str) -> str:
    """'avatarctl.fit.loop' -> 'fit'; 'avatarctl' -> '__init__'."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _is_module(dotted: str) -> bool:
    """'avatarctl.cli.demo' names a module (file or package) of the package."""
    rel = Path(*dotted.split(".")[1:]) if "." in dotted else Path()
    return (PKG / rel).with_suffix(".py").is_file() or (PKG / rel / "__init__.py").is_file()


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, imported avatarctl module) for every import statement of the file."""
    module = "avatarctl." + ".".join(path.relative_to(PKG).with_suffix("").parts)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            names = [f"{base}.{a.name}" if _is_module(f"{base}.{a.name}") else base for a in node.names]
            out += [(node.lineno, n) for n in names]
    return [(line, n) for line, n in out if n == "avatarctl" or n.startswith("avatarctl.")]


def _edges() -> list[tuple[str, int, str, str]]:
    """(file, line, importing module, imported module) over the package."""
    edges = []
    for path in sorted(PKG.rglob("*.py")):
        module = "avatarctl." + ".".join(path.relative_to(PKG).with_suffix("").parts)
        edges += [(str(path.relative_to(PKG.parent)), line, module, target) for line, target in _imports(path)]
    return edges


def test_every_room_has_a_layer():
    rooms = {p.stem if p.is_file() else p.name for p in PKG.iterdir() if p.suffix == ".py" or
             (p.is_dir() and (p / "__init__.py").is_file())}
    assert rooms <= set(LAYER), f"add {sorted(rooms - set(LAYER))} to a layer here and in docs/architecture.md"


def test_no_lower_layer_imports_a_higher_one():
    bad = [f"{f}:{line} {src} imports {dst}" for f, line, src, dst in _edges()
           if LAYER[_room(dst)] > LAYER[_room(src)]]
    assert not bad, "\n".join(bad)


def test_core_model_is_independent_of_files_and_the_cli():
    bad = [f"{f}:{line} imports {dst}" for f, line, src, dst in _edges()
           if _room(src) == "model" and _room(dst) in {"io", "cli", "project", "stages"}]
    assert not bad, "\n".join(bad)


def test_cli_calls_stages_only():
    bad = [f"{f}:{line} imports {dst}" for f, line, src, dst in _edges()
           if _room(src) == "cli" and _room(dst) not in CLI_MAY_IMPORT]
    assert not bad, "\n".join(bad)


def test_a_stage_borrows_nothing_from_another_stage():
    bad = []
    for f, line, src, dst in _edges():
        if _room(src) == "stages" and _room(dst) == "stages" and src not in CHAINS:
            target = dst.split(".")[2] if dst.count(".") >= 2 else "__init__"
            if target not in {"common", src.split(".")[2]}:
                bad.append(f"{f}:{line} imports {dst}")
    assert not bad, "\n".join(bad)


def test_the_checker_sees_imports_at_any_depth():
    """Not vacuous: module-level, function-level and `from avatarctl import x` imports are all found."""
    edges = {(src, dst) for _, _, src, dst in _edges()}
    assert ("avatarctl.render.engine", "avatarctl.model.avatar") in edges  # module level
    assert ("avatarctl.cli.app", "avatarctl.cli.demo") in edges  # inside a function: from avatarctl.cli import demo
    assert ("avatarctl.cli.app", "avatarctl") in edges  # from avatarctl import __version__
