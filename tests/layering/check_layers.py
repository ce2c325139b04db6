#!/usr/bin/env python3
"""The layering check of include/epona (issue #35).

The map is the table between the `layer-map` markers of docs/architecture.md: one row per
folder of include/epona, saying which other folders its headers may include. This script reads
that table, scans every `#include "epona/..."` (or <epona/...>) of every header under include/epona, and fails,
naming each offending edge (file:line, its layer, the included layer), when a header includes
a folder its row does not list, when a folder is missing from the map, when an included header
does not exist, or when headers include each other in a cycle.

  check_layers.py [REPO]     check the repository at REPO (default: two folders up)
  check_layers.py --self-test  run the checker on small fixture trees (one clean, one with an
                             upward include, one with a cycle) and check that it says so

Python 3 standard library only: it runs wherever ctest does.
"""

import os
import re
import sys
import tempfile
import unittest

MAP_BEGIN = "<!-- layer-map:begin -->"
MAP_END = "<!-- layer-map:end -->"
HEADER_SUFFIXES = (".hpp", ".h", ".cuh")
INCLUDE_RE = re.compile(r'^\s*#\s*include\s*[<"]epona/([^">]+)[">]')


def strip_cell(cell):
    return cell.strip().strip("`").strip()


def read_map(doc_path):
    """Folder -> set of folders it may include (its own folder always allowed; '*' = any)."""
    with open(doc_path, encoding="utf-8") as f:
        text = f.read()
    if MAP_BEGIN not in text or MAP_END not in text:
        raise SystemExit(f"{doc_path}: no layer map (the table between {MAP_BEGIN} and {MAP_END})")
    table = text.split(MAP_BEGIN, 1)[1].split(MAP_END, 1)[0]
    layers = {}
    for line in table.splitlines():
        line = line.strip()
        if not line.startswith("|"):
            continue
        cells = [strip_cell(c) for c in line.strip("|").split("|")]
        if len(cells) < 2 or set(cells[0]) <= set("-: ") or cells[0].lower() == "folder":
            continue  # separator or header row
        folder = cells[0].rstrip("/")
        allowed = set()
        for name in cells[1].split(","):
            name = strip_cell(name).rstrip("/")
            if name and name not in ("—", "-", "nothing"):
                allowed.add(name)
        allowed.add(folder)
        layers[folder] = allowed
    if not layers:
        raise SystemExit(f"{doc_path}: the layer map has no rows")
    return layers


def layer_of(rel_path):
    """The layer of a path under include/epona: its first folder, or the file name at the top.

    Sub-folders belong to the layer of their top folder (cuda/gemm/x.cuh is layer cuda,
    nn/blocks/y.hpp layer nn): they group a layer's headers by concern and need no row."""
    return rel_path.split("/", 1)[0]


def scan_headers(include_root):
    """rel path -> [(line number, included rel path)] for every header under include_root."""
    headers = {}
    for dirpath, dirnames, filenames in os.walk(include_root):
        dirnames.sort()
        for name in sorted(filenames):
            if not name.endswith(HEADER_SUFFIXES):
                continue
            path = os.path.join(dirpath, name)
            rel = os.path.relpath(path, include_root).replace(os.sep, "/")
            edges = []
            with open(path, encoding="utf-8", errors="replace") as f:
                for number, line in enumerate(f, 1):
                    m = INCLUDE_RE.match(line)
                    if m:
                        edges.append((number, m.group(1)))
            headers[rel] = edges
    return headers


def find_cycles(headers):
    """Each strongly connected set of headers that include each other (Tarjan, iterative)."""
    graph = {h: sorted({inc for _, inc in edges if inc in headers}) for h, edges in headers.items()}
    index, low, on_stack, stack, cycles = {}, {}, set(), [], []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, 0)]
        while work:
            node, i = work.pop()
            if i == 0:
                index[node] = low[node] = counter
                counter += 1
                stack.append(node)
                on_stack.add(node)
            if i < len(graph[node]):
                work.append((node, i + 1))
                nxt = graph[node][i]
                if nxt not in index:
                    work.append((nxt, 0))
                elif nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
                continue
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1 or node in graph[node]:
                    cycles.append(sorted(component))
    return cycles


def check(repo):
    """The list of problems of the repository at `repo` (empty = the layering holds)."""
    layers = read_map(os.path.join(repo, "docs", "architecture.md"))
    include_root = os.path.join(repo, "include", "epona")
    headers = scan_headers(include_root)
    problems = []
    for folder in sorted({layer_of(h) for h in headers} - set(layers)):
        problems.append(f"include/epona/{folder}: not in the layer map of docs/architecture.md")
    for header, edges in sorted(headers.items()):
        source = layer_of(header)
        allowed = layers.get(source, {source})
        for number, included in edges:
            where = f"include/epona/{header}:{number}"
            if included not in headers:
                problems.append(f"{where}: includes epona/{included}, which does not exist")
                continue
            target = layer_of(included)
            if "*" not in allowed and target not in allowed:
                problems.append(f"{where}: layer {source} includes layer {target} (epona/{included}); "
                                f"{source} may include: {', '.join(sorted(allowed))}")
    for cycle in find_cycles(headers):
        problems.append("include cycle: " + " <-> ".join(f"epona/{h}" for h in cycle))
    return problems


def main(argv):
    if argv[1:] == ["--self-test"]:
        result = unittest.main(argv=[argv[0]], exit=False, verbosity=2).result
        return 0 if result.wasSuccessful() else 1
    repo = argv[1] if len(argv) > 1 else os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..")
    problems = check(repo)
    for p in problems:
        print(p)
    if problems:
        print(f"layering check: {len(problems)} problem(s); the map is docs/architecture.md")
        return 1
    print("layering check: every include of include/epona follows docs/architecture.md")
    return 0


class SelfTest(unittest.TestCase):
    MAP = f"""# Fixture
{MAP_BEGIN}
| folder | may include | what |
|---|---|---|
| `low` | — | bottom |
| `high` | `low` | top |
{MAP_END}
"""

    def make_tree(self, files):
        root = tempfile.TemporaryDirectory()
        self.addCleanup(root.cleanup)
        files = dict(files)
        files.setdefault("docs/architecture.md", self.MAP)
        for rel, text in files.items():
            path = os.path.join(root.name, rel)
            os.makedirs(os.path.dirname(path), exist_ok=True)
            with open(path, "w", encoding="utf-8") as f:
                f.write(text)
        return root.name

    def test_clean_tree_passes(self):
        repo = self.make_tree({"include/epona/low/a.hpp": "#pragma once\n",
                               "include/epona/high/b.hpp": '#pragma once\n#include "epona/low/a.hpp"\n'})
        self.assertEqual(check(repo), [])
        self.assertEqual(main(["check_layers.py", repo]), 0)

    def test_upward_include_fails_naming_the_edge(self):
        repo = self.make_tree({"include/epona/low/a.hpp": '#pragma once\n\n#include "epona/high/b.hpp"\n',
                               "include/epona/high/b.hpp": "#pragma once\n"})
        problems = check(repo)
        self.assertEqual(len(problems), 1)
        self.assertIn("include/epona/low/a.hpp:3: layer low includes layer high", problems[0])
        self.assertEqual(main(["check_layers.py", repo]), 1)

    def test_angle_bracket_include_is_checked(self):
        repo = self.make_tree({"include/epona/low/a.hpp": "#include <epona/high/b.hpp>\n",
                               "include/epona/high/b.hpp": "#pragma once\n"})
        self.assertEqual(len(check(repo)), 1)

    def test_cycle_fails(self):
        repo = self.make_tree({"include/epona/low/a.hpp": '#include "epona/low/b.hpp"\n',
                               "include/epona/low/b.hpp": '#include "epona/low/a.hpp"\n'})
        self.assertEqual(check(repo), ["include cycle: epona/low/a.hpp <-> epona/low/b.hpp"])

    def test_unmapped_folder_and_missing_header_fail(self):
        repo = self.make_tree({"include/epona/other/c.hpp": '#include "epona/low/gone.hpp"\n'})
        problems = check(repo)
        self.assertIn("include/epona/other: not in the layer map of docs/architecture.md", problems)
        self.assertIn("include/epona/other/c.hpp:1: includes epona/low/gone.hpp, which does not exist", problems)

    def test_sub_folder_is_its_top_folders_layer(self):
        repo = self.make_tree({"include/epona/low/sub/a.hpp": "#pragma once\n",
                               "include/epona/low/b.hpp": '#include "epona/low/sub/a.hpp"\n',
                               "include/epona/high/deep/c.hpp": '#include "epona/low/sub/a.hpp"\n'})
        self.assertEqual(check(repo), [])
        repo = self.make_tree({"include/epona/low/sub/a.hpp": '#include "epona/high/deep/c.hpp"\n',
                               "include/epona/high/deep/c.hpp": "#pragma once\n"})
        problems = check(repo)
        self.assertEqual(len(problems), 1)
        self.assertIn("include/epona/low/sub/a.hpp:1: layer low includes layer high", problems[0])

    def test_map_is_read_from_the_table(self):
        repo = self.make_tree({})
        self.assertEqual(read_map(os.path.join(repo, "docs", "architecture.md")),
                         {"low": {"low"}, "high": {"high", "low"}})


if __name__ == "__main__":
    sys.exit(main(sys.argv))
