"""List the functions longer than a limit, with and without their docstrings.

Run: ``python tools/function_lengths.py [--max-lines 60] cwfs_ros/wfs cwfs_ros/frames
cwfs_ros/sim``.  Prints ``lines  code-lines  path:line  name`` per function over the limit,
longest first; ``code-lines`` leaves out the docstring.
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path


def long_functions(paths: list[Path], max_lines: int) -> list[tuple[int, int, str, str]]:
    """``(lines, code_lines, "path:line", name)`` of every function over ``max_lines``."""
    rows = []
    for root in paths:
        for path in sorted(root.rglob("*.py")) if root.is_dir() else [root]:
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                lines = node.end_lineno - node.lineno + 1
                doc = 0
                first = node.body[0]
                if (isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant)
                        and isinstance(first.value.value, str)):
                    doc = first.end_lineno - first.lineno + 1
                if lines > max_lines:
                    rows.append((lines, lines - doc, f"{path}:{node.lineno}", node.name))
    return sorted(rows, reverse=True)


def main(argv: list[str]) -> int:
    """Print the long functions; exit 0 (a report, not a check)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", type=Path)
    parser.add_argument("--max-lines", type=int, default=60)
    args = parser.parse_args(argv)
    for lines, code, where, name in long_functions(args.paths, args.max_lines):
        print(f"{lines:4d} {code:4d}  {where}  {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
