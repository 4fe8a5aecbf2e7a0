"""Mutation testing of the solve core: do the unit tests fail when the code is wrong?

A small mutator of its own (mutmut 3 runs the tests on a copy in `mutants/`, which calibcoach's
import root, mapped onto app/, drivers/ and coverage/ by `package-dir`, never imports): each
mutant changes one operator or constant of one module in place (comparison, arithmetic, and/or,
not, unary minus, a number n -> n + 1, True <-> False; strings, f-strings and docstrings are left
alone), runs only that module's fast unit tests (`pytest -x`), and restores the file.

    .venv/bin/python bench/mutation.py                 # all targets, ~25 min on one core
    .venv/bin/python bench/mutation.py verdict select  # targets whose path contains a word
    .venv/bin/python bench/mutation.py --list          # the mutants, without running anything

Survivors are listed as path:line with the mutated source line; results go to
bench/results/mutation.json. Not part of the normal test run.
"""

from __future__ import annotations

import argparse
import ast
import copy
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TARGETS = {  # module -> its fast unit tests
    "app/solve/robust.py": ["tests/app/test_robust.py", "tests/app/test_robust_limits.py"],
    "app/solve/weighted.py": ["tests/app/test_weighted.py", "tests/app/test_robust.py", "tests/app/test_robust_limits.py",
                              "tests/app/test_uncertainty.py::test_weighted_refinement_discounts_noisy_views"],
    "app/solve/verdict.py": ["tests/app/test_verdict.py"],
    "app/solve/model_choice.py": ["tests/app/test_model_choice_rule.py", "tests/app/test_model_choice.py"],  # fast tests first (-x)
    "coverage/select.py": ["tests/coverage/test_select_unit.py", "tests/coverage/test_coverage_selection.py"],
}
_SWAP = {
    ast.Lt: ast.LtE, ast.LtE: ast.Lt, ast.Gt: ast.GtE, ast.GtE: ast.Gt, ast.Eq: ast.NotEq, ast.NotEq: ast.Eq,
    ast.In: ast.NotIn, ast.NotIn: ast.In, ast.Is: ast.IsNot, ast.IsNot: ast.Is,
    ast.Add: ast.Sub, ast.Sub: ast.Add, ast.Mult: ast.Div, ast.Div: ast.Mult, ast.Pow: ast.Mult, ast.FloorDiv: ast.Div,
    ast.And: ast.Or, ast.Or: ast.And,
}


def _skipped(node: ast.AST) -> bool:
    """Nodes whose insides are not mutated: f-strings, docstrings, annotations."""
    return isinstance(node, ast.JoinedStr | ast.arg) or (isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant))


def sites(tree: ast.Module) -> list[tuple[int, str]]:
    """(index of the node in ast.walk order, description) for every mutation of `tree`."""
    out: list[tuple[int, str]] = []
    skip: set[int] = set()
    for i, node in enumerate(ast.walk(tree)):
        if id(node) in skip:
            continue
        if _skipped(node):
            skip.update(id(n) for n in ast.walk(node))
            continue
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            for n in [node.returns, *[a.annotation for a in node.args.args + node.args.kwonlyargs]]:
                if n is not None:
                    skip.update(id(m) for m in ast.walk(n))
        if isinstance(node, ast.AnnAssign):
            skip.update(id(m) for m in ast.walk(node.annotation))
        line = getattr(node, "lineno", 0)
        if isinstance(node, ast.Compare):
            for k, op in enumerate(node.ops):
                if type(op) in _SWAP:
                    out.append((i, f"{line}: compare {k} {type(op).__name__} -> {_SWAP[type(op)].__name__}"))
        elif isinstance(node, ast.BinOp | ast.BoolOp) and type(node.op) in _SWAP:
            out.append((i, f"{line}: {type(node.op).__name__} -> {_SWAP[type(node.op)].__name__}"))
        elif isinstance(node, ast.AugAssign) and type(node.op) in _SWAP:
            out.append((i, f"{line}: {type(node.op).__name__}= -> {_SWAP[type(node.op)].__name__}="))
        elif isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.Not | ast.USub):
            out.append((i, f"{line}: drop {type(node.op).__name__}"))
        elif isinstance(node, ast.Constant) and type(node.value) in (int, float):
            out.append((i, f"{line}: {node.value!r} -> {node.value + 1!r}"))
        elif isinstance(node, ast.Constant) and type(node.value) is bool:
            out.append((i, f"{line}: {node.value} -> {not node.value}"))
    return out


def mutate(tree: ast.Module, index: int, description: str) -> str:
    """The source of `tree` with mutation `description` applied to its `index`-th node."""
    tree = copy.deepcopy(tree)
    nodes = list(ast.walk(tree))
    node = nodes[index]
    what = description.split(": ", 1)[1]
    if isinstance(node, ast.Compare):
        k = int(what.split()[1])
        node.ops[k] = _SWAP[type(node.ops[k])]()
    elif isinstance(node, ast.BinOp | ast.BoolOp | ast.AugAssign):
        node.op = _SWAP[type(node.op)]()
    elif isinstance(node, ast.UnaryOp):
        for parent in nodes:
            for field, value in ast.iter_fields(parent):
                if value is node:
                    setattr(parent, field, node.operand)
                elif isinstance(value, list):
                    value[:] = [node.operand if v is node else v for v in value]
    elif isinstance(node, ast.Constant):
        node.value = (not node.value) if type(node.value) is bool else node.value + 1
    return ast.unparse(tree)


def run_tests(tests: list[str], timeout_s: float) -> str:
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
    cmd = [str(ROOT / ".venv/bin/pytest"), "-x", "-q", "--tb=no", "-p", "no:cacheprovider", *tests]
    try:
        rc = subprocess.run(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=timeout_s).returncode
    except subprocess.TimeoutExpired:
        return "timeout"
    return "survived" if rc == 0 else "killed"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("only", nargs="*", help="run only the targets whose path contains one of these words")
    parser.add_argument("--list", action="store_true", help="list the mutants and exit")
    args = parser.parse_args()
    targets = {p: t for p, t in TARGETS.items() if not args.only or any(w in p for w in args.only)}
    results: dict[str, list[dict]] = {}
    for path, tests in targets.items():
        file = ROOT / path
        original = file.read_text()
        tree = ast.parse(original)
        mutants = sites(tree)
        if args.list:
            print(f"{path}: {len(mutants)} mutants")
            for _, d in mutants:
                print("  ", d)
            continue
        t0 = time.time()
        if run_tests(tests, 600) != "survived":
            print(f"{path}: the tests fail on the unmutated code", file=sys.stderr)
            return 2
        timeout = 3 * (time.time() - t0) + 10
        rows = []
        try:
            for index, description in mutants:
                file.write_text(mutate(tree, index, description))
                outcome = run_tests(tests, timeout)
                line = int(description.split(":")[0])
                rows.append({"mutant": description, "outcome": outcome, "source": original.splitlines()[line - 1].strip()})
                print(f"{path}:{description}: {outcome}", flush=True)
        finally:
            file.write_text(original)
        results[path] = rows
    if args.list:
        return 0
    out = ROOT / "bench" / "results" / "mutation.json"
    total = killed = 0
    for path, rows in results.items():
        k = sum(r["outcome"] != "survived" for r in rows)
        total, killed = total + len(rows), killed + k
        print(f"{path}: {k}/{len(rows)} killed ({100 * k / max(len(rows), 1):.0f}%)")
        for r in rows:
            if r["outcome"] == "survived":
                print(f"   survived {path}:{r['mutant']}    | {r['source']}")
    print(f"mutation score: {killed}/{total} = {100 * killed / max(total, 1):.1f}%")
    if not args.only:
        out.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
