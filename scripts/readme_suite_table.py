"""Replace a suite's table in README.md with the one in its results folder (written by `ddp suite --report`).

    python3 scripts/readme_suite_table.py metaworld_cpu

The README's copy is the markdown table that follows the line `<!-- suite-table: <suite> -->` (blank lines
between them allowed).
"""
import argparse
import sys
from pathlib import Path

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("suite", help="the suite's name: its table is results/suites/<suite>/table.md")
suite = parser.parse_args().suite
root = Path(__file__).resolve().parents[1]
source = root / "results" / "suites" / suite / "table.md"
if not source.is_file():
    sys.exit(f"{source}: not found; run `ddp suite suites/{suite}.yaml --report` first")
table = [l for l in source.read_text().splitlines() if l.startswith("|")]
if len(table) < 3:  # a header, its rule and at least one row: else the README's table would be deleted
    sys.exit(f"{source}: no table in it; run `ddp suite suites/{suite}.yaml --report` again")
lines = (root / "README.md").read_text().split("\n")
marker = f"<!-- suite-table: {suite} -->"
if marker not in lines:
    known = sorted(l.split(":", 1)[1].strip(" ->") for l in lines if l.startswith("<!-- suite-table:"))
    sys.exit(f"README.md: no line '{marker}' (tables marked: {', '.join(known) or 'none'})")
start = lines.index(marker) + 1
while start < len(lines) and not lines[start].strip():
    start += 1
if start == len(lines) or not lines[start].startswith("|"):
    sys.exit(f"README.md: no table after '{marker}' (line {lines.index(marker) + 1})")
end = start
while end < len(lines) and lines[end].startswith("|"):
    end += 1
lines[start:end] = table
(root / "README.md").write_text("\n".join(lines))
print(f"README.md: {suite} table, {len(table) - 2} rows (lines {start + 1}-{start + len(table)})")
