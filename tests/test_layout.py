"""The package's shape: no import cycle, no private name across subpackages, the public API kept."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

import difftex

ROOT = Path(difftex.__file__).resolve().parent


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted(ROOT.rglob("*.py"))}


def _package_of(name: str) -> str:
    return name if MODULES[name].name == "__init__.py" else name.rpartition(".")[0]


def _imports(name: str) -> list[tuple[str, list[str], int]]:
    """(imported difftex module, names taken from it, line) of every import statement run when ``name`` loads.

    Function bodies are skipped: an import there runs on a call, after every module has loaded, so it
    cannot take part in an import cycle (``difftex.mapping.__getattr__`` uses one on purpose).
    """
    tree = ast.parse(MODULES[name].read_text(), str(MODULES[name]))
    out = []

    def visit(nodes) -> None:
        for node in nodes:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                continue
            if isinstance(node, ast.Import):
                out.extend((a.name, [], node.lineno) for a in node.names if a.name.split(".")[0] == "difftex")
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = _package_of(name).split(".")
                    base = base[:len(base) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target.split(".")[0] != "difftex":
                    continue
                names = [a.name for a in node.names]
                # ``from pkg import mod`` imports the module pkg.mod.
                modules = [f"{target}.{n}" for n in names if f"{target}.{n}" in MODULES]
                out.extend((m, [], node.lineno) for m in modules)
                rest = [n for n in names if f"{target}.{n}" not in MODULES]
                if rest or not modules:
                    out.append((target, rest, node.lineno))
            else:
                visit(ast.iter_child_nodes(node))

    visit(tree.body)
    return out


def test_every_import_resolves_to_a_module():
    for name in MODULES:
        for target, _, line in _imports(name):
            assert target in MODULES, f"{name}:{line} imports {target}, which is no module of difftex"


def _find_cycle(graph: dict[str, list[str]]) -> list[str] | None:
    """One import cycle of ``graph`` (module -> modules it imports) as a path that closes, or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def walk(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in graph.get(node, []):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (found := walk(nxt)):
                return found
        path.pop()
        state[node] = 2
        return None

    for name in sorted(graph):
        if name not in state and (found := walk(name)):
            return found
    return None


def test_no_import_cycle():
    graph = {name: sorted({t for t, _, _ in _imports(name)}) for name in MODULES}
    cycle = _find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_the_cycle_finder_finds_cycles():
    # It must be able to fail: a three-module loop behind an acyclic entry, and a self-import.
    assert _find_cycle({"a": ["b"], "b": ["c"], "c": ["d", "b"], "d": []}) == ["b", "c", "b"]
    assert _find_cycle({"a": ["a"]}) == ["a", "a"]
    assert _find_cycle({"a": ["b", "c"], "b": ["c"], "c": []}) is None


def _subpackage(name: str) -> str:
    """The top-level area a module belongs to: ``difftex.texture``, ``difftex.io``, ... or the module itself."""
    return ".".join(name.split(".")[:2])


def test_no_private_name_crosses_a_subpackage():
    for name in MODULES:
        for target, names, line in _imports(name):
            if _subpackage(target) == _subpackage(name):
                continue
            private = [n for n in names if n.startswith("_")]
            assert not private, f"{name}:{line} imports private {private} from {target}"


# Every name ``from difftex import ...`` offered before the layout change, and the ones it added.
PUBLIC = {
    "sample", "WRAP_MODES", "io", "mapping", "Mesh", "load_mesh", "load_texture", "save_image", "planar_uv",
    "cylindrical_uv", "spherical_uv", "box_uv", "normal_uv", "direction_to_equirect_uv", "direction_to_cube",
    "texture_matrix", "uv_transform", "Fragments", "rasterize", "interpolate", "camera", "Mipmap", "mipmap", "lod",
    "TexturedMesh", "levels_needed",
    # added with the subpackages
    "backend", "envmap", "metrics", "equirect_uv_to_direction", "cube_to_direction",
    # textures in shading: baking, solid and 3D textures
    "ambient_occlusion", "bake", "noise", "sample3d",
    # shading (issue 17)
    "shading", "blinn_phong", "bump", "combine", "displace", "normal_map", "tangent_frames",
    # visibility (issue 16)
    "antialias", "composite", "depth_peel", "painter",
    # ripmaps (issue 19)
    "Ripmap", "ripmap",
}


def test_public_names_are_kept():
    missing = sorted(n for n in PUBLIC if not hasattr(difftex, n))
    assert not missing, f"difftex lost public names: {missing}"
    assert set(difftex.__all__) == PUBLIC
    for name in ("planar_uv", "texture_matrix", "uv_transform", "EPS", "CUBE_FACES"):
        assert getattr(difftex.mapping, name) is not None
    # The environment-map directions live in difftex.envmap (and at the top level) only: mapping, a floor
    # below envmap, no longer re-exports them (no import runs back up a floor).
    assert difftex.direction_to_cube is difftex.envmap.direction_to_cube
    assert not hasattr(difftex.mapping, "direction_to_cube")
    with pytest.raises(AttributeError, match="has no attribute 'nope'"):
        difftex.mapping.nope
    for name in ("look_at", "perspective", "orthographic", "transform"):
        assert callable(getattr(difftex.camera, name))
    for name in ("load_mesh", "load_texture", "save_image", "data_path", "Mesh", "DATA_DIR"):
        assert hasattr(difftex.io, name)


# The floors of the package, lowest first: a module imports only from its own floor or below, so each floor
# can be read, tested and replaced without the ones above it. Subpackages (and top-level modules) not named
# here fail the test until they are given a floor.
FLOORS = [
    {"difftex._native", "difftex._checks", "difftex.backend", "difftex.metrics"},  # the ground: kernels, checks
    {"difftex.mapping"},
    {"difftex.geometry"},
    {"difftex.texture"},
    {"difftex.envmap"},
    {"difftex.shading", "difftex.io"},
    {"difftex.nn", "difftex.nvdiffrast", "difftex.testing", "difftex"},
]


def _floor(name: str) -> int:
    area = _subpackage(name)
    for i, names in enumerate(FLOORS):
        if area in names:
            return i
    raise AssertionError(f"{name} is on no floor: add {area} to FLOORS")


def _all_imports(name: str) -> list[tuple[str, int]]:
    """(imported difftex module, line) of every import in ``name``, function bodies included."""
    tree = ast.parse(MODULES[name].read_text(), str(MODULES[name]))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend((a.name, node.lineno) for a in node.names if a.name.split(".")[0] == "difftex")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = _package_of(name).split(".")
                target = ".".join(base[:len(base) - node.level + 1] + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] == "difftex":
                modules = [f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in MODULES]
                out.extend((m, node.lineno) for m in modules or [target])
    return out


def test_no_import_runs_up_a_floor():
    up = []
    for name in MODULES:
        if name == "difftex":  # the package's face re-exports every floor
            continue
        for target, line in _all_imports(name):
            if target != "difftex" and _floor(target) > _floor(name):
                up.append(f"{name}:{line} imports {target} (floor {_floor(target)} > {_floor(name)})")
    assert not up, "imports up a floor:\n" + "\n".join(up)
