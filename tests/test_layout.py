"""The package tree is the pipeline: each folder is a stage, and a stage imports only the
stages below it (no loops), read from the source's own import statements, function-level
imports included. Only ``flamerecon/run/`` knows Hydra or OmegaConf. ``viewer/`` (the web viewer's
server loop) sits above the run layer; ``__main__`` (the ``flamerecon`` command) above all."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.helpers import REPO

PACKAGE = REPO / "flamerecon"

#: stage -> rank; a module may import a module of the same or a lower rank only. Top-level
#: leaf modules are the foundation; ``api`` and ``__init__`` are the front door above all.
RANKS = {
    "errors": 0, "device": 0, "resources": 0, "plain": 0, "rules": 0, "arguments": 0, "native": 0,
    "progress": 0, "machine": 0, "interrupt": 0,
    "geometry": 1, "operators": 2, "solvers": 3, "outputs": 4, "scenes": 5, "evaluate": 6,
    "fit": 7, "dynamics": 8, "run": 9, "viewer": 10, "api": 11, "__main__": 11, "": 11,
}


def stage(module: str) -> str:
    """``flamerecon.fit.build`` -> ``fit``; ``flamerecon`` -> ``""`` (the front door)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> set[str]:
    """The flamerecon modules ``path`` imports (``from flamerecon.x import y``: ``flamerecon.x``,
    or ``flamerecon.x.y`` where y is a module)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level:
            pytest.fail(f"{path.relative_to(REPO)}:{node.lineno}: relative import; use flamerecon.<stage>...")
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("flamerecon"):
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                is_module = (REPO / (sub.replace(".", "/") + ".py")).is_file() or (
                    REPO / sub.replace(".", "/") / "__init__.py").is_file()
                found.add(sub if is_module else node.module)
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("flamerecon")}
    return found


MODULES = {module_name(p): p for p in PACKAGE.rglob("*.py")}


def test_every_module_sits_in_a_known_stage():
    unknown = sorted(m for m in MODULES if stage(m) not in RANKS)
    assert not unknown, f"modules outside the stages of RANKS: {unknown}"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_run_down_the_stages(module):
    here = RANKS[stage(module)]
    upward = sorted(m for m in imports(MODULES[module])
                    if RANKS.get(stage(m), -1) > here)
    assert not upward, f"{module} (stage rank {here}) imports higher stages: {upward}"


def test_there_is_no_import_loop():
    # a package's __init__ importing its own submodules is how it registers them, not a loop
    graph = {m: {i for i in imports(p) if i in MODULES and i != m and not i.startswith(m + ".")}
             for m, p in MODULES.items()}
    state: dict[str, int] = {}

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                pytest.fail("import loop: " + " -> ".join([*path[path.index(n):], n]))
            if n not in state:
                visit(n, [*path, n])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])


def test_only_the_run_layer_knows_hydra():
    offenders = []
    for module, path in sorted(MODULES.items()):
        if stage(module) == "run":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([node.module or ""] if isinstance(node, ast.ImportFrom)
                     else [a.name for a in node.names] if isinstance(node, ast.Import) else [])
            if any(n.split(".")[0] in ("hydra", "omegaconf") for n in names):
                offenders.append(f"{module}:{node.lineno}")
    assert not offenders, f"Hydra/OmegaConf imported outside flamerecon/run/: {offenders}"


def test_the_dynamics_stage_sits_between_the_method_and_the_run_layer():
    assert RANKS["fit"] < RANKS["dynamics"] < RANKS["run"]
    assert RANKS["evaluate"] < RANKS["dynamics"]
    # what moved there is gone from fit/
    assert not [n for n in ("flow", "motion", "prediction") if (PACKAGE / "fit" / f"{n}.py").exists()]
    assert (PACKAGE / "dynamics" / "flow.py").is_file()


def test_the_old_flat_paths_are_gone():
    old = ["cameras", "grid", "projector", "sparse_ops", "discretization", "reconstruction",
           "pipeline", "evaluation", "temporal_run", "run_hook", "tb_logging", "options"]
    assert not [n for n in old if (PACKAGE / f"{n}.py").exists()]
    assert not (PACKAGE / "solvers" / "smoothness.py").exists()
