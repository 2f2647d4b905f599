"""Write the layer sketch at the top of docs/architecture.md from the import rules the import-graph test encodes.

``tests/core/test_import_graph.py`` declares the repository's packages and what each may import (``PACKAGES``),
what the core may never import (``LAYER_RULES``) and the core's floors (``FLOORS``), and fails on an import that
breaks them. The sketch stands between the layers markers of docs/architecture.md and is drawn from those
declarations, so it cannot say other than what the test keeps. ``--check`` fails when it differs from them.

    .venv/bin/python tools/layer_sketch.py --write
    .venv/bin/python tools/layer_sketch.py --check
"""

from __future__ import annotations

import difflib
import importlib.util
import sys
import textwrap
from pathlib import Path
from types import ModuleType

from generated_docs import write_or_check  # tools/generated_docs.py: the script's own folder is on sys.path

REPO = Path(__file__).resolve().parents[1]
RULES = REPO / "tests" / "core" / "test_import_graph.py"
DOC = "docs/architecture.md"
BEGIN = "<!-- layers:begin (written by tools/layer_sketch.py from tests/core/test_import_graph.py) -->"
END = "<!-- layers:end -->"


def load_rules(path: Path = RULES) -> ModuleType:
    """The import-graph test module, read for its declarations (no test runs)."""
    spec = importlib.util.spec_from_file_location("import_graph_rules", path)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # the module's dataclasses and NamedTuples look themselves up here
    spec.loader.exec_module(module)
    return module


def sketch(rules: ModuleType) -> list[str]:
    """The sketch's lines: the packages top first, each with what it may import, then the core's floors."""
    repo = {layer.name for layer in rules.PACKAGES}
    lines = ["```text"]
    for layer in rules.PACKAGES:
        imports = ", ".join(layer.members) or "no package of this repository"
        lines.append(f"{layer.name + '/':<14}{'-> ' + imports:<34}{layer.role}")
        outside = [n for n in rules.LAYER_RULES.get(layer.name, ()) if n not in repo]
        if outside:
            never = textwrap.wrap(f"never {', '.join(outside)}", width=100)
            lines += [f"{'':<14}{part}" for part in never]
    lines.append("")
    lines.append("panogs_core/ floors, top first: a module imports from its own floor and the floors below")
    for i, floor in reversed(list(enumerate(rules.FLOORS))):
        members = " ".join("(package)" if m == "panogs_core" else m for m in floor.members)
        lines.append(f"  {i} {floor.name:<10}{members}")
        lines.append(f"{'':<15}{floor.role}")
    lines.append("```")
    return lines


def block(lines: list[str]) -> str:
    return "\n".join([BEGIN, *lines, END])


def current_block(text: str) -> str:
    """The text between (and with) the markers; refuses a document without them."""
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        raise SystemExit(f"{DOC}: no layers markers ({BEGIN} ... {END})")
    return text[start : end + len(END)]


def sketch_difference(root: Path = REPO) -> list[str]:
    """A unified diff when the document's sketch is not the rules'; empty when it is."""
    text = (root / DOC).read_text(encoding="utf-8")
    old, new = current_block(text), block(sketch(load_rules()))
    if old == new:
        return []
    return ["\n".join(difflib.unified_diff(old.splitlines(), new.splitlines(), f"{DOC} (now)", "(rules)", n=0))]


def write(root: Path = REPO) -> bool:
    """Rewrite the sketch; whether it changed."""
    path = root / DOC
    text = path.read_text(encoding="utf-8")
    new = text.replace(current_block(text), block(sketch(load_rules())))
    if new == text:
        return False
    path.write_text(new, encoding="utf-8")
    return True


def main(argv: list[str] | None = None) -> int:
    return write_or_check(
        argv,
        description=__doc__.splitlines()[0],
        what="the sketch between the markers",
        source="the rules",
        write=lambda: [DOC] if write() else [],
        differences=sketch_difference,
        hint="run tools/layer_sketch.py --write",
    )


if __name__ == "__main__":
    raise SystemExit(main())
