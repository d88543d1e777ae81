"""Draw the import graph between rigd's layers from the code, and check that no arrow runs up.

The layers are the import-linter *layers* contract in pyproject.toml (one source of truth):
each layer is a box, each sibling in a layer (`a | b`) its own node, and an arrow counts the
module-to-module imports between two nodes (imports inside functions included: a lazy import
is still a dependency). The graph is written into docs/architecture.md between the
`import-graph` markers.

    python tools/import_graph.py            # rewrite the graph in docs/architecture.md
    python tools/import_graph.py --check    # exit 1 if an arrow runs up or sideways, or the doc is stale
"""

from __future__ import annotations

import argparse
import collections
import sys
import tomllib
from pathlib import Path

import grimp

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "architecture.md"
START, END = "<!-- import-graph:start -->", "<!-- import-graph:end -->"


def layers() -> list[list[str]]:
    """The layers contract's layers, top first; each a list of its independent siblings."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    for contract in config["contracts"]:
        if contract["type"] == "layers":
            return [[name.strip() for name in layer.split("|")] for layer in contract["layers"]]
    raise SystemExit("pyproject.toml has no import-linter layers contract")


def node_of(module: str, nodes: list[str]) -> str | None:
    """The most specific node a module belongs to (rigd.products before rigd)."""
    best = None
    for node in nodes:
        if (module == node or module.startswith(node + ".")) and (best is None or len(node) > len(best)):
            best = node
    return best


def edges(stack: list[list[str]]) -> collections.Counter[tuple[str, str]]:
    """Module-level imports counted between nodes (a pair of modules counts once)."""
    nodes = [n for layer in stack for n in layer]
    roots = sorted({n.split(".")[0] for n in nodes})
    sys.path.insert(0, str(ROOT))
    graph = grimp.build_graph(*roots, include_external_packages=False)
    counts: collections.Counter[tuple[str, str]] = collections.Counter()
    for importer in graph.modules:
        a = node_of(importer, nodes)
        if a is None:
            continue
        for imported in graph.find_modules_directly_imported_by(importer):
            b = node_of(imported, nodes)
            if b is not None and b != a:
                counts[(a, b)] += 1
    return counts


def wrong_way(stack: list[list[str]], counts: collections.Counter[tuple[str, str]]) -> list[str]:
    """Arrows that run up a layer or sideways between siblings of one layer."""
    rank = {n: i for i, layer in enumerate(stack) for n in layer}
    bad = []
    for (a, b), n in sorted(counts.items()):
        if rank[a] > rank[b]:
            bad.append(f"{a} -> {b}: {n} import(s) run up a layer")
        elif rank[a] == rank[b]:
            bad.append(f"{a} -> {b}: {n} import(s) between siblings that must be independent")
    return bad


def mermaid(stack: list[list[str]], counts: collections.Counter[tuple[str, str]]) -> str:
    """A top-down mermaid flowchart: one subgraph per layer, arrows labelled with their counts."""
    ident = {n: n.replace(".", "_") for layer in stack for n in layer}
    lines = ["```mermaid", "flowchart TD"]
    for i, layer in enumerate(stack):
        lines.append(f'  subgraph L{i}["layer {i + 1}"]')
        lines += [f'    {ident[n]}["{n}"]' for n in layer]
        lines.append("  end")
    for (a, b), n in sorted(counts.items()):
        lines.append(f"  {ident[a]} -->|{n}| {ident[b]}")
    lines.append("```")
    return "\n".join(lines)


def render_doc(text: str, block: str) -> str:
    if START not in text or END not in text:
        raise SystemExit(f"{DOC}: the {START} / {END} markers are missing")
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{START}\n{block}\n{END}{tail}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="fail on a wrong-way arrow or a stale doc")
    args = parser.parse_args(argv)
    stack = layers()
    counts = edges(stack)
    bad = wrong_way(stack, counts)
    for line in bad:
        print(f"import graph: {line}", file=sys.stderr)
    text = DOC.read_text()
    new = render_doc(text, mermaid(stack, counts))
    if args.check:
        if new != text:
            print(f"{DOC.relative_to(ROOT)} is stale: run python tools/import_graph.py", file=sys.stderr)
            return 1
        return 1 if bad else 0
    DOC.write_text(new)
    print(f"wrote the graph of {sum(counts.values())} imports between {len(stack)} layers into {DOC.name}")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
