"""Where tests find the checkout and the shared data beside it (`../shared`: the paper and the
authors' reference records, read in place and never copied into the project)."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
REFERENCE = SHARED / "reference"
RECORDS = REFERENCE / "records"
PAPER_TEX = SHARED / "spec" / "vlaquantbench-paper.tex"
