"""The import structure docs/architecture.md promises, read from the source (ast).

- no import cycle between modules of processing/, app/ and drivers/ (imports
  inside functions count: a lazy import is still a dependency);
- no cycle between the units of the layers either (processing, drivers and
  each sub-package of app: app.files must not import app.capture while
  capture imports files);
- no private name (``_x``) imported from another module, nor read from an
  imported module (``module._x``).
"""

import ast
import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("processing", "app", "drivers")


def _modules():
    mods = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT).with_suffix("")
            name = ".".join(rel.parts)
            if name.endswith(".__init__"):
                name = name[: -len(".__init__")]
            mods[name] = path
    return mods


MODULES = _modules()


def _is_package(name):
    return MODULES[name].name == "__init__.py"


def _known(target):
    """The project module ``target`` names (or the nearest package above it), or None."""
    while target and target not in MODULES:
        if "." not in target:
            return None
        target = target.rsplit(".", 1)[0]
    return target or None


def _imports(name):
    """``[(imported module, imported name or None, line)]`` of module ``name``, and the
    local names bound to project modules."""
    tree = ast.parse(MODULES[name].read_text(), str(MODULES[name]))
    out, aliases = [], {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] in PACKAGES:
                    out.append((_known(a.name), None, node.lineno))
                    if a.asname:
                        aliases[a.asname] = a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")
                if not _is_package(name):
                    base = base[:-1]
                base = base[: len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if module.split(".")[0] not in PACKAGES:
                continue
            for a in node.names:
                full = f"{module}.{a.name}"
                if full in MODULES:  # from package import module
                    out.append((full, None, node.lineno))
                    aliases[a.asname or a.name] = full
                else:
                    out.append((_known(module), a.name, node.lineno))
    return out, aliases, tree


def _graph(unit=lambda m: m):
    edges = {}
    for name in MODULES:
        for target, _, _ in _imports(name)[0]:
            a, b = unit(name), unit(target) if target else None
            if b is None or a == b:
                continue
            if b in PACKAGES:  # a package's __init__ (app.version and the like): not a layer
                continue
            edges.setdefault(a, set()).add(b)
    return edges


def _cycles(edges):
    """Strongly connected components with more than one member (Tarjan)."""
    index, low, stack, on, found = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(set(edges) | {w for ws in edges.values() for w in ws}):
        if v not in index:
            visit(v)
    return found


def _layer(module):
    parts = module.split(".")
    return ".".join(parts[:2]) if parts[0] == "app" and len(parts) > 1 else parts[0]


def test_the_walk_sees_the_project():
    # what the tests below rely on: the modules are found and their imports resolved
    assert {"processing.reconstruct", "processing.gpu", "app.batch.engine", "app.files.h5safe",
            "drivers.base"} <= set(MODULES)
    graph = _graph()
    assert "processing.chain_checkerboard" in graph["processing.reconstruct"]
    assert "processing.demodulation" in graph["processing.chain_checkerboard"]
    assert "app.batch.parallel" in graph["app.batch.engine"]
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycle_between_modules():
    assert _cycles(_graph()) == []


def test_no_import_cycle_between_layers():
    assert _cycles(_graph(_layer)) == []


def test_no_private_name_imported_or_read_across_modules():
    found = []
    for name in MODULES:
        imports, aliases, tree = _imports(name)
        for target, imported, line in imports:
            if imported and imported.startswith("_") and not imported.startswith("__") and target != name:
                found.append(f"{os.path.relpath(MODULES[name], ROOT)}:{line} imports {imported} from {target}")
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                    and node.value.id in aliases and node.attr.startswith("_") and not node.attr.startswith("__")):
                found.append(f"{os.path.relpath(MODULES[name], ROOT)}:{node.lineno} reads "
                             f"{aliases[node.value.id]}.{node.attr}")
    assert found == []


def _private_reads_off_other_objects(path):
    """``obj._name`` where ``obj`` is not ``self``/``cls``: another object's private
    attribute (in processing/gpu.py: the CPU chain's Reconstructor, Demodulator,
    HeightSolver)."""
    tree = ast.parse(path.read_text(), str(path))
    return [f"{path.name}:{node.lineno} {ast.unparse(node)}" for node in ast.walk(tree)
            if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
            and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))]


def test_gpu_chain_reads_only_public_names_of_the_cpu_chain(tmp_path):
    # issue 19 point 3: it read ~41 private attributes and wrote the series memory
    assert _private_reads_off_other_objects(ROOT / "processing" / "gpu.py") == []
    # the check sees such reads where they are (what gpu.py did before)
    sample = tmp_path / "sample.py"
    sample.write_text("def f(r, self):\n    return r._prev_phase, self._own\n")
    assert _private_reads_off_other_objects(sample) == ["sample.py:2 r._prev_phase"]


def test_chains_read_no_private_attribute_of_another_object():
    # the stage modules of issue 19 point 2 talk through public names only
    # (the facade's chain, the height solver's solve_at_tolerance / solve_spectral)
    # and so do the height solver's paths and the camera model split off their classes
    for name in ("reconstruct", "chain_checkerboard", "chain_image", "chain_dots", "series", "mask", "refine",
                 "fullgrid", "live_view", "height_spectral", "height_masked", "camera_model"):
        assert _private_reads_off_other_objects(ROOT / "processing" / f"{name}.py") == [], name
