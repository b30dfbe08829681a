"""Type-check ``kohpymc`` with mypy against a baseline that may only shrink.

The code base predates its type check, so mypy still reports errors. Rather than fix them all
at once or switch the check off, ``tools/typecheck_baseline.json`` records how many errors each
file has today, and this script fails when any file has more. Fixing errors is then rewarded
(the note printed here asks you to lock the lower count in) and new code cannot add to them.

Usage (from anywhere; ``make typecheck`` runs the first form)::

    python tools/typecheck.py           # compare with the baseline; exit 1 if a file got worse
    python tools/typecheck.py --update  # rewrite the baseline with today's counts

mypy reads its settings (``packages``, ``cache_dir``, the untyped third-party modules) from
``[tool.mypy]`` in ``pyproject.toml``; with a warm cache a run takes about a second.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BASELINE = ROOT / "tools" / "typecheck_baseline.json"


@dataclass(frozen=True)
class MypyError:
    """One error reported by mypy."""

    file: str
    line: int
    code: str | None
    message: str

    def __str__(self) -> str:
        code = f"  [{self.code}]" if self.code else ""
        return f"{self.file}:{self.line}: {self.message}{code}"


def run_mypy() -> list[MypyError]:
    """Run mypy with the project's configuration and return its errors (notes dropped)."""
    proc = subprocess.run(
        [sys.executable, "-m", "mypy", "--output", "json"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    errors, other = [], []
    for line in proc.stdout.splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            other.append(line)
            continue
        if record.get("severity") == "error":
            file = Path(record["file"]).as_posix()
            errors.append(MypyError(file, record["line"], record.get("code"), record["message"]))
    # Exit status 2 is a crash or a configuration error, not type errors: never compare then.
    if proc.returncode not in (0, 1) or (proc.returncode == 1 and not errors):
        sys.exit(
            f"typecheck: mypy failed (exit status {proc.returncode}):\n"
            + "\n".join(other + proc.stderr.splitlines())
        )
    return errors


def load_baseline() -> dict[str, int]:
    """Read the committed per-file error counts (an absent file means no errors allowed)."""
    if not BASELINE.exists():
        return {}
    return json.loads(BASELINE.read_text())


def write_baseline(counts: Counter[str]) -> None:
    """Write per-file counts, sorted, one file a line, so the diff of an update reads easily."""
    data = {file: counts[file] for file in sorted(counts) if counts[file] > 0}
    BASELINE.write_text(json.dumps(data, indent=2) + "\n")


def main(argv: list[str] | None = None) -> int:
    """Compare mypy's per-file error counts with the baseline, or rewrite it with ``--update``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--update", action="store_true", help="rewrite the baseline with the current counts"
    )
    args = parser.parse_args(argv)

    errors = run_mypy()
    counts = Counter(error.file for error in errors)
    baseline = load_baseline()
    files = sorted(set(counts) | set(baseline))
    total, allowed = sum(counts.values()), sum(baseline.values())

    if args.update:
        write_baseline(counts)
        for file in files:
            if counts[file] != baseline.get(file, 0):
                print(f"  {file}: {baseline.get(file, 0)} -> {counts[file]}")
        print(
            f"typecheck: baseline {BASELINE.relative_to(ROOT)} updated "
            f"({allowed} -> {total} errors in {len(counts)} files)"
        )
        return 0

    worse = [file for file in files if counts[file] > baseline.get(file, 0)]
    better = [file for file in files if counts[file] < baseline.get(file, 0)]
    if worse:
        print("typecheck: FAILED, mypy errors grew in these files (the baseline only shrinks):\n")
        for file in worse:
            print(f"{file}: {counts[file]} errors, baseline allows {baseline.get(file, 0)}")
            for error in errors:
                if error.file == file:
                    print(f"    {error}")
            print()
        print(
            "Fix the new errors (or, if mypy is wrong, add a `# type: ignore[code]` with a "
            "reason). The lines above are all of each file's errors: the baseline keeps "
            "counts, not lines."
        )
        return 1

    print(f"typecheck: OK, {total} mypy errors in {len(counts)} files (baseline {allowed})")
    if better:
        print("\nFewer errors than the baseline in:")
        for file in better:
            print(f"  {file}: {baseline[file]} -> {counts[file]}")
        print(
            "Lock the improvement in: python tools/typecheck.py --update "
            "(and commit tools/typecheck_baseline.json)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
