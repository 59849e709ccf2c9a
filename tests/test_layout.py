"""The house rules of `gvae_core` (DESIGN.md, Layout), read from the source with `ast`.

A *room* is a top-level module of gvae_core (`hessian.py`) or a subpackage (`rendering/`, all its
modules together); an *arrow* is an import of one module by another, function-local imports
included (a local import still ties the two together: it only hides the loop at import time), and
`importlib.import_module` of a literal name. The rooms stand on the floors of `FLOORS`, from the
ground up, the way data flows in DESIGN.md. The rules:

1. every module belongs to a room that `FLOORS` places (a new module is given its floor here);
2. no upward import: no arrow points to a room on a higher floor (arrows within a floor may);
3. no circle: neither among the rooms nor among the modules (a package's own modules included,
   its `__init__` one of them);
4. no module imports another room's private name (one with a leading underscore): what a room
   shares is its public, documented interface (the rasteriser's steps that the Hessian recomputes).

The top floor holds the entry points (`cli`, `benchmarks`, `__main__` and gvae_core's own
`__init__` with its lazy re-exports): they may import anything, and nothing below imports them.

One home per convention: the opacity sigmoid is `conventions.sigmoid` (the form that keeps a logit
of +-inf as opacity 1 / 0) and `conventions.activate_opacities` (clamped); no hand-written logistic
(`1 / (1 + exp(-x))` in any spelling, `expit`, a sigmoid of something named for opacity) in
gvae_core, gvae_addon or tools outside `conventions.py`, but where `SIGMOID_ELSEWHERE` says why.

`python -m tests.test_layout` prints the counts: rooms, arrows, circles, upward imports.
"""

from __future__ import annotations

import ast
import functools
import re
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "gvae_core"

#: The floors of gvae_core, from the ground up (DESIGN.md, Layout): a room may import its own
#: floor and those below it.
FLOORS: tuple[tuple[str, frozenset[str]], ...] = tuple((name, frozenset(rooms.split())) for name, rooms in (
    # conventions and plain helpers that know no Gaussians
    ("ground", "conventions camera atomic resources parallel progress quaternions losses plateau"),
    # the cloud, its transforms and what says how it is drawn (anti-aliasing sizes, octaves)
    ("cloud", "cloud transform antialias octaves"),
    # files: splat formats, images and captures, generated scenes and examples
    ("files", "ply formats datasets capture scenes examples"),
    ("rendering", "rendering"),
    # progressive 3DGS training, where it starts, its densification and the lineages it records
    ("training", "train initialization densify lineage"),
    ("vae", "vae"),
    ("hessian", "hessian"),
    # refine and compact, and what they build on (DESIGN.md step 5)
    ("refinement", "refinement budget fidelity detail superres compaction controls warmup"),
    ("evaluation", "metrics experiment report"),
    # entry points: may import anything
    ("top", "cli benchmarks __main__ __init__"),
))
FLOOR_OF = {room: level for level, (_, rooms) in enumerate(FLOORS) for room in rooms}

#: Where a hand-written logistic may stay, and why.
SIGMOID_ELSEWHERE = {
    "gvae_core/rendering/reference.py": "the float64 oracle keeps its own arithmetic: it is the check on the fast path",
    "gvae_core/rendering/kernels.py": "Numba kernels call no Python; the tests hold them to the torch path",
}
SIGMOID_SCAN = ("gvae_core", "gvae_addon", "tools")
SIGMOID_HOME = "gvae_core/conventions.py"


# ------------------------------------------------------------------------------ the import graph

def modules(root: Path = ROOT) -> dict[str, tuple[Path, bool]]:
    """Dotted name -> (file, is a package's __init__) of every module of gvae_core."""
    out = {}
    for path in sorted((root / PACKAGE).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return out


def _targets(name: str, is_package: bool, node: ast.AST, known) -> list[str]:
    """The gvae_core modules that one import node names (`from X import m` names X.m when m is a
    module, else X)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names if a.name.split(".")[0] == PACKAGE]
    if isinstance(node, ast.Call):  # importlib.import_module("name" or ".name", __package__)
        arg = node.args[0].value
        if arg.startswith("."):
            base = name.split(".") if is_package else name.split(".")[:-1]
            arg = ".".join(base) + arg
        return [arg] if arg.split(".")[0] == PACKAGE else []
    if node.level:
        base = name.split(".") if is_package else name.split(".")[:-1]
        target = ".".join(base[:len(base) - node.level + 1] + ([node.module] if node.module else []))
    else:
        target = node.module or ""
        if target.split(".")[0] != PACKAGE:
            return []
    return [f"{target}.{a.name}" if f"{target}.{a.name}" in known else target for a in node.names]


def _is_import_module(node: ast.AST) -> bool:
    return (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
            and (getattr(node.func, "attr", None) or getattr(node.func, "id", None)) == "import_module")


def import_graph(root: Path = ROOT) -> tuple[dict[str, set[str]], list[tuple[str, str, str]]]:
    """(module -> the modules it imports, [(module, other room's module, private name)])."""
    known = modules(root)
    edges: dict[str, set[str]] = {name: set() for name in known}
    private = []
    for name, (path, is_package) in known.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not (isinstance(node, (ast.Import, ast.ImportFrom)) or _is_import_module(node)):
                continue
            targets = set()
            for target in _targets(name, is_package, node, known):
                while target not in known:
                    target = target.rsplit(".", 1)[0]
                targets.add(target)
            edges[name] |= targets - {name}
            hidden = [a.name for a in node.names] if isinstance(node, ast.ImportFrom) else []
            hidden = [h for h in hidden if re.match(r"_[^_]", h)]
            if hidden and any(room(t) != room(name) for t in targets):
                private.append((name, min(targets), ", ".join(hidden)))
    return edges, private


def room(module: str) -> str:
    """The room of a module: its top-level module or subpackage under gvae_core."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def room_graph(edges: dict[str, set[str]]) -> dict[str, set[str]]:
    out: dict[str, set[str]] = defaultdict(set)
    for a, targets in edges.items():
        out[room(a)]
        for b in targets:
            if room(a) != room(b):
                out[room(a)].add(room(b))
    return dict(out)


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one node (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def upward(edges: dict[str, set[str]]) -> list[str]:
    """Every module-to-module arrow into a room on a higher floor, as 'a (floor) -> b (floor)'."""
    out = []
    for a, targets in sorted(edges.items()):
        for b in sorted(targets):
            fa, fb = FLOOR_OF.get(room(a)), FLOOR_OF.get(room(b))
            if fa is not None and fb is not None and fb > fa:
                out.append(f"{a} ({FLOORS[fa][0]}) -> {b} ({FLOORS[fb][0]})")
    return out


def counts(root: Path = ROOT) -> dict[str, int]:
    edges, private = import_graph(root)
    rooms = room_graph(edges)
    return {"modules": len(edges), "module arrows": sum(map(len, edges.values())), "rooms": len(rooms),
            "room arrows": sum(map(len, rooms.values())), "room circles": len(circles(rooms)),
            "module circles": len(circles(edges)), "upward imports": len(upward(edges)),
            "private imports across rooms": len(private)}


# ------------------------------------------------------------------------------ the sigmoid

def _name(func: ast.AST) -> str | None:
    return getattr(func, "attr", None) or getattr(func, "id", None)


def _is_one(node: ast.AST) -> bool:
    """1, 1.0, np.float32(1.0), a constant named ONE."""
    if isinstance(node, ast.Constant):
        return node.value == 1 and not isinstance(node.value, bool)
    if isinstance(node, ast.Call) and len(node.args) == 1:
        return _is_one(node.args[0])
    return isinstance(node, (ast.Name, ast.Attribute)) and (_name(node) or "").strip("_").upper() == "ONE"


def _exp_of_negation(node: ast.AST, exp_names: set[str]) -> bool:
    """exp(-x) as np.exp(-x), math.exp(-x), (-x).exp(), or a name assigned from one."""
    if isinstance(node, ast.Name):
        return node.id in exp_names
    if not isinstance(node, ast.Call):
        return False
    while isinstance(node, ast.Call) and _name(node.func) == "astype":  # np.exp(-x).astype(f32)
        node = node.func.value
    if not (isinstance(node, ast.Call) and _name(node.func) == "exp"):
        return False
    arg = node.args[0] if node.args else getattr(node.func, "value", None)
    return isinstance(arg, ast.UnaryOp) and isinstance(arg.op, ast.USub)


def _one_plus_exp(node: ast.AST, exp_names: set[str]) -> bool:
    return (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add)
            and any(_is_one(a) and _exp_of_negation(b, exp_names)
                    for a, b in ((node.left, node.right), (node.right, node.left))))


def hand_written_sigmoids(path: Path) -> list[str]:
    """'line: code' of every logistic written out in a file (see the module's docstring)."""
    tree = ast.parse(path.read_text(), str(path))
    conventions = {a.asname or a.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
                   and (node.module or "").split(".")[-1] == "conventions" for a in node.names}
    exp_names = {t.id for node in ast.walk(tree) if isinstance(node, ast.Assign)
                 and any(_exp_of_negation(n, set()) for n in ast.walk(node.value))
                 for t in node.targets if isinstance(t, ast.Name)}
    found = []
    for node in ast.walk(tree):
        hit = False
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
            hit = _one_plus_exp(node.right, exp_names)
        elif isinstance(node, ast.Call) and _name(node.func) == "reciprocal" and node.args:
            hit = _one_plus_exp(node.args[0], exp_names)
        elif isinstance(node, (ast.Name, ast.Attribute)) and _name(node) == "expit":
            hit = True
        elif isinstance(node, ast.Call) and _name(node.func) in ("sigmoid", "sigmoid_"):
            ours = isinstance(node.func, ast.Name) and node.func.id in conventions or (
                isinstance(node.func, ast.Attribute) and _name(node.func.value) == "conventions")
            operands = [*node.args, *([node.func.value] if isinstance(node.func, ast.Attribute) else [])]
            hit = not ours and any(re.search("opacit", ast.unparse(a), re.I) for a in operands)
        if hit:
            found.append((node.lineno, f"{node.lineno}: {ast.unparse(node)}"))
    return [text for _, text in sorted(found)]


def sigmoid_files(root: Path = ROOT) -> list[Path]:
    return sorted(p for base in SIGMOID_SCAN for p in (root / base).rglob("*.py")
                  if p.relative_to(root).as_posix() not in (SIGMOID_HOME, *SIGMOID_ELSEWHERE))


# ------------------------------------------------------------------------------ tests

@functools.lru_cache(maxsize=1)
def _graph() -> tuple[dict[str, set[str]], list[tuple[str, str, str]]]:
    """The project's import graph, read once for all the tests below (none of them changes it)."""
    return import_graph()


def test_every_module_has_a_floor():
    edges, _ = _graph()
    homeless = sorted({room(m) for m in edges} - set(FLOOR_OF))
    assert not homeless, f"rooms of gvae_core that FLOORS does not place: {homeless}"
    assert not set(FLOOR_OF) - {room(m) for m in edges}, "FLOORS names rooms that do not exist"


def test_no_upward_import():
    """Rendering knows nothing of the Hessian, training or refinement, and so on up the house."""
    found = upward(_graph()[0])
    assert not found, "imports of a higher floor (FLOORS in tests/test_layout.py):\n" + "\n".join(found)


def test_no_import_circle():
    edges, _ = _graph()
    assert circles(room_graph(edges)) == [], "rooms that import each other"
    assert circles(edges) == [], "modules that import each other (function-local imports count)"


def test_no_private_name_across_rooms():
    _, private = _graph()
    assert not private, "private names imported from another room:\n" + "\n".join(map(str, private))


def test_the_rules_catch_what_they_are_for():
    """The checks themselves: a circle, an upward arrow, a sigmoid in each spelling that was here."""
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert upward({"gvae_core.rendering.compiled": {"gvae_core.hessian"}}) == [
        "gvae_core.rendering.compiled (rendering) -> gvae_core.hessian (hessian)"]
    assert upward({"gvae_core.hessian": {"gvae_core.rendering.compiled"}}) == []


def test_one_sigmoid(tmp_path):
    """Every logistic of an opacity goes through `conventions`; the spellings that were written out
    before are caught."""
    found = {p.relative_to(ROOT).as_posix(): hits for p in sigmoid_files() if (hits := hand_written_sigmoids(p))}
    assert not found, f"hand-written sigmoids outside {SIGMOID_HOME}: {found}"
    sample = tmp_path / "sample.py"
    sample.write_text(
        "import numpy as np, torch\nfrom scipy.special import expit\nfrom gvae_core.conventions import sigmoid\n"
        "a = 1.0 / (1.0 + np.exp(-x.astype(np.float64)))\n"
        "b = 1 / (1 + np.exp(-x))\n"
        "e = np.exp(-x.astype(np.float64)).astype(np.float32)\n"
        "c = np.float32(1.0) / (np.float32(1.0) + e)\n"
        "d = torch.sigmoid(pred[..., APP_OPACITY])\n"
        "f = np.reciprocal(1 + np.exp(-x))\n"
        "g = expit(x)\n"
        "ok = (sigmoid(opacities), torch.sigmoid(exist_logit), np.exp(-d2 / 2), 1 / (2 + np.exp(-x)))\n")
    assert [hit.split(":")[0] for hit in hand_written_sigmoids(sample)] == ["4", "5", "7", "8", "9", "10"]


if __name__ == "__main__":
    for key, value in counts().items():
        print(f"{key}: {value}")
    edges, private = import_graph()
    for line in upward(edges):
        print("upward:", line)
    for component in circles(room_graph(edges)) + circles(edges):
        print("circle:", " <-> ".join(component))
    for item in private:
        print("private:", *item)
