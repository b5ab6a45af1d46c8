"""The largest modules and functions of a package, at a git revision or in the working tree (ast-based).

Lines of a module: its physical lines. Lines of a function: ``end_lineno - lineno + 1`` of its ``def``
(docstring and body, decorators not counted); methods and nested functions are listed under their qualified
name (``Class.method``, ``outer.<locals>.inner``) and also count inside their parent.

Usage::

    python bench/code_size.py                      # working tree, ptrack/
    python bench/code_size.py --rev 28b2797        # a commit (read with git show, the tree is not touched)
    python bench/code_size.py --rev 51828d8 --rev 28b2797 --rev HEAD --top 5 --under ptrack sim
"""
from __future__ import annotations

import argparse
import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), *args], check=True, capture_output=True, text=True).stdout


def sources(rev: str | None, under: str) -> dict[str, str]:
    """{path: source text} of the ``.py`` files below ``under`` at ``rev`` (None: the working tree)."""
    if rev is None:
        return {str(p.relative_to(ROOT)): p.read_text(encoding="utf-8")
                for p in sorted((ROOT / under).rglob("*.py")) if ".venv" not in p.parts}
    names = [n for n in _git("ls-tree", "-r", "--name-only", rev, "--", under).splitlines() if n.endswith(".py")]
    return {n: _git("show", f"{rev}:{n}") for n in names}


def functions(tree: ast.AST):
    """(qualified name, lines) of every function and method in a module."""
    out = []

    def visit(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = prefix + child.name
                out.append((name, child.end_lineno - child.lineno + 1))
                visit(child, name + ".<locals>.")
            elif isinstance(child, ast.ClassDef):
                visit(child, prefix + child.name + ".")
            else:
                visit(child, prefix)

    visit(tree, "")
    return out


def code_size(rev: str | None = None, under: str = "ptrack"):
    """(modules, functions): lists of (lines, path) and (lines, path, qualified name), largest first."""
    mods, funcs = [], []
    for path, text in sources(rev, under).items():
        mods.append((len(text.splitlines()), path))
        try:
            tree = ast.parse(text)
        except SyntaxError as exc:          # an old revision in another Python: say so, keep the module count
            print(f"  (could not parse {path}: {exc})", file=sys.stderr)
            continue
        funcs += [(n, path, q) for q, n in functions(tree)]
    return sorted(mods, reverse=True), sorted(funcs, reverse=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rev", action="append", help="git revision (repeatable); default: the working tree")
    ap.add_argument("--under", nargs="+", default=["ptrack"], help="folders to measure (default: ptrack)")
    ap.add_argument("--top", type=int, default=5, help="rows per list (default 5)")
    args = ap.parse_args(argv)
    for rev in args.rev or [None]:
        label = "working tree" if rev is None else f"{rev} ({_git('log', '-1', '--format=%h %cs', rev).strip()})"
        for under in args.under:
            mods, funcs = code_size(rev, under)
            total = sum(n for n, _ in mods)
            print(f"== {under}/ at {label}: {len(mods)} modules, {total} lines, {len(funcs)} functions")
            print("  largest modules (lines):")
            for n, p in mods[:args.top]:
                print(f"    {n:6d}  {p}")
            print("  largest functions (lines of the def):")
            for n, p, q in funcs[:args.top]:
                print(f"    {n:6d}  {p}:{q}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
