"""Fail if a module of the package imports another module's private name.

import-linter checks which modules import which; this checks what they import: a name with a
leading underscore belongs to its module, and no other module of the package may import it
(top-level or inside a function). Run: ``python tools/check_private_imports.py``.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def private_imports(path: Path) -> list[str]:
    """``file:line: module._name`` for each private name ``path`` imports from the package."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("cwfs_ros"):
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}: "
                                 f"{node.module}.{alias.name}")
    return found


def main() -> int:
    bad = [hit for p in sorted((ROOT / "cwfs_ros").rglob("*.py")) for hit in private_imports(p)]
    for hit in bad:
        print(f"private import across modules: {hit}", file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
