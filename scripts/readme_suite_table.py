"""Replace a suite's table in README.md with the one in its results folder (written by `ddp suite --report`).

    python3 scripts/readme_suite_table.py metaworld_cpu

The README's copy is the markdown table that follows the first prose line (not a table row) naming
`suites/<suite>.yaml`.
"""
import sys
from pathlib import Path

suite = sys.argv[1]
root = Path(__file__).resolve().parents[1]
table = [l for l in (root / "results" / "suites" / suite / "table.md").read_text().splitlines() if l.startswith("|")]
lines = (root / "README.md").read_text().split("\n")
anchor = next(i for i, l in enumerate(lines) if f"`suites/{suite}.yaml`" in l and not l.startswith("|"))
start = next(i for i in range(anchor, len(lines)) if lines[i].startswith("|"))
end = start
while end < len(lines) and lines[end].startswith("|"):
    end += 1
lines[start:end] = table
(root / "README.md").write_text("\n".join(lines))
print(f"README.md: {suite} table, {len(table) - 2} rows (lines {start + 1}-{start + len(table)})")
