"""The import direction of docs/architecture.md, checked on the code: every `import`, also inside functions and
type-only ones (under `if TYPE_CHECKING:`), since a type-only import that runs up the layers is still a cycle of
ideas a reader must untangle.

    __main__ -> cli -> stages -> libraries -> base (geometry, project, ...)

and the libraries in strict levels of their own (LIBRARY_LEVEL): a library imports only libraries of a lower level,
never one of its own level or above (render/ below model/: the engine renders any `render.engine.ViewModel`, while
model/ composites with `render.volume`). The core model never imports io/, cli/ or project.py; a stage never
imports another stage's module (the chains, demo and reproduce, excepted); the CLI imports no library.
"""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "avatarctl"
LIBRARY_LEVEL = {  # 1 = just above the base; docs/architecture.md "Layers" draws the same table
    "splat": 1, "body": 1, "evaluate": 1,
    "render": 2, "io": 2,
    "model": 3, "ingest": 3, "synth": 3,
    "fit": 4, "export": 4, "viewer": 4,
}
BASE = {"geometry", "project", "atomic", "lock", "errors", "device", "frames", "allocator", "safe_pickle", "dist",
        "progress", "lists", "__init__"}
TOP = max(LIBRARY_LEVEL.values())
LAYER = {"__main__": TOP + 3, "cli": TOP + 2, "stages": TOP + 1, **LIBRARY_LEVEL, **{b: 0 for b in BASE}}
CHAINS = {"avatarctl.stages.demo", "avatarctl.stages.reproduce"}  # stages that run other stages
CLI_MAY_IMPORT = {"cli", "stages", "project", "errors", "allocator", "progress", "lists", "__init__"}


def _room(module: str) -> str:
    """'avatarctl.fit.loop' -> 'fit'; 'avatarctl' -> '__init__'."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _is_module(dotted: str) -> bool:
    """'avatarctl.cli.demo' names a module (file or package) of the package."""
    rel = Path(*dotted.split(".")[1:]) if "." in dotted else Path()
    return (PKG / rel).with_suffix(".py").is_file() or (PKG / rel / "__init__.py").is_file()


def _imports(path: Path, source: str | None = None) -> list[tuple[int, str]]:
    """(line, imported avatarctl module) for every import statement of the file (of `source` when given), at any
    depth: module level, inside functions, under `if TYPE_CHECKING:`."""
    module = "avatarctl." + ".".join(path.relative_to(PKG).with_suffix("").parts)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text() if source is None else source, str(path))):
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


def test_no_import_runs_up_or_sideways():
    """Each import goes to a strictly lower layer (or stays in its own room): no two rooms share a level and import
    each other, type-only imports included."""
    bad = [f"{f}:{line} {src} (level {LAYER[_room(src)]}) imports {dst} (level {LAYER[_room(dst)]})"
           for f, line, src, dst in _edges()
           if _room(dst) != _room(src) and LAYER[_room(dst)] >= LAYER[_room(src)] and LAYER[_room(src)] > 0]
    assert not bad, "\n".join(bad)


def test_base_imports_nothing_above_it():
    bad = [f"{f}:{line} {src} imports {dst}" for f, line, src, dst in _edges()
           if LAYER[_room(src)] == 0 and LAYER[_room(dst)] > 0]
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
    assert ("avatarctl.model.avatar", "avatarctl.render.volume") in edges  # module level
    assert ("avatarctl.stages.common", "avatarctl.fit.checkpoint") in edges  # type-only, under TYPE_CHECKING
    assert ("avatarctl.cli.app", "avatarctl.cli.demo") in edges  # inside a function: from avatarctl.cli import demo
    assert ("avatarctl.cli.app", "avatarctl") in edges  # from avatarctl import __version__


def test_a_type_only_import_running_up_is_caught():
    """The old hole: `render/engine.py` importing `model/avatar.py` for types only, while model imports render."""
    src = ("from typing import TYPE_CHECKING\n"
           "if TYPE_CHECKING:\n"
           "    from avatarctl.model.avatar import SlrfAvatar\n")
    found = _imports(PKG / "render" / "engine.py", src)
    assert found == [(3, "avatarctl.model.avatar")]
    assert LAYER[_room("avatarctl.model.avatar")] > LAYER[_room("avatarctl.render.engine")]


# where the kind of local field may be named: the configs (which keys a field reads, old saved presets) and the one
# interface (model/local_field.py)
FIELD_KIND_HOME = {"avatarctl/model/config.py", "avatarctl/fit/config.py", "avatarctl/model/local_field.py"}
_ASKS_KIND = ("ray_marched", 'field == "gaussians"', 'field != "gaussians"', 'field == "mlp"', 'field != "mlp"',
              "ImageBatch)")


def _asks_which_field(path: Path, text: str) -> list[str]:
    return [f"{path}:{i} {line.strip()}" for i, line in enumerate(text.splitlines(), 1)
            if any(a in line for a in _ASKS_KIND) and not line.lstrip().startswith("#")]


def test_only_the_field_interface_asks_which_kind_of_field():
    """The fit, render, eval, export and the viewer call `model.field_kind` (`LocalField`) and never test which kind
    of local field they hold (issue 49: the kind was decided in ~14 places outside the field)."""
    bad = []
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG.parent).as_posix()
        if rel not in FIELD_KIND_HOME:
            bad += _asks_which_field(path.relative_to(PKG.parent), path.read_text())
    assert not bad, "ask model.field_kind (model/local_field.py) instead:\n" + "\n".join(bad)


def test_the_field_kind_check_catches_a_branch():
    """Not vacuous: the branch the loop used to hold is caught."""
    src = "    Sampler = RaySampler if cfg.model.ray_marched else ImageSampler\n"
    assert len(_asks_which_field(Path("avatarctl/fit/loop.py"), src)) == 1
