"""Generate the documentation pages that must not drift from their sources.

    python docs/gen_pages.py          # rewrite docs/configuration.md and docs/results.md
    python docs/gen_pages.py --check  # exit 1 if either committed page differs from what it generates

- docs/configuration.md: every key of every JSON Schema the project validates YAML and records with
  (src/vlaquantbench/config/schemas/*.yaml, src/vlaquantbench/records/schemas/*.yaml), with its type,
  allowed values, default and description, read from the schema files.
- docs/results.md: the measured figures of benchmarks/results/summary.json, the test tiers' times of
  benchmarks/results/test_tiers.json and the committed study tables (tables/*.tex of the studies whose
  records are committed), each naming the file it comes from.

tests/test_docs.py checks both pages are what this script writes, so a schema change or a re-measurement
that is not regenerated fails the tests.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SCHEMA_DIRS = (ROOT / "src/vlaquantbench/config/schemas", ROOT / "src/vlaquantbench/records/schemas")
SUMMARY = ROOT / "benchmarks/results/summary.json"
TEST_TIERS = ROOT / "benchmarks/results/test_tiers.json"
# Study tables rendered from committed records: (title, committed table definition, command that renders it).
STUDY_TABLES = (
    ("Quantization methods on the pi0.5 trained here (Meta-World)",
     "config/methods_2026/tables/methods_2026.yaml",
     "snakemake --cores 2 tables/methods_2026.tex --configfile config/trained_cpu.yaml",
     "results/methods_2026", "manifests/methods_2026.tsv"),
    ("Live sequential stopping rule on the trained policy",
     "config/trained_sequential/tables/trained_sequential.yaml",
     "snakemake --cores 2 tables/trained_sequential.tex --configfile config/trained_sequential.yaml",
     "results/trained_sequential/live", "manifests/trained_sequential_live.tsv"),
    ("Real low-bit kernels on the GPU-trained policy",
     "config/gpu_kernels/tables/gpu_kernels.yaml",
     "snakemake --cores 2 tables/gpu_kernels.tex --configfile config/gpu_study.yaml config/gpu_kernels.yaml "
     "--config records_dir=results/gpu_study/fixed manifest=manifests/gpu_study_fixed.tsv",
     "results/gpu_study/fixed", "manifests/gpu_study_fixed.tsv"),
)


# ----------------------------------------------------------------------------- configuration reference

def schema_files() -> list[Path]:
    return [path for folder in SCHEMA_DIRS for path in sorted(folder.glob("*.schema.yaml"))]


def _type(node: dict) -> str:
    if "enum" in node:
        return "one of " + ", ".join(f"`{json.dumps(v)}`" for v in node["enum"])
    if "const" in node:
        return f"`{json.dumps(node['const'])}`"
    if "$ref" in node:
        return f"see `{node['$ref'].split('/')[-1].lstrip('#')}`"
    kind = node.get("type")
    if isinstance(kind, list):
        text = " or ".join(kind)
    elif kind:
        text = kind
    elif any(k in node for k in ("oneOf", "anyOf")):
        text = " or ".join(_type(alt) for alt in node.get("oneOf", node.get("anyOf", [])))
    else:
        text = "any"
    if kind == "array" or (isinstance(kind, list) and "array" in kind):
        items = node.get("items")
        if isinstance(items, dict) and items:
            text += f" of {_type(items)}"
    bounds = [f"{word} {node[key]}" for key, word in (("minimum", "≥"), ("maximum", "≤"), ("exclusiveMinimum", ">"),
                                                    ("exclusiveMaximum", "<"), ("minItems", "items ≥"),
                                                    ("pattern", "pattern")) if key in node]
    if bounds:
        text += " (" + ", ".join(f"`{b}`" if b.startswith("pattern") else b for b in bounds) + ")"
    return text


def _cell(text) -> str:
    """One table cell: one line, pipes escaped, and `<...>` outside code spans shown, not read as HTML."""
    parts = " ".join(str(text).split()).replace("|", "\\|").split("`")
    return "`".join(p if i % 2 else p.replace("<", "&lt;").replace(">", "&gt;") for i, p in enumerate(parts))


def walk(node: dict, path: str, rows: list[tuple[str, str, str]], required: bool = False) -> None:
    """Append (key path, type, description) for `node` and every key below it."""
    if not isinstance(node, dict):
        return
    if path:
        description = node.get("description", "")
        if "default" in node:
            description += f" Default: `{json.dumps(node['default'])}`."
        if required:
            description = "**required.** " + description
        rows.append((path, _type(node), description))
    needed = set(node.get("required", []))
    for key, child in (node.get("properties") or {}).items():
        walk(child, f"{path}.{key}" if path else key, rows, key in needed)
    extra = node.get("additionalProperties")
    if isinstance(extra, dict) and extra:
        walk(extra, f"{path}.<name>" if path else "<name>", rows)
    for key, child in (node.get("patternProperties") or {}).items():
        walk(child, f"{path}.<{key}>" if path else f"<{key}>", rows)
    items = node.get("items")
    if isinstance(items, dict) and (items.get("properties") or items.get("oneOf") or items.get("anyOf")):
        walk_inner(items, f"{path}[]", rows)
    for word in ("oneOf", "anyOf", "allOf"):
        for alt in node.get(word, []):
            walk_inner(alt, path, rows)


def walk_inner(node: dict, path: str, rows: list) -> None:
    """The keys of an item or alternative, without a row for the node itself."""
    needed = set(node.get("required", []))
    for key, child in (node.get("properties") or {}).items():
        walk(child, f"{path}.{key}" if path else key, rows, key in needed)
    extra = node.get("additionalProperties")
    if isinstance(extra, dict) and extra:
        walk(extra, f"{path}.<name>", rows)
    for word in ("oneOf", "anyOf", "allOf"):
        for alt in node.get(word, []):
            walk_inner(alt, path, rows)


def schema_keys(schema: dict) -> set[str]:
    """Every property name anywhere in a schema (what the reference must cover)."""
    keys: set[str] = set()

    def visit(node):
        if isinstance(node, dict):
            for key, child in node.items():
                if key in ("properties", "$defs", "definitions", "patternProperties") and isinstance(child, dict):
                    if key == "properties":
                        keys.update(child)
                    for value in child.values():
                        visit(value)
                else:
                    visit(child)
        elif isinstance(node, list):
            for child in node:
                visit(child)

    visit(schema)
    return keys


def configuration_page() -> str:
    out = [
        "# Configuration reference",
        "",
        "<!-- Generated by docs/gen_pages.py from the JSON Schemas; do not edit by hand. -->",
        "",
        "Every YAML file the project reads, and every record it checks, is validated against one of these",
        "JSON Schemas; an error names the file, the key path and the allowed keys or values. This page is",
        "generated from the schema files, so it lists exactly the keys they accept. `<name>` stands for a key",
        "you choose (a model, a table, a cell name); `[]` for each item of a list. Defaults not stated here",
        "live in the dataclasses of `vlaquantbench.config.study`.",
        "",
    ]
    for path in schema_files():
        schema = yaml.safe_load(path.read_text())
        rel = path.relative_to(ROOT)
        out += [f"## `{path.name.removesuffix('.schema.yaml')}`", "", f"Schema: `{rel}`.", ""]
        if schema.get("description"):
            out += [_cell(schema["description"]), ""]
        rows: list[tuple[str, str, str]] = []
        walk_inner(schema, "", rows)
        for name, definition in (schema.get("$defs") or {}).items():
            walk(definition, f"$defs.{name}", rows)
        out += ["| key | type | description |", "|---|---|---|"]
        out += [f"| `{key}` | {_cell(kind)} | {_cell(text)} |" for key, kind, text in rows]
        out.append("")
    return "\n".join(out)


# ----------------------------------------------------------------------------- results

def _flatten(value, prefix: str = "") -> list[tuple[str, object]]:
    if isinstance(value, dict):
        return [row for key, child in value.items() for row in _flatten(child, f"{prefix}.{key}" if prefix else key)]
    return [(prefix, value)]


def _value(value) -> str:
    if isinstance(value, list):
        return ", ".join(_value(v) for v in value[:12]) + (" …" if len(value) > 12 else "")
    if isinstance(value, float):
        return f"{value:.4g}"
    return _cell(value)


def results_page() -> str:
    out = [
        "# Results",
        "",
        "<!-- Generated by docs/gen_pages.py from benchmarks/results/summary.json, benchmarks/results/test_tiers.json",
        "     and the committed study tables; do not edit by hand. -->",
        "",
        "Every figure on this page is read from a committed results file, named with it; a re-measurement",
        "that rewrites the file updates this page (`python docs/gen_pages.py`). How each figure is measured,",
        "and the one command that measures it, is in `benchmarks/README.md`.",
        "",
    ]
    if TEST_TIERS.exists():
        tiers = json.loads(TEST_TIERS.read_text())
        out += ["## Test suite", "", f"From `{TEST_TIERS.relative_to(ROOT)}`.", "",
                "| tier | command | wall time | tests | measured on | date |", "|---|---|---|---|---|---|"]
        for name, tier in tiers.get("tiers", {}).items():
            minutes = tier.get("wall_s")
            wall = f"{minutes / 60:.1f} min" if isinstance(minutes, (int, float)) else "not measured"
            out.append(f"| {name} | `{tier.get('command', '')}` | {wall} | {_cell(tier.get('tests', ''))} "
                       f"| {_cell(tier.get('machine', tiers.get('machine', '')))} | {tier.get('date', '')} |")
        out.append("")
    summary = json.loads(SUMMARY.read_text())
    out += ["## Benchmarks", "", f"From `{SUMMARY.relative_to(ROOT)}` (`python benchmarks/gpu_summary.py` rewrites "
            "its GPU figures). Each section is one key of the file.", ""]
    for key, entry in summary.items():
        out += [f"### `{key}`", ""]
        if isinstance(entry, dict):
            source = entry.get("source") or entry.get("file") or entry.get("results")
            if source:
                out += [f"Source: `{_cell(source)}`.", ""]
            out += ["| field | value |", "|---|---|"]
            out += [f"| `{field}` | {_value(value)} |" for field, value in _flatten(entry)
                    if field not in ("source", "file", "results")]
        else:
            out.append(_value(entry))
        out.append("")
    out += ["## Study tables", "",
            "Rendered here from the committed records, checked against their manifest, by the code that renders",
            "the tables in the workflow; the definition, records and manifest are named with each.", ""]
    for title, definition, command, records, manifest in STUDY_TABLES:
        out += [f"### {title}", "", f"Definition `{definition}`; records `{records}`, checked against `{manifest}`;",
                f"the workflow renders it with `{command}`.", "", study_table(definition, records, manifest), ""]
    return "\n".join(out)


def study_table(definition: str, records: str, manifest: str) -> str:
    """The table `definition` rendered from the cell folders under `records` (one per reference), as HTML."""
    from vlaquantbench.manifest import verified
    from vlaquantbench.tables import load_table
    from vlaquantbench.tables.latex import booktabs, read_cells

    table = load_table(ROOT / definition)
    refs = table.refs()
    folders = [str(ROOT / records / ref) for ref in refs]
    checked = verified([str(ROOT / manifest)], str(ROOT / records), folders)
    page = booktabs(table, read_cells(refs, dict(zip(refs, checked)))).html()
    return page[page.index("<table"):page.index("</table>") + len("</table>")]


PAGES = {"configuration.md": configuration_page, "results.md": results_page}


def main(argv: list[str]) -> int:
    stale = []
    for name, make in PAGES.items():
        path, text = DOCS / name, make() + "\n"
        if "--check" in argv:
            if not path.exists() or path.read_text() != text:
                stale.append(name)
        else:
            path.write_text(text)
    if stale:
        print("stale: " + ", ".join(stale) + " (python docs/gen_pages.py rewrites them)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
