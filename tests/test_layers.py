"""The package's layers: core (standard library only) <- lm (torch, transformers) <- workflow (Hydra, MLflow)
<- report. A module imports only from its own layer and the ones before it; this test fails naming the
import that goes the wrong way. And no modules import each other in a cycle, lazily inside a function or not."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

from conftest import ROOT

LAYERS = ("core", "lm", "workflow", "report")
PACKAGE = ROOT / "pipeline"
# What each layer may import from outside the project (beyond the standard library); later layers may also
# import what earlier ones may.
THIRD_PARTY = {
    "core": set(),
    "lm": {"torch", "transformers", "tokenizers", "accelerate", "vllm", "safetensors", "tqdm"},
    "workflow": {"hydra", "omegaconf", "mlflow"},
    "report": {"pandas", "numpy", "matplotlib", "scipy"},
}


def _imports(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
    return found


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "pipeline" and parts[1] in LAYERS else None


def wrong_way_imports() -> list[str]:
    problems = []
    for layer_index, layer in enumerate(LAYERS):
        allowed_layers = set(LAYERS[: layer_index + 1])
        allowed_outside = set().union(*(THIRD_PARTY[name] for name in LAYERS[: layer_index + 1]))
        for path in sorted((PACKAGE / layer).rglob("*.py")):
            for line, module in _imports(path):
                top = module.split(".")[0]
                where = f"{path.relative_to(ROOT)}:{line} imports {module}"
                if top == "pipeline":
                    target = _layer(module)
                    if target is None or target not in allowed_layers:
                        problems.append(f"{where} (layer {layer} may import pipeline.{{{', '.join(sorted(allowed_layers))}}})")
                elif top not in sys.stdlib_module_names and top not in allowed_outside and top != "__future__":
                    problems.append(f"{where} (layer {layer} may not depend on {top})")
    return problems


def test_every_import_goes_the_right_way():
    assert wrong_way_imports() == []


def test_the_rule_catches_a_wrong_way_import(tmp_path, monkeypatch):
    fake = tmp_path / "pipeline"
    for layer in LAYERS:
        (fake / layer).mkdir(parents=True)
    (fake / "core" / "bad.py").write_text("import torch\nfrom pipeline.workflow.config import validate\n")
    (fake / "lm" / "bad.py").write_text("from pipeline.workflow import config\nimport mlflow\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", fake)
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    problems = wrong_way_imports()
    assert len(problems) == 4
    assert any("core/bad.py:1 imports torch" in p for p in problems)
    assert any("lm/bad.py:1 imports pipeline.workflow" in p for p in problems)


def _module(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph() -> dict[str, set[str]]:
    """Each module of the package and the package's modules it imports anywhere in its body (so also lazily,
    inside a function). ``from a import b`` imports the module a.b when there is one, else a."""
    paths = {_module(path): path for path in sorted(PACKAGE.rglob("*.py"))}
    graph = {}
    for name, path in paths.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module
                if node.level:  # relative: from the module's package, less one level per dot after the first
                    base = ".".join(filter(None, (package.rsplit(".", node.level - 1)[0], node.module)))
                targets |= {f"{base}.{alias.name}" if f"{base}.{alias.name}" in paths else base for alias in node.names}
        graph[name] = {target for target in targets if target in paths and target != name}
    return graph


def import_cycle(graph: dict[str, set[str]]) -> list[str]:
    """One cycle of the graph as the modules along it (the first repeated at the end), or [] if it has none."""
    done: set[str] = set()

    def visit(name: str, path: list[str]) -> list[str]:
        if name in path:
            return path[path.index(name):] + [name]
        if name in done:
            return []
        for target in sorted(graph[name]):
            cycle = visit(target, [*path, name])
            if cycle:
                return cycle
        done.add(name)
        return []

    return next((cycle for name in sorted(graph) if (cycle := visit(name, []))), [])


def test_no_modules_import_each_other_in_a_cycle():
    assert import_cycle(import_graph()) == []


def test_the_cycle_check_sees_lazy_imports(tmp_path, monkeypatch):
    fake = tmp_path / "pipeline" / "core"
    fake.mkdir(parents=True)
    (fake / "a.py").write_text("from pipeline.core.b import f\n")
    (fake / "b.py").write_text("def f():\n    from pipeline.core import a\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", tmp_path / "pipeline")
    assert import_cycle(import_graph()) == ["pipeline.core.a", "pipeline.core.b", "pipeline.core.a"]


def test_the_top_level_keeps_the_domain_api():
    import pipeline

    assert {"World", "conversation"} <= set(pipeline.__all__)
