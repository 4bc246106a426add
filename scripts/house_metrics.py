"""House metrics (issue 32): single-task against multi-task checks, the places that decide which task a
checkpoint serves, and the longest function and largest class of the package's code.

    python scripts/house_metrics.py            # from the repository root
"""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

PACKAGES = ("rllock", "orchestration", "actors", "learner", "cluster")
# A branch or signature that tells one task from a task set apart.
TASK_CHECK = re.compile(
    r"\btasks? is (not )?None|\bTask \| None|\bTaskSet \| None|\bTaskSpec \| TaskSet|\.multitask\b"
    r"|isinstance\([^)]*, Task(Set|Spec)\)"
)
# Code that decides which task a checkpoint serves: a multi-task checkpoint's task, or a check of a
# single-task one's against a task named by the user.
SERVES = re.compile(r"serves many tasks|check_same_task\(|check_fits\(")


def sources(root: Path) -> list[Path]:
    return sorted(p for package in PACKAGES for p in (root / package).rglob("*.py"))


def task_checks(files: list[Path], root: Path) -> tuple[int, int]:
    hits = [(f, line) for f in files for line in f.read_text().splitlines() if TASK_CHECK.search(line)]
    return len(hits), len({f for f, _ in hits})


def serving_places(files: list[Path], root: Path) -> list[str]:
    """Files outside the definitions' own module that call or spell the decision."""
    return sorted(str(f.relative_to(root)) for f in files if SERVES.search(f.read_text()))


def sizes(files: list[Path], root: Path) -> tuple[tuple[int, str], tuple[int, str]]:
    """(lines, name) of the longest function and of the largest class."""
    longest, largest = (0, ""), (0, "")
    for f in files:
        for node in ast.walk(ast.parse(f.read_text())):
            if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                continue
            span = (node.end_lineno or node.lineno) - node.lineno + 1
            where = f"{f.relative_to(root)}:{node.name}"
            if not isinstance(node, ast.ClassDef):
                longest = max(longest, (span, where))
            else:
                largest = max(largest, (span, where))
    return longest, largest


def main() -> None:
    root = Path(sys.argv[1] if len(sys.argv) > 1 else ".").resolve()
    files = sources(root)
    checks, in_files = task_checks(files, root)
    places = serving_places(files, root)
    (f_lines, f_name), (c_lines, c_name) = sizes(files, root)
    longest_module = max((len(f.read_text().splitlines()), str(f.relative_to(root))) for f in files)
    print(f"task / task-set checks: {checks} in {in_files} files")
    print(f"files that decide which task a checkpoint serves: {len(places)} ({', '.join(places)})")
    print(f"longest function: {f_lines} lines ({f_name})")
    print(f"largest class: {c_lines} lines ({c_name})")
    print(f"longest module: {longest_module[0]} lines ({longest_module[1]})")


if __name__ == "__main__":
    main()
